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
Shared by all: the range checks of a model config (checks.check_model_config), the grid
(grid.VoxelGrid, with the cap on a tensor's memory), losses as plain functions (losses), BatchNorm
settings (norm). Every stage is exported here; helpers stay importable from their modules.
"""
from .anchor_head import AnchorGenerator, AnchorHead, AnchorHeadOutput, assign_targets
from .backbone2d import BEVBackbone
from .backbone3d import SparseBackbone8x
from .bev import HeightCompression
from .checks import MAX_ANCHOR_SIZES, ModelConfigError, check_model_config
from .center_head import CenterHead, CenterHeadOutput, build_center_targets, decode_regression
from .ct3d_head import (
    ChannelWiseAttention, ChannelWiseDecoderLayer, CT3DRoIHead, CylinderPoints, cylinder_radius,
    encode_proposal_points, gather_cylinder_points,
)
from .grid import VoxelGrid, check_memory, max_tensor_bytes
from .norm import dense_bn, sparse_bn
from .pillar_encoder import DynamicPillarEncoder
from .pillarnet_neck import SpatialSemanticNeck
from .point_head import PointHead, PointHeadOutput, PointTargets, point_targets
from .pointnet2 import (
    FeaturePropagation, PointLevel, PointNet2MSG, SampledPoints, SetAbstraction, SharedMLP, sample_frame_points,
)
from .pointrcnn_head import PointRCNNRoIHead
from .postprocess import select_detections
from .sparse_resnet2d import EncoderFeatures, SparseResNet2d
from .two_stage import (
    LOG_SIZE_CLAMP, OUTPUT_STAGES, PAD_ROI, PROPOSAL_KEYS, TARGET_KEYS, OutputStageSwitch, Proposals, RefineHead,
    RefineOutput, RoIs, RoiTargets, confidence_targets, decode_refined, encode_refine_targets, fold_heading,
    predict_refined, proposal_budgets, refine_loss, require_keys, rois_for_refinement, rotate_z,
    sample_proposal_targets, select_proposals,
)
from .vfe import MeanVFE

__all__ = [
    "AnchorGenerator", "AnchorHead", "AnchorHeadOutput", "assign_targets",
    "BEVBackbone",
    "SparseBackbone8x",
    "HeightCompression",
    "MAX_ANCHOR_SIZES", "ModelConfigError", "check_model_config",
    "CenterHead", "CenterHeadOutput", "build_center_targets", "decode_regression",
    "ChannelWiseAttention", "ChannelWiseDecoderLayer", "CT3DRoIHead", "CylinderPoints", "cylinder_radius",
    "encode_proposal_points", "gather_cylinder_points",
    "VoxelGrid", "check_memory", "max_tensor_bytes",
    "dense_bn", "sparse_bn",
    "DynamicPillarEncoder",
    "SpatialSemanticNeck",
    "PointHead", "PointHeadOutput", "PointTargets", "point_targets",
    "FeaturePropagation", "PointLevel", "PointNet2MSG", "SampledPoints", "SetAbstraction", "SharedMLP",
    "sample_frame_points",
    "PointRCNNRoIHead",
    "select_detections",
    "EncoderFeatures", "SparseResNet2d",
    "LOG_SIZE_CLAMP", "OUTPUT_STAGES", "PAD_ROI", "PROPOSAL_KEYS", "TARGET_KEYS", "OutputStageSwitch", "Proposals",
    "RefineHead", "RefineOutput", "RoIs", "RoiTargets", "confidence_targets", "decode_refined", "encode_refine_targets",
    "fold_heading", "predict_refined", "proposal_budgets", "refine_loss", "require_keys", "rois_for_refinement",
    "rotate_z", "sample_proposal_targets", "select_proposals",
    "MeanVFE",
]
