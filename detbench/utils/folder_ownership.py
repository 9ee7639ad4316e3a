"""Folders detbench owns: which writer made a folder, and whether a writer may replace, write into or clear it.

The one rule for every writer that replaces or deletes a folder: a folder is replaced only when
detbench can prove it wrote it, by the owner file (OWNER_FILE, written into a new folder before
anything else) or by what a finished folder of its kind holds (`FolderKind`: its marker or its
evidence, never entry names alone). `check_replaceable` applies it before a folder is replaced
whole (the replacement itself: detbench.utils.staged_folders), and `check_claimable` before a process
writes into a folder for a while (the claim and its lock: detbench.utils.folder_locks, whose
`clear_folder` empties a folder `check_replaceable` allows to be replaced). A refusal is `FolderNotReplaceable`,
naming the folder and the fix.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

from detbench.utils.atomic import atomic_write_json

__all__ = ["FolderInUse", "FolderKind", "FolderNotReplaceable", "LOCK_FILE", "OWNER_FILE", "check_claimable",
           "check_replaceable", "folder_entries", "folder_owner", "write_owner"]


class FolderNotReplaceable(FileExistsError, ValueError):
    """A writer may not replace (or write into) this folder: it is a file, it holds files the writer does not
    own, or it holds an earlier result and replacing it was not asked for. The message names the folder and
    the fix."""


class FolderInUse(FolderNotReplaceable):
    """Another process holds the folder's lock (`detbench.utils.folder_locks.acquire_folder_lock`); the message
    names its pid and host."""


# the file by which a folder says which detbench writer made it: {"kind": "dataset"}; written into a new
# folder before anything else, so that even an unfinished folder is known to be detbench's own
OWNER_FILE = ".detbench-owner.json"
# the lock of a folder a process writes into for a while (a training run, a study):
# `detbench.utils.folder_locks.acquire_folder_lock`
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


def folder_entries(dest: Path) -> list[str]:
    """The names in `dest` that count: not temporary files of interrupted writes, nor locks (the folder's own,
    and those of folders being written in it: `.detbench-lock-<name>`)."""
    return sorted(p.name for p in dest.iterdir() if not p.name.startswith((".tmp-", LOCK_FILE)))


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
    (`detbench.utils.staged_folders.staged_folder`), so nothing of the old one survives and an
    interrupted replacement loses nothing. `flag` is how the caller's user asks to replace
    (`--overwrite`, `overwrite=True`), `out` how the user names the folder (`--out`). Temporary
    entries (`.tmp-*`) of interrupted writes and the lock are not counted.
    """
    dest = Path(dest)
    if not dest.exists():
        return []
    if not dest.is_dir():
        raise FolderNotReplaceable(f"{dest}: exists and is not a folder; choose another {out}")
    entries = folder_entries(dest)
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
    entries = folder_entries(dest)
    if not entries:
        return
    if kind.key and folder_owner(dest) == kind.key:
        return
    if not _is_kind(dest, kind):
        raise _not_this_kind(dest, kind, _listing(entries), out)
    _refuse_foreign(dest, entries, kind, f", and no {OWNER_FILE} says that the rest is detbench's; move {{it}} "
                                         f"elsewhere first or choose another {out}")
