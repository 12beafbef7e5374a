"""Message <-> numpy conversions for beo_ros (pure functions, no node).

- :func:`cloud_to_xyz`: sensor_msgs/PointCloud2 -> (n, 3) float64 points in the cloud frame.
- :func:`xyz_to_cloud`: (n, 3) points (+ optional float32 per-point fields) -> PointCloud2.
- pose helpers: 4x4 homogeneous matrix <-> geometry_msgs/Pose, yaw about an up axis -> Quaternion.
- :func:`estimate_to_msg`: core ``Estimate`` -> beo_interfaces/ObjectEstimate.

Only this ROS layer imports message packages; the core stays array-only.
"""
from __future__ import annotations

import array
import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
from sensor_msgs.msg import PointField, PointCloud2

from beo_ros.core.bank import object_extent
from beo_ros.core.grid import quaternion_matrix, unit_vector, wrap_yaw
from beo_ros.ros import MAX_STAMP_NS

__all__ = [
    'CloudFormatError', 'cloud_to_xyz', 'xyz_to_cloud', 'matrix_to_pose', 'pose_to_matrix',
    'rotation_to_quaternion', 'quaternion_to_rotation', 'yaw_quaternion', 'object_dimensions',
    'estimate_to_msg', 'interfaces',
]

# PointField datatype -> numpy base type (sensor_msgs/PointField constants).
_DATATYPES = {
    PointField.INT8: 'i1', PointField.UINT8: 'u1',
    PointField.INT16: 'i2', PointField.UINT16: 'u2',
    PointField.INT32: 'i4', PointField.UINT32: 'u4',
    PointField.FLOAT32: 'f4', PointField.FLOAT64: 'f8',
}
_XYZ_TYPES = (PointField.FLOAT32, PointField.FLOAT64)


class CloudFormatError(ValueError):
    """A PointCloud2 whose layout cannot be read (missing x/y/z, short data, bad steps...)."""


def _field_size(f) -> int:
    return int(np.dtype(_DATATYPES[f.datatype]).itemsize) * max(int(f.count), 1)


def cloud_to_xyz(msg: PointCloud2):
    """Read x, y, z of a PointCloud2 as float64.

    Accepts any field order, float32 or float64 x/y/z, organized (height > 1) clouds with row
    padding (``row_step > width * point_step``), either byte order (``is_bigendian``). Points with
    a NaN/Inf coordinate are dropped.

    Returns:
        ``(points, n_dropped)``: points float64 (n, 3) in ``msg.header.frame_id``; n_dropped is
        the number of points removed as non-finite. An empty cloud gives ``(zeros((0, 3)), 0)``,
        also one without fields (``PointCloud2()``, as the ``completed_cloud`` the node leaves
        empty in its ObjectEstimate).

    Raises:
        CloudFormatError: missing, duplicate, overlapping or non-float x/y/z, a field
        overrunning ``point_step``, ``row_step < width * point_step`` (height > 1: an
        unorganized cloud's is taken as ``width * point_step``), data shorter or longer than
        the layout (longer than ``height * row_step``).
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    n_points = height * width
    if n_points == 0 and not msg.fields:   # a default PointCloud2(), e.g. an unfilled field
        return np.zeros((0, 3), dtype=np.float64), 0
    fields = {}
    for f in msg.fields:
        # only x, y, z must be unique (PCD pads with repeated '_' fields, others are ignored)
        if f.name in fields and f.name in ('x', 'y', 'z'):
            raise CloudFormatError(f'PointCloud2 has duplicate field {f.name!r}')
        fields.setdefault(f.name, f)
    missing = [k for k in 'xyz' if k not in fields]
    if missing:
        raise CloudFormatError(
            f'PointCloud2 lacks field(s) {", ".join(missing)} (has: {sorted(fields) or "none"})')
    for k in 'xyz':
        f = fields[k]
        if f.datatype not in _XYZ_TYPES:
            raise CloudFormatError(
                f'PointCloud2 field {k!r} has datatype {f.datatype}; only FLOAT32 (7) and '
                f'FLOAT64 (8) are supported for x/y/z')
    if n_points == 0:
        return np.zeros((0, 3), dtype=np.float64), 0
    if point_step <= 0:
        raise CloudFormatError(f'PointCloud2 point_step must be > 0, got {point_step}')
    for f in (fields[k] for k in 'xyz'):  # other fields are ignored
        if int(f.offset) + _field_size(f) > point_step:
            raise CloudFormatError(
                f'PointCloud2 field {f.name!r} (offset {f.offset}, {_field_size(f)} bytes) '
                f'overruns point_step {point_step}')
    spans = sorted((int(fields[k].offset), int(fields[k].offset) + _field_size(fields[k]), k)
                   for k in 'xyz')
    for (_, end, a), (start, _, b) in zip(spans, spans[1:]):
        if start < end:
            raise CloudFormatError(f'PointCloud2 fields {a!r} and {b!r} overlap (bytes '
                                   f'{fields[a].offset}.., {fields[b].offset}..)')
    if height > 1 and row_step < width * point_step:
        raise CloudFormatError(
            f'PointCloud2 row_step {row_step} < width*point_step {width * point_step}')
    if height == 1 and row_step < width * point_step:
        row_step = width * point_step  # unorganized clouds: tolerate a zero/wrong row_step
    data = memoryview(msg.data).cast('B') if not isinstance(msg.data, bytes) else msg.data
    need = (height - 1) * row_step + width * point_step
    if not need <= len(data) <= height * row_step:   # the last row's padding may be missing
        raise CloudFormatError(
            f'PointCloud2 data has {len(data)} bytes, layout {height}x{width} (point_step '
            f'{point_step}, row_step {row_step}'
            + (f' for the {int(msg.row_step)} given' if row_step != int(msg.row_step) else '')
            + f') needs {need} to {height * row_step}')
    order = '>' if msg.is_bigendian else '<'
    dtype = np.dtype({
        'names': ['x', 'y', 'z'],
        'formats': [order + _DATATYPES[fields[k].datatype] for k in 'xyz'],
        'offsets': [int(fields[k].offset) for k in 'xyz'],
        'itemsize': point_step,
    })
    arr = np.ndarray(shape=(height, width), dtype=dtype, buffer=data, offset=0,
                     strides=(row_step, point_step))
    pts = np.empty((n_points, 3), dtype=np.float64)
    # a byte-swapped signalling NaN raises 'invalid' when widened; non-finite points are
    # dropped and counted below
    with np.errstate(invalid='ignore'):
        for i, k in enumerate('xyz'):
            pts[:, i] = arr[k].reshape(-1)
    finite = np.isfinite(pts).all(axis=1)
    n_dropped = int(n_points - np.count_nonzero(finite))
    if n_dropped:
        pts = pts[finite]
    return pts, n_dropped


def xyz_to_cloud(points, header, extra_fields: dict | None = None) -> PointCloud2:
    """Build an unorganized little/native-endian float32 PointCloud2.

    Args:
        points: (n, 3) array-like, metres in ``header.frame_id``.
        header: std_msgs/Header copied into the message.
        extra_fields: optional ordered ``name -> (n,)`` arrays stored as float32 after x y z
            (e.g. ``{'probability': p}``).
    """
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        if pts.shape[:1] == (0,):   # no points (not n points without coordinates)
            pts = pts.reshape(0, 3)
        else:
            raise ValueError(f'points must be (n, 3), got shape {pts.shape}')
    n = pts.shape[0]
    names = ['x', 'y', 'z']
    cols = [pts[:, 0], pts[:, 1], pts[:, 2]]
    for name, values in (extra_fields or {}).items():
        if name in names:
            raise ValueError(f'duplicate field name {name!r}')
        v = np.asarray(values, dtype=np.float32).reshape(-1)
        if v.shape[0] != n:
            raise ValueError(f'field {name!r} has {v.shape[0]} values for {n} points')
        names.append(name)
        cols.append(v)
    dtype = np.dtype({'names': names, 'formats': ['<f4'] * len(names),
                      'offsets': [4 * i for i in range(len(names))], 'itemsize': 4 * len(names)})
    buf = np.empty(n, dtype=dtype)
    for name, v in zip(names, cols):
        buf[name] = v
    msg = PointCloud2()
    msg.header = header
    msg.height = 1
    msg.width = n
    msg.fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, name in enumerate(names)]
    msg.is_bigendian = False
    msg.point_step = 4 * len(names)
    msg.row_step = msg.point_step * n
    data = array.array('B')
    data.frombytes(buf.tobytes())
    msg.data = data
    msg.is_dense = bool(np.isfinite(pts).all())
    return msg


def rotation_to_quaternion(r) -> np.ndarray:
    """(3, 3) rotation matrix -> unit quaternion (x, y, z, w) with w >= 0."""
    m = np.asarray(r, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quaternion_to_rotation(q) -> np.ndarray:
    """Quaternion (x, y, z, w) (any norm > 0) -> (3, 3) rotation matrix; ValueError for one
    that is all 0 or not finite. (Normalized without overflow: one of 1e200 components came
    out the identity, one of 1e-170 NaN.)"""
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,) or not np.isfinite(q).all() or not np.abs(q).max() > 0:
        raise ValueError(f'quaternion must be 4 finite components, not all 0, got {q.tolist()}')
    x, y, z, w = unit_vector(q)
    return quaternion_matrix((w, x, y, z))


def matrix_to_pose(t) -> Pose:
    """(4, 4) homogeneous transform (object frame in the parent frame) -> geometry_msgs/Pose."""
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4):
        raise ValueError(f'pose must be a finite (4, 4) matrix, got shape {t.shape}')
    bad = int(t.size - np.count_nonzero(np.isfinite(t)))
    if bad:
        raise ValueError(f'pose must be a finite (4, 4) matrix, got {bad} non-finite entries: '
                         f'{t.tolist()}')
    q = rotation_to_quaternion(t[:3, :3])
    return Pose(position=Point(x=float(t[0, 3]), y=float(t[1, 3]), z=float(t[2, 3])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                       w=float(q[3])))


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """geometry_msgs/Pose -> (4, 4) float64 homogeneous transform (ValueError for an
    orientation that is all 0 or not finite)."""
    o = pose.orientation
    t = np.eye(4)
    t[:3, :3] = quaternion_to_rotation([o.x, o.y, o.z, o.w])
    t[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return t


def yaw_quaternion(yaw: float, up=(0.0, 0.0, 1.0)) -> Quaternion:
    """Rotation by ``yaw`` radians (right-handed) about the axis ``up`` (normalized here).

    Not the published object orientation unless ``up`` is the frame's z axis: that one turns
    the frame's z onto up as well (``Estimate.pose``, the object frame: z up, x the heading)."""
    axis = np.asarray(up, dtype=np.float64)
    if axis.shape != (3,) or not np.isfinite(axis).all() or not np.abs(axis).max() > 0:
        raise ValueError(f'up must be a finite non-zero vector, got {up!r}')
    axis = unit_vector(axis) * math.sin(yaw / 2.0)   # no overflow: up=(0, 0, 1e200) was refused
    return Quaternion(x=float(axis[0]), y=float(axis[1]), z=float(axis[2]),
                      w=float(math.cos(yaw / 2.0)))


def object_dimensions(est) -> np.ndarray:
    """Extent (3,) in metres of the completed object along the object frame axes (0 if none):
    ``est.dimensions`` when ``estimate_points`` set it (from float64 points), else that of
    ``est.completed_points`` (float32: centimetres off far from the origin)."""
    if getattr(est, 'dimensions', None) is not None:
        return np.asarray(est.dimensions, dtype=np.float64)
    pts = est.completed_points
    if pts is None or len(pts) == 0 or est.pose is None:
        return np.zeros(3)
    return object_extent(pts, est.pose, _voxel_size(est))   # voxel centres -> outer faces


def _voxel_size(est) -> float:
    """Edge length (m) of one voxel of ``est.grid_to_input`` (0 if unknown)."""
    g = getattr(est, 'grid_to_input', None)
    if g is None:
        return 0.0
    return float(np.linalg.norm(np.asarray(g)[:3, 0]))


def stamp_from_ns(ns: int) -> Time:
    """``builtin_interfaces/Time`` of ``ns`` nanoseconds (>= 0); ValueError beyond what its
    int32 seconds hold (``MAX_STAMP_NS``, 2038): the middleware wrapped them negative."""
    if not 0 <= int(ns) <= MAX_STAMP_NS:
        raise ValueError(f'a stamp of {int(ns)} ns is outside what a builtin_interfaces/Time '
                         f'holds (0 to {MAX_STAMP_NS} ns, 2038-01-19)')
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def ns_from_stamp(stamp) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time``."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


_interfaces = None


def interfaces():
    """Import and return ``beo_interfaces.msg`` (after making the built package findable; once
    found, the module is kept: every published estimate asks for it)."""
    global _interfaces
    if _interfaces is not None:
        return _interfaces
    from beo_ros.ros.env import ensure_ament_prefix
    ensure_ament_prefix()
    import beo_interfaces.msg as msgs
    if not hasattr(msgs, 'ObjectEstimate'):
        raise ImportError(
            'beo_interfaces is not built (found only the source folder); run scripts/setup')
    _interfaces = msgs
    return msgs


def estimate_to_msg(est, header, source_topic: str = '', latency: float = 0.0,
                    include_cloud: bool = False, status: str = 'ok', class_names=None):
    """Core Estimate -> beo_interfaces/ObjectEstimate.

    Args:
        est: :class:`beo_ros.core.estimate.Estimate` from ``estimate_points`` (pose and
            completed points in the frame of ``header``).
        header: std_msgs/Header of the input cloud (frame and stamp).
        source_topic: input topic or service name.
        latency: seconds from receipt of the cloud to this estimate.
        include_cloud: also fill ``completed_cloud`` (x y z probability).
        status: 'ok' or why the estimate is partial.
        class_names: order of ``class_names``/``class_probabilities`` (default: ``est.scores``).
    """
    msgs = interfaces()
    out = msgs.ObjectEstimate()
    out.header = header
    out.source_topic = str(source_topic)
    out.label = str(est.label)
    out.probability = float(est.probability)
    names = list(class_names) if class_names is not None else list(est.scores)
    out.class_names = [str(n) for n in names]
    out.class_probabilities = [float(est.scores.get(n, 0.0)) for n in names]
    if est.pose is not None:
        out.pose = matrix_to_pose(est.pose)
    else:
        out.pose.orientation.w = 1.0
    d = object_dimensions(est)
    out.dimensions = Vector3(x=float(d[0]), y=float(d[1]), z=float(d[2]))
    # headings about up in the header frame, not the estimator's grid frame (whose x axis
    # follows the bearing from the sensor to the object)
    off = float(getattr(est, 'heading_offset', None) or 0.0)
    out.hypotheses = [msgs.YawHypothesis(label=str(h.label), yaw=wrap_yaw(h.yaw + off),
                                         score=float(h.score))
                      for h in (est.hypotheses or [])]
    out.symmetric_yaws = [wrap_yaw(y + off) for y in (est.symmetric_yaws or [])]
    if include_cloud and est.completed_points is not None:
        out.completed_cloud = completed_cloud(est, header)
    else:
        out.completed_cloud.header = header
    out.latency = float(latency)
    out.status = str(status)
    return out


def completed_cloud(est, header) -> PointCloud2:
    """PointCloud2 (x y z probability) of the completed object in the frame of ``header``."""
    pts = est.completed_points if est.completed_points is not None else np.zeros((0, 3))
    prob = est.completed_probability
    if prob is None:
        prob = np.ones(len(pts), dtype=np.float32)
    return xyz_to_cloud(pts, header, {'probability': prob})

