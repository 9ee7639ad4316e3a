"""Hostile files: a small file that asks for memory without bound, a link out of the folder the user named,
a line or frame id too long to print, structures nested or aliased beyond reason, names that are not UTF-8.
Each is refused with one line naming the file, quoting at most a short escaped excerpt; nothing is changed."""
import os
import pickle
import struct
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest

from tests.faults.faultkit import ROOT, snapshot

SECRET = "SECRET_API_KEY=sk-live-0123456789abcdef"


def _text(s: str) -> bytes:
    b = s.encode()
    return b"X" + struct.pack("<I", len(b)) + b


def _entry(frame_id: bytes, boxes: bytes) -> bytes:
    """A protocol-2 result.pkl holding one OpenPCDet entry, frame_id and boxes_lidar given as pickle opcodes."""
    return (b"\x80\x02](" + _text("frame_id") + frame_id + _text("boxes_lidar") + boxes + _text("score") + b"]d"
            + b"a.")


# a 100 000 x 100 000 float64 array (80 GB) asked for by numpy.ndarray((100000, 100000), 'f8') in 102 bytes
HUGE_NDARRAY = _entry(_text("0002_000"), b"cnumpy\nndarray\n(J\xa0\x86\x01\x00J\xa0\x86\x01\x00t" + _text("f8")
                      + b"\x86R")
# an array of 50 million objects (400 MB of pointers) asked for by the state of a 3-element object array
HUGE_STATE = pickle.dumps([{"frame_id": "0002_000", "boxes_lidar": np.zeros(3, object), "score": []}],
                          protocol=3).replace(b"K\x03\x85", b"J\x80\xf0\xfa\x02\x85")
# the unpickler's memo grown to 32 million slots (256 MB) by one 7-byte opcode
HUGE_MEMO = b"\x80\x04]r\x00\x00\x00\x02."


@pytest.mark.parametrize("payload", [HUGE_NDARRAY, HUGE_STATE, HUGE_MEMO], ids=["ndarray", "state", "memo"])
def test_small_result_pkl_cannot_make_the_reader_allocate(payload, tmp_path):
    """What a result.pkl may allocate is bounded by its size on disk; beyond that it is refused unallocated."""
    from detbench.eval.external import predictions_from_result_pkl

    path = tmp_path / "result.pkl"
    path.write_bytes(payload)
    assert len(payload) < 300
    tracemalloc.start()
    try:
        try:
            got = predictions_from_result_pkl(path)
        except ValueError as e:
            got = str(e)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 32 * 2**20, f"{peak / 2**20:.0f} MiB allocated for a {len(payload)}-byte file"
    if payload is not HUGE_MEMO:
        assert f"{path}: not read: it asks for arrays of" in got and "more than its size on disk allows" in got


def test_eval_refuses_a_result_pkl_asking_for_80_gb(fault_data, tool, tmp_path):
    """tools/eval.py refuses a result.pkl that asks for an 80 GB array in one line naming the file, unallocated,
    and writes no report."""
    path = tmp_path / "result.pkl"
    path.write_bytes(HUGE_NDARRAY)
    code, err = tool("eval", "--data", fault_data, "--height", "1.8", "--pred", path, "--out", tmp_path / "e",
                     "--no-progress")
    assert code == 2 and f"error: {path}: not read: it asks for arrays of 80,000,000,000 bytes" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "e").exists()


def test_links_out_of_the_named_folder_are_refused_and_lines_are_not_echoed(data_copy, tool, tmp_path):
    """A prediction or label file linking to a file elsewhere is refused without reading it; a malformed line
    is quoted as a short escaped excerpt, never whole."""
    secret = tmp_path / "credentials"
    secret.write_text(SECRET + "\n")
    preds = tmp_path / "pred"
    preds.mkdir()
    (preds / "0002_000.txt").symlink_to(secret)
    code, err = tool("eval", "--data", data_copy, "--height", "1.8", "--pred", preds, "--out", tmp_path / "e",
                     "--no-progress")
    assert code == 2 and f"{preds / '0002_000.txt'}: a link to {secret}, outside the prediction folder" in err
    assert "SECRET" not in err and not (tmp_path / "e").exists()

    label = data_copy / "labels" / "0002_001.txt"
    label.unlink()
    label.symlink_to(secret)
    before = snapshot(data_copy)
    code, err = tool("validate", data_copy)
    assert code == 1 and f"{label}: a link to {secret}, outside {data_copy}" in err and "SECRET" not in err
    (tmp_path / "empty").mkdir()
    code, err = tool("eval", "--data", data_copy, "--height", "1.8", "--pred", tmp_path / "empty", "--out",
                     tmp_path / "e", "--no-progress")
    assert code == 2 and f"{label}: a link to {secret}" in err and "SECRET" not in err
    assert snapshot(data_copy) == before

    # a malformed line inside the folder: quoted escaped and cut, with its length
    label.unlink()
    label.write_text("\x1b[2J" + "x" * 5000 + "\n")
    (preds / "0002_000.txt").unlink()
    (preds / "0002_000.txt").write_text("\x1b]0;pwned\x07" + "y" * 5000 + "\n")
    code, err = tool("validate", data_copy)
    assert code == 1 and f"{label}:1: 1 columns, expected 8" in err and "'\\x1b[2Jxxx" in err
    assert "(5004 characters)" in err and "\x1b" not in err and "x" * 100 not in err
    code, err = tool("eval", "--data", data_copy, "--height", "1.8", "--pred", preds, "--out", tmp_path / "e",
                     "--no-progress")
    assert code == 2 and "0002_000.txt:1: expected 8 numbers" in err and "\x1b" not in err and "y" * 100 not in err


def test_npy_header_claiming_1e11_rows_is_refused_unallocated(data_copy, tool, tmp_path):
    """A points file whose .npy header claims more data than the file holds is refused by validate and analyze
    naming the file and both sizes, without allocating what the header asks for; the dataset is unchanged."""
    pts = data_copy / "points" / "1.8" / "0002_000.npy"
    header = {"descr": "<f4", "fortran_order": False, "shape": (10**11, 4)}
    with open(pts, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        fh.write(np.zeros((10, 4), np.float32).tobytes())
    assert pts.stat().st_size < 300
    before = snapshot(data_copy)
    code, err = tool("validate", data_copy)
    assert code == 1 and f"{pts}: the header says shape (100000000000, 4) of <f4 (1,600,000,000,000 bytes) but " \
                         f"the file holds 160 bytes of data" in err
    code, err = tool("analyze", "--data", data_copy, "--out", tmp_path / "a", "--no-figures", "--no-progress")
    assert code == 2 and f"{pts}: the header says shape" in err
    assert snapshot(data_copy) == before


def _alias_bomb(levels: int = 7, width: int = 10) -> str:
    """YAML of `width ** levels` values in a few hundred bytes: each anchor repeats the one before."""
    rows = ["&a0 [" + ", ".join(["x"] * width) + "]"]
    rows += [f"&a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]" for i in range(1, levels)]
    return "[" + ", ".join(rows) + "]"


def test_yaml_alias_bomb_is_refused_in_set_in_files_and_in_a_checkpoint(tool, fault_data, tmp_path):
    """YAML that expands beyond 100,000 values is refused, unexpanded, wherever it comes in: a --set value, a
    config file, the config stored in a checkpoint; the tool refuses it before anything is written."""
    import torch

    from detbench.config import ConfigError, load_config, parse_override
    from detbench.train.checkpoint import CKPT_FORMAT, CKPT_VERSION, CheckpointError, load_checkpoint

    bomb = _alias_bomb()
    assert len(bomb) < 400
    with pytest.raises(ConfigError, match=r"--set 'study.models': not read: it expands to more than 100000 values"):
        parse_override(f"study.models={bomb}")
    cfg_file = tmp_path / "bomb.yaml"
    cfg_file.write_text(f"_base_: second.yaml\nstudy:\n  models: {bomb}\n")
    with pytest.raises(ConfigError, match=r"bomb.yaml: not read: it expands to more than 100000 values"):
        load_config(cfg_file)
    # a checkpoint holding such a config (as one written with the --set above) is refused before it is compared
    cfg = {"study": {"models": __import__("yaml").safe_load(bomb)}}
    ckpt = tmp_path / "epoch_001.pt"
    torch.save({"format": CKPT_FORMAT, "version": CKPT_VERSION, "model_name": "second", "config": cfg, "data": {},
                "state": {}, "model": {}}, ckpt)
    with pytest.raises(CheckpointError, match=r"epoch_001.pt: the checkpoint's config is not read: it expands"):
        load_checkpoint(ckpt, config={"study": {"models": []}})
    # the tool: refused before anything is written
    out = tmp_path / "run"
    code, err = tool("train", "--model", "second", "--preset", "smoke", "--data", fault_data, "--height", "1.8",
                     "--out", out, "--set", f"study.models={bomb}")
    assert code == 2 and "not read: it expands to more than 100000 values" in err and not out.exists()


def test_deeply_nested_json_and_pickles_are_refused_in_one_line(fault_data, data_copy, tool, tmp_path):
    """A dataset.json or a result.pkl nested deeper than 64 levels is refused in one line naming the file; the
    dataset is unchanged."""
    info = data_copy / "dataset.json"
    info.write_text('{"format": ' + "[" * 100_000 + "]" * 100_000 + "}")
    before = snapshot(data_copy)
    code, err = tool("analyze", "--data", data_copy, "--out", tmp_path / "a", "--no-figures", "--no-progress")
    assert code == 2 and f"{info}: not read: it is nested deeper than 64 levels" in err
    assert snapshot(data_copy) == before

    deep = 100_000
    path = tmp_path / "result.pkl"
    path.write_bytes(_entry(b"]" * deep + b"a" * (deep - 1), b"]"))
    code, err = tool("eval", "--data", fault_data, "--height", "1.8", "--pred", path, "--out", tmp_path / "e",
                     "--no-progress")
    assert code == 2 and f"{path}: not read: it is nested deeper than 64 levels" in err


def test_huge_and_long_frame_ids_are_named_in_short_lines(fault_data, data_copy, tool, tmp_path):
    """A 25 MB frame id in a result.pkl is quoted cut; a 300-character id in ImageSets (longer than a file name
    may be) is refused naming the list and line."""
    path = tmp_path / "result.pkl"
    path.write_bytes(pickle.dumps([{"frame_id": "y" * 25_000_000, "boxes_lidar": np.zeros((0, 7)),
                                    "score": np.zeros(0)}]))
    code, err = tool("eval", "--data", fault_data, "--height", "1.8", "--pred", path, "--out", tmp_path / "e",
                     "--no-progress")
    assert code == 2 and "unknown frame id 'yyyy" in err and "(25000000 characters)" in err and len(err) < 1000

    listing = data_copy / "ImageSets" / "test.txt"
    n = len(listing.read_text().splitlines())
    with open(listing, "a") as fh:
        fh.write("a" * 300 + "\n")
    (tmp_path / "empty").mkdir()
    code, err = tool("eval", "--data", data_copy, "--height", "1.8", "--pred", tmp_path / "empty", "--out",
                     tmp_path / "e", "--no-progress")
    assert code == 2 and f"{listing}:{n + 1}: frame id 'aaaa" in err and "longer than 200 characters" in err
    assert len(err) < 1000


def test_a_name_that_is_not_utf8_is_printed_escaped(fault_data, tmp_path):
    """On a UTF-8 terminal (strict encoding) a folder name with undecodable bytes is printed and written with
    those bytes escaped, instead of a traceback after the work is done."""
    out = os.fsdecode(os.fsencode(str(tmp_path)) + b"/out\xff")
    preds = tmp_path / "pred"
    preds.mkdir()
    env = dict(os.environ, PYTHONIOENCODING="utf-8", PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "tools/eval.py", "--data", str(fault_data), "--height", "1.8", "--pred",
                           str(preds), "--out", out, "--no-progress", "--bootstrap", "0"],
                          cwd=ROOT, capture_output=True, env=env, timeout=300)
    stdout = proc.stdout.decode("utf-8")
    assert proc.returncode == 0, proc.stderr.decode("utf-8", "replace")[-2000:]
    assert f"{tmp_path}/out\\xff/report.json" in stdout
    assert os.path.isfile(os.path.join(out, "report.md"))


def test_study_refuses_a_data_folder_without_dataset_json_before_touching_out(tool, tmp_path):
    """A --data folder without dataset.json is refused naming the file before the study's --out is touched:
    --fresh deletes nothing and a new --out is not created."""
    data = tmp_path / "data"
    (data / "points").mkdir(parents=True)
    out = tmp_path / "study"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    code, err = tool("study", "--preset", "smoke", "--data", data, "--out", out, "--fresh", "--no-progress")
    assert code == 2 and f"--data {data}: {data / 'dataset.json'}: dataset.json not found" in err
    assert snapshot(tmp_path) == before
    code, err = tool("study", "--preset", "smoke", "--data", data, "--out", tmp_path / "new", "--no-progress")
    assert code == 2 and "dataset.json not found" in err and not (tmp_path / "new").exists()
