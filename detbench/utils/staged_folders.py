"""Folders replaced whole: the new folder is built beside the old one and swapped in when complete.

`staged_folder(dest)` yields an empty sibling `.tmp-new-<name>-<pid>` to build in; when the block ends
normally it takes `dest`'s place (`swap_in`: one atomic exchange where the system has it, else two
renames), when it raises it is removed. So an interruption at any moment leaves either the complete
old folder or the complete new one, and `recover_staged` (run first by every staged build) finishes
what a killed process left: a half-built folder removed, an old folder moved aside put back. Whether
`dest` may be replaced at all is decided beforehand (detbench.utils.folder_ownership.check_replaceable).
"""
from __future__ import annotations

import errno
import os
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path
from collections.abc import Iterator

__all__ = ["STAGED_NEW", "STAGED_OLD", "pid_alive", "recover_staged", "staged_folder", "swap_in"]


STAGED_NEW = ".tmp-new-"  # `.tmp-new-<name>-<pid>`: the folder being built (or, after an exchange, the old one)
STAGED_OLD = ".tmp-old-"  # `.tmp-old-<name>-<pid>`: the old folder moved aside by a two-rename swap


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
