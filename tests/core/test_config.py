"""Config loading/validation, atomic writes and the Frame/Sensor types."""
import json
import os

import numpy as np
import pytest

from detbench import config as C
from detbench.data.frame import Frame, Sensor, height_key
from detbench.utils import atomic
from tests.helpers import ROOT


def write(p, text):
    p.write_text(text)
    return p


def test_base_inheritance_and_overrides(tmp_path):
    write(tmp_path / "base.yaml", "model:\n  name: second\n  width: 64\ntrain:\n  lr: 0.001\n  epochs: 10\n")
    write(tmp_path / "child.yaml", "_base_: base.yaml\nmodel:\n  width: 32\n")
    cfg = C.load_config(tmp_path / "child.yaml")
    assert cfg == {"model": {"name": "second", "width": 32}, "train": {"lr": 0.001, "epochs": 10}}
    ref = C.load_config(tmp_path / "base.yaml")
    out = C.apply_overrides(cfg, ["train.lr=3e-3", "model.name=pillarnet"], reference=ref)
    assert out["train"]["lr"] == pytest.approx(3e-3) and out["model"]["name"] == "pillarnet"
    assert cfg["train"]["lr"] == 0.001  # the input is not modified


def test_unknown_key_names_closest(tmp_path):
    ref = {"train": {"epochs": 1, "lr": 0.1}}
    with pytest.raises(C.ConfigError, match=r"'train.epoch'.*did you mean 'epochs'"):
        C.validate({"train": {"epoch": 3}}, ref, where="my.yaml")
    with pytest.raises(C.ConfigError, match=r"--set tran.lr=1.*did you mean 'train'"):
        C.apply_overrides({}, ["tran.lr=1"], reference=ref)
    C.validate({"train": {"lr": 0.2}}, ref)  # known keys pass


def test_base_cycle_and_bad_yaml(tmp_path):
    write(tmp_path / "a.yaml", "_base_: b.yaml\n")
    write(tmp_path / "b.yaml", "_base_: a.yaml\n")
    with pytest.raises(C.ConfigError, match="cycle"):
        C.load_config(tmp_path / "a.yaml")
    write(tmp_path / "bad.yaml", "a: [1, 2\n")
    with pytest.raises(C.ConfigError, match="bad.yaml: not valid YAML"):
        C.load_config(tmp_path / "bad.yaml")
    with pytest.raises(C.ConfigError, match="not found"):
        C.load_config(tmp_path / "missing.yaml")
    with pytest.raises(C.ConfigError, match="key.sub=value"):
        C.apply_overrides({}, ["novalue"])


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "report.json"
    atomic.atomic_write_json(target, {"a": 1, "nan": float("nan"), "arr": np.arange(3)})
    assert json.loads(target.read_text()) == {"a": 1, "nan": None, "arr": [0, 1, 2]}

    def failing_writer(p):
        p.write_text("partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic.atomic_save(target, failing_writer)
    assert json.loads(target.read_text())["a"] == 1
    assert [f for f in os.listdir(tmp_path) if f.startswith(".tmp")] == []


def test_read_json_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        atomic.read_json(tmp_path / "nope.json")
    write(tmp_path / "broken.json", "{\"a\": ")
    with pytest.raises(ValueError, match="broken.json: not valid JSON"):
        atomic.read_json(tmp_path / "broken.json")


def test_height_key():
    assert [height_key(h) for h in (0.5, 1, 1.8, 0.25, 2.0)] == ["0.5", "1.0", "1.8", "0.25", "2.0"]
    for bad in (0, -1, float("nan")):
        with pytest.raises(ValueError):
            height_key(bad)


def _frame(points, boxes):
    m = len(boxes)
    return Frame("0000_000", "0000", points, boxes, np.array(["car"] * m), np.arange(m), np.zeros(m, np.int64),
                 Sensor(height=1.8))


def test_frame_check():
    good = _frame(np.zeros((3, 4), np.float32), np.array([[10, 0, 0.75, 4.5, 1.8, 1.5, 0]], np.float32))
    good.check()
    with pytest.raises(ValueError, match="float32"):
        _frame(np.zeros((3, 4), np.float64), good.boxes).check()
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        _frame(np.zeros((3, 3), np.float32), good.boxes).check()
    nan_pts = np.zeros((3, 4), np.float32)
    nan_pts[1, 2] = np.nan
    with pytest.raises(ValueError, match="1 point"):
        _frame(nan_pts, good.boxes).check(where="x.npy")
    neg = good.boxes.copy()
    neg[0, 3] = -1
    with pytest.raises(ValueError, match="negative sizes"):
        _frame(good.points, neg).check()


def test_sensor_roundtrip():
    s = Sensor(height=1.8, pitch_deg=2.5, vfov_deg=(-15.0, 10.0), name="h3-1.8")
    assert Sensor.from_dict(s.to_dict()) == s
    with pytest.raises(ValueError, match="unknown sensor field"):
        Sensor.from_dict({**s.to_dict(), "colour": "red"})


def test_atomic_write_uses_normal_file_mode(tmp_path):
    target = atomic.atomic_write_text(tmp_path / "r.md", "x")
    mask = os.umask(0)
    os.umask(mask)
    assert (target.stat().st_mode & 0o777) == (0o666 & ~mask)


def test_typed_configs_read_their_defaults_from_default_yaml():
    """configs/default.yaml is the one home of the defaults: the typed configs name exactly its keys and,
    given nothing, hold its values (fails when the YAML and a dataclass disagree)."""
    import math
    from dataclasses import fields

    from detbench.data.augment import AUGMENT_DEFAULTS, AugmentConfig
    from detbench.data.gt_database import GT_SAMPLING_DEFAULTS, GTSamplingConfig
    from detbench.sim.dataset import DATA_DEFAULTS
    from detbench.train.train_config import TRAIN_DEFAULTS, TrainConfig

    shipped = C.load_config(C.CONFIG_DIR / "default.yaml")
    aug_yaml = shipped["augment"]
    assert (TRAIN_DEFAULTS, AUGMENT_DEFAULTS, GT_SAMPLING_DEFAULTS, DATA_DEFAULTS) == \
        (shipped["train"], aug_yaml, aug_yaml["gt_sampling"], shipped["data"])

    def as_field(v):
        return tuple(v) if isinstance(v, list) else v

    train = TrainConfig.from_dict({})
    assert [f.name for f in fields(TrainConfig)] == list(shipped["train"])
    assert {k: getattr(train, k) for k in shipped["train"]} == {k: as_field(v) for k, v in shipped["train"].items()}

    aug = AugmentConfig.from_dict({})
    assert [f.name for f in fields(GTSamplingConfig)] == list(aug_yaml["gt_sampling"])
    assert {k: getattr(aug.gt_sampling, k) for k in aug_yaml["gt_sampling"]} == \
        {k: as_field(v) for k, v in aug_yaml["gt_sampling"].items()}
    flip, rot, scl = (aug_yaml[k] for k in ("random_world_flip", "random_world_rotation", "random_world_scaling"))
    assert set(aug_yaml) == {"random_world_flip", "random_world_rotation", "random_world_scaling", "gt_sampling"}
    assert (set(flip), set(rot), set(scl)) == ({"enabled", "probability"}, {"enabled", "world_rot_angle_deg"},
                                               {"enabled", "world_scale_range"})
    assert (aug.flip, aug.flip_probability) == (flip["enabled"], flip["probability"])
    assert (aug.rotation, aug.rotation_range) == (rot["enabled"],
                                                  tuple(math.radians(d) for d in rot["world_rot_angle_deg"]))
    assert (aug.scaling, aug.scale_range) == (scl["enabled"], tuple(scl["world_scale_range"]))
    none = AugmentConfig.none()
    assert not (none.flip or none.rotation or none.scaling or none.gt_sampling.enabled)

    # keys read one at a time: signatures take None for them and resolve here, argparse defaults too
    from detbench.data.layout import SceneRule
    from detbench.eval.evaluate import EVAL_DEFAULTS, evaluate

    assert EVAL_DEFAULTS == shipped["eval"]
    for dotted in RESOLVED_DEFAULTS.values():
        section, key = dotted.split(".")
        assert C.shipped_default(dotted) == shipped[section][key] and C.shipped_default(dotted, 0.25) == 0.25
    assert SceneRule("block").frames_per_scene == shipped["data"]["frames_per_scene"]
    rep = evaluate([])
    assert (rep["iou_threshold"], rep["score_threshold"]) == \
        (shipped["eval"]["iou_threshold"], shipped["eval"]["score_threshold"])
    with pytest.raises(KeyError, match="eval.iou_treshold"):
        C.shipped_default("eval.iou_treshold")


# parameter name -> its key in configs/default.yaml; `(option, key)` of the tools' argparse defaults follow
RESOLVED_DEFAULTS = {"iou_threshold": "eval.iou_threshold", "score_threshold": "eval.score_threshold",
                     "test_fraction": "data.test_fraction", "frames_per_scene": "data.frames_per_scene"}


def _literal(node) -> bool:
    """A number written in the source: 0.7, -1, 1 / 3."""
    import ast

    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float)) and not isinstance(node.value, bool)
    if isinstance(node, ast.UnaryOp):
        return _literal(node.operand)
    return isinstance(node, ast.BinOp) and _literal(node.left) and _literal(node.right)


def test_no_literal_defaults_for_the_keys_of_default_yaml():
    """The evaluator's thresholds, test_fraction and frames_per_scene have their defaults only in
    configs/default.yaml: no function signature, dataclass field or argparse option of detbench/ or tools/
    writes one as a number (models/ is left out: its post-processing thresholds are the detectors' own
    model.post keys, whose home is the model YAMLs)."""
    import ast

    options = {"--" + name.replace("_", "-") for name in RESOLVED_DEFAULTS}
    bad = []
    for path in sorted([*(ROOT / "detbench").rglob("*.py"), *(ROOT / "tools").rglob("*.py")]):
        rel = path.relative_to(ROOT).as_posix()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                a = node.args
                pairs = list(zip(a.posonlyargs + a.args, [None] * (len(a.posonlyargs + a.args) - len(a.defaults))
                                 + a.defaults)) + list(zip(a.kwonlyargs, a.kw_defaults))
                bad += [f"{rel}:{node.lineno}: {arg.arg}={ast.unparse(d)}" for arg, d in pairs
                        if arg.arg in RESOLVED_DEFAULTS and d is not None and _literal(d)]
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) \
                    and node.target.id in RESOLVED_DEFAULTS and node.value is not None and _literal(node.value):
                bad.append(f"{rel}:{node.lineno}: {node.target.id} = {ast.unparse(node.value)}")
            elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument" and node.args \
                    and isinstance(node.args[0], ast.Constant) and node.args[0].value in options:
                bad += [f"{rel}:{node.lineno}: {node.args[0].value} default={ast.unparse(k.value)}"
                        for k in node.keywords if k.arg == "default" and _literal(k.value)]
    assert not bad, "literal defaults of keys whose home is configs/default.yaml (take None and use " \
                    "detbench.config.shipped_default):\n" + "\n".join(bad)


def test_pyproject_lists_every_package_and_ships_the_configs():
    """pyproject.toml lists its packages by hand (configs/ is mapped to detbench.configs): none may be missed."""
    tomllib = pytest.importorskip("tomllib")

    setup = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for top in ("detbench", "models")
               for p in (ROOT / top).rglob("__init__.py")}
    assert set(setup["packages"]) == on_disk | {"detbench.configs"}
    assert setup["package-dir"] == {"detbench.configs": "configs"}
    shipped = {p.relative_to(ROOT / "configs").as_posix() for p in (ROOT / "configs").rglob("*.yaml")}
    globs = setup["package-data"]["detbench.configs"]
    assert shipped == {p.relative_to(ROOT / "configs").as_posix() for g in globs for p in (ROOT / "configs").glob(g)}


@pytest.mark.slow
def test_wheel_ships_the_configs_and_every_module(tmp_path):
    """A wheel built from the source holds detbench/configs (default.yaml, presets/*.yaml, one YAML per
    model) and every module of detbench and models, so an installed detbench runs without the checkout.
    Built offline from a copy of the sources, so the checkout gets no build/ or egg-info."""
    pytest.importorskip("setuptools")
    import shutil
    import subprocess
    import sys
    import zipfile

    from models import REGISTRY

    src = tmp_path / "src"
    for name in ("detbench", "models", "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-q", "-w", str(tmp_path / "dist"), str(src)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("detbench-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = {"detbench/configs/default.yaml"} | {f"detbench/configs/{m}.yaml" for m in REGISTRY}
    configs |= {f"detbench/configs/presets/{p.name}" for p in (ROOT / "configs" / "presets").glob("*.yaml")}
    assert len(configs) > 5 and configs <= names, sorted(configs - names)
    modules = {p.relative_to(ROOT).as_posix() for top in ("detbench", "models") for p in (ROOT / top).rglob("*.py")}
    assert modules <= names, sorted(modules - names)


def test_a_config_names_its_detector_by_file_name_base_or_model_name(tmp_path):
    from detbench.train.run_config import load_run_config, width_keys

    assert C.model_name_of("ct3d.yaml") == "ct3d" and C.model_name_of("default.yaml") is None
    write(tmp_path / "mine.yaml", "_base_: ct3d.yaml\ntrain:\n  lr: 0.001\n")
    cfg = load_run_config(config=tmp_path / "mine.yaml")
    assert cfg["model"]["name"] == "ct3d" and list(cfg["model"])[0] == "name" and cfg["train"]["lr"] == 0.001
    write(tmp_path / "named.yaml", "_base_: second.yaml\nmodel:\n  name: other\n")
    assert load_run_config(config=tmp_path / "named.yaml")["model"]["name"] == "other"
    write(tmp_path / "none.yaml", "model:\n  voxel_size: [0.1, 0.1, 0.1]\n")
    with pytest.raises(C.ConfigError, match="names no detector"):
        load_run_config(config=tmp_path / "none.yaml")
    with pytest.raises(C.ConfigError, match="width_keys"):
        width_keys("default")
