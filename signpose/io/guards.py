"""Checks a text reader of ``signpose.io`` runs before it parses: size and nesting.

PyYAML parses brackets nested a thousand deep for seconds before it gives up
with a RecursionError; a calibration file or a bag's ``metadata.yaml`` is
never nested more than a few levels, so deeper nesting is refused at once,
with the limit in the message.

The check itself lives in ``signpose.core.nesting`` (the map loader, below
``io``, uses it too); this module keeps its names for the ``io`` readers.
"""

from __future__ import annotations

from signpose.core.nesting import MAX_NESTING, check_nesting, flow_nesting

__all__ = ["MAX_NESTING", "check_nesting", "flow_nesting"]
