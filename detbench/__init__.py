"""detbench: LiDAR mounting-height benchmark (Height3 study) -- data, simulator, ops, evaluation, training."""

__version__ = "0.1.0"
