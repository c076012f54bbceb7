"""Atomic file output: write to a temporary name beside the target, then rename."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from signpose.core.errors import OutputError

# What the user can do about each filesystem error an output meets.
_OUTPUT_HINTS = {
    errno.ENOSPC: "free space on that disk or choose another --out",
    errno.EDQUOT: "free space within your quota or choose another --out",
    errno.EFBIG: "the file is larger than that filesystem allows; choose another --out",
    errno.EROFS: "that filesystem is read-only; choose another --out",
    errno.EACCES: "you may not write there; choose another --out",
    errno.EPERM: "you may not write there; choose another --out",
    errno.EISDIR: "a folder is in the way; name a file or remove the folder",
    errno.EIO: "the disk reported an I/O error; check it or choose another --out",
}

# Errors raised while the caller writes into the handle that are the output's
# fault (an OSError with another errno, e.g. reading an input, passes through).
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO})


def output_error(target: Path, exc: OSError) -> OutputError:
    """One-line OutputError for ``exc`` naming the final path and what to fix."""
    reason = exc.strerror or type(exc).__name__
    hint = _OUTPUT_HINTS.get(exc.errno, "check that folder or choose another --out")
    return OutputError(f"{target}: cannot write ({reason}); {hint}")


# Temporary names carry the writer's process id, ``.<name>.<pid>.<random>[.tmp|<suffix>]``,
# so that a later run can tell a killed run's leftovers from a live writer's file.
_TEMP_NAME = re.compile(r"^\.(?P<base>.+)\.(?P<pid>\d+)\.[a-z0-9_]{8}(\.[^.]*)?$")


def _temp_prefix(name: str) -> str:
    return f".{name}.{os.getpid()}."


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: another user's live process
        return True
    return True


def remove_stale_temporaries(folder: str | os.PathLike, base: str | None = None) -> list[Path]:
    """Remove the temporaries that writers killed before their rename left in ``folder``.

    Only files (and ``temp_dir_beside``'s folders) named as ``atomic_write``/
    ``atomic_path`` name them whose process no longer runs (SIGKILL, a power
    cut); a live writer's file stays.

    Args:
        folder: the output folder.
        base: only the temporaries of this output name (``observations.jsonl``
            for atomic_write's, its stem for atomic_path's); None: all.

    Returns:
        The files removed.
    """
    removed = []
    with contextlib.suppress(OSError):
        for entry in os.scandir(folder):
            m = _TEMP_NAME.match(entry.name)
            if m is None or (base is not None and m["base"] != base):
                continue
            is_dir = entry.is_dir(follow_symlinks=False)
            if not (is_dir or entry.is_file(follow_symlinks=False)):
                continue
            if _pid_alive(int(m["pid"])):
                continue
            with contextlib.suppress(OSError):
                if is_dir:
                    shutil.rmtree(entry.path)
                else:
                    os.unlink(entry.path)
                removed.append(Path(entry.path))
    return removed


def temp_dir_beside(target: str | os.PathLike) -> Path:
    """Create an empty temporary folder beside ``target`` for a writer of a whole folder.

    Named like ``atomic_write``'s temporaries (with this process's id), so the
    next write or ``ensure_dir`` removes it if this process is killed; a
    killed writer's folder for the same ``target`` is removed first.

    Raises:
        OutputError: the folder cannot be created (named with ``target``).
    """
    target = Path(target)
    parent = target.parent if str(target.parent) else Path(".")
    remove_stale_temporaries(parent, target.name)
    try:
        return Path(tempfile.mkdtemp(prefix=_temp_prefix(target.name), suffix=".tmp", dir=parent))
    except OSError as exc:
        raise output_error(target, exc) from None


def _refuse_folder(target: Path) -> None:
    if target.is_dir():
        raise OutputError(f"{target}: is a folder; name a file inside it or remove the folder")


def umask_mode(directory: bool = False) -> int:
    """Mode a plain ``open()`` (or ``mkdir()`` if ``directory``) would give.

    mkstemp/mkdtemp alone would leave 0600/0700.
    """
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


def ensure_dir(path: str | os.PathLike) -> Path:
    """Create ``path`` (and parents) or raise OutputError naming it."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{p}: cannot create output folder ({exc.strerror})") from None
    if not os.access(p, os.W_OK):
        raise OutputError(f"{p}: output folder is not writable; choose another --out")
    remove_stale_temporaries(p)
    return p


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it over ``path`` on success.

    On any exception (including KeyboardInterrupt) the temporary file is
    removed, so ``path`` is either its old content or the complete new one.
    """
    target = Path(path)
    _refuse_folder(target)
    parent = target.parent if str(target.parent) else Path(".")
    remove_stale_temporaries(parent, target.name)
    try:
        fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(target.name), suffix=".tmp", dir=parent)
    except OSError as exc:
        raise output_error(target, exc) from None
    try:
        os.chmod(tmp, umask_mode())
        with os.fdopen(fd, mode, **kwargs) as handle:
            try:
                yield handle
            except OSError as exc:
                if exc.errno in _WRITE_ERRNOS:
                    raise output_error(target, exc) from None
                raise
            _finish(handle, target)
        _replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _finish(handle: IO, target: Path) -> None:
    try:
        handle.flush()
        os.fsync(handle.fileno())
    except OSError as exc:
        raise output_error(target, exc) from None


def _replace(tmp: str | os.PathLike, target: Path) -> None:
    try:
        os.replace(tmp, target)
    except OSError as exc:
        raise output_error(target, exc) from None


def atomic_path(path: str | os.PathLike) -> contextlib.AbstractContextManager[Path]:
    """Yield a temporary path beside ``path`` for writers that want a filename.

    Used for writers such as ``cv2.imwrite``/``cv2.VideoWriter`` that open the
    file themselves. The temporary file keeps ``path``'s suffix so that
    extension-based writers pick the right format.
    """
    return _atomic_path(Path(path))


@contextlib.contextmanager
def _atomic_path(target: Path) -> Iterator[Path]:
    _refuse_folder(target)
    parent = target.parent if str(target.parent) else Path(".")
    remove_stale_temporaries(parent, target.stem)
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=_temp_prefix(target.stem), suffix=target.suffix, dir=parent
        )
    except OSError as exc:
        raise output_error(target, exc) from None
    os.close(fd)
    os.chmod(tmp, umask_mode())
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
        except OSError as exc:
            if exc.errno in _WRITE_ERRNOS:
                raise output_error(target, exc) from None
            raise
        if not tmp_path.exists() or tmp_path.stat().st_size == 0:
            raise OutputError(f"{target}: writer produced no data")
        _replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise
