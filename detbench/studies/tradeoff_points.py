"""The trade study's points: which knobs it turns, by how much, and the config changes of each point.

For each model, from the preset's point, one knob at a time and a few joint points (the list is
in tools/tradeoff.py's help). A point changes the model trained for it (`Point.train`, dotted
overrides under `model:`) or only how the preset's model runs (`Point.infer`: precision,
threads, a test-time point budget, inference-only model keys). Points with the same training
share one training run. The road knob trains the model with the opposite of its config's `road.drop`
(road points removed before voxelising or sampling, or kept; detbench.data.road), the one knob whose
override lies outside `model:`. The width knob scales the channel widths that each model's config lists
under `width_keys` (`detbench.train.run_config.width_keys`); a model that lists none has no width knob.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field

import numpy as np

from detbench.data.regions import RANGES
from detbench.studies.registry import ModelRegistry
from detbench.train.run_config import width_keys

KNOBS = ("voxel", "width", "region", "points", "road", "proposals", "precision", "threads", "joint", "curve")
VOXEL_FACTORS = (0.5, 2.0)
WIDTH_FACTORS = (0.5, 2.0)
REGION_RANGES = ("small", "moderate")  # "large" is the full grid: the preset's point
TEST_POINT_BUDGETS = (16384, 4096)
PROPOSAL_FACTORS = (0.25, 0.5)
ROI_FACTORS = (0.5, 2.0)
NUM_POINTS_FACTORS = (0.5, 2.0)
# one vehicle-sized box: enough for the data-derived config values when only a grid is checked
_PROBE_BOXES = [[20.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0]]


@dataclass
class Point:
    """One point of the sweep. `train`: dotted run-config overrides of the model trained for it ({} =
    the preset's model; keys under `model.`, and `road.drop` for the road knob); `infer`: what changes at
    inference only (precision, threads, subsample [method, points], model {dotted: value})."""

    model: str
    name: str
    knob: str
    value: str
    train: dict = field(default_factory=dict)
    infer: dict = field(default_factory=dict)
    train_factor: float = 1.0  # estimated training cost relative to the preset's
    measure_factor: float = 1.0
    region_range: str | None = None  # region points: the range the shrunk grid models
    tier: int = 0  # planning priority: 0 preset, 1 inference-only, 2 trained, 4 joint (3 is the curve)

    @property
    def id(self) -> str:
        return slug(self.name)

    train_id: str = ""  # the training run's folder: "preset", or the first point trained so + a digest

    @property
    def train_key(self) -> str:
        return json.dumps(self.train, sort_keys=True)


def slug(text: str) -> str:
    """A file-name form of a point's name: "random 16384 points" -> "random_16384_points"."""
    out = "".join(c if c.isalnum() or c in ".-" else "_" for c in text.lower())
    return "_".join(p for p in out.split("_") if p)


def get_dotted(cfg: dict, dotted: str):
    """cfg["a"]["b"] for "a.b", None when a key is missing."""
    node = cfg
    for k in dotted.split("."):
        if not isinstance(node, dict) or k not in node:
            return None
        node = node[k]
    return node


def set_dotted(cfg: dict, dotted: str, value) -> None:
    """cfg["a"]["b"] = value for "a.b", creating the dicts on the way."""
    keys = dotted.split(".")
    node = cfg
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value


def scale_widths(model: str, model_cfg: dict, factor: float) -> dict:
    """{"model.<key>": scaled value} for the model's width keys present in `model_cfg`: every
    integer (nested lists too) times `factor`, rounded, at least 1; CT3D's hidden_dim stays a
    multiple of its attention heads. {} when the model has no width keys."""
    def scale(v):
        if isinstance(v, list):
            return [scale(x) for x in v]
        if isinstance(v, bool) or not isinstance(v, int):
            return v
        return max(1, int(round(v * factor)))

    out = {}
    for key in width_keys(model):
        value = get_dotted(model_cfg, key)
        if value is None:
            continue
        new = scale(value)
        if key == "roi_head.hidden_dim":
            heads = int(get_dotted(model_cfg, "roi_head.heads") or 1)
            new = max(heads, int(round(new / heads)) * heads)
        out[f"model.{key}"] = new
    return out


def _builds(registry: ModelRegistry, model: str, model_cfg: dict) -> bool:
    try:
        cfg = registry.prepare_model_config(model, model_cfg, np.asarray(_PROBE_BOXES, np.float32))
        registry.build_model(model, cfg)
    except ValueError:
        return False
    return True


def fit_range(model: str, model_cfg: dict, x_max: float, y_half: float, *, registry: ModelRegistry) -> list[float]:
    """The smallest point-cloud range [x0, -y, z0, x1, y, z1] with x1 >= `x_max` and y >= `y_half`
    (metres; x0, z0, z1 as the config's) on which the model builds: a whole number of voxels
    that divides by the network's strides (tried as multiples of voxel x 2^k). Raises
    ValueError when none up to 2^7 voxels does."""
    pcr = [float(v) for v in model_cfg["point_cloud_range"]]
    vs = model_cfg.get("voxel_size")
    if not vs:  # a point-based model: no grid to fit
        cand = [pcr[0], -round(y_half, 6), pcr[2], round(x_max, 6), round(y_half, 6), pcr[5]]
        if _builds(registry, model, {**model_cfg, "point_cloud_range": cand}):
            return cand
        return _no_fit(model, x_max, y_half)
    for k in range(8):
        sx, sy = float(vs[0]) * 2 ** k, float(vs[1]) * 2 ** k
        x1 = pcr[0] + math.ceil((x_max - pcr[0]) / sx - 1e-6) * sx
        half = math.ceil(2 * y_half / sy - 1e-6) * sy / 2
        cand = [pcr[0], -round(half, 6), pcr[2], round(x1, 6), round(half, 6), pcr[5]]
        if _builds(registry, model, {**model_cfg, "point_cloud_range": cand}):
            return cand
    return _no_fit(model, x_max, y_half)


def _no_fit(model, x_max, y_half):
    raise ValueError(f"{model}: no point-cloud range with x up to >= {x_max:g} m and |y| >= {y_half:g} m builds "
                     f"with this voxel size; change the knob's values in detbench/studies/tradeoff_points.py")


def sweep_points(model: str, model_cfg: dict, knobs, device: str, cores: int, default_threads: int, *,
                 registry: ModelRegistry, road_drop: bool = False) -> list[Point]:
    """The points of one model's sweep, from its preset `model:` config section and its `road.drop`."""
    pts = [Point(model, "preset", "preset", "the preset's settings")]
    mc = model_cfg
    pcr = [float(v) for v in mc["point_cloud_range"]]
    vs = mc.get("voxel_size")
    margin_x = max(0.0, pcr[3] - RANGES["large"][1])
    margin_y = max(0.0, pcr[4] - RANGES["large"][2])
    is_two_stage = isinstance(get_dotted(mc, "roi_head.proposals"), dict)
    num_points = get_dotted(mc, "sampling.num_points")

    def voxel_over(f: float) -> dict:
        new_vs = [round(float(vs[0]) * f, 6), round(float(vs[1]) * f, 6), float(vs[2])]
        over = {"model.voxel_size": new_vs}
        cfg = {**mc, "voxel_size": new_vs}
        if not _builds(registry, model, cfg):
            over["model.point_cloud_range"] = fit_range(model, cfg, pcr[3], pcr[4], registry=registry)
        return over

    if "voxel" in knobs and vs:
        for f in VOXEL_FACTORS:
            pts.append(Point(model, f"voxel x{f:g}", "voxel", f"{float(vs[0]) * f:g} x {float(vs[1]) * f:g} m",
                             voxel_over(f), train_factor=1 / f ** 2, tier=2))
    if "width" in knobs and width_keys(model):
        for f in WIDTH_FACTORS:
            pts.append(Point(model, f"width x{f:g}", "width", f"channels x{f:g}", scale_widths(model, mc, f),
                             train_factor=f ** 2, tier=2))
    region_over = {}
    if "region" in knobs or "joint" in knobs:
        for r in REGION_RANGES:
            _, x1, y = RANGES[r]
            fitted = fit_range(model, mc, x1 + margin_x, y + margin_y, registry=registry)
            region_over[r] = (fitted, (fitted[3] - fitted[0]) * (fitted[4] - fitted[1])
                              / ((pcr[3] - pcr[0]) * (pcr[4] - pcr[1])))
    if "region" in knobs:
        for r in REGION_RANGES:
            fitted, area = region_over[r]
            _, x1, y = RANGES[r]
            pts.append(Point(model, f"region {r}", "region", f"x <= {x1:g} m, |y| <= {y:g} m (grid x to {fitted[3]:g}, "
                             f"|y| to {fitted[4]:g} m)", {"model.point_cloud_range": fitted},
                             train_factor=max(area, 0.05), region_range=r, tier=2))
    if "points" in knobs:
        for method in ("random", "fps"):
            for n in TEST_POINT_BUDGETS:
                pts.append(Point(model, f"{method} {n} points", "points", f"{n} points per frame ({method}, test time)",
                                 infer={"subsample": [method, n]}, measure_factor=1.2 if method == "fps" else 1.0,
                                 tier=1))
        if num_points:
            for f in NUM_POINTS_FACTORS:
                n = max(64, int(round(num_points * f)))
                pts.append(Point(model, f"sampled points x{f:g}", "points", f"{n} sampled points per frame (trained)",
                                 {"model.sampling.num_points": n}, train_factor=f, tier=2))
    if "road" in knobs:
        drop = not road_drop
        pts.append(Point(model, "road dropped" if drop else "road kept", "road",
                         "road points removed before the model (trained)" if drop
                         else "road points kept in the model's input (trained)",
                         {"road.drop": drop}, train_factor=0.5 if drop else 2.0, tier=2))
    if "proposals" in knobs and is_two_stage:
        test_k = int(get_dotted(mc, "roi_head.proposals.test.post_nms_top_k"))
        for f in PROPOSAL_FACTORS:
            k = max(1, int(round(test_k * f)))
            pts.append(Point(model, f"test proposals x{f:g}", "proposals", f"{k} proposals refined (test time)",
                             infer={"model": {"roi_head.proposals.test.post_nms_top_k": k}}, tier=1))
        rois = int(get_dotted(mc, "roi_head.targets.roi_per_image"))
        for f in ROI_FACTORS:
            k = max(2, int(round(rois * f)))
            pts.append(Point(model, f"training rois x{f:g}", "proposals", f"{k} training RoIs per frame (trained)",
                             {"model.roi_head.targets.roi_per_image": k}, tier=2))
    if "precision" in knobs:
        for prec in (("fp16", "bf16") if device.startswith("cuda") else ("bf16",)):
            pts.append(Point(model, prec, "precision", {"bf16": "bfloat16 autocast", "fp16": "float16 autocast"}[prec],
                             infer={"precision": prec}, measure_factor=1.5, tier=1))
    if "threads" in knobs:
        counts = sorted({2 ** k for k in range(8) if 2 ** k <= cores} | {cores})
        for n in counts:
            if n != default_threads:
                pts.append(Point(model, f"{n} threads", "threads", f"{n} torch / numba threads", infer={"threads": n},
                                 tier=1))
    if "joint" in knobs:
        fast = dict(scale_widths(model, mc, 0.5))
        if vs:
            fast.update(voxel_over(2.0))
        elif num_points:
            fast["model.sampling.num_points"] = max(64, int(round(num_points * 0.5)))
        if fast:
            pts.append(Point(model, "fast", "joint", "voxel x2 (or sampled points x0.5) + width x0.5", fast,
                             train_factor=0.25 * 0.25, tier=4))
            pts.append(Point(model, "fast + bf16", "joint", "fast, run in bfloat16", fast,
                             infer={"precision": "bf16"}, train_factor=0.25 * 0.25, measure_factor=1.5, tier=4))
        fitted, area = region_over["small"]
        near = {"model.point_cloud_range": fitted}
        if vs:
            fine_vs = [round(float(vs[0]) * 0.5, 6), round(float(vs[1]) * 0.5, 6), float(vs[2])]
            near["model.voxel_size"] = fine_vs
            near["model.point_cloud_range"] = fit_range(model, {**mc, "voxel_size": fine_vs},
                                                        RANGES["small"][1] + margin_x, RANGES["small"][2] + margin_y,
                                                        registry=registry)
        elif num_points:
            near["model.sampling.num_points"] = int(num_points * 2)
        pts.append(Point(model, "near field", "joint", "small region + voxel x0.5 (or sampled points x2)", near,
                         train_factor=max(area, 0.05) * 4, region_range="small", tier=4))
        pts.append(Point(model, "bf16 + random 16384 points", "joint", "bfloat16 and 16384 random points (test time)",
                         infer={"precision": "bf16", "subsample": ["random", 16384]}, measure_factor=1.5, tier=4))
    seen, runs = set(), {}
    for p in pts:
        if p.id in seen:
            raise AssertionError(f"two points of {model} named {p.name!r}")
        seen.add(p.id)
        digest = hashlib.sha1(p.train_key.encode()).hexdigest()[:6]
        p.train_id = runs.setdefault(p.train_key, "preset" if not p.train else f"{p.id}-{digest}")
    return pts



__all__ = ["KNOBS", "Point", "fit_range", "get_dotted", "scale_widths", "set_dotted", "slug",
           "sweep_points"]
