"""signpose: UAV trajectories from coded signs on power pylons.

This package is the application layer (CLI, pipeline, file plumbing). The
image side lives in ``frontend``, the pose side in ``estimator`` and the
landmark maps in ``maps``.
"""

__version__ = "0.1.0"
