"""detbench: LiDAR mounting-height benchmark (Height3 study) -- data, simulator, ops, evaluation, training."""

# First: the thread runtimes' environment defaults, before anything imports torch or numba
# (detbench/runtime.py; a user's own environment variables win).
from detbench import runtime

__version__ = "0.1.0"
