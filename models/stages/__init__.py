"""Stages shared by the detectors (OpenPCDet's topology, explicit tensors in and out).

SECOND:    voxel encoder (vfe.MeanVFE) -> sparse 3D backbone (backbone3d) -> BEV (bev)
           -> 2D backbone (backbone2d) -> anchor head (anchor_head) -> post-processing (postprocess)
PillarNet: pillar encoder (pillar_encoder) -> sparse 2D ResNet (sparse_resnet2d) -> neck
           (pillarnet_neck) -> center head (center_head) -> post-processing (postprocess)
Shared by all: the grid (grid.VoxelGrid), losses as plain functions (losses), BatchNorm
settings (norm). Every stage is exported here; helpers stay importable from their modules.
"""
from .anchor_head import AnchorGenerator, AnchorHead, AnchorHeadOutput, assign_targets
from .backbone2d import BEVBackbone
from .backbone3d import SparseBackbone8x
from .bev import HeightCompression
from .center_head import CenterHead, CenterHeadOutput, build_center_targets, decode_regression
from .grid import VoxelGrid
from .norm import dense_bn, sparse_bn
from .pillar_encoder import DynamicPillarEncoder
from .pillarnet_neck import SpatialSemanticNeck
from .postprocess import select_detections
from .sparse_resnet2d import EncoderFeatures, SparseResNet2d
from .vfe import MeanVFE

__all__ = [
    "AnchorGenerator", "AnchorHead", "AnchorHeadOutput", "assign_targets",
    "BEVBackbone",
    "SparseBackbone8x",
    "HeightCompression",
    "CenterHead", "CenterHeadOutput", "build_center_targets", "decode_regression",
    "VoxelGrid",
    "dense_bn", "sparse_bn",
    "DynamicPillarEncoder",
    "SpatialSemanticNeck",
    "select_detections",
    "EncoderFeatures", "SparseResNet2d",
    "MeanVFE",
]
