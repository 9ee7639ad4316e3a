"""One process at a time in a folder it writes into for a while (a training run, a study).

`acquire_folder_lock(dest, what)` takes the kernel's lock (`flock`) on `dest/LOCK_FILE`, so it ends
with its process however that ends (a kill -9 included); the file names the holder (pid, host,
since when), a second process is refused with `FolderInUse` naming it, and a file left by a killed
holder is taken over with a note. `claim_folder` is what a run or a study holds its folder by:
the ownership check (detbench.utils.folder_ownership.check_claimable), the lock, and the owner
file, released when its block ends.
"""
from __future__ import annotations

import errno
import json
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from collections.abc import Callable, Iterator

from detbench.utils.atomic import NEW_FILE_MODE
from detbench.utils.folder_ownership import (
    LOCK_FILE, OWNER_FILE, FolderInUse, FolderKind, check_claimable, check_replaceable, folder_entries, folder_owner,
    write_owner,
)

__all__ = ["FolderLock", "acquire_folder_lock", "claim_folder", "clear_folder", "lock_file"]


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
    """The lock of one folder, held by this process (`acquire_folder_lock`). `recovered` is what the lock file said
    of an earlier holder that ended without releasing it (killed), or None."""

    def __init__(self, path: Path, fd: int, recovered: dict | None, shared: bool = False):
        self.path, self.fd, self.recovered, self.shared = path, fd, recovered, shared

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
            if self.shared:  # the last reader removes the file: only when no one else holds it
                import fcntl

                try:
                    fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    return
            self.path.unlink(missing_ok=True)  # while still held: no other process has it open and locked
        finally:
            os.close(self.fd)  # closing the file releases the lock
            self.fd = -1


def _only_readers(fd: int) -> bool:
    """Whether the lock on `fd`'s file that refused an exclusive lock is held by readers alone (shared)."""
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return False
    fcntl.flock(fd, fcntl.LOCK_UN)
    return True


READERS = "processes that read it (a training, for one)"  # how a refusal names the holders of a shared lock


def lock_file(path: str | os.PathLike, what: str, in_use: Callable[[str], BaseException],
              wait: Callable[[str], None] | None = None, *, shared: bool = False) -> FolderLock:
    """Take the kernel's lock (`flock`) on the file `path` (created when missing) for this process, so it ends
    with its process however that ends (a kill -9 included), and write into it who holds it (`what`, pid,
    host, since when); a file left by a killed holder is taken over (`FolderLock.recovered`). While another
    process holds it: with `wait`, `wait(words naming the holder)` is called once and the call blocks until
    the lock is free; without, `in_use(words naming the holder)` is raised. The kernel's lock reaches other
    pid namespaces (containers) on this machine, and other machines on a file system that shares locks
    (NFS). `shared`: a reader's lock, held by any number of readers at once and refused while a writer holds
    the exclusive one (and the other way round); a reader leaves the file as it is."""
    import socket
    import time

    path = Path(path)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        return FolderLock(path, -1, None)
    waited = False
    mode = fcntl.LOCK_SH if shared else fcntl.LOCK_EX
    for _ in range(100):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, NEW_FILE_MODE)
        try:
            fcntl.flock(fd, mode | fcntl.LOCK_NB)
        except OSError as e:
            busy = e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)
            words = (READERS if not shared and busy and _only_readers(fd) else _holder_words(_read_holder(fd)))
            if not busy or wait is None:
                os.close(fd)
                if not busy:
                    raise
                raise in_use(words) from None
            if not waited:
                wait(words)
                waited = True
            try:
                fcntl.flock(fd, mode)
            except BaseException:
                os.close(fd)
                raise
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:  # released and removed by its holder between our open and our lock
            same = False
        if same:
            break
        os.close(fd)
    else:  # pragma: no cover - another process creates and removes the lock a hundred times in a row
        raise in_use(f"processes that keep taking and releasing its lock {path}")
    if shared:
        return FolderLock(path, fd, None, shared=True)
    recovered = _read_holder(fd)
    holder = {"what": what, "pid": os.getpid(), "host": socket.gethostname(),
              "since": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, json.dumps(holder).encode("utf-8"))
    os.fsync(fd)
    return FolderLock(path, fd, recovered)


def acquire_folder_lock(dest: str | os.PathLike, what: str, *, out: str = "--out") -> FolderLock:
    """Lock the folder `dest` (which exists) for this process (`lock_file` on `dest/LOCK_FILE`): `FolderInUse`
    naming the holder's pid and host when another process holds it. `what` names this holder for the
    others' refusal."""
    path = Path(dest) / LOCK_FILE
    return lock_file(path, what, lambda holder: FolderInUse(
        f"{dest}: in use by {holder} (its lock is {path}); wait for it to end, or choose another {out}"))


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
        if folder_entries(dest) in ([], [OWNER_FILE]):
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


def check_members_free(dest: str | os.PathLike, fix: str) -> None:
    """`FolderInUse` naming the first folder in `dest` (a study's run, say) whose lock a process holds (a
    training that outlived its killed study driver), then `fix`; nothing when none is held. A lock left by a
    killed holder is removed on the way."""
    dest = Path(dest)
    if not dest.is_dir():
        return
    for p in sorted(dest.iterdir()):
        if p.is_dir() and not p.is_symlink() and (p / LOCK_FILE).is_file():
            lock_file(p / LOCK_FILE, "a check of its lock", lambda holder, p=p: FolderInUse(
                f"{p}: in use by {holder}; {fix}")).release()


def clear_folder(dest: str | os.PathLike, kind: FolderKind, *, flag: str, out: str = "--out") -> list[str]:
    """Delete what `dest` holds (the folder itself, its OWNER_FILE and its lock stay) once `check_replaceable`
    allows it to be replaced (`overwrite` given as `flag`). A folder in it that a process holds (a training run
    of a study, still running after its study was killed) is refused first (`FolderInUse`, naming the holder),
    before anything is deleted; the others' locks are held while they are deleted. Returns the entries removed."""
    dest = Path(dest)
    removed = check_replaceable(dest, True, kind, flag=flag, out=out)
    locks: list[FolderLock] = []
    try:
        for e in removed:
            p = Path(e)
            if p.is_dir() and not p.is_symlink() and (p / LOCK_FILE).is_file():
                locks.append(lock_file(p / LOCK_FILE, f"{flag} of {dest}", lambda holder, p=p: FolderInUse(
                    f"{p}: in use by {holder}; {flag} would delete it under that process: stop it (or wait for it "
                    f"to end), then run the same command again")))
        for e in removed:
            p = Path(e)
            if p.name == OWNER_FILE:
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink(missing_ok=True)
    finally:
        for lock in locks:
            lock.release()
    return [e for e in removed if Path(e).name != OWNER_FILE]
