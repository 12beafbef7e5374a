"""beo_ros: Bayesian Eigenobjects for ROS 2.

The public entry point is ROS-free::

    bank = beo_ros.load_models(path)      # default: the shipped models/modelnet10_32
    est = bank.estimate(grid, yaw=None)   # grid: int8 (N,N,N), 1 occupied, 0 free, -1 unknown
    est = bank.estimate_points(points, sensor_origin, up)
"""
from .core.bank import ModelBank, ModelError, default_model_dir, load_models
from .core.estimate import Estimate, Hypothesis
from .core.grid import GridSpec

__all__ = ['ModelBank', 'ModelError', 'load_models', 'default_model_dir', 'Estimate',
           'Hypothesis', 'GridSpec']
__version__ = '0.1.0'
