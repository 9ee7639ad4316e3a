"""Atomic writes: a reader never sees half a report or half a checkpoint.

Every writer goes to a temporary file in the destination folder, flushes and fsyncs it,
then renames it over the target (an atomic operation on POSIX and on Windows for files on
the same volume). An interrupted write leaves the old file intact and at most a stray
`.tmp-*` file behind (a process killed mid-write cannot remove it; `remove_stale_temporaries`
does, at the next start). A write that fails because the disk or the file-size limit is
full raises `DiskFullError` naming the file, never the writer's own obscure error.
"""
from __future__ import annotations

import errno
import json
import math
import os
import re
import shutil
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable, Iterator
from typing import Any

from detbench.utils.untrusted import ESCAPE_ERRORS, MAX_DEPTH, structure_problem


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()
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
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual mode
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


# --------------------------------------------------------------------------- folders replaced whole

class FolderNotReplaceable(FileExistsError, ValueError):
    """A writer may not replace (or write into) this folder: it is a file, it holds files the writer does not
    own, or it holds an earlier result and replacing it was not asked for. The message names the folder and
    the fix."""


class FolderInUse(FolderNotReplaceable):
    """Another process holds the folder's lock (`folder_lock`); the message names its pid and host."""


# the file by which a folder says which detbench writer made it: {"kind": "dataset"}; written into a new
# folder before anything else, so that even an unfinished folder is known to be detbench's own
OWNER_FILE = ".detbench-owner.json"
# the lock of a folder a process writes into for a while (a training run, a study): `folder_lock`
LOCK_FILE = ".detbench-lock"


@dataclass(frozen=True)
class FolderKind:
    """What a folder holds that a writer replaces whole (`check_replaceable`) or writes into (`claim_folder`).

    name: one such folder, with its article ("a dataset"); marker: the file a finished one holds
    ("dataset.json"); entries: every name it may hold (anything else belongs to the user, and a
    replacement would delete it); foreign: how a refusal describes other names ("part of a dataset");
    unfinished: what a folder of such entries without the marker is called ("an unfinished dataset")
    when `overwrite` may replace it, or None when it may not; removes: said when asking for
    `overwrite`, what a replacement removes besides the obvious; key: the kind its writer records in
    OWNER_FILE ("" when it writes none); patterns: regular expressions of further names it may hold
    ("eval_h1.8_test"); members: (regular expression, kind) of the folders of another kind it may hold
    (a study's training runs); evidence: glob patterns of files that show a folder written before
    OWNER_FILE existed to be of this kind (besides `marker`).

    What proves a folder to be of this kind: its OWNER_FILE names `key`, or it holds `marker` or
    `evidence`. Entry names alone prove nothing (an OpenPCDet folder has a dataset's points/ and labels/).
    """

    name: str
    marker: str
    entries: tuple[str, ...]
    foreign: str
    unfinished: str | None = None
    removes: str = ""
    key: str = ""
    patterns: tuple[str, ...] = ()
    members: tuple[tuple[str, FolderKind], ...] = ()
    evidence: tuple[str, ...] = ()


def folder_owner(dest: str | os.PathLike) -> str | None:
    """The kind of folder `dest`'s OWNER_FILE names ("dataset"), or None when it has none (or an unreadable one)."""
    path = Path(dest) / OWNER_FILE
    try:
        if path.is_file() and not path.is_symlink() and path.stat().st_size < 4096:
            kind = json.loads(path.read_text(encoding="utf-8")).get("kind")
            return kind if isinstance(kind, str) else None
    except (OSError, ValueError, AttributeError):
        return None
    return None


def write_owner(dest: str | os.PathLike, kind: FolderKind) -> None:
    """Record in `dest` (a folder) that it is a folder of `kind`, written by detbench."""
    if kind.key:
        atomic_write_json(Path(dest) / OWNER_FILE, {"kind": kind.key, "written_by": "detbench",
                                                    "note": "this folder was made by detbench; its tools replace "
                                                            "or delete only folders that hold this file"})


def _folder_entries(dest: Path) -> list[str]:
    """The names in `dest` that count: not temporary files of interrupted writes, nor the lock."""
    return sorted(p.name for p in dest.iterdir() if not p.name.startswith(".tmp-") and p.name != LOCK_FILE)


def _is_kind(dest: Path, kind: FolderKind) -> bool:
    """`dest` (a folder) shows that it is of `kind` (OWNER_FILE, `marker` or `evidence`)."""
    if kind.key and folder_owner(dest) == kind.key:
        return True
    return (dest / kind.marker).is_file() or any(next(dest.glob(g), None) is not None for g in kind.evidence)


def _own_entry(dest: Path, name: str, kind: FolderKind) -> bool:
    """Whether entry `name` of `dest` is one that a folder of `kind` holds."""
    if name in kind.entries or name == OWNER_FILE or any(re.fullmatch(p, name) for p in kind.patterns):
        return True
    path = dest / name
    return any(re.fullmatch(p, name) and path.is_dir() and not path.is_symlink() and _is_kind(path, k)
               for p, k in kind.members)


def _listing(names: list[str]) -> str:
    return f"{', '.join(names[:5])}{', ...' if len(names) > 5 else ''}"


def _not_this_kind(dest: Path, kind: FolderKind, listing: str, out: str) -> FolderNotReplaceable:
    other = folder_owner(dest)
    if other is not None:
        return FolderNotReplaceable(f"{dest}: holds a detbench {other} (its {OWNER_FILE} says so), not "
                                    f"{kind.name}; choose another {out}")
    return FolderNotReplaceable(f"{dest}: the folder is not empty ({listing}) and nothing in it shows that detbench "
                                f"wrote it as {kind.name} (no {kind.marker}, no {OWNER_FILE}); detbench does not "
                                f"write into or delete folders it did not make: choose an empty or new {out}")


def check_replaceable(dest: str | os.PathLike, overwrite: bool, kind: FolderKind, *, flag: str = "--overwrite",
                      out: str = "output folder") -> list[str]:
    """Refuse (`FolderNotReplaceable`) to write `kind` over `dest` unless `dest` is new or empty, or
    `overwrite` is set and `dest` is proven to be of `kind` and holds only `kind`'s entries (with its
    marker, unless `kind` allows an unfinished one). Returns the entries a replacement removes (none
    for a new or empty folder).

    The one rule for every writer that replaces or deletes a folder: a folder is replaced only when
    detbench can prove it wrote it (`FolderKind`: OWNER_FILE, the marker or the evidence, never entry
    names alone); the writer then builds the new folder beside the old one and swaps it in whole
    (`staged_folder`), so nothing of the old one survives and an interrupted replacement loses
    nothing. `flag` is how the caller's user asks to replace (`--overwrite`, `overwrite=True`), `out`
    how the user names the folder (`--out`). Temporary entries (`.tmp-*`) of interrupted writes and
    the lock are not counted.
    """
    dest = Path(dest)
    if not dest.exists():
        return []
    if not dest.is_dir():
        raise FolderNotReplaceable(f"{dest}: exists and is not a folder; choose another {out}")
    entries = _folder_entries(dest)
    if not entries or (entries == [OWNER_FILE] and folder_owner(dest) == kind.key):
        return []
    listing = _listing(entries)
    if not _is_kind(dest, kind):
        raise _not_this_kind(dest, kind, listing, out)
    if not (dest / kind.marker).is_file() and (kind.unfinished is None or not overwrite):
        fix = f", or pass {flag} to replace it ({kind.unfinished})" if kind.unfinished is not None else ""
        raise FolderNotReplaceable(f"{dest}: the folder is not empty and holds no {kind.marker} ({listing}); choose "
                                   f"an empty or new {out}{fix}")
    if not overwrite:
        removes = f" ({kind.removes})" if kind.removes else ""
        raise FolderNotReplaceable(f"{dest / kind.marker}: {kind.name} already exists here; choose another {out} "
                                   f"or pass {flag} to replace it{removes}")
    _refuse_foreign(dest, entries, kind, f"; {flag} replaces the whole folder, so move {{it}} elsewhere first or "
                                         f"choose another {out}")
    return [str(dest / e) for e in entries]


def _refuse_foreign(dest: Path, entries: list[str], kind: FolderKind, tail: str) -> None:
    """FolderNotReplaceable naming the entries of `dest` that are not `kind`'s own; `tail` ends the message,
    its `{it}` reads "it" or "them"."""
    foreign = [e for e in entries if not _own_entry(dest, e, kind)]
    if foreign:
        one = len(foreign) == 1
        raise FolderNotReplaceable(f"{dest}: holds {_listing(foreign)}, which {'is' if one else 'are'} not "
                                   f"{kind.foreign}" + tail.format(it="it" if one else "them"))


def check_claimable(dest: str | os.PathLike, kind: FolderKind, *, out: str = "--out") -> None:
    """Refuse (`FolderNotReplaceable`) to write into `dest` as a folder of `kind` unless it is new, empty or
    proven to be of `kind` (`FolderKind`); one written before OWNER_FILE existed must hold nothing but
    `kind`'s entries. Nothing is written."""
    dest = Path(dest)
    if not dest.exists():
        return
    if not dest.is_dir():
        raise FolderNotReplaceable(f"{dest}: exists and is not a folder; choose another {out}")
    entries = _folder_entries(dest)
    if not entries:
        return
    if kind.key and folder_owner(dest) == kind.key:
        return
    if not _is_kind(dest, kind):
        raise _not_this_kind(dest, kind, _listing(entries), out)
    _refuse_foreign(dest, entries, kind, f", and no {OWNER_FILE} says that the rest is detbench's; move {{it}} "
                                         f"elsewhere first or choose another {out}")


def clear_folder(dest: str | os.PathLike, kind: FolderKind, *, flag: str, out: str = "--out") -> list[str]:
    """Delete what `dest` holds (the folder itself, its OWNER_FILE and its lock stay) once `check_replaceable`
    allows it to be replaced (`overwrite` given as `flag`). Returns the entries removed."""
    dest = Path(dest)
    removed = check_replaceable(dest, True, kind, flag=flag, out=out)
    for e in removed:
        p = Path(e)
        if p.name == OWNER_FILE:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink(missing_ok=True)
    return [e for e in removed if Path(e).name != OWNER_FILE]


STAGED_NEW = ".tmp-new-"  # `.tmp-new-<name>-<pid>`: the folder being built (or, after an exchange, the old one)
STAGED_OLD = ".tmp-old-"  # `.tmp-old-<name>-<pid>`: the old folder moved aside by a two-rename swap


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _staged_leftovers(dest: Path, prefix: str) -> list[Path]:
    """`<prefix><dest.name>-<pid>` folders beside `dest` whose process no longer runs."""
    head = f"{prefix}{dest.name}-"
    out = []
    for p in dest.parent.glob(f"{prefix}*"):
        tail = p.name[len(head):] if p.name.startswith(head) else ""
        if tail.isdigit() and p.is_dir() and not p.is_symlink() and not pid_alive(int(tail)):
            out.append(p)
    return sorted(out)


def recover_staged(dest: str | os.PathLike) -> list[str]:
    """Finish what a killed `staged_folder` left beside `dest`; returns one note per thing done.

    A half-built or not-swapped new folder is removed; an old folder moved aside is put back
    when `dest` is missing (the kill fell between the two renames of a swap), else removed
    (the swap had finished). Only folders of processes that no longer run are touched.
    """
    dest = Path(dest)
    if not dest.parent.is_dir():
        return []
    notes = []
    for old in _staged_leftovers(dest, STAGED_OLD):
        if not dest.exists() and not dest.is_symlink():
            os.rename(old, dest)
            notes.append(f"{dest}: put back from {old.name} (a replacement of this folder was interrupted)")
        else:
            shutil.rmtree(old)
            notes.append(f"{old}: removed (the old folder of an interrupted replacement of {dest.name})")
    for new in _staged_leftovers(dest, STAGED_NEW):
        shutil.rmtree(new)
        notes.append(f"{new}: removed (left by an interrupted write of {dest.name}; {dest.name} is unchanged)")
    return notes


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux renameat2 RENAME_EXCHANGE); False when not available here."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP):  # file system or kernel without it
        return False
    raise OSError(err, os.strerror(err), str(b))


def swap_in(staged: Path, dest: Path) -> None:
    """Put the complete folder `staged` at `dest`, removing what was there: one atomic exchange where the
    system has it, else two renames (`recover_staged` repairs a kill between them)."""
    if dest.is_dir() and not any(dest.iterdir()):
        dest.rmdir()
    if not dest.exists():
        os.rename(staged, dest)
        return
    if _exchange(staged, dest):
        shutil.rmtree(staged)  # it now holds the old folder
        return
    old = dest.parent / f"{STAGED_OLD}{dest.name}-{os.getpid()}"
    os.rename(dest, old)
    try:
        os.rename(staged, dest)
    except BaseException:
        os.rename(old, dest)
        raise
    shutil.rmtree(old)


@contextmanager
def staged_folder(dest: str | os.PathLike) -> Iterator[Path]:
    """Build a folder that replaces `dest` whole, so that an interruption at any moment leaves either the
    complete old folder or the complete new one.

    Yields an empty sibling `.tmp-new-<name>-<pid>`; when the block ends normally it is swapped in
    (`swap_in`), when it raises it is removed and `dest` is untouched. Leftovers of killed
    processes are repaired first (`recover_staged`). The caller decides beforehand whether `dest`
    may be replaced. A symbolic link `dest` is followed (the folder it points to is replaced).
    """
    dest = Path(dest)
    if dest.is_symlink():
        dest = dest.resolve()
    dest.parent.mkdir(parents=True, exist_ok=True)
    recover_staged(dest)
    staged = dest.parent / f"{STAGED_NEW}{dest.name}-{os.getpid()}"
    if staged.exists():
        shutil.rmtree(staged)
    staged.mkdir()
    try:
        yield staged
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        raise
    try:
        swap_in(staged, dest)
    except BaseException:
        if staged.exists() and not (dest.exists() and dest.samefile(staged)):
            shutil.rmtree(staged, ignore_errors=True)
        raise


# --------------------------------------------------------------------------- folders written into for a while

def _holder_words(holder: dict | None) -> str:
    if not holder:
        return "another process (it did not say which)"
    what = f"{holder.get('what')} " if holder.get("what") else ""
    since = f", since {holder['since']}" if holder.get("since") else ""
    return f"{what}pid {holder.get('pid', '?')} on host {holder.get('host', '?')}{since}"


def _read_holder(fd: int) -> dict | None:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 4096).decode("utf-8", "replace")
        holder = json.loads(text) if text.strip() else None
    except (OSError, ValueError):
        return None
    return holder if isinstance(holder, dict) else None


class FolderLock:
    """The lock of one folder, held by this process (`folder_lock`). `recovered` is what the lock file said
    of an earlier holder that ended without releasing it (killed), or None."""

    def __init__(self, path: Path, fd: int, recovered: dict | None):
        self.path, self.fd, self.recovered = path, fd, recovered

    def note(self) -> str | None:
        """One line about a lock taken over from a killed holder, or None."""
        if self.recovered is None:
            return None
        return (f"{self.path}: taken over from {_holder_words(self.recovered)}, which ended without releasing it "
                f"(killed?)")

    def release(self) -> None:
        if self.fd < 0:
            return
        try:
            self.path.unlink(missing_ok=True)  # while still held: no other process has it open and locked
        finally:
            os.close(self.fd)  # closing the file releases the lock
            self.fd = -1


def acquire_folder_lock(dest: str | os.PathLike, what: str, *, out: str = "--out") -> FolderLock:
    """Lock the folder `dest` (which exists) for this process: `FolderInUse` naming the holder's pid and host
    when another process holds it. The lock is the kernel's (`flock`) on `dest/LOCK_FILE`, so it ends with
    its process however that ends (a kill -9 included); the file names the holder, and a file left by a
    killed holder is taken over (`FolderLock.recovered`). `what` names this holder for the others' refusal."""
    import socket
    import time

    path = Path(dest) / LOCK_FILE
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        return FolderLock(path, -1, None)
    for _ in range(100):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666 & ~_UMASK)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = _read_holder(fd)
            os.close(fd)
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            raise FolderInUse(f"{dest}: in use by {_holder_words(holder)} (its lock is {path}); wait for it to end, "
                              f"or choose another {out}") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:  # released and removed by its holder between our open and our lock
            same = False
        if same:
            break
        os.close(fd)
    else:  # pragma: no cover - another process creates and removes the lock a hundred times in a row
        raise FolderInUse(f"{dest}: its lock {path} keeps changing hands; try again, or choose another {out}")
    recovered = _read_holder(fd)
    holder = {"what": what, "pid": os.getpid(), "host": socket.gethostname(),
              "since": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, json.dumps(holder).encode("utf-8"))
    os.fsync(fd)
    return FolderLock(path, fd, recovered)


@contextmanager
def claim_folder(dest: str | os.PathLike, kind: FolderKind, what: str, *, out: str = "--out",
                 notes: Callable[[str], None] | None = None) -> Iterator[FolderLock]:
    """Hold `dest` as a folder of `kind` for the block: refused (`FolderNotReplaceable`) when it is not new,
    empty or of `kind` (`check_claimable`), or (`FolderInUse`) while another process holds it; otherwise it
    is created, locked (`acquire_folder_lock`; a lock left by a killed holder is taken over and reported
    through `notes`) and marked as `kind`'s (OWNER_FILE). Released when the block ends, however it ends; a
    folder the block left with nothing in it is removed again (with the parents the claim created), so a
    refused start leaves no trace."""
    dest = Path(dest)
    check_claimable(dest, kind, out=out)
    created = [p for p in (dest, *dest.parents) if not p.exists()]
    dest.mkdir(parents=True, exist_ok=True)
    try:
        lock = acquire_folder_lock(dest, what, out=out)
    except BaseException:
        _remove_created(dest, created)
        raise
    try:
        if lock.note() is not None and notes is not None:
            notes(lock.note())
        check_claimable(dest, kind, out=out)  # again, now that no other process writes in it
        if folder_owner(dest) is None:
            write_owner(dest, kind)
        yield lock
    finally:
        if _folder_entries(dest) in ([], [OWNER_FILE]):
            (dest / OWNER_FILE).unlink(missing_ok=True)
        lock.release()
        _remove_created(dest, created)


def _remove_created(dest: Path, created: list[Path]) -> None:
    """Remove the folders in `created` (`dest` and parents made for it) that are empty, innermost first."""
    for p in created:
        try:
            p.rmdir()
        except OSError:
            break
