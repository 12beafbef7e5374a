"""The beo node's parameters: their declarations (defaults, descriptions, ranges) and the
checks of values that the descriptors' ranges do not make. No node state: :class:`BeoNode
<beo_ros.ros.node.BeoNode>` declares them with :func:`declare` and refuses what
:func:`refusal` names."""
from __future__ import annotations

import math

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

from beo_ros.core.bank import YAW_STEP_RANGE_DEG
from beo_ros.core.bank import default_model_dir as shipped_model_dir
from beo_ros.core.outliers import OUTLIER_MADS, OUTLIER_NEIGHBORS
from beo_ros.core.voxelize import MAX_COORDINATE, MIN_DIRECTION, MIN_POINTS
from beo_ros.ros.markers import AUTO_LIFETIME_INTERVALS, MIN_AUTO_LIFETIME

DEFAULT_MODEL = 'modelnet10_32'
MIN_ESTIMATE_TIMEOUT = 1.0  # s; an estimate takes 0.03-0.1 s
INPUT_RELIABILITY = ('best_effort', 'reliable')
YAW_STEP_DEG = (YAW_STEP_RANGE_DEG[0], 45.0)   # the parameter's range (the core's goes to 90)
# checked with check() when the node starts (class_prior and model_dir: by loading the models)
CHECKED_AT_START = ('sensor_origin', 'up_vector', 'min_points', 'max_points', 'workers',
                    'worker_processes', 'completion_threshold', 'yaw_step_deg',
                    'input_reliability', 'estimate_timeout')


def default_model_dir() -> str:
    """Shipped model dir: the installed share dir when present, else the package source tree."""
    return str(shipped_model_dir(DEFAULT_MODEL))


def package_params_file() -> str | None:
    """The package's own ``config/beo.yaml`` (beside the shipped models: the installed share
    dir, else the source tree), or None when it is not there."""
    from pathlib import Path
    path = Path(shipped_model_dir(DEFAULT_MODEL)).parent.parent / 'config' / 'beo.yaml'
    return str(path) if path.is_file() else None


def vector_reason(name, value, nonzero=False) -> str | None:
    """Why the 3-vector ``value`` of ``name`` is invalid (None when it is fine): not 3 finite
    components within +-MAX_COORDINATE, or (``nonzero``) none of them as large as the core's
    MIN_DIRECTION (as ``unit_direction`` refuses it: a length above it was accepted, and every
    cloud then rejected)."""
    v = list(value)
    if len(v) != 3:
        return f'{name} must have 3 elements, got {len(v)}'
    if not all(math.isfinite(x) for x in v):
        return f'{name} must be finite, got {v}'
    if max(abs(x) for x in v) > MAX_COORDINATE:
        return f'{name} components must be within +-{MAX_COORDINATE:g}, got {v}'
    if nonzero and max(abs(x) for x in v) < MIN_DIRECTION:
        return f'{name} must be non-zero (largest component at least {MIN_DIRECTION:g})'
    return None


def _fdesc(description, lo=None, hi=None, read_only=False):
    d = ParameterDescriptor(description=description, read_only=read_only)
    if lo is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                     step=0.0)]
    return d


def _idesc(description, lo, hi, read_only=False):
    return ParameterDescriptor(description=description, read_only=read_only,
                               integer_range=[IntegerRange(from_value=lo, to_value=hi, step=1)])


def declare(declare_parameter) -> tuple:
    """Declare every parameter (name, default value, ParameterDescriptor) with
    ``declare_parameter`` (a node's), in this order; returns their names."""
    names = []

    def d(name, value, descriptor):
        names.append(name)
        declare_parameter(name, value, descriptor)

    d('model_dir', default_model_dir(), ParameterDescriptor(
        description="Directory of the trained BEO model bank ('' = the shipped "
                    f"models/{DEFAULT_MODEL}; a shipped model's name such as 'tabletop_32' "
                    "is that model); changing it reloads the models",
        type=ParameterType.PARAMETER_STRING))
    d('input_topics', ['/beo/input'], ParameterDescriptor(
        description='PointCloud2 topics of segmented objects (one object per cloud)',
        type=ParameterType.PARAMETER_STRING_ARRAY, read_only=True))
    d('input_reliability', 'best_effort', ParameterDescriptor(
        description="QoS reliability of the input_topics subscriptions (depth 5 either "
                    "way): 'best_effort' (sensor-data QoS; matches every publisher) or "
                    "'reliable' (needs reliable publishers; with Fast DDS, clouds of more "
                    'than about 0.5 MB between processes arrive only this way). Read-only',
        type=ParameterType.PARAMETER_STRING, read_only=True))
    d('base_frame', '', ParameterDescriptor(
        description="Gravity-aligned frame (z up) looked up in TF to get the up vector; "
                    "'' uses the up_vector parameter (TF only when tf2_ros is installed)",
        type=ParameterType.PARAMETER_STRING))
    d('sensor_origin', [0.0, 0.0, 0.0], ParameterDescriptor(
        description='Sensor position in the cloud frame (m), for free-space carving',
        type=ParameterType.PARAMETER_DOUBLE_ARRAY))
    d('up_vector', [0.0, 0.0, 1.0], ParameterDescriptor(
        description='Gravity-up direction in the cloud frame (e.g. [0.0, -1.0, 0.0] for a '
                    'camera optical frame held level; floats, with a decimal point)',
        type=ParameterType.PARAMETER_DOUBLE_ARRAY))
    d('yaw_step_deg', 1.0, _fdesc('Resolution of the returned yaw (degrees); the search '
                                  'over all classes runs at max(2, this)', *YAW_STEP_DEG))
    d('min_points', 30, _idesc('Fewer finite points than this: the cloud is rejected',
                               MIN_POINTS, 1_000_000))
    d('max_points', 50000, _idesc('More points than this: random downsampling (fixed seed)',
                                  10, 100_000_000))
    d('outlier_mads', OUTLIER_MADS, _fdesc(
        'Statistical outlier removal before the voxelization (the extent of the points '
        'places the grid, so one stray point far away spoils it): a point whose mean '
        'distance to its outlier_neighbors nearest points is more than this many scaled '
        'MADs above the median is removed (counted in outlier_points); 0: off', 0.0, 1000.0))
    d('outlier_neighbors', OUTLIER_NEIGHBORS, _idesc(
        'Neighbours per point of the outlier removal', 1, 100))
    d('cluster_tolerance', 0.0, _fdesc(
        'After the outlier removal keep only the largest cluster of points (m; points '
        'closer than this are always in one cluster, a gap of 3.5x this always separates '
        'two), for segments that caught part of another surface or object; the others '
        'are counted in off_cluster_points; 0: off', 0.0, 100.0))
    d('completion_threshold', 0.5, _fdesc(
        'Occupancy probability for a voxel to be in the completed cloud (0 refused)',
        0.0, 1.0))
    d('publish_completed', True, ParameterDescriptor(
        description='Publish ~/completed (x y z probability)',
        type=ParameterType.PARAMETER_BOOL))
    d('marker_lifetime', 0.0, _fdesc(
        'Seconds the ~/markers of an estimate stay up in RViz unless the next estimate of '
        f'their input topic replaces them; 0: automatic, {AUTO_LIFETIME_INTERVALS:g}x the '
        f"interval since the topic's previous estimate, at least {MIN_AUTO_LIFETIME:g} s "
        '(a topic that stops sends no more updates: its markers go). A cloud that is rejected '
        "or fails deletes its topic's markers", 0.0, 3600.0))
    d('class_prior', '', ParameterDescriptor(
        description="Prior over the classes: '' = the model directory's, 'train' = the "
                    "training set's class frequencies, 'uniform', or 'name=weight,...' "
                    'with every class (e.g. a kitchen: more chairs than beds; a name with a '
                    'comma in double quotes: \'"a,b"=0.3,c=0.7\')',
        type=ParameterType.PARAMETER_STRING))
    d('diagnostics_period', 1.0, _fdesc('Seconds between /diagnostics messages', 0.1, 60.0))
    d('workers', 1, _idesc('Estimation worker threads (concurrent estimates, services '
                           'included); at least worker_processes are used. Without worker '
                           'processes more than 1 helps only with idle cores to spare '
                           '(the GIL). Read-only', 1, 64, read_only=True))
    d('worker_processes', 0, _idesc('Processes that run the estimates, each with its own '
                                    'copy of the models (0: in the worker threads); '
                                    'several estimate in parallel without sharing the '
                                    "node's GIL. Read-only", 0, 64, read_only=True))
    d('estimate_timeout', 30.0, _fdesc(
        'Seconds a worker process may take for one estimate (worker_processes > 0 only): '
        'after that its processes are taken for hung, killed and restarted, and the cloud '
        f'counted in errors and worker_timeouts; 0: no limit, else at least '
        f'{MIN_ESTIMATE_TIMEOUT:g}', 0.0, 3600.0))
    d('blas_threads', 1, _idesc('Threads of the BLAS library for the node process and '
                                'each worker process (0: leave its default); parallelism '
                                'comes from the workers. Read-only', 0, 64, read_only=True))
    return tuple(names)


def check(name, value, merged) -> str | None:
    """Reason why ``value`` is invalid for parameter ``name`` (None when it is fine)."""
    if name == 'sensor_origin':
        return vector_reason(name, value)
    if name == 'up_vector':
        return vector_reason(name, value, nonzero=True)
    if name in ('min_points', 'max_points') and merged['min_points'] > merged['max_points']:
        return (f"min_points ({merged['min_points']}) must not exceed max_points "
                f"({merged['max_points']})")
    if name == 'input_reliability' and value not in INPUT_RELIABILITY:
        return f'input_reliability must be one of {INPUT_RELIABILITY}, got {value!r}'
    if name == 'yaw_step_deg' and not YAW_STEP_DEG[0] <= value <= YAW_STEP_DEG[1]:
        # rclpy's range check lets values within 1e-6 (relative) of a bound pass
        return (f'yaw_step_deg must be in [{YAW_STEP_DEG[0]:g}, {YAW_STEP_DEG[1]:g}] degrees, '
                f'got {value!r}')
    if name == 'estimate_timeout' and 0 < value < MIN_ESTIMATE_TIMEOUT:
        # each timeout kills and restarts the worker processes (seconds): a limit below
        # what an estimate takes would restart them for every cloud
        return (f'estimate_timeout must be 0 (no limit) or at least '
                f'{MIN_ESTIMATE_TIMEOUT:g} s, got {value!r}')
    if name == 'completion_threshold' and not 0 < value <= 1:
        return f'completion_threshold must be in (0, 1], got {value!r}'
    if name == 'workers' and not (isinstance(value, int) and 1 <= value <= 64):
        return f'workers must be an integer in 1 .. 64, got {value!r}'
    if name == 'worker_processes' and not (isinstance(value, int) and 0 <= value <= 64):
        return f'worker_processes must be an integer in 0 .. 64, got {value!r}'
    return None


def refusal(changes, merged) -> str | None:
    """The reason why the first invalid one of ``changes`` ((name, value) pairs) is refused,
    ``merged`` being all the values with the changes applied; None when they are all fine."""
    for name, value in changes:
        reason = check(name, value, merged)
        if reason:
            return reason
    return None
