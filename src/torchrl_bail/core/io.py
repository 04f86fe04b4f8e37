"""Atomic file writes: a crashed or interrupted run never leaves a half-written file under the final name.

Everything is written to a temporary name in the target directory, flushed to disk, then renamed over the
final name with :func:`os.replace` (atomic on POSIX). A write that fails for a reason the user mends -- a full
disk, a quota, no permission, a read-only file system -- leaves the final name untouched (the old file, if any,
is still whole), removes the temporary file and raises :class:`FileSystemError`: one line naming the file and the
remedy, which the command lines print as their one error line (exit status 2).

Examples:
    >>> import json, tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_json_atomic(d / "summary.json", {"final_return": 1.5})
    >>> json.loads((d / "summary.json").read_text())
    {'final_return': 1.5}
    >>> sorted(p.name for p in d.iterdir())
    ['summary.json']
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["FileSystemError", "atomic_path", "describe_file_error", "file_fault", "write_atomic",
           "write_json_atomic", "write_text_atomic"]

_NO_SPACE = "free space on that disk, or write elsewhere (another hydra.run.dir, data_dir=)"
_NO_ACCESS = "choose a directory you can write (another hydra.run.dir, data_dir=) or fix its permissions"
#: the file-system faults a user mends, with the remedy
REMEDIES = {errno.ENOSPC: _NO_SPACE, errno.EDQUOT: _NO_SPACE, errno.EACCES: _NO_ACCESS, errno.EPERM: _NO_ACCESS,
            errno.EROFS: "it is on a read-only file system: write elsewhere (another hydra.run.dir, data_dir=)",
            errno.ENOTDIR: "a file stands where a directory is needed: move it or choose another hydra.run.dir",
            errno.EEXIST: "a file stands where a directory is needed: move it or choose another hydra.run.dir"}


class FileSystemError(OSError):
    """A file could not be written for a reason the user mends (full disk, permissions, read-only file system); the
    message is one line naming the file and the remedy."""


def file_fault(err: BaseException | None) -> OSError | None:
    """The file-system fault of :data:`REMEDIES` that ``err`` is or was raised while handling (``torch.save``'s
    writer, told of a failed write, raises its own ``RuntimeError`` on top of the ``OSError``), else ``None``."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, OSError) and err.errno in REMEDIES:
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


def describe_file_error(err: BaseException, path: str | os.PathLike | None = None) -> str | None:
    """One line for a file-system fault of :data:`REMEDIES` (naming ``path``, else the error's own file), or
    ``None`` for any other error. An error raised while handling such a fault counts as the fault.

    Examples:
        >>> describe_file_error(OSError(errno.EROFS, "Read-only file system"), "run/checkpoint.pt")[:55]
        'cannot write run/checkpoint.pt: Read-only file system; '
        >>> describe_file_error(ValueError("not a file-system fault")) is None
        True
    """
    if isinstance(err, FileSystemError):
        return str(err)
    err = file_fault(err)
    if err is None:
        return None
    where = path if path is not None else err.filename
    what = f"cannot write {where}" if where is not None else "a write failed"
    return f"{what}: {err.strerror or os.strerror(err.errno)}; {REMEDIES[err.errno]}"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yields a temporary path beside ``path``; on success it is fsynced and renamed to ``path``.

    On any exception (``KeyboardInterrupt`` included) the temporary file is removed and ``path`` is untouched; a
    file-system fault (:func:`describe_file_error`) is raised as a :class:`FileSystemError` naming ``path``.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else ".tmp",
                                    dir=path.parent)
        os.close(fd)
        tmp = Path(name)
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as err:
        message = describe_file_error(err, path)
        if message is None:
            raise
        raise FileSystemError(message) from err
    finally:
        if tmp is not None and tmp.exists():
            tmp.unlink()


def write_atomic(path: str | os.PathLike, write: Callable[[IO[bytes]], Any]) -> Path:
    """Calls ``write(f)`` on a temporary binary file beside ``path``, then renames it over ``path``.

    Through an open file a full disk surfaces as an ``OSError`` at the failing write (``torch.save`` to a *path*
    reports it as an opaque ``RuntimeError`` of its zip writer): ``write_atomic(p, lambda f: torch.save(obj, f))``.
    """
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        write(f)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    return write_atomic(path, lambda f: f.write(text.encode()))


def write_json_atomic(path: str | os.PathLike, obj: Any) -> Path:
    return write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=False, default=_jsonable) + "\n")


def _jsonable(value: Any) -> Any:
    """JSON fallback for numpy / torch scalars and paths."""
    if hasattr(value, "item"):
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")
