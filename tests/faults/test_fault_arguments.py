"""Arguments and config values that would zero or void a result, or crash with a traceback: each is refused in one
line (exit status 2) naming the flag or key and what it must be, before any frame is read or file written. A
checkpoint whose stored config was edited, or asks for more memory than a tensor may take, is refused; inputs with
no vehicle or no point give a warning, not a silent LDR of 0.00."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from tests.faults.faultkit import load_checkpoint_dict, snapshot, train_argv


def _one_line(code: int, err: str, named: str) -> None:
    assert code == 2 and err.startswith("error: ") and named in err, err[-2000:]
    assert err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("argv, named", [
    (["--batch-size", "0"], "--batch-size 0: must be an integer >= 1"),
    (["--batch-size", "-3"], "--batch-size -3: must be an integer >= 1"),
    (["--score-threshold", "5"], "--score-threshold 5: must be a score in [0, 1]"),
    (["--iou-threshold", "0"], "--iou-threshold 0: must be an IoU in (0, 1]"),
    (["--bootstrap", "-1"], "--bootstrap -1: must be an integer >= 0"),
])
def test_eval_refuses_arguments_that_zero_the_result(argv, named, fault_data, tool, tmp_path):
    """An argument that would evaluate no frame, drop every prediction or match nothing (a batch size below 1, a
    score threshold above 1, an IoU threshold of 0, a negative bootstrap) is refused in one line naming it, and
    no report is written."""
    out = tmp_path / "e"
    code, err = tool("eval", "--data", fault_data, "--height", "1.8", "--pred", tmp_path, "--out", out,
                     "--no-progress", *argv)
    _one_line(code, err, named)
    assert not out.exists()


@pytest.mark.parametrize("argv, named", [
    (["--device", "cuda"] if not torch.cuda.is_available() else ["--device", "cuda:99"], "--device cuda"),
    (["--device", "gpu7"], "--device 'gpu7': not a torch device"),
    (["--out", "{file}"], "is a file, not a folder; choose another --out"),
    (["--model", "pillarnet"], "--model pillarnet: --ckpt {ckpt} is a second checkpoint"),
])
def test_eval_of_a_checkpoint_checks_device_out_and_model_first(argv, named, trained_run, tool, tmp_path):
    """A bad device, an --out that is a file, or a --model other than the checkpoint's is refused in one line
    before the prediction pass, so no report carries a model name that --combine would trust wrongly."""
    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    file = tmp_path / "a_file"
    file.write_text("not a folder")
    out = tmp_path / "e"
    argv = [a.replace("{file}", str(file)) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(out)]
    code, err = tool("eval", "--ckpt", ckpt, "--no-progress", *argv)
    _one_line(code, err, named.replace("{ckpt}", str(ckpt)))
    assert not out.exists() and file.read_text() == "not a folder"


def test_precision_refuses_a_score_threshold_above_one(trained_run, tool, tmp_path):
    """A score threshold outside [0, 1] is refused in one line before the checkpoint runs, and nothing is written."""
    code, err = tool("precision", "--ckpt", trained_run / "checkpoints" / "epoch_002.pt", "--score-threshold", "7",
                     "--out", tmp_path / "p", "--no-progress")
    _one_line(code, err, "--score-threshold 7: must be a score in [0, 1]")
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("name, argv, named", [
    ("analyze", ["--data", "{data}", "--lane-width", "0"], "--lane-width 0.0: must be a positive number of metres"),
    ("analyze", ["--data", "{data}", "--out", "{file}"], "is a file, not a folder; choose another --out"),
    ("analyze", ["--simulate", "2", "--heights", "0"], "--heights 0: a mounting height is a positive number"),
    ("sweep", ["--heights", "0", "1.8"], "--heights 0: mounting height must be a positive number of metres"),
    ("sweep", ["--frames", "2", "--voxel", "0"], "--voxel 0.0: must be a positive number"),
    ("benchmark", ["--frames", "-2"], "--frames -2: must be an integer >= 1"),
    ("benchmark", ["--warmup", "-1"], "--warmup -1: must be an integer >= 0"),
    ("benchmark", ["--device", "gpu7"], "--device 'gpu7': not a torch device"),
    ("simulate", ["--frames", "2", "--heights", "0.0004"], "--heights 0.0004: mounting height 0.0004 m is below 1 mm"),
])
def test_study_tools_end_a_bad_argument_with_one_line(name, argv, named, fault_data, tool, tmp_path):
    """Each study tool refuses an argument that cannot give a result (a lane width, height or voxel of 0, a
    negative count, an unknown device, an --out that is a file, a height below 1 mm that no reader accepts) in
    one line naming it, and writes or changes nothing."""
    file = tmp_path / "a_file"
    file.write_text("not a folder")
    out = tmp_path / "out"
    argv = [a.replace("{file}", str(file)).replace("{data}", str(fault_data)) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(out)]
    before = snapshot(fault_data)
    code, err = tool(name, *argv, *(["--no-progress"] if name != "benchmark" else []))
    _one_line(code, err, named)
    assert not out.exists() and file.read_text() == "not a folder" and snapshot(fault_data) == before


@pytest.mark.parametrize("override, named", [
    ("train.momentum_range=[5, -5]", "train: momentum_range must be [low, high] with 0 <= low <= high < 1"),
    ("train.final_div_factor=1e-300", "train: final_div_factor must be >= 1"),
    ("train.betas=[0.9, 1.5]", "train: betas must be two numbers in [0, 1)"),
    ("train.lr=.nan", "train: lr must be finite"),
    ("model.head.rotations=[]", "model.head.rotations must be a non-empty list of anchor angles"),
    ("model.backbone2d.layer_strides=[0, 2]", "model.backbone2d.layer_strides must be made of integers >= 1"),
    ("model.head.anchor_sizes=[[.nan, 1.6, 1.5]]", "model.head.anchor_sizes must be finite"),
    ("model.head.anchor_sizes=[[-4, 1.6, 1.5]]", "model.head.anchor_sizes must be auto or a non-empty list"),
    ("model.post.post_nms_top_k=0", "model.post.post_nms_top_k must be an integer >= 1"),
    ("model.post.score_threshold=2", "model.post.score_threshold must be a fraction in [0, 1]"),
    ("model.head.num_anchor_sizes=0", "model.head.num_anchor_sizes must be an integer from 1 to 16"),
    ("model.head.num_anchor_sizes=-3", "model.head.num_anchor_sizes must be an integer from 1 to 16"),
    ("model.head.num_anchor_sizes=100000", "model.head.num_anchor_sizes must be an integer from 1 to 16"),
    ("model.head.pos_iou=0.3", "model.head.neg_iou (0.45) must not exceed model.head.pos_iou (0.3)"),
    ("model.voxel_size=[0.00005, 0.00005, 0.15]", "GiB, above the 16 GiB a tensor may take"),
])
def test_config_values_out_of_range_are_refused_before_training(override, named, fault_data, tool, tmp_path):
    """A config value outside its range (e.g. momenta, betas, schedule factors, a NaN learning rate, empty anchor
    rotations, a stride of 0, NaN or negative anchor sizes, a grid larger than a tensor may be) is refused in
    one line naming the key, before any checkpoint is written."""
    out = tmp_path / "run"
    code, err = tool("train", *train_argv(fault_data, out, "--set", override))
    assert code == 2 and named in err and "Traceback" not in err, err[-3000:]
    assert not (out / "checkpoints").exists()


def test_exponents_inside_a_list_override_are_numbers():
    """`--set key=[0, 1e30]`: a number written with an exponent is a number inside a list or a mapping too,
    although YAML 1.1 alone reads 1e30 as a string."""
    from detbench.config import apply_overrides, parse_override, shipped_defaults

    assert parse_override("a=[0, 1e30]") == (["a"], [0, 1e30])
    assert parse_override("a={b: [1e-3, x]}") == (["a"], {"b": [1e-3, "x"]})
    ref = {"train": shipped_defaults("train")}
    assert apply_overrides(ref, ["train.betas=[0.9, 9.9e-1]"], reference=ref)["train"]["betas"] == [0.9, 0.99]


def _resave(ckpt: dict, path, digest: bool) -> None:
    from detbench.train.checkpoint import config_digest

    if digest:
        ckpt["config_digest"] = config_digest(ckpt["config"])
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, path)


def test_checkpoint_with_an_edited_config_is_refused(trained_run, tool, tmp_path):
    """A checkpoint whose stored config was edited after it was written (its voxel size, its range) is refused
    naming the file: its weights are never evaluated on another grid than the one they learned."""
    for key, value in (("voxel_size", [0.1, 0.1, 0.15]), ("point_cloud_range", [0.0, -16.0, -0.6, 76.8, 16.0, 4.2])):
        ckpt = load_checkpoint_dict(trained_run / "checkpoints" / "epoch_002.pt")
        assert ckpt["config"]["model"][key] != value
        ckpt["config"]["model"][key] = value
        bad = tmp_path / key / "epoch_002.pt"
        _resave(ckpt, bad, digest=False)
        code, err = tool("eval", "--ckpt", bad, "--out", tmp_path / "e", "--no-progress")
        _one_line(code, err, f"{bad}: the config stored in this checkpoint was changed after it was written")
        assert not (tmp_path / "e").exists()


def test_checkpoint_asking_for_terabytes_is_refused_before_allocating(trained_run, tool, tmp_path):
    """A checkpoint whose config (consistently stored) asks for a grid larger than a tensor may be is refused in
    one line naming the file, before anything is allocated."""
    ckpt = load_checkpoint_dict(trained_run / "checkpoints" / "epoch_002.pt")
    ckpt["config"]["model"]["voxel_size"] = [0.00005, 0.00005, 0.15]
    big = tmp_path / "big" / "epoch_002.pt"
    _resave(ckpt, big, digest=True)
    code, err = tool("eval", "--ckpt", big, "--out", tmp_path / "e", "--no-progress")
    _one_line(code, err, "GiB, above the 16 GiB a tensor may take (DETBENCH_MAX_TENSOR_GB)")
    assert f"{big}: cannot rebuild model 'second'" in err


def test_a_missing_or_nan_height_is_named_not_suggested_for_simulation(trained_run, fault_data, tool, tmp_path):
    """A NaN height is named as no mounting height, never suggested for simulation; a checkpoint that records
    no training height asks for --height."""
    from detbench.data import DatasetError, read_info

    with pytest.raises(DatasetError, match=r"height nan is not a mounting height") as e:
        read_info(fault_data).height(math.nan)
    assert "simulate" not in str(e.value)
    ckpt = load_checkpoint_dict(trained_run / "checkpoints" / "epoch_002.pt")
    del ckpt["data"]["height"]
    bad = tmp_path / "noheight" / "epoch_002.pt"
    _resave(ckpt, bad, digest=True)
    code, err = tool("eval", "--ckpt", bad, "--out", tmp_path / "e", "--no-progress")
    _one_line(code, err, f"--ckpt {bad}: records no training height (data.height); give --height H")
    assert "simulate nan" not in err


@pytest.mark.parametrize("emptied, named, eval_named", [
    ("points", "not one point lies in any of the", "not one point lies in any vehicle box in the 4 frame(s)"),
    ("labels", "no vehicle in any range of the 12 frame(s)", "no vehicle in any range in the 4 frame(s)"),
])
def test_analyze_and_eval_warn_when_every_points_file_or_box_is_empty(emptied, named, eval_named, data_copy, tool,
                                                                      tmp_path):
    """When every points file (or every label file) is empty, analyze and eval finish with a warning per height
    that no point lies in any box (no vehicle lies in any range): an LDR or recall of 0 is never reported
    without a word."""
    for f in (data_copy / emptied).rglob("*"):
        if f.is_file() and emptied == "points":
            np.save(f, np.load(f)[:0])
        elif f.is_file():
            f.write_text("")
    for f in (data_copy / "meta").glob("*.json") if emptied == "labels" else ():
        f.write_text(json.dumps({**json.loads(f.read_text()), "track_ids": [], "lanes": []}))
    code, out = tool("analyze", "--data", data_copy, "--out", tmp_path / "a", "--no-figures", "--bootstrap", "0",
                     "--no-progress")
    assert code == 0 and f"warning: 1.8 m: {named}" in out and f"warning: 0.5 m: {named}" in out, out[-2000:]
    (tmp_path / "pred").mkdir()
    code, out = tool("eval", "--data", data_copy, "--height", "1.8", "--pred", tmp_path / "pred", "--out",
                     tmp_path / "e", "--bootstrap", "0", "--no-extras", "--no-progress")
    assert code == 0 and f"warning: {eval_named} of the 'test' split at 1.8 m" in out, out[-2000:]
