"""Geometry on CPU (numba) and GPU (torch): boxes, voxels and the point operations of the
point-based detectors. Import the public names from here (`from detbench.ops import ball_query`).

Modules
- box_coder: box corners, heading wrap, `ResidualBoxCoder`, `PointBinCoder`.
- points_in_boxes: which points lie in which boxes (`points_in_boxes`, `points_in_boxes_mask`).
- iou: exact rotated IoU in BEV and 3D; nms: rotated BEV NMS (`nms_bev`).
- voxelize: hard and dynamic voxelization, scatter reductions.
- Point operations (batches, indices, arithmetic and backends: point_batch):
  - sampling: `farthest_point_sample`.
  - grouping: `ball_query` -> `BallQuery`, `group_points`, `group_neighbours`, `group_linear`.
  - interpolate: `three_nn`, `three_interpolate`, `three_nn_interpolate`.
  - roi_pool: `roi_point_pool` -> `RoIPoints`, `to_canonical`, `from_canonical`.
  - cylinder: `cylinder_query` (CT3D).

Backends: numba kernels for numpy arrays and CPU tensors, vectorised torch for tensors on other
devices; `DETBENCH_OPS=torch` sends CPU tensors down the torch path too, so the GPU's path runs and is
tested on the CPU (backend: `use_torch`, `forced_backend`).

Boxes are (x, y, z, dx, dy, dz, heading) in metres and radians (docs/architecture.md, Conventions).
numpy inputs return numpy arrays; torch inputs return tensors on the inputs' device (the point
operations take tensors or arrays and always return tensors).

Empty slots. An op that returns a fixed number of index slots per query fills a slot that holds
no point with `EMPTY_INDEX` (-1): `ball_query` (an empty ball), `three_nn` (a frame with fewer
than three sources), `roi_point_pool` (an empty RoI) and `cylinder_query` (an empty cylinder).
Every real index is >= 0, so `index >= 0` marks the filled slots; `group_points` and
`three_interpolate` gather zeros from empty slots. (`farthest_point_sample` has no empty slots:
a small frame repeats its samples. `points_in_boxes` marks a point in no box with -1 too.)
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
from detbench.ops.cylinder import cylinder_query
from detbench.ops.grouping import BallQuery, ball_query, group_linear, group_neighbours, group_points
from detbench.ops.interpolate import three_interpolate, three_nn, three_nn_interpolate
from detbench.ops.point_batch import EMPTY_INDEX
from detbench.ops.roi_pool import RoIPoints, from_canonical, roi_point_pool, to_canonical
from detbench.ops.sampling import farthest_point_sample
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
