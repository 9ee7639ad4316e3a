"""Box geometry on CPU (numba) and GPU (torch): points in boxes, rotated IoU, NMS, box coding;
voxelization; PointNet++ / PointRCNN point operations (detbench.ops.points).

Boxes are (x, y, z, dx, dy, dz, heading) in metres and radians (docs/architecture.md, Conventions).
numpy inputs return numpy arrays; torch inputs return tensors on the inputs' device (the point
operations take tensors or arrays and always return tensors).
"""
from detbench.ops.box_coder import (
    BinTargets,
    PointBinCoder,
    ResidualBoxCoder,
    boxes_to_corners_3d,
    boxes_to_corners_bev,
    limit_period,
    normalize_heading,
)
from detbench.ops.points_in_boxes import points_in_boxes, points_in_boxes_mask
from detbench.ops.iou import (
    boxes_iou3d,
    boxes_iou3d_aligned,
    boxes_iou_bev,
    boxes_iou_bev_aligned,
    boxes_overlap_bev,
    iou3d_matrix_nb,
    iou3d_pair_nb,
    iou_bev_matrix_nb,
    iou_bev_pair_nb,
    overlap_bev_pair_nb,
)
from detbench.ops.nms import nms_bev
from detbench.ops.grouping import (
    BallQuery,
    RoIPoints,
    ball_query,
    cylinder_query,
    farthest_point_sample,
    from_canonical,
    group_neighbours,
    group_points,
    roi_point_pool,
    three_interpolate,
    three_nn,
    three_nn_interpolate,
    to_canonical,
)
from detbench.ops.voxelize import (
    HardVoxels,
    dynamic_voxelize,
    scatter_max,
    scatter_mean,
    unique_voxels,
    voxel_grid_size,
    voxelize,
    voxelize_batch,
)
