"""The context-manager pair of an output that appears only when it is finished.

A writer of such an output (MCAP, video, an image folder) has ``close()``,
which publishes it, and ``abort()``, which drops the partial one; ``with``
calls the first when the block ends normally and the second when it raises.
"""

from __future__ import annotations

from typing import Any, Self


class PublishOnExit:
    """``with writer:`` closes on success, aborts on an exception."""

    def close(self) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    def abort(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
