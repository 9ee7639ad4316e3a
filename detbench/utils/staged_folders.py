"""Folders replaced whole: the new folder is built beside the old one and swapped in when complete.

`staged_folder(dest)` yields an empty sibling `.tmp-new-<name>-<pid>` to build in; when the block ends
normally it takes `dest`'s place (`swap_in`: one atomic exchange where the system has it, else two
renames), when it raises it is removed. So an interruption at any moment leaves either the complete
old folder or the complete new one, and `recover_staged` (run first by every staged build) finishes
what a killed process left: a half-built folder removed, an old folder moved aside put back. Whether
`dest` may be replaced at all is decided beforehand (detbench.utils.folder_ownership.check_replaceable)
and again under the destination's lock (`check`).

One writer per destination: a build holds the kernel's lock on `.detbench-lock-<name>` beside `dest`
(`hold_destination`) from before its first check to after its swap, so a second writer of the same
`dest` is refused (`FolderInUse`, naming the first's pid and host) or waits for it, and nothing beside
`dest` is cleaned up while a build of it runs: a build is dead when its destination's lock is free
(which holds across pid namespaces and, on a file system that shares locks, across machines), never
by its pid alone. A staged folder holds a build marker (`BUILD_MARKER`, naming its destination) until
its swap, and `recover_marked` cleans up only folders so marked: a user's `.tmp-thesis-2023` is never
taken for a build.
"""
from __future__ import annotations

import errno
import json
import os
import re
import shutil
import socket
import sys
from contextlib import ExitStack, contextmanager
from pathlib import Path
from collections.abc import Callable, Iterator

from detbench.utils.folder_locks import FolderLock, lock_file
from detbench.utils.folder_ownership import LOCK_FILE, FolderInUse

__all__ = ["BUILD_MARKER", "STAGED_NEW", "STAGED_OLD", "destination_lock", "hold_destination", "pid_alive",
           "reading_folder", "recover_marked", "recover_staged", "staged_folder", "swap_in"]


STAGED_NEW = ".tmp-new-"  # `.tmp-new-<name>-<pid>`: the folder being built (or, after an exchange, the old one)
STAGED_OLD = ".tmp-old-"  # `.tmp-old-<name>-<pid>`: the old folder moved aside by a two-rename swap
BUILD_MARKER = ".tmp-detbench-build.json"  # in a staged folder until its swap: {"dest": name, "pid", "host", "what"}
_HELD: dict[Path, FolderLock] = {}  # the destinations this process holds (`hold_destination` is re-entrant)


class _Busy(Exception):
    """Another process holds a destination's lock (`_try_hold`)."""


def destination_lock(dest: Path) -> Path:
    """The lock file of the destination `dest`: `.detbench-lock-<name>` beside it (it may not exist yet)."""
    return dest.parent / f"{LOCK_FILE}-{dest.name}"


@contextmanager
def hold_destination(dest: str | os.PathLike, what: str, *, out: str = "--out",
                     wait: Callable[[str], None] | None = None) -> Iterator[None]:
    """Hold the lock of the destination `dest` (`destination_lock`) for the block: while another process holds
    it, `FolderInUse` naming its pid and host, or (with `wait`) `wait(holder)` and then block until it is free.
    Re-entrant in one process. The lock file is removed when the block ends."""
    key = Path(os.path.abspath(dest))
    if key in _HELD:
        yield
        return
    key.parent.mkdir(parents=True, exist_ok=True)
    try:
        lock = lock_file(destination_lock(key), what, lambda holder: FolderInUse(
            f"{dest}: in use by {holder}; wait for it to end, or choose another {out}"), wait=wait)
    except OSError as e:  # the folder the destination is made in cannot be written: name it, not the lock file
        if isinstance(e, FolderInUse) or e.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
            raise
        raise OSError(e.errno, e.strerror, str(key.parent)) from None
    _HELD[key] = lock
    try:
        yield
    finally:
        del _HELD[key]
        lock.release()


@contextmanager
def reading_folder(dest: str | os.PathLike, what: str, *, flag: str = "--data") -> Iterator[None]:
    """Read the folder `dest` (a dataset a training reads for hours) in the block under a reader's lock on its
    destination lock: no detbench writer replaces it meanwhile (`hold_destination` refuses, naming the
    readers), and while one is replacing it the read is refused (`FolderInUse`, naming the writer). A folder
    whose parent takes no lock file (read-only) cannot be replaced by detbench either: read without one."""
    key = Path(os.path.abspath(dest))
    if key in _HELD:
        yield
        return
    try:
        lock = lock_file(destination_lock(key), what, lambda holder: FolderInUse(
            f"{flag} {dest}: in use by {holder}, which replaces it; wait for it to end"), shared=True)
    except OSError as e:
        if isinstance(e, FolderInUse) or e.errno not in (errno.EACCES, errno.EROFS, errno.EPERM):
            raise
        lock = None
    try:
        yield
    finally:
        if lock is not None:
            lock.release()


@contextmanager
def _try_hold(dest: Path) -> Iterator[bool]:
    """Hold `dest`'s lock for the block when no other process does: yields True, else False (nothing held). A
    folder in which no lock file can be made (read-only) yields False."""
    held = ExitStack()
    try:
        held.enter_context(hold_destination(dest, "a clean-up of interrupted writes"))
    except FolderInUse:
        ok = False
    except OSError as e:
        if e.errno not in (errno.EACCES, errno.EROFS, errno.EPERM):
            raise
        ok = False
    else:
        ok = True
    with held:
        yield ok


def pid_alive(pid: int) -> bool:
    """Whether a process with this id runs on this machine (someone else's included)."""
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
    (the swap had finished). Nothing is touched while another process holds `dest`'s lock (it is
    writing `dest`), nor a folder whose pid runs on this machine.
    """
    dest = Path(dest)
    if not dest.parent.is_dir() or not (_staged_leftovers(dest, STAGED_OLD) or _staged_leftovers(dest, STAGED_NEW)):
        return []
    with _try_hold(dest) as held:
        return _recover(dest) if held else []


def _recover(dest: Path) -> list[str]:
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


def _mark(staged: Path, dest: Path, what: str) -> None:
    text = json.dumps({"dest": dest.name, "pid": os.getpid(), "host": socket.gethostname(), "what": what})
    (staged / BUILD_MARKER).write_text(text, encoding="utf-8")


def _marked_dest(folder: Path) -> str | None:
    """The destination name a staged folder's BUILD_MARKER names, when it is a marked build of detbench's."""
    path = folder / BUILD_MARKER
    try:
        if not path.is_file() or path.is_symlink() or path.stat().st_size > 4096:
            return None
        name = json.loads(path.read_text(encoding="utf-8")).get("dest")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(name, str) or not name or "/" in name or "\\" in name or name in (".", ".."):
        return None
    return name if re.fullmatch(re.escape(f"{STAGED_NEW}{name}-") + r"\d+", folder.name) else None


def recover_marked(parent: str | os.PathLike) -> list[str]:
    """`recover_staged` for every destination in `parent` (a cache folder) with a staged folder that carries
    detbench's build marker; a folder without one (a user's `.tmp-backup-2023`) is never touched."""
    parent = Path(parent)
    if not parent.is_dir():
        return []
    dests = set()
    for d in parent.glob(f"{STAGED_NEW}*"):
        name = _marked_dest(d) if d.is_dir() and not d.is_symlink() else None
        if name is not None:
            dests.add(name)
    return [note for name in sorted(dests) for note in recover_staged(parent / name)]


@contextmanager
def staged_folder(dest: str | os.PathLike, *, what: str = "a detbench writer", out: str = "--out",
                  check: Callable[[], object] | None = None,
                  wait: Callable[[str], None] | None = None) -> Iterator[Path]:
    """Build a folder that replaces `dest` whole, so that an interruption at any moment leaves either the
    complete old folder or the complete new one.

    Holds `dest`'s lock for the whole build (`hold_destination`; `what` names this writer to a second one,
    which is refused, or waits with `wait`), then repairs the leftovers of killed builds (`recover_staged`)
    and runs `check()` (the caller's `check_replaceable`, again now that no other writer of `dest` runs).
    Yields an empty, marked sibling `.tmp-new-<name>-<pid>`; when the block ends normally it is swapped in
    (`swap_in`), when it raises it is removed and `dest` is untouched. A symbolic link `dest` is followed
    (the folder it points to is replaced).
    """
    dest = Path(dest)
    if dest.is_symlink():
        dest = dest.resolve()
    dest.parent.mkdir(parents=True, exist_ok=True)
    with hold_destination(dest, what, out=out, wait=wait):
        recover_staged(dest)
        if check is not None:
            check()
        staged = dest.parent / f"{STAGED_NEW}{dest.name}-{os.getpid()}"
        if staged.exists():
            shutil.rmtree(staged)
        staged.mkdir()
        try:
            _mark(staged, dest, what)
            yield staged
        except BaseException:
            shutil.rmtree(staged, ignore_errors=True)
            raise
        try:
            (staged / BUILD_MARKER).unlink(missing_ok=True)
            swap_in(staged, dest)
        except BaseException:
            if staged.exists() and not (dest.exists() and dest.samefile(staged)):
                shutil.rmtree(staged, ignore_errors=True)
            raise
