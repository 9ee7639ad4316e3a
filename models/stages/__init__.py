"""Stages shared by the detectors (OpenPCDet's topology, explicit tensors in and out).

SECOND:    voxel encoder (vfe.MeanVFE) -> sparse 3D backbone (backbone3d) -> BEV (bev)
           -> 2D backbone (backbone2d) -> anchor head (anchor_head) -> post-processing (postprocess)
PillarNet: pillar encoder (pillar_encoder) -> sparse 2D ResNet (sparse_resnet2d) -> neck
           (pillarnet_neck) -> center head (center_head) -> post-processing (postprocess)
PointRCNN: point sampling and PointNet++ backbone (pointnet2) -> point head (point_head)
           -> proposals and target sampling (two_stage) -> RoI point pooling head
           (pointrcnn_head) -> refinement, loss and prediction (two_stage)
CT3D:      SECOND's stages -> proposals and target sampling (two_stage) -> channel-wise
           transformer head (ct3d_head) -> refinement, loss and prediction (two_stage)
Shared by all: the reader of a model's config into typed stage configs (config.Section,
config.StageConfig; each stage's frozen config dataclass lives beside the stage), the grid
(grid.VoxelGrid, with the cap on a tensor's memory), losses as plain functions (losses), BatchNorm
settings (norm). Every stage and stage config is exported here; helpers stay importable from their modules.
"""
from .anchor_head import (
    MAX_ANCHOR_SIZES, AnchorGenerator, AnchorHead, AnchorHeadConfig, AnchorHeadOutput, AnchorLossWeights,
    assign_targets,
)
from .backbone2d import BEVBackbone, BEVBackboneConfig
from .backbone3d import SparseBackbone8x, SparseBackboneConfig
from .bev import HeightCompression
from .center_head import (
    CenterHead, CenterHeadConfig, CenterHeadOutput, CenterLossWeights, CenterPostConfig, build_center_targets,
    decode_regression,
)
from .config import ModelConfigError, Section, StageConfig
from .ct3d_head import (
    ChannelWiseAttention, ChannelWiseDecoderLayer, CT3DHeadConfig, CT3DLossWeights, CT3DRoIHead, CylinderPoints,
    cylinder_radius, encode_proposal_points, gather_cylinder_points,
)
from .grid import VoxelGrid, check_memory, max_tensor_bytes, read_point_cloud_range
from .norm import dense_bn, sparse_bn
from .pillar_encoder import DynamicPillarEncoder, PillarEncoderConfig
from .pillarnet_neck import NeckConfig, SpatialSemanticNeck
from .point_head import BinCodingConfig, PointHead, PointHeadConfig, PointHeadOutput, PointLossWeights, PointTargets, \
    point_targets
from .pointnet2 import (
    FeaturePropagation, PointLevel, PointNet2Config, PointNet2MSG, SampledPoints, SamplingConfig, SetAbstraction,
    SharedMLP, sample_frame_points,
)
from .pointrcnn_head import PointRCNNRoIHead, PointRCNNRoIHeadConfig, TestSplitConfig
from .postprocess import PostConfig, select_detections
from .sparse_resnet2d import EncoderFeatures, SparseResNet2d
from .two_stage import (
    LOG_SIZE_CLAMP, OUTPUT_STAGES, PAD_ROI, OutputStageSwitch, ProposalBudget, ProposalConfig, Proposals,
    RefineHead, RefineLossWeights, RefineOutput, RoIs, RoiTargets, TargetConfig, confidence_targets, decode_refined,
    encode_refine_targets, fold_heading, predict_refined, refine_loss, rois_for_refinement, rotate_z,
    sample_proposal_targets, select_proposals,
)
from .vfe import MeanVFE, VFEConfig

__all__ = [
    "MAX_ANCHOR_SIZES", "AnchorGenerator", "AnchorHead", "AnchorHeadConfig", "AnchorHeadOutput", "AnchorLossWeights",
    "assign_targets",
    "BEVBackbone", "BEVBackboneConfig",
    "SparseBackbone8x", "SparseBackboneConfig",
    "HeightCompression",
    "CenterHead", "CenterHeadConfig", "CenterHeadOutput", "CenterLossWeights", "CenterPostConfig",
    "build_center_targets", "decode_regression",
    "ModelConfigError", "Section", "StageConfig",
    "ChannelWiseAttention", "ChannelWiseDecoderLayer", "CT3DHeadConfig", "CT3DLossWeights", "CT3DRoIHead",
    "CylinderPoints", "cylinder_radius", "encode_proposal_points", "gather_cylinder_points",
    "VoxelGrid", "check_memory", "max_tensor_bytes", "read_point_cloud_range",
    "dense_bn", "sparse_bn",
    "DynamicPillarEncoder", "PillarEncoderConfig",
    "NeckConfig", "SpatialSemanticNeck",
    "BinCodingConfig", "PointHead", "PointHeadConfig", "PointHeadOutput", "PointLossWeights", "PointTargets",
    "point_targets",
    "FeaturePropagation", "PointLevel", "PointNet2Config", "PointNet2MSG", "SampledPoints", "SamplingConfig",
    "SetAbstraction", "SharedMLP", "sample_frame_points",
    "PointRCNNRoIHead", "PointRCNNRoIHeadConfig", "TestSplitConfig",
    "PostConfig", "select_detections",
    "EncoderFeatures", "SparseResNet2d",
    "LOG_SIZE_CLAMP", "OUTPUT_STAGES", "PAD_ROI", "OutputStageSwitch", "ProposalBudget", "ProposalConfig",
    "Proposals", "RefineHead", "RefineLossWeights", "RefineOutput", "RoIs", "RoiTargets", "TargetConfig",
    "confidence_targets", "decode_refined", "encode_refine_targets", "fold_heading", "predict_refined",
    "refine_loss", "rois_for_refinement", "rotate_z", "sample_proposal_targets", "select_proposals",
    "MeanVFE",
    "VFEConfig",
]
