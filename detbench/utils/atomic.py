"""Atomic writes: a reader never sees half a report or half a checkpoint.

Every writer goes to a temporary file in the destination folder, flushes and fsyncs it,
then renames it over the target (an atomic operation on POSIX and on Windows for files on
the same volume). An interrupted write leaves the old file intact and at most a stray
`.tmp-*` file behind (a process killed mid-write cannot remove it; `remove_stale_temporaries`
does, at the next start). A write that fails because the disk or the file-size limit is
full raises `DiskFullError` naming the file, never the writer's own obscure error.

JSON goes through `to_json` (numpy values converted, NaN and inf written as null: strict JSON)
and comes back through `read_json`, which names the file of a malformed, undecodable or
hostile (too deeply nested) one.
"""
from __future__ import annotations

import errno
import json
import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from collections.abc import Callable, Iterator
from typing import Any

from detbench.utils.untrusted import ESCAPE_ERRORS, MAX_DEPTH, structure_problem

__all__ = ["DiskFullError", "NEW_FILE_MODE", "atomic_path", "atomic_save", "atomic_write_bytes", "atomic_write_json",
           "atomic_write_text", "read_json", "remove_stale_temporaries", "to_json"]


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


NEW_FILE_MODE = 0o666 & ~_current_umask()  # the mode a file created by this process gets (its umask applied)
_FULL_ERRNOS = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}
_LOW_SPACE = 1 << 20  # bytes: a write that fails with less free than this failed for lack of space


class DiskFullError(OSError):
    """A write failed because the disk, the quota or the file-size limit is full; names the file.

    Attributes `path` (the file) and `reason` (e.g. "No space left on device") when raised by `atomic_path`."""

    path: Path | None = None
    reason: str = ""


def _full_reason(exc: BaseException, tmp: Path) -> str | None:
    """Why writing `tmp` failed when it is for lack of space (errno anywhere in the chain, little
    free space left, or the file reached the process's file-size limit), else None."""
    e: BaseException | None = exc
    while e is not None:
        if isinstance(e, OSError) and e.errno in _FULL_ERRNOS:
            return os.strerror(e.errno)
        e = e.__cause__ or e.__context__
    if not isinstance(exc, (OSError, RuntimeError)):
        return None
    if shutil.disk_usage(tmp.parent).free < _LOW_SPACE:
        return os.strerror(errno.ENOSPC)
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    except (ImportError, OSError, ValueError):  # pragma: no cover - not POSIX
        return None
    if limit != resource.RLIM_INFINITY and tmp.is_file() and tmp.stat().st_size >= limit:
        return f"{os.strerror(errno.EFBIG)} (the file-size limit, ulimit -f, is {limit} bytes)"
    return None


def _disk_full(exc: BaseException, path: Path, tmp: Path) -> DiskFullError | None:
    reason = _full_reason(exc, tmp)
    if reason is None:
        return None
    free = shutil.disk_usage(path.parent).free / 2**20
    err = DiskFullError(f"{path}: could not be written: {reason} ({free:.0f} MiB free in {path.parent}); free "
                        f"some space (or raise the limit) and run the same command again; any previous version "
                        f"of the file is unchanged")
    err.errno = errno.ENOSPC
    err.path, err.reason = path, reason  # for a caller that words its own message
    return err


def remove_stale_temporaries(directory: str | os.PathLike, pattern: str = ".tmp-*") -> list[Path]:
    """Delete the leftover temporary files of writes that a killed process never finished."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    stale = [p for p in directory.glob(pattern) if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success it replaces `path` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".tmp-{path.name}-", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, NEW_FILE_MODE)  # mkstemp makes 0600; give the file the usual mode
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, path)
    except BaseException as e:
        full = _disk_full(e, path, tmp_path)
        tmp_path.unlink(missing_ok=True)
        if full is not None:
            raise full from None
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """UTF-8 text; a file name in it that is not UTF-8 is written with its bytes escaped (`\\xff`)."""
    return atomic_write_bytes(path, text.encode("utf-8", ESCAPE_ERRORS))


def _json_default(obj: Any):
    try:
        import numpy as np

        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def _nan_to_none(obj: Any):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_nan_to_none(v) for v in obj]
    return obj


def to_json(obj: Any, indent: int | None = 2) -> str:
    """JSON text with numpy scalars converted and NaN/inf written as null (strict JSON)."""
    text = json.dumps(obj, default=_json_default, indent=indent, allow_nan=True)
    return json.dumps(_nan_to_none(json.loads(text)), indent=indent, allow_nan=False) + "\n"


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> Path:
    return atomic_write_text(path, to_json(obj, indent=indent))


def atomic_save(path: str | os.PathLike, writer: Callable[[Path], None]) -> Path:
    """Call `writer(tmp_path)` (e.g. `lambda p: torch.save(obj, p)`) and rename into place."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno}); "
                         f"re-create it or fix the file") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (byte {e.start} cannot be decoded), so not JSON; re-create it "
                         f"or fix the file") from None
    except RecursionError:
        data = _TOO_DEEP
    problem = f"it is nested deeper than {MAX_DEPTH} levels" if data is _TOO_DEEP else structure_problem(data)
    if problem:
        raise ValueError(f"{path}: not read: {problem}; re-create it or fix the file")
    return data


_TOO_DEEP = object()
