"""Stages shared by the detectors (OpenPCDet's topology, explicit tensors in and out).

voxel encoder (vfe) -> sparse 3D backbone (backbone3d) -> BEV (bev) -> 2D backbone
(backbone2d) -> dense head (anchor_head, ...) -> post-processing (postprocess).
"""
from .anchor_head import AnchorGenerator, AnchorHead, AnchorHeadOutput, assign_targets
from .backbone2d import BEVBackbone
from .backbone3d import SparseBackbone8x
from .bev import HeightCompression
from .grid import VoxelGrid
from .postprocess import select_detections
from .vfe import MeanVFE

__all__ = ["AnchorGenerator", "AnchorHead", "AnchorHeadOutput", "assign_targets", "BEVBackbone",
           "SparseBackbone8x", "HeightCompression", "VoxelGrid", "select_detections", "MeanVFE"]
