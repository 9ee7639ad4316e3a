"""Model configs as checkpoints written by earlier versions of detbench store them.

A checkpoint stores the `model:` section it was trained with. Some keys of today's YAMLs were
values in code before (the anchor head's loss weights, focal loss and direction bins, the
post-processing selection, the point head's focal loss, SECOND's voxel features in absolute
x, y; PointRCNN's sampling without thinning to voxel cells) and one block was spelled
`pre_top_k / post_top_k` in PillarNet's `post:`.
`upgrade_stored_model_config` turns such a stored section into today's: it renames the old
spelling and fills each key that had a value in code with exactly that value, so the rebuilt
model computes what the checkpoint's model computed.
A section that already holds today's keys comes back unchanged.
"""
from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any

from .stages import ModelConfigError

_POST = {"post.score_threshold": 0.1, "post.pre_nms_top_k": 1000, "post.nms_threshold": 0.1, "post.post_nms_top_k": 100}
_ANCHOR_HEAD = {"head.num_anchor_sizes": 1, "head.num_dir_bins": 2, "head.dir_offset": math.pi / 4,
                "head.focal_alpha": 0.25, "head.focal_gamma": 2.0, "head.loss_weights.cls": 1.0,
                "head.loss_weights.box": 2.0, "head.loss_weights.dir": 0.2, **_POST}

# the voxel features of SECOND's encoder: absolute x, y before `vfe.xy` was a key
_VFE = {"vfe.xy": "absolute"}

# dotted key -> the value the code used when a stored config has no such key
CODE_VALUES: dict[str, dict[str, Any]] = {
    "second": {**_VFE, **_ANCHOR_HEAD},
    "ct3d": {**_VFE, **_ANCHOR_HEAD},
    "pillarnet": {"head.loss_weights.hm": 1.0, "head.loss_weights.reg": 0.25, "head.loss_weights.iou": 1.0,
                  "head.loss_weights.od_iou": 1.0, "post.method": "nms", **_POST, "post.iou_rectifier": 0.68},
    "pointrcnn": {"point_head.focal_alpha": 0.25, "point_head.focal_gamma": 2.0, **_POST,
                  "sampling.voxel_size": 0.0},
}
# dotted key as stored -> today's spelling
RENAMED: dict[str, dict[str, str]] = {
    "pillarnet": {"post.pre_top_k": "post.pre_nms_top_k", "post.post_top_k": "post.post_nms_top_k"},
}


def upgrade_stored_model_config(name: str, model_cfg: dict) -> dict:
    """A copy of the stored `model:` section of a `name` checkpoint in today's keys: old spellings
    renamed, keys that had a value in code filled with that value; ModelConfigError when a section
    holds a key in both spellings."""
    cfg = copy.deepcopy(model_cfg)
    for old, new in RENAMED.get(name, {}).items():
        parent, old_key = _parent(cfg, old)
        if parent is None or old_key not in parent:
            continue
        new_parent, new_key = _parent(cfg, new)
        if new_key in new_parent:
            raise ModelConfigError(f"the stored config of this {name} checkpoint holds both model.{old} and "
                                   f"model.{new}; keep model.{new}")
        new_parent[new_key] = parent.pop(old_key)
    for dotted, value in CODE_VALUES.get(name, {}).items():
        parent, key = _parent(cfg, dotted, create=True)
        if parent is not None and key not in parent:
            parent[key] = value
    return cfg


def upgrade_stored_run_config(name: str, run_cfg: Mapping) -> dict:
    """A copy of a `name` checkpoint's whole stored run config with its `model:` section in today's keys
    (`upgrade_stored_model_config`), so a run started by an earlier version resumes."""
    cfg = dict(run_cfg)
    if isinstance(cfg.get("model"), dict):
        cfg["model"] = upgrade_stored_model_config(name, cfg["model"])
    return cfg


def _parent(cfg: dict, dotted: str, create: bool = False) -> tuple[dict | None, str]:
    """(the mapping that holds the last part of `dotted`, that part); None when a section on the way is
    missing (created empty with `create`) or not a mapping."""
    *path, key = dotted.split(".")
    node = cfg
    for part in path:
        if part not in node and create:
            node[part] = {}
        node = node.get(part)
        if not isinstance(node, dict):
            return None, key
    return node, key
