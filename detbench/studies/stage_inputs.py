"""What each finished stage of a study was computed from, recorded in the study's folder and compared on its next run.

A study resumes by skipping the stages whose output exists; that output is the study's only if it
was computed from the same inputs. Each stage's inputs (the data's content fingerprint at the
heights it reads, the digest of its config, its own settings, the checkpoint it evaluates) are
written to OUT/stage_inputs/<stage>.json when the stage finishes, and `changes` lists, key by key,
what differs now. The study recomputes a cheap stage whose inputs changed (the ability study, an
evaluation) and refuses to report a training run whose inputs changed, naming the folder and why.

The data fingerprint hashes the content of the files a stage reads (dataset.json without its
provenance and with only those heights, ImageSets, labels, meta and points); each file's SHA-1 is
cached in OUT/stage_inputs/file_hashes.json under its size and modification time, so a rerun on
unchanged data reads no file again.
"""
from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from detbench.data.dataset import Height3Dataset, split_ids
from detbench.data.frame import data_key
from detbench.data.layout import INFO_FILE, imageset_path
from detbench.train.checkpoint import config_diff
from detbench.train.train_config import RESUME_IGNORE_KEYS
from detbench.utils.atomic import atomic_write_json, read_json

RECORDS_DIR = "stage_inputs"
RECORD_FORMAT = "detbench-study-stage"
HASHES_FILE = "file_hashes.json"

__all__ = ["FileHashes", "RECORDS_DIR", "changes", "config_digest", "dataset_fingerprint", "read_record",
           "training_config", "write_record"]


class FileHashes:
    """SHA-1 of files, cached in a JSON file under each file's (size, mtime_ns); `save` writes the cache."""

    def __init__(self, cache: str | os.PathLike):
        self.cache = Path(cache)
        self.table: dict[str, list] = {}
        if self.cache.is_file():
            try:
                table = read_json(self.cache)
                self.table = table if isinstance(table, dict) else {}
            except (OSError, ValueError):
                self.table = {}
        self.dirty = False

    def sha1(self, path: str | os.PathLike) -> str:
        """The file's SHA-1 ("absent" for a missing file)."""
        path = Path(path)
        try:
            st = path.stat()
        except OSError:
            return "absent"
        key = str(path.resolve())
        known = self.table.get(key)
        if isinstance(known, list) and len(known) == 3 and known[:2] == [st.st_size, st.st_mtime_ns]:
            return str(known[2])
        h = hashlib.sha1()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        self.table[key] = [st.st_size, st.st_mtime_ns, h.hexdigest()]
        self.dirty = True
        return h.hexdigest()

    def save(self) -> None:
        if self.dirty:
            atomic_write_json(self.cache, self.table)
            self.dirty = False


def config_digest(cfg: Any) -> str:
    """SHA-1 of a config (or any JSON-like value) written with sorted keys."""
    return hashlib.sha1(json.dumps(cfg, sort_keys=True, default=str).encode("utf-8")).hexdigest()


def training_config(cfg: Mapping) -> dict:
    """A run config as a training stage's input: JSON values, without the keys a resumed run may change
    (RESUME_IGNORE_KEYS: they do not change what is trained) and without `data.root` (the data are compared by
    content)."""
    def keep(d: Mapping, prefix: str) -> dict:
        out = {}
        for k, v in d.items():
            key = f"{prefix}{k}"
            if key == "data.root" or any(key == i or key.startswith(i + ".") for i in RESUME_IGNORE_KEYS):
                continue
            out[str(k)] = keep(v, key + ".") if isinstance(v, Mapping) else v
        return out

    return json.loads(json.dumps(keep(cfg, ""), default=str))


def dataset_fingerprint(root: str | os.PathLike, heights: Iterable[float], hashes: FileHashes) -> str:
    """SHA-1 of what a stage reads of the dataset at `root` at `heights` (metres, or rigs' names): dataset.json
    without its `source` and with only those heights, ImageSets, and every listed frame's label, meta and points
    files."""
    root = Path(root)
    keys = sorted({data_key(h) for h in heights})
    info = dict(read_json(root / INFO_FILE))
    info.pop("source", None)
    info["heights"] = {k: v for k, v in (info.get("heights") or {}).items() if k in keys}
    h = hashlib.sha1(config_digest(info).encode())
    for split in ("train", "test"):
        h.update(hashes.sha1(imageset_path(root, split)).encode())
    ids = split_ids(root, "all")
    for k in keys:
        ds = Height3Dataset(root, k, "all", check_files=False)
        for fid in ids:
            for path in ds.frame_files(fid):
                h.update(f"{path.relative_to(root)}:{hashes.sha1(path)}\n".encode())
    return h.hexdigest()


def _record_path(out: Path, stage: str) -> Path:
    return Path(out) / RECORDS_DIR / f"{stage}.json"


def read_record(out: str | os.PathLike, stage: str) -> dict | None:
    """The inputs recorded for `stage` of the study in `out`, or None (none recorded, or unreadable)."""
    path = _record_path(Path(out), stage)
    if not path.is_file():
        return None
    try:
        rec = read_json(path)
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or rec.get("format") != RECORD_FORMAT or not isinstance(rec.get("inputs"), dict):
        return None
    return rec["inputs"]


def write_record(out: str | os.PathLike, stage: str, inputs: Mapping) -> None:
    """Record that `stage` finished computed from `inputs`."""
    path = _record_path(Path(out), stage)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, {"format": RECORD_FORMAT, "stage": stage, "inputs": dict(inputs)})


def _short(v: Any) -> str:
    if isinstance(v, str) and len(v) == 40 and all(c in "0123456789abcdef" for c in v):
        return v[:12]  # a digest
    text = json.dumps(v, default=str)
    return text if len(text) <= 80 else text[:77] + "..."


def changes(out: str | os.PathLike, stage: str, inputs: Mapping) -> list[str]:
    """What differs between the inputs recorded for `stage` and `inputs`, one 'key: then X, now Y' a key
    ([] when nothing does; one line when nothing was recorded). A config key that the record lacks and that
    holds its configs/default.yaml value now is no change (a newer detbench added it: `config_diff`)."""
    old = read_record(out, stage)
    if old is None:
        return [f"no record of its inputs ({Path(out) / RECORDS_DIR / (stage + '.json')} is missing: it was "
                f"written by an earlier detbench or by another command)"]
    now = json.loads(json.dumps(dict(inputs), default=str))
    lines = []
    for k in sorted(set(old) | set(now)):
        a, b = old.get(k, "<absent>"), now.get(k, "<absent>")
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            diff = [ln.replace(" (checkpoint) vs ", " then, ").replace(" (now)", " now")
                    for ln in config_diff(a, b)]
            lines += [f"{k} {ln}" for ln in diff[:3]] + ([f"{k}: and {len(diff) - 3} more"] if len(diff) > 3 else [])
        else:
            lines.append(f"{k}: then {_short(a)}, now {_short(b)}")
    return lines
