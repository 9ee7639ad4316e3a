"""Data layer: the Frame type, the on-disk layout, readers, the writer and validation.

See docs/data-format.md for the layout and docs/architecture.md for the conventions.
"""
from detbench.data.frame import LANE_OPPOSITE, LANE_UNKNOWN, Frame, Sensor, height_key
from detbench.data.errors import DatasetError, MissingFileError
from detbench.data.layout import DatasetInfo, HeightInfo, SceneRule, assign_splits, read_info, split_scenes
from detbench.data.readers import format_labels, parse_labels, read_labels, read_meta, read_points
from detbench.data.transforms import ground_to_sensor, sensor_to_ground
from detbench.data.writer import DatasetWriter
from detbench.data.dataset import Height3Dataset, split_ids

__all__ = [
    "Frame", "Sensor", "height_key", "LANE_OPPOSITE", "LANE_UNKNOWN",
    "DatasetError", "MissingFileError",
    "DatasetInfo", "HeightInfo", "SceneRule", "read_info", "split_scenes", "assign_splits", "split_ids",
    "read_points", "read_labels", "parse_labels", "read_meta", "format_labels",
    "sensor_to_ground", "ground_to_sensor",
    "DatasetWriter", "Height3Dataset",
]
