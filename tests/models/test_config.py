"""The typed model configs: every key read from the YAML, checked by what it means, no value in code, one
spelling per key; the upgrade of a config stored by an earlier version; the evaluator's threshold floor."""
from __future__ import annotations

import ast
import copy
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import models
from detbench.config import ConfigError, load_config
from detbench.train.run_config import load_run_config, preset_names
from models.stages import ModelConfigError
from tests.helpers import ROOT
from tests.models.test_golden import TRAIN_BOXES, golden_batch, golden_model

NAMES = sorted(models.REGISTRY)
STORED = json.loads((Path(__file__).parent / "expected" / "stored_model_configs.json").read_text())


def smoke(name: str) -> dict:
    return load_run_config(name, "smoke")["model"]


@pytest.mark.parametrize("preset", [None, *preset_names()])
@pytest.mark.parametrize("name", NAMES)
def test_every_model_and_preset_config_reads_completely(name, preset):
    """Each model's YAML at each preset reads into its typed config, every key taken (an unread key is an
    error), and the evaluator keeps at least the model's score threshold."""
    cfg = load_run_config(name, preset)
    typed = models.check_model_config(cfg["model"])
    assert isinstance(typed, models.REGISTRY[name].CONFIG)
    assert cfg["eval"]["score_threshold"] >= cfg["model"]["post"]["score_threshold"]


@pytest.mark.parametrize("name", NAMES)
def test_a_missing_key_is_named_with_its_file(name):
    cfg = smoke(name)
    section = "head" if "head" in cfg else "point_head"
    key = sorted(k for k, v in cfg[section].items() if not isinstance(v, dict))[0]
    del cfg[section][key]
    with pytest.raises(ModelConfigError, match=rf"^configs/{name}\.yaml: model\.{section}\.{key} is missing"):
        models.build_model(name, cfg)
    with pytest.raises(ModelConfigError, match=rf"^my\.yaml: model\.{section}\.{key} is missing"):
        models.check_model_config(cfg, where="my.yaml")


@pytest.mark.parametrize("name", NAMES)
def test_an_unknown_key_is_an_error_with_the_closest_known_one(name):
    cfg = smoke(name)
    cfg["post"]["score_treshold"] = 0.2
    with pytest.raises(ModelConfigError, match=rf"configs/{name}\.yaml: unknown key model\.post\.score_treshold; "
                                               r"did you mean 'score_threshold'\?"):
        models.build_model(name, cfg)


@pytest.mark.parametrize("name, key, value, need", [
    ("ct3d", "roi_head.targets.fg_ratio", 1.5, "a share in [0, 1]"),
    ("ct3d", "roi_head.dropout", -0.1, "a probability in [0, 1]"),
    ("ct3d", "roi_head.radius_scale", 0.0, "a positive scale"),
    ("ct3d", "roi_head.heads", 3, "a divisor of hidden_dim (16)"),
    ("ct3d", "roi_head.proposals.test.nms_threshold", 1.2, "an IoU in [0, 1]"),
    ("ct3d", "roi_head.targets.roi_per_image", -1, "an integer >= 0"),
    ("second", "head.dir_offset", math.nan, "finite"),
    ("second", "head.loss_weights.box", -2.0, "a number >= 0"),
    ("second", "head.num_dir_bins", 0, "an integer >= 1"),
    ("pillarnet", "head.min_overlap", 1.0, "an IoU in (0, 1)"),
    ("pillarnet", "post.iou_rectifier", 1.5, "an exponent in [0, 1]"),
    ("pillarnet", "encoder.blocks", [1, 1, 1], "made of integers >= 0, a list of 5"),
    ("pointrcnn", "sampling.far_threshold", -5.0, "a distance >= 0 in metres"),
    ("pointrcnn", "point_head.bin.loc_scope", 0.0, "a positive number of metres"),
    ("pointrcnn", "roi_head.sa_radii", [0.8, -1.0], "a non-empty list of positive radii in metres"),
    ("pointrcnn", "backbone.mlps", [[[8, 0], [8, 16]], [[16, 32], [16, 32]]],
     "a non-empty list of non-empty lists of non-empty lists of integers >= 1"),
])
def test_values_are_checked_by_what_they_mean(name, key, value, need):
    cfg = smoke(name)
    *path, last = key.split(".")
    node = cfg
    for part in path:
        node = node[part]
    node[last] = value
    with pytest.raises(ModelConfigError, match=re.escape(f"model.{key} must be {need}")):
        models.check_model_config(cfg)


@pytest.mark.parametrize("name, key, value", [
    ("second", "head.focal_gamma", 3.0),  # an exponent, not a fraction
    ("pointrcnn", "point_head.fg_bottom_lift", 1.5),  # metres, not a fraction
    ("second", "head.dir_offset", -2.5),  # an angle
    ("ct3d", "roi_head.enc_layers", 0),  # no encoder layer
    ("pointrcnn", "point_head.cls_fc", []),  # a linear branch
])
def test_values_in_their_range_pass(name, key, value):
    cfg = smoke(name)
    *path, last = key.split(".")
    node = cfg
    for part in path:
        node = node[part]
    node[last] = value
    models.check_model_config(cfg)


def test_the_neighbouring_thresholds_keep_their_order():
    cfg = smoke("second")
    cfg["head"]["pos_iou"] = 0.3
    with pytest.raises(ModelConfigError, match=r"model\.head\.neg_iou \(0\.45\) must not exceed model\.head\.pos_iou"):
        models.check_model_config(cfg)
    cfg = smoke("ct3d")
    cfg["roi_head"]["targets"]["cls_bg_thresh_lo"] = 0.5
    with pytest.raises(ModelConfigError, match=r"cls_bg_thresh_lo \(0\.5\) must not exceed .*cls_bg_thresh \(0\.25\)"):
        models.check_model_config(cfg)


def test_one_spelling_of_the_post_processing_keys():
    """Every model's `post:` block holds the same four selection keys, and the other spelling is refused
    with a pointer to this one."""
    for name in NAMES:
        assert {"score_threshold", "pre_nms_top_k", "nms_threshold", "post_nms_top_k"} <= set(smoke(name)["post"])
    for path in (ROOT / "configs").glob("*.yaml"):
        assert "pre_top_k" not in path.read_text() and "post_top_k" not in path.read_text(), path
    with pytest.raises(ConfigError, match="pre_nms_top_k"):
        load_run_config("pillarnet", "smoke", overrides=["model.post.pre_top_k=500"])


def _yaml_keys(node, out: set[str]) -> set[str]:
    if isinstance(node, dict):
        for k, v in node.items():
            out.add(str(k))
            _yaml_keys(v, out)
    return out


def _literal(node) -> bool:
    """A value written in the source: a constant (not None), a container of them, math.pi and the like."""
    if isinstance(node, ast.Constant):
        return node.value is not None
    if isinstance(node, (ast.Tuple, ast.List)):
        return all(_literal(e) for e in node.elts)
    if isinstance(node, ast.Dict):
        return True
    if isinstance(node, ast.UnaryOp):
        return _literal(node.operand)
    if isinstance(node, ast.BinOp):
        return _literal(node.left) and _literal(node.right)
    return isinstance(node, ast.Attribute) and ast.unparse(node).startswith("math.")


def test_no_value_of_a_model_key_is_written_in_code():
    """The model YAMLs are the one home of every model key: no function parameter, dataclass field or module
    constant under models/ named like a key of a model's `model:` section gives it a literal value."""
    keys: set[str] = set()
    for name in NAMES:
        _yaml_keys(load_config(f"{name}.yaml")["model"], keys)
    keys -= {"name"}
    bad = []
    for path in sorted((ROOT / "models").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "models/stored_config.py":  # the values earlier versions used, for stored configs
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                a = node.args
                pos = a.posonlyargs + a.args
                pairs = list(zip(pos[len(pos) - len(a.defaults):], a.defaults)) + list(zip(a.kwonlyargs, a.kw_defaults))
                bad += [f"{rel}:{node.lineno}: {arg.arg}={ast.unparse(d)}" for arg, d in pairs
                        if arg.arg in keys and d is not None and _literal(d)]
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.value is not None \
                    and node.target.id in keys and _literal(node.value):
                bad.append(f"{rel}:{node.lineno}: {node.target.id} = {ast.unparse(node.value)}")
            elif isinstance(node, ast.Call) and ast.unparse(node.func).endswith((".get", "setdefault")) \
                    and len(node.args) == 2 and isinstance(node.args[0], ast.Constant) and node.args[0].value in keys:
                bad.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
    assert not bad, "values of model keys written in code (give them in configs/<model>.yaml):\n" + "\n".join(bad)


# ---------------------------------------------------------------- configs stored by an earlier version
@pytest.mark.parametrize("name", NAMES)
def test_a_stored_config_upgrades_to_todays(name):
    """The model config a checkpoint stored before the model keys moved into the YAMLs (old spelling, no
    loss weights, focal or direction keys) upgrades to exactly today's config of the same run, with the
    voxel features that checkpoint trained on (absolute x, y) where today's YAML takes offsets."""
    stored = STORED[name]
    today = models.prepare_model_config(name, smoke(name), TRAIN_BOXES)
    assert stored != today
    then = copy.deepcopy(today)
    if "vfe" in then:
        assert then["vfe"] == {"xy": "offset"} and "vfe" not in stored
        then["vfe"]["xy"] = "absolute"
    assert models.upgrade_stored_model_config(name, stored) == then
    assert models.upgrade_stored_model_config(name, today) == today  # today's config is left as it is
    if name == "pillarnet":
        assert "pre_top_k" in stored["post"] and "pre_top_k" not in today["post"]


def test_a_section_with_both_spellings_is_refused():
    stored = copy.deepcopy(STORED["pillarnet"])
    stored["post"]["pre_nms_top_k"] = 500
    with pytest.raises(ModelConfigError, match="both model.post.pre_top_k and model.post.pre_nms_top_k"):
        models.upgrade_stored_model_config("pillarnet", stored)


@pytest.mark.parametrize("name", NAMES)
def test_a_checkpoint_with_a_stored_config_of_an_earlier_version_loads(name, tmp_path):
    """load_from_checkpoint rebuilds the model from a checkpoint whose config holds the earlier keys, and
    the rebuilt model predicts what the saved one does."""
    from detbench.train.checkpoint import TrainState, save_checkpoint

    model = models.build_model(name, models.upgrade_stored_model_config(name, STORED[name]))  # as built then
    model.load_state_dict(golden_model(name).state_dict())
    model.eval()
    run_cfg = load_run_config(name, "smoke")
    run_cfg["model"] = STORED[name]
    path = save_checkpoint(tmp_path / "epoch_001.pt", model=model, state=TrainState(), config=run_cfg,
                           data={"source": str(tmp_path), "height": 1.8}, model_name=name)
    loaded, ck = models.load_from_checkpoint(path)
    assert ck["config"]["model"] == STORED[name]  # the stored config itself is not rewritten
    batch = golden_batch()
    with torch.no_grad():
        want = model.eval().predict(model(batch), batch)
        got = loaded.predict(loaded(batch), batch)
    assert all(torch.equal(a.boxes, b.boxes) and torch.equal(a.scores, b.scores) for a, b in zip(want, got))
    assert sum(d.scores.numel() for d in got) > 0


# ---------------------------------------------------------------- the evaluator's threshold floor
def test_the_evaluator_threshold_may_not_undercut_the_models():
    with pytest.raises(ConfigError, match=r"^eval\.score_threshold 0\.05 is below model\.post\.score_threshold 0\.1, "
                                          r"under which the model keeps no box; set model\.post\.score_threshold "
                                          r"to 0\.05 as well, or use eval\.score_threshold 0\.1 or above$"):
        load_run_config("second", "smoke", overrides=["eval.score_threshold=0.05"])
    cfg = load_run_config("second", "smoke", overrides=["eval.score_threshold=0.05", "model.post.score_threshold=0.05"])
    assert cfg["eval"]["score_threshold"] == 0.05
    higher = load_run_config("pillarnet", "smoke", overrides=["eval.score_threshold=0.3"])
    assert higher["eval"]["score_threshold"] == 0.3


def test_yaml_comments_carry_no_measured_figures():
    """Model YAMLs say what a setting does and point to the results docs for what it measured."""
    for name in [*NAMES, "presets/cpu"]:
        text = (ROOT / "configs" / f"{name}.yaml").read_text()
        comments = "\n".join(line.split("#", 1)[1] for line in text.splitlines() if "#" in line)
        found = re.findall(r"AP@R40[^.;\n]*\d\.\d\d|\d+(?:\.\d+)? ?ms\b|\d+(?:\.\d+)?x faster|\d+(?:-\d+)? min\b"
                           r"|\d+(?:\.\d+)? ?s per epoch", comments)
        assert not found, f"configs/{name}.yaml: measured figures in comments: {found}"
    assert yaml.safe_load((ROOT / "configs" / "presets" / "cpu.yaml").read_text())  # still a valid file


def test_train_boxes_size_the_anchors():
    """prepare_model_config's auto values come from the training boxes, after the check."""
    cfg = models.prepare_model_config("second", smoke("second"), TRAIN_BOXES)
    assert np.allclose(cfg["head"]["anchor_sizes"][0], TRAIN_BOXES[:, 3:6].mean(axis=0), atol=1e-3)
