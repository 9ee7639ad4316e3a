"""The voxel grid a detector works on: point-cloud range, voxel size and the derived shapes.

Model only what the scene requires: the study looks at x in [0, 150] m and |y| <= 15 m
ahead of the car, so grids cover that region plus a margin (stated in each config), not a
360-degree disc. Sizes are checked at construction so a config whose range is not a whole
number of voxels, or whose grid does not divide by the backbone's stride, fails at start-up
with a message that says which numbers to change.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

from .config import Section

# the largest tensor a model may ask for (bytes): a config whose grid or anchors would need more is refused before
# anything is allocated; DETBENCH_MAX_TENSOR_GB raises or lowers it
MAX_TENSOR_GB_DEFAULT = 16.0


def max_tensor_bytes() -> int:
    """The cap on one tensor's size in bytes: DETBENCH_MAX_TENSOR_GB (GiB) or 16 GiB."""
    raw = os.environ.get("DETBENCH_MAX_TENSOR_GB", "")
    try:
        gb = float(raw) if raw else MAX_TENSOR_GB_DEFAULT
    except ValueError:
        gb = MAX_TENSOR_GB_DEFAULT
    return int(gb * 2**30)


def check_memory(nbytes: float, what: str) -> None:
    """ValueError when a tensor of `nbytes` (`what` it holds) is above the cap, before it is allocated."""
    cap = max_tensor_bytes()
    if nbytes > cap:
        raise ValueError(f"{what} would need {nbytes / 2**30:,.1f} GiB, above the {cap / 2**30:g} GiB a tensor may "
                         f"take (DETBENCH_MAX_TENSOR_GB); make the voxel_size larger or the point_cloud_range smaller")



def read_point_cloud_range(s: Section) -> tuple[float, float, float, float, float, float]:
    """`point_cloud_range` of a model section: [x_min, y_min, z_min, x_max, y_max, z_max] in metres."""
    r = s.numbers("point_cloud_range", 6, need="6 numbers [x_min, y_min, z_min, x_max, y_max, z_max] in metres")
    if any(r[i] >= r[i + 3] for i in range(3)):
        raise s.error("point_cloud_range", "a range whose minima are below its maxima")
    return r


@dataclass(frozen=True)
class VoxelGrid:
    point_cloud_range: tuple[float, float, float, float, float, float]  # x0, y0, z0, x1, y1, z1 (m)
    voxel_size: tuple[float, float, float]  # vx, vy, vz (m)

    @classmethod
    def read(cls, s: Section) -> VoxelGrid:
        """The grid of a model section's `point_cloud_range` and `voxel_size` (metres)."""
        return cls(read_point_cloud_range(s),
                   s.numbers("voxel_size", 3, low=0, need="3 positive numbers [vx, vy, vz] in metres"))

    def __post_init__(self):
        r, v = tuple(map(float, self.point_cloud_range)), tuple(map(float, self.voxel_size))
        if len(r) != 6 or len(v) != 3:
            raise ValueError(f"point_cloud_range needs 6 numbers (x0 y0 z0 x1 y1 z1) and voxel_size 3 (vx vy vz); "
                             f"got {list(r)} and {list(v)}")
        if not all(map(math.isfinite, r + v)):
            raise ValueError(f"point_cloud_range and voxel_size must be finite numbers, got {list(r)} and {list(v)}")
        if any(s <= 0 for s in v):
            raise ValueError(f"voxel_size must be positive, got {list(v)}")
        for axis, (lo, hi, s) in enumerate(zip(r[:3], r[3:], v)):
            name = "xyz"[axis]
            if hi <= lo:
                raise ValueError(f"point_cloud_range: {name} max {hi} must exceed {name} min {lo}")
            n = (hi - lo) / s
            if abs(n - round(n)) > 1e-4:
                raise ValueError(f"point_cloud_range {name} extent {hi - lo:g} m is not a whole number of voxels "
                                 f"of {s:g} m ({n:.4f}); change the range or the voxel size")
        object.__setattr__(self, "point_cloud_range", r)
        object.__setattr__(self, "voxel_size", v)
        nx, ny, nz = self.grid_size
        check_memory(4.0 * nx * ny * nz, f"the voxel grid {nx} x {ny} x {nz} (point_cloud_range {list(r)}, "
                                         f"voxel_size {list(v)}) at one float32 per voxel")

    @property
    def grid_size(self) -> tuple[int, int, int]:
        """(nx, ny, nz) voxels along x, y, z."""
        r, v = self.point_cloud_range, self.voxel_size
        return tuple(int(round((r[i + 3] - r[i]) / v[i])) for i in range(3))

    @property
    def spatial_shape(self) -> tuple[int, int, int]:
        """(Z, Y, X) as sparse tensors index it."""
        nx, ny, nz = self.grid_size
        return nz, ny, nx

    def check_divisible(self, stride_xy: int, where: str) -> None:
        """Raise if the BEV grid does not divide by `stride_xy` (the network's total BEV stride)."""
        nx, ny, _ = self.grid_size
        if nx % stride_xy or ny % stride_xy:
            vx, vy = self.voxel_size[:2]
            step_x, step_y = stride_xy * vx, stride_xy * vy
            raise ValueError(
                f"{where}: the BEV grid {nx} x {ny} voxels must divide by the network stride {stride_xy}; make the "
                f"x extent a multiple of {step_x:g} m and the y extent a multiple of {step_y:g} m "
                f"(now {self.point_cloud_range[3] - self.point_cloud_range[0]:g} m and "
                f"{self.point_cloud_range[4] - self.point_cloud_range[1]:g} m)")

    def bev_cell(self, stride: int) -> tuple[float, float]:
        """Size (m) of one cell of a BEV map at `stride` voxels."""
        return self.voxel_size[0] * stride, self.voxel_size[1] * stride
