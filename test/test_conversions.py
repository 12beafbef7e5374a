"""PointCloud2 <-> numpy and pose conversions against clouds built by hand."""
import array
import math

import numpy as np
import pytest
from geometry_msgs.msg import Pose
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from beo_ros.ros.conversions import (
    CloudFormatError, cloud_to_xyz, matrix_to_pose, pose_to_matrix, quaternion_to_rotation,
    rotation_to_quaternion, xyz_to_cloud, yaw_quaternion)

F32, F64 = PointField.FLOAT32, PointField.FLOAT64
NP = {PointField.FLOAT32: 'f4', PointField.FLOAT64: 'f8', PointField.UINT8: 'u1',
      PointField.INT16: 'i2', PointField.UINT32: 'u4'}


def hand_cloud(points, layout, point_step, *, height=1, row_pad=0, big=False, extra=None):
    """Pack ``points`` (n, 3) by hand with ``layout`` = [(name, offset, datatype), ...].

    Rows of an organized cloud (height > 1) get ``row_pad`` zero bytes of padding each.
    ``extra`` maps other field names to per-point values.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    width = n // height
    assert width * height == n
    order = '>' if big else '<'
    row_step = width * point_step + row_pad
    raw = bytearray(row_step * height)
    for name, off, dt in layout:
        values = points[:, 'xyz'.index(name)] if name in 'xyz' else np.asarray(extra[name])
        enc = np.asarray(values).astype(order + NP[dt])
        for i in range(n):
            r, c = divmod(i, width)
            start = r * row_step + c * point_step + off
            raw[start:start + enc.itemsize] = enc[i:i + 1].tobytes()  # keeps byte order
    msg = PointCloud2()
    msg.header = Header(frame_id='cam')
    msg.height, msg.width = height, width
    msg.fields = [PointField(name=name, offset=off, datatype=dt, count=1)
                  for name, off, dt in layout]
    msg.is_bigendian = big
    msg.point_step, msg.row_step = point_step, row_step
    msg.data = array.array('B', bytes(raw))
    msg.is_dense = False
    return msg


@pytest.fixture
def pts():
    return np.random.default_rng(1).uniform(-2, 2, size=(24, 3))


def test_round_trip_with_probability(pts):
    prob = np.linspace(0, 1, len(pts), dtype=np.float32)
    msg = xyz_to_cloud(pts, Header(frame_id='base'), {'probability': prob})
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'probability']
    assert msg.point_step == 16 and msg.row_step == 16 * len(pts) and msg.is_dense
    out, dropped = cloud_to_xyz(msg)
    assert dropped == 0 and out.dtype == np.float64 and out.shape == pts.shape
    np.testing.assert_allclose(out, pts, atol=1e-6)
    rec = np.frombuffer(bytes(msg.data), dtype='<f4').reshape(-1, 4)
    np.testing.assert_array_equal(rec[:, 3], prob)


def test_empty_round_trip():
    msg = xyz_to_cloud(np.zeros((0, 3)), Header(), {'probability': np.zeros(0)})
    out, dropped = cloud_to_xyz(msg)
    assert out.shape == (0, 3) and dropped == 0


@pytest.mark.parametrize('layout,step', [
    ([('x', 0, F32), ('y', 4, F32), ('z', 8, F32)], 12),
    ([('z', 0, F32), ('x', 4, F32), ('y', 8, F32)], 16),           # reordered, tail padding
    ([('rgb', 0, PointField.UINT32), ('y', 4, F32), ('i', 8, PointField.INT16),
      ('x', 12, F32), ('z', 20, F32)], 32),                       # interleaved other fields
    ([('x', 0, F64), ('y', 8, F64), ('z', 16, F64)], 24),           # float64
    ([('y', 0, F64), ('z', 8, F32), ('x', 16, F64)], 24),           # mixed widths
])
@pytest.mark.parametrize('big', [False, True])
def test_field_orders_types_endianness(pts, layout, step, big):
    extra = {'rgb': np.arange(len(pts)), 'i': -np.arange(len(pts))}
    msg = hand_cloud(pts, layout, step, big=big, extra=extra)
    out, dropped = cloud_to_xyz(msg)
    assert dropped == 0
    f64 = all(dt == F64 for name, _, dt in layout if name in 'xyz')
    np.testing.assert_allclose(out, pts, atol=0 if f64 else 1e-6)


def test_organized_with_row_padding(pts):
    layout = [('x', 0, F32), ('y', 4, F32), ('z', 8, F32)]
    msg = hand_cloud(pts, layout, 16, height=4, row_pad=7)
    assert msg.height == 4 and msg.width == 6 and msg.row_step == 6 * 16 + 7
    out, dropped = cloud_to_xyz(msg)
    np.testing.assert_allclose(out, pts, atol=1e-6)  # row-major order is kept
    assert dropped == 0


def test_organized_missing_last_row_padding_is_accepted(pts):
    msg = hand_cloud(pts, [('x', 0, F32), ('y', 4, F32), ('z', 8, F32)], 12, height=3, row_pad=4)
    msg.data = msg.data[:-4]  # some drivers omit the padding of the final row
    np.testing.assert_allclose(cloud_to_xyz(msg)[0], pts, atol=1e-6)


def test_nan_and_inf_are_dropped_and_counted(pts):
    bad = pts.copy()
    bad[[1, 5, 9], [0, 1, 2]] = np.nan
    bad[11, 0] = np.inf
    bad[12, 2] = -np.inf
    msg = hand_cloud(bad, [('x', 0, F32), ('y', 4, F32), ('z', 8, F32)], 12, height=2)
    out, dropped = cloud_to_xyz(msg)
    keep = np.isfinite(bad).all(axis=1)
    assert dropped == 5 and out.shape == (len(pts) - 5, 3)
    np.testing.assert_allclose(out, pts[keep], atol=1e-6)


def test_signalling_nan_is_dropped_without_a_warning(pts):
    import warnings
    msg = hand_cloud(pts, [('x', 0, F32), ('y', 4, F32), ('z', 8, F32)], 12, big=True)
    data = bytearray(msg.data)
    data[3 * 12 + 4:3 * 12 + 8] = b'\x7f\xa0\x00\x00'   # point 3's y: a signalling NaN
    msg.data = bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        out, dropped = cloud_to_xyz(msg)
    assert dropped == 1 and out.shape == (len(pts) - 1, 3)


def test_all_nan_gives_empty(pts):
    msg = hand_cloud(np.full_like(pts, np.nan), [('x', 0, F64), ('y', 8, F64), ('z', 16, F64)], 24)
    out, dropped = cloud_to_xyz(msg)
    assert out.shape == (0, 3) and dropped == len(pts)


def test_empty_cloud_without_data():
    msg = PointCloud2()
    msg.fields = [PointField(name=k, offset=4 * i, datatype=F32, count=1)
                  for i, k in enumerate('xyz')]
    out, dropped = cloud_to_xyz(msg)
    assert out.shape == (0, 3) and dropped == 0


def test_empty_cloud_without_fields_is_empty():
    # the completed_cloud the node leaves empty in its ObjectEstimate (and a failed Complete
    # response's) is PointCloud2() with its header: before, the package's own parser refused
    # it ('lacks field(s) x, y, z'); a cloud with points and no fields still is refused
    from beo_ros.ros.conversions import estimate_to_msg
    from beo_ros.core.estimate import Estimate
    z = np.zeros((4, 4, 4), np.float32)
    est = Estimate(label='chair', scores={'chair': 1.0}, yaw=0.0, completion=z, variance=z)
    msg = estimate_to_msg(est, Header(frame_id='cam'))
    out, dropped = cloud_to_xyz(msg.completed_cloud)
    assert out.shape == (0, 3) and dropped == 0
    msg.completed_cloud.width = msg.completed_cloud.height = 1
    with pytest.raises(CloudFormatError, match='lacks field'):
        cloud_to_xyz(msg.completed_cloud)


def test_unorganized_zero_row_step_tolerated(pts):
    msg = hand_cloud(pts, [('x', 0, F32), ('y', 4, F32), ('z', 8, F32)], 12)
    msg.row_step = 0
    np.testing.assert_allclose(cloud_to_xyz(msg)[0], pts, atol=1e-6)
    # data too long: the error named row_step 288 (what it was taken as), not the 0 given
    msg.data = msg.data + msg.data[:12]
    with pytest.raises(CloudFormatError, match=r'row_step 288 for the 0 given\) needs 288 to'):
        cloud_to_xyz(msg)


def test_duplicate_fields_other_than_xyz_are_ignored(pts):
    # PCD writers pad with fields named '_'; only the x, y, z names must be unique
    msg = hand_cloud(pts, [('x', 0, F32), ('y', 4, F32), ('z', 8, F32)], 20)
    msg.fields += [PointField(name='_', offset=o, datatype=F32, count=1) for o in (12, 16)]
    np.testing.assert_allclose(cloud_to_xyz(msg)[0], pts, atol=1e-6)
    # names that are substrings of 'xyz' are other fields too
    for name in ('', 'xy', 'yz'):
        msg.fields[3].name = msg.fields[4].name = name
        np.testing.assert_allclose(cloud_to_xyz(msg)[0], pts, atol=1e-6)


def _good(pts):
    return hand_cloud(pts, [('x', 0, F32), ('y', 4, F32), ('z', 8, F32)], 12, height=2)


@pytest.mark.parametrize('breaker,match', [
    (lambda m: setattr(m, 'fields', m.fields[1:]), 'lacks field.*x'),
    (lambda m: setattr(m, 'fields', m.fields[:2]), 'lacks field.*z'),
    (lambda m: setattr(m, 'fields', []), 'lacks field'),
    (lambda m: setattr(m.fields[0], 'datatype', PointField.INT16), 'datatype'),
    (lambda m: setattr(m.fields[2], 'datatype', 42), 'datatype'),
    (lambda m: m.fields.append(PointField(name='y', offset=0, datatype=F32, count=1)),
     'duplicate'),
    (lambda m: setattr(m, 'point_step', 8), 'overruns point_step'),         # smaller than fields
    (lambda m: setattr(m.fields[2], 'offset', 10), 'overruns point_step'),
    (lambda m: setattr(m, 'point_step', 0), 'point_step must be > 0, got 0'),
    (lambda m: setattr(m, 'data', m.data[:-5]), 'needs'),                    # truncated
    (lambda m: setattr(m, 'data', array.array('B')), 'needs'),              # no data at all
    (lambda m: setattr(m, 'width', m.width * 2), 'row_step'),                # header lies
    (lambda m: setattr(m, 'row_step', 11), r'row_step 11 < width\*point_step 144'),  # organized
    (lambda m: setattr(m, 'data', m.data + array.array('B', [0] * 12)), 'needs'),  # data too long
    (lambda m: setattr(m, 'height', 1), 'needs'),                            # 2nd row ignored
    (lambda m: setattr(m.fields[1], 'offset', 2), 'overlap'),
    (lambda m: [setattr(f, 'offset', 0) for f in m.fields], 'overlap'),
    (lambda m: setattr(m.fields[0], 'count', 2), 'overlap'),                 # x[2] runs into y
    (lambda m: setattr(m.fields[2], 'count', 2), 'overruns point_step'),     # z[2] past the point
    (lambda m: setattr(m.fields[2], 'offset', 9), 'overruns point_step'),    # by one byte
    # count 0 is one value (as count 1): still 4 bytes, past the point at offset 10
    (lambda m: [setattr(m.fields[2], 'count', 0), setattr(m.fields[2], 'offset', 10)],
     'overruns point_step'),
])
def test_malformed_clouds_raise_named_error(pts, breaker, match):
    msg = _good(pts)
    breaker(msg)
    with pytest.raises(CloudFormatError, match=match):
        cloud_to_xyz(msg)
    assert issubclass(CloudFormatError, ValueError)


def test_xyz_to_cloud_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r'points must be \(n, 3\), got shape \(4, 2\)'):
        xyz_to_cloud(np.zeros((4, 2)), Header())
    with pytest.raises(ValueError, match="field 'p' has 3 values for 4 points"):
        xyz_to_cloud(np.zeros((4, 3)), Header(), {'p': np.zeros(3)})
    with pytest.raises(ValueError, match="duplicate field name 'x'"):
        xyz_to_cloud(np.zeros((4, 3)), Header(), {'x': np.zeros(4)})
    # is_dense says whether every point is finite
    assert not xyz_to_cloud([[0, 0, 1], [np.nan, 0, 1]], Header()).is_dense
    # 3 points without coordinates were an empty cloud (size 0), not an error
    with pytest.raises(ValueError, match=r'must be \(n, 3\), got shape \(3, 0\)'):
        xyz_to_cloud(np.zeros((3, 0)), Header())
    assert xyz_to_cloud(np.zeros(0), Header()).width == 0   # no points at all is fine


def _random_rotation(rng):
    q = rng.normal(size=4)
    return quaternion_to_rotation(q)


def test_pose_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(50):
        t = np.eye(4)
        t[:3, :3] = _random_rotation(rng)
        t[:3, 3] = rng.normal(size=3)
        pose = matrix_to_pose(t)
        assert isinstance(pose, Pose)
        q = [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
        np.testing.assert_allclose(pose_to_matrix(pose), t, atol=1e-12)
    for r in (np.diag([1, -1, -1]), np.diag([-1, 1, -1]), np.diag([-1, -1, 1])):  # 180 deg
        np.testing.assert_allclose(quaternion_to_rotation(rotation_to_quaternion(r)), r,
                                   atol=1e-12)
    with pytest.raises(ValueError, match='16 non-finite entries'):
        matrix_to_pose(np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match=r'shape \(3, 4\)'):
        matrix_to_pose(np.eye(4)[:3])
    # a NaN entry was reported as 'got shape (4, 4)': the shape it asks for
    t = np.eye(4)
    t[0, 3] = np.nan
    with pytest.raises(ValueError, match='1 non-finite entries') as err:
        matrix_to_pose(t)
    assert 'shape' not in str(err.value)


@pytest.mark.parametrize('up', [(0, 0, 1), (0, -1, 0), (1, 2, 3)])
def test_yaw_quaternion_rotates_about_up(up):
    yaw = 0.7
    q = yaw_quaternion(yaw, up)
    r = quaternion_to_rotation([q.x, q.y, q.z, q.w])
    u = np.asarray(up, float) / np.linalg.norm(up)
    np.testing.assert_allclose(r @ u, u, atol=1e-12)  # the axis is fixed
    assert math.isclose(np.trace(r), 1 + 2 * math.cos(yaw), abs_tol=1e-12)
    if up == (0, 0, 1):
        np.testing.assert_allclose(r[:2, :2], [[math.cos(yaw), -math.sin(yaw)],
                                               [math.sin(yaw), math.cos(yaw)]], atol=1e-12)
    with pytest.raises(ValueError, match='up must be a finite non-zero vector'):
        yaw_quaternion(1.0, (0, 0, 0))


def test_quaternions_of_huge_or_tiny_norm():
    # normalized by the norm alone: one of 1e200 components overflowed to the identity, one of
    # 1e-170 underflowed to NaN, and yaw_quaternion refused up=(0, 0, 1e200) as not finite
    quarter = quaternion_to_rotation([0, 0, 1, 1])
    for scale in (1e200, 1e-170, 1e-300):
        np.testing.assert_allclose(quaternion_to_rotation([0, 0, scale, scale]), quarter,
                                   atol=1e-12)
        q = yaw_quaternion(0.7, (0, 0, scale))
        np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, math.sin(0.35), math.cos(0.35)],
                                   atol=1e-12)
    for bad in ([0, 0, 0, 0], [0, 0, np.nan, 1], [0, 0, 1]):
        with pytest.raises(ValueError, match='quaternion'):
            quaternion_to_rotation(bad)


def test_estimate_to_msg():
    conv = pytest.importorskip('beo_ros.ros.conversions')
    try:
        conv.interfaces()
    except ImportError as e:
        pytest.skip(f'beo_interfaces not built: {e}')
    from beo_ros.core.estimate import Estimate, Hypothesis
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_rotation([0, 0, math.sin(0.25), math.cos(0.25)])
    pose[:3, 3] = [1.0, 2.0, 0.5]
    local = np.array([[-0.2, -0.1, -0.3], [0.2, 0.1, 0.3], [0.0, 0.0, 0.0]])
    g2i = np.eye(4) * 0.01
    g2i[3, 3] = 1
    est = Estimate(label='chair', scores={'chair': 0.8, 'table': 0.2}, yaw=0.5,
                   completion=np.zeros((4, 4, 4), np.float32),
                   variance=np.zeros((4, 4, 4), np.float32),
                   hypotheses=[Hypothesis('chair', 0.5, -1.0), Hypothesis('table', 1.0, -3.0)],
                   symmetric_yaws=[0.5 - np.pi], pose=pose, grid_to_input=g2i,
                   completed_points=(local @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32),
                   completed_probability=np.array([0.9, 0.8, 0.7], np.float32))
    h = Header(frame_id='cam')
    m = conv.estimate_to_msg(est, h, '/in', 0.25, include_cloud=True,
                             class_names=['table', 'chair'])
    assert m.label == 'chair' and abs(m.probability - 0.8) < 1e-6
    assert list(m.class_names) == ['table', 'chair']
    np.testing.assert_allclose(m.class_probabilities, [0.2, 0.8], atol=1e-6)
    np.testing.assert_allclose(pose_to_matrix(m.pose), pose, atol=1e-9)
    np.testing.assert_allclose([m.dimensions.x, m.dimensions.y, m.dimensions.z],
                               [0.41, 0.21, 0.61], atol=1e-5)
    assert [hh.label for hh in m.hypotheses] == ['chair', 'table']
    assert [hh.score for hh in m.hypotheses] == [-1.0, -3.0]
    prob = np.frombuffer(bytes(m.completed_cloud.data), '<f4').reshape(3, 4)[:, 3]
    np.testing.assert_array_equal(prob, np.float32([0.9, 0.8, 0.7]))
    np.testing.assert_allclose(m.symmetric_yaws, [0.5 - np.pi], rtol=1e-7)
    assert m.source_topic == '/in' and abs(m.latency - 0.25) < 1e-6 and m.status == 'ok'
    assert m.completed_cloud.width == 3 and m.completed_cloud.header.frame_id == 'cam'
    m2 = conv.estimate_to_msg(est, h, '/in', 0.0, include_cloud=False)
    assert m2.completed_cloud.width == 0 and list(m2.class_names) == ['chair', 'table']
    assert m2.completed_cloud.header.frame_id == 'cam'
    # a class the scores do not name has probability 0; no completed probability: 1 each
    m4 = conv.estimate_to_msg(est, h, class_names=['sofa', 'chair'])
    np.testing.assert_allclose(m4.class_probabilities, [0.0, 0.8], atol=1e-6)
    est.completed_probability = None
    m5 = conv.estimate_to_msg(est, h, include_cloud=True)
    prob = np.frombuffer(bytes(m5.completed_cloud.data), '<f4').reshape(3, 4)[:, 3]
    np.testing.assert_array_equal(prob, [1.0, 1.0, 1.0])
    # an estimate without pose: the identity orientation; no completed points: no extent
    bare = Estimate(label='chair', scores={'chair': 1.0}, yaw=0.0, completion=est.completion,
                    variance=est.variance)
    m6 = conv.estimate_to_msg(bare, h)
    assert (m6.pose.orientation.w, m6.pose.orientation.x) == (1.0, 0.0)
    bare.pose, bare.completed_points = pose, np.zeros((0, 3), np.float32)
    m7 = conv.estimate_to_msg(bare, h)
    assert [m7.dimensions.x, m7.dimensions.y, m7.dimensions.z] == [0.0, 0.0, 0.0]
    # yaws from estimate_points are in the grid frame: the message has headings in its frame
    est.heading_offset = 3.0
    m3 = conv.estimate_to_msg(est, h)
    np.testing.assert_allclose([hh.yaw for hh in m3.hypotheses],
                               [3.5 - 2 * np.pi, 4.0 - 2 * np.pi], atol=1e-9)
    np.testing.assert_allclose(m3.symmetric_yaws, [3.5 - np.pi], rtol=1e-6)


def test_stamps_round_trip_nanoseconds():
    from beo_ros.ros.bag import T0_NS
    from beo_ros.ros.conversions import ns_from_stamp, stamp_from_ns
    for ns in (0, 1, 999_999_999, 1_000_000_000, T0_NS + 123_456_789):
        t = stamp_from_ns(ns)
        assert 0 <= t.nanosec < 1_000_000_000 and ns_from_stamp(t) == ns
    assert (stamp_from_ns(T0_NS + 5).sec, stamp_from_ns(T0_NS + 5).nanosec) == (1_700_000_000, 5)
    from beo_ros.ros import MAX_STAMP_NS
    assert ns_from_stamp(stamp_from_ns(MAX_STAMP_NS)) == MAX_STAMP_NS
    for bad in (-1, MAX_STAMP_NS + 1):
        with pytest.raises(ValueError, match='outside what a builtin_interfaces/Time holds'):
            stamp_from_ns(bad)


def test_dimensions_keep_their_precision_far_from_the_origin(ros_tiny_model_dir):
    # the float32 completed points of a map frame are centimetres off at 1e6 m: the published
    # dimensions (and the marker box) came from them, up to 5 cm off on a 0.4 m object, while
    # the pose centre stayed exact
    conv = pytest.importorskip('beo_ros.ros.conversions')
    try:
        conv.interfaces()
    except ImportError as e:
        pytest.skip(f'beo_interfaces not built: {e}')
    from beo_ros.core.bank import load_models
    from beo_ros.core.synthetic import render_view_points
    bank = load_models(ros_tiny_model_dir)
    n = bank.spec.size
    occ = bank.models[0].mean.reshape((n,) * 3) > 0.5
    pts, origin = render_view_points(occ, 0.5, 0.3, np.deg2rad(30), distance=2.0, size=0.4)
    dims = []
    for shift in (np.zeros(3), np.array([9.9e5, -7e5, 10.0])):
        est = bank.estimate_points(pts + shift, sensor_origin=origin + shift, outlier_mads=None)
        d = conv.estimate_to_msg(est, Header(frame_id='map')).dimensions
        dims.append([d.x, d.y, d.z])
    assert min(dims[0]) > 0.1
    np.testing.assert_allclose(dims[1], dims[0], atol=1e-6)


def test_rotation_to_quaternion_near_half_turns_about_each_axis():
    # about 180 deg the quaternion comes from the largest diagonal entry: a branch taken for
    # another entry divides by a tiny s and loses the digits
    for axis in np.eye(3):
        for tilt in (1e-6, -1e-6):
            a = axis + tilt * np.roll(axis, 1)
            a /= np.linalg.norm(a)
            r = 2 * np.outer(a, a) - np.eye(3)            # 180 deg about a
            np.testing.assert_allclose(quaternion_to_rotation(rotation_to_quaternion(r)), r,
                                       atol=1e-12)


def test_matrix_to_pose_gives_a_unit_quaternion_of_a_rounded_rotation():
    # a rotation through float32 is no exact rotation: the quaternion is still normalised
    t = np.eye(4)
    t[:3, :3] = quaternion_to_rotation([0.3, -0.2, 0.5, 0.8]).astype(np.float32)
    o = matrix_to_pose(t).orientation
    assert abs(np.linalg.norm([o.x, o.y, o.z, o.w]) - 1) < 1e-12


def test_object_markers_box_label_and_lifetime():
    # the label floats 0.08 m above the highest completed point along the unit up vector
    # (here a camera optical frame's -y, given with length 2), the box has the estimate's pose
    # and dimensions (at least 1 cm), each marker the lifetime rounded to the nanosecond
    from types import SimpleNamespace

    from visualization_msgs.msg import Marker

    from beo_ros.ros.markers import delete_all_markers, delete_markers, object_markers
    centre = np.array([1.0, 2.0, 3.0])
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = centre
    pose.orientation.z, pose.orientation.w = math.sin(0.3), math.cos(0.3)
    out = SimpleNamespace(pose=pose, label='chair', probability=0.874)
    pts = centre + np.array([[0.0, -0.5, 0.1], [0.0, 0.3, 0.0], [0.2, 0.0, -0.1]])
    est = SimpleNamespace(dimensions=np.array([0.3, 0.0, 0.2]), completed_points=pts)
    h = Header(frame_id='cam')
    box, text = object_markers(est, out, h, 3, [0.0, -2.0, 0.0], lifetime=1.001).markers
    assert (box.ns, box.id, box.type, box.action) == ('beo', 6, Marker.CUBE, Marker.ADD)
    assert (text.ns, text.id, text.type) == ('beo', 7, Marker.TEXT_VIEW_FACING)
    assert box.header.frame_id == text.header.frame_id == 'cam'
    np.testing.assert_allclose(pose_to_matrix(box.pose), pose_to_matrix(pose), atol=1e-12)
    assert (box.scale.x, box.scale.y, box.scale.z) == (0.3, 0.01, 0.2)
    p = text.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], centre + [0.0, -0.58, 0.0], atol=1e-12)
    assert text.pose.orientation.w == 1.0 and text.text == 'chair 87%'
    for m in (box, text):
        assert (m.lifetime.sec, m.lifetime.nanosec) == (1, 1_000_000)   # 1000999999.9999999 ns
    # no completed points above the centre, or none at all: just above the centre
    for completed in (centre - [[0.0, 0.0, 0.4]], None):
        est = SimpleNamespace(dimensions=np.array([0.3, 0.2, 0.2]), completed_points=completed)
        _, text = object_markers(est, out, h, 0, [0.0, 0.0, 1.0], lifetime=2.5).markers
        p = text.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], centre + [0.0, 0.0, 0.08], atol=1e-12)
        assert (text.lifetime.sec, text.lifetime.nanosec) == (2, 500_000_000)
    assert [(m.ns, m.id, m.action) for m in delete_markers(h, 3).markers] == [
        ('beo', 6, Marker.DELETE), ('beo', 7, Marker.DELETE)]
    (every,) = delete_all_markers(h).markers
    assert (every.ns, every.action, every.header.frame_id) == ('beo', Marker.DELETEALL, 'cam')


@pytest.mark.parametrize('interval, seconds', [
    (None, 1.0), (float('inf'), 1.0), (float('nan'), 1.0), (0.2, 1.0), (0.5, 1.5)])
def test_auto_marker_lifetime(interval, seconds):
    # three intervals between estimates, at least 1 s (also with no finite interval yet)
    from beo_ros.ros.markers import auto_lifetime
    assert auto_lifetime(interval) == pytest.approx(seconds)
