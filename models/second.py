"""SECOND (Yan, Mao and Li, "SECOND: Sparsely Embedded Convolutional Detection", 2018).

The model is the composition of shared stages, read top to bottom:

  points (P, 5) --MeanVFE--> sparse voxels --SparseBackbone8x--> sparse 8x
  --HeightCompression--> BEV (B, C*D, H, W) --BEVBackbone--> BEV features
  --AnchorHead--> class / box / direction logits --> loss | Detections

`SECONDStages` holds that chain; `SECOND` is the detector made of it alone, and CT3D uses
it as its first stage.

Configuration: configs/second.yaml (`model:` section), read by `SECONDConfig`. Anchor sizes
come from the data (`anchor_sizes: auto` is resolved by tools/train.py from the training split
before the model is built, and the resolved sizes are stored in the checkpoint's config).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn

from detbench.data.batch import Batch, Detections

from .stages import (
    AnchorHead, AnchorHeadConfig, AnchorHeadOutput, BEVBackbone, BEVBackboneConfig, HeightCompression, MeanVFE,
    PostConfig, Section, SparseBackbone8x, SparseBackboneConfig, StageConfig, VFEConfig, VoxelGrid,
)


@dataclass(frozen=True)
class SECONDConfig(StageConfig):
    """SECOND's `model:` section (configs/second.yaml); CT3D's first stage reads the same keys."""

    grid: VoxelGrid  # point_cloud_range and voxel_size
    vfe: VFEConfig
    backbone3d: SparseBackboneConfig
    backbone2d: BEVBackboneConfig
    head: AnchorHeadConfig
    post: PostConfig

    @classmethod
    def read(cls, s: Section) -> SECONDConfig:
        s.skip("name")  # the registry's key, configs/<name>.yaml
        return cls(grid=VoxelGrid.read(s), vfe=s.section("vfe", VFEConfig),
                   backbone3d=s.section("backbone3d", SparseBackboneConfig),
                   backbone2d=s.section("backbone2d", BEVBackboneConfig), head=s.section("head", AnchorHeadConfig),
                   post=s.section("post", PostConfig))


class SECONDStages:
    """SECOND's network: its stage modules and the forward / loss / predict that chain them.

    A plain holder, not an `nn.Module`: the detector that uses it registers its modules under
    `MODULES`' names (`attach`), so SECOND and a model with SECOND as its first stage (CT3D)
    name their weights alike and a SECOND checkpoint initialises that first stage.
    """

    MODULES = ("vfe", "backbone3d", "to_bev", "backbone2d", "head")  # in build order

    def __init__(self, cfg: SECONDConfig):
        self.grid = cfg.grid
        self.vfe = MeanVFE(self.grid, cfg.vfe)
        self.backbone3d = SparseBackbone8x(self.vfe.out_channels, self.grid.spatial_shape, cfg.backbone3d)
        # the BEV backbone returns to its input resolution, so the head works at the 3D
        # backbone's stride; the grid must also divide by the 2D blocks' strides
        stride = self.backbone3d.bev_stride
        self.grid.check_divisible(stride * _prod(cfg.backbone2d.layer_strides), "SECOND")
        self.to_bev = HeightCompression()
        self.backbone2d = BEVBackbone(self.backbone3d.bev_channels, cfg.backbone2d)
        self.head = AnchorHead(self.backbone2d.out_channels, self.grid, stride, cfg.head, cfg.post)

    def attach(self, owner: nn.Module) -> None:
        """Register the stage modules as top-level children of `owner`, named as in `MODULES`."""
        for name in self.MODULES:
            owner.add_module(name, getattr(self, name))

    def __call__(self, batch: Batch) -> AnchorHeadOutput:
        voxels = self.vfe(batch.points, batch.batch_size)
        sparse = self.backbone3d(voxels)
        bev = self.backbone2d(self.to_bev(sparse))
        return self.head(bev)

    def loss(self, out: AnchorHeadOutput, batch: Batch) -> tuple[torch.Tensor, dict]:
        return self.head.loss(out, batch.gt_boxes, batch.gt_mask)

    def predict(self, out: AnchorHeadOutput) -> list[Detections]:
        return self.head.predict(out)


class SECOND(nn.Module):
    CONFIG = SECONDConfig  # reads and checks the `model:` section
    # top-level children per stage, for tools/benchmark.py's latency split
    STAGES = {"voxelize": ["vfe"], "backbone3d": ["backbone3d"], "bev": ["to_bev", "backbone2d"], "head": ["head"]}

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = SECONDConfig.from_config(cfg, source="configs/second.yaml")
        self.net = SECONDStages(self.cfg)
        self.net.attach(self)

    @staticmethod
    def prepare_config(model_cfg: dict, train_boxes: np.ndarray) -> dict:
        """Resolve `head.anchor_sizes: auto` from the training boxes (N, 7), metres.

        One size: the mean (length, width, height). k sizes (`head.num_anchor_sizes`):
        k-means (scikit-learn) cluster centres of the sizes, sorted by length.
        """
        cfg = copy.deepcopy(model_cfg)
        head = cfg["head"]
        if head["anchor_sizes"] != "auto":
            return cfg
        sizes = np.asarray(train_boxes, dtype=np.float64).reshape(-1, 7)[:, 3:6]
        if len(sizes) == 0:
            raise ValueError("SECOND: head.anchor_sizes is 'auto' but the training split has no LiDAR-detected "
                             "vehicles to size them from; give head.anchor_sizes explicitly")
        k = int(head["num_anchor_sizes"])
        if k <= 1 or len(sizes) < k:
            centres = sizes.mean(axis=0, keepdims=True)
        else:
            from sklearn.cluster import KMeans

            centres = KMeans(n_clusters=k, n_init=10, random_state=0).fit(sizes).cluster_centers_
            centres = centres[np.argsort(centres[:, 0])]
        head["anchor_sizes"] = [[round(float(v), 3) for v in c] for c in centres]
        return cfg

    def forward(self, batch: Batch) -> AnchorHeadOutput:
        return self.net(batch)

    def loss(self, out: AnchorHeadOutput, batch: Batch) -> tuple[torch.Tensor, dict]:
        return self.net.loss(out, batch)

    def predict(self, out: AnchorHeadOutput, batch: Batch) -> list[Detections]:
        return self.net.predict(out)


def _prod(xs) -> int:
    p = 1
    for x in xs:
        p *= int(x)
    return p
