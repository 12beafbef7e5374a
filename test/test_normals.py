"""Side-normal descriptors of raw object points (beo_ros.core.normals), on generated clouds."""
import numpy as np
import pytest

from beo_ros.core.normals import RADIUS, point_normals, side_normal_descriptors

UP = np.array([0.0, 0.0, 1.0])
SENSOR = np.array([-0.6, -0.45, 0.4])        # in front of and above the object at the origin


def _grid(a, b, step=0.004):
    u, v = np.meshgrid(np.arange(0, a, step), np.arange(0, b, step), indexing='ij')
    return u.ravel(), v.ravel()


def box_front(w=0.12, d=0.08, h=0.15, rng=None):
    """The faces of an axis-aligned box visible from SENSOR: -x and -y sides and the top."""
    rng = rng or np.random.default_rng(0)
    parts = []
    u, v = _grid(d, h)
    parts.append(np.c_[np.zeros_like(u), u, v])            # x = 0 face
    u, v = _grid(w, h)
    parts.append(np.c_[u, np.zeros_like(u), v])            # y = 0 face
    u, v = _grid(w, d)
    parts.append(np.c_[u, v, np.full_like(u, h)])          # top
    p = np.concatenate(parts) - [w / 2, d / 2, 0]
    return p + rng.normal(0, 0.0005, p.shape)


def cylinder_front(r=0.04, h=0.12, rng=None):
    """The half of a vertical cylinder's side facing SENSOR, and its top."""
    rng = rng or np.random.default_rng(1)
    toward = np.arctan2(SENSOR[1], SENSOR[0])
    a, z = np.meshgrid(toward + np.linspace(-np.pi / 2, np.pi / 2, 80),
                       np.arange(0, h, 0.004), indexing='ij')
    side = np.c_[r * np.cos(a.ravel()), r * np.sin(a.ravel()), z.ravel()]
    u, v = _grid(2 * r, 2 * r)
    top = np.c_[u - r, v - r, np.full_like(u, h)]
    top = top[np.hypot(top[:, 0], top[:, 1]) <= r]
    p = np.concatenate([side, top])
    return p + rng.normal(0, 0.0005, p.shape)


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_box_faces_fold_onto_one_direction_and_a_cylinder_front_does_not():
    r4_box, f_box = side_normal_descriptors(box_front(), UP, SENSOR)
    r4_cyl, f_cyl = side_normal_descriptors(cylinder_front(), UP, SENSOR)
    assert r4_box > 0.8 and f_box > 0.8, (r4_box, f_box)   # edges blur a few normals
    assert r4_cyl < 0.2 and f_cyl < 0.4, (r4_cyl, f_cyl)


@pytest.mark.parametrize('make', [box_front, cylinder_front])
def test_invariant_to_rotation_about_up_and_to_the_frame(make):
    pts = make()
    ref = side_normal_descriptors(pts, UP, SENSOR)
    for a in (0.3, 1.0, 2.5):
        R = rot_z(a)
        got = side_normal_descriptors(pts @ R.T, UP, R @ SENSOR)
        np.testing.assert_allclose(got, ref, atol=0.02)
    # a camera-like frame (z forward, y down) with up expressed in it, sensor at its origin
    M = np.array([[0, -1.0, 0], [0.3, 0, -0.954], [0.954, 0, 0.3]])
    M, _ = np.linalg.qr(M)
    M *= np.sign(np.linalg.det(M))
    got = side_normal_descriptors((pts - SENSOR) @ M.T, M @ UP, np.zeros(3))
    np.testing.assert_allclose(got, ref, atol=0.02)


def test_normals_point_toward_the_sensor_and_subsampling_is_bounded():
    pts = box_front()
    idx, n, sv = point_normals(pts, SENSOR, max_query=500)
    assert len(idx) <= 500 and n.shape == (len(idx), 3) and sv.shape == (len(idx),)
    ok = np.isfinite(n).all(axis=1)
    assert ok.mean() > 0.99
    assert (np.einsum('ij,ij->i', n[ok], SENSOR - pts[idx][ok]) >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(n[ok], axis=1), 1.0, atol=1e-9)
    full = side_normal_descriptors(pts, UP, SENSOR, max_query=None)
    np.testing.assert_allclose(side_normal_descriptors(pts, UP, SENSOR), full, atol=0.03)


def test_undefined_for_tiny_or_sideless_clouds():
    assert np.isnan(side_normal_descriptors(box_front()[:5], UP, SENSOR)).all()
    u, v = _grid(0.2, 0.2)
    flat = np.c_[u, v, np.zeros_like(u)]                  # a table top: no side normals
    assert np.isnan(side_normal_descriptors(flat, UP, SENSOR)).all()
    isolated = np.arange(60, dtype=float)[:, None] * [0.1, 0.0, 0.0]   # no neighbours in 2 cm
    assert np.isnan(side_normal_descriptors(isolated, UP, SENSOR)).all()


def test_copies_of_points_and_lines_do_not_make_side_normals():
    # copies used to fill each neighbourhood (30 nearest rows) with one place and lines have no
    # normal: both gave an arbitrary but fixed axis at every point, i.e. a perfect "box"
    cyl = cylinder_front()
    want = side_normal_descriptors(cyl, UP, SENSOR)
    np.testing.assert_array_equal(side_normal_descriptors(np.repeat(cyl, 30, axis=0), UP, SENSOR),
                                  want)
    line = np.linspace(0, 0.2, 200)[:, None] * [0.0, 0.0, 1.0]      # a vertical line
    assert np.isnan(side_normal_descriptors(line, UP, SENSOR)).all()
    _, normals, sv = point_normals(line, SENSOR)
    assert np.isnan(normals).all() and np.isnan(sv).all()


def test_no_points_have_no_normals():
    # cKDTree.query of an empty cloud failed with numpy's 'zero-size array to reduction
    # operation maximum which has no identity'
    idx, normals, sv = point_normals(np.zeros((0, 3)), SENSOR)
    assert idx.shape == (0,) and normals.shape == (0, 3) and sv.shape == (0,)


@pytest.mark.parametrize('points, up, origin, msg', [
    (np.zeros((20, 2)), UP, SENSOR, r'\(n, 3\)'),
    (np.r_[box_front()[:20], [[np.nan, 0, 0]]], UP, SENSOR, 'NaN'),
    (box_front()[:20], np.zeros(3), SENSOR, 'up'),
    (box_front()[:20], np.array([0, 0, np.inf]), SENSOR, 'up'),
    (box_front()[:20], UP, np.array([0.0, 1.0]), 'sensor_origin'),
])
def test_bad_input_is_refused(points, up, origin, msg):
    with pytest.raises(ValueError, match=msg):
        side_normal_descriptors(points, up, origin)


def test_frac10_and_r4_match_their_definitions():
    from beo_ros.core.normals import descriptors_from_normals
    rng = np.random.default_rng(3)
    theta = np.r_[rng.normal(0.4, 0.05, 300), rng.normal(0.4 + np.pi / 2, 0.05, 200),
                  rng.uniform(-np.pi, np.pi, 500)]
    n = np.c_[np.cos(theta), np.sin(theta), rng.uniform(-0.3, 0.3, len(theta))]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    r4, frac10, ns = descriptors_from_normals(n, UP)
    assert ns == len(theta)
    assert r4 == pytest.approx(abs(np.mean(np.exp(4j * theta))), abs=1e-9)
    t90 = np.degrees(theta) % 90.0
    dist = np.abs((t90[None, :] - np.arange(90.0)[:, None] + 45.0) % 90.0 - 45.0)
    assert frac10 == pytest.approx((dist <= 10.0).mean(axis=1).max(), abs=2.0 / len(theta))
    assert frac10 > 0.5


@pytest.mark.parametrize('kwargs, msg', [
    (dict(max_nn=0), 'max_nn must be an integer >= 1, got 0'),
    (dict(max_nn=2.5), 'max_nn'),
    (dict(max_nn=float('nan')), 'max_nn'),
    (dict(radius=-0.02), 'radius must be a finite number > 0'),
    (dict(radius=float('nan')), 'radius'),
    (dict(max_query=-5), 'max_query must be an integer >= 1 or None, got -5'),
])
def test_bad_neighbourhood_parameters_are_refused_by_name(kwargs, msg):
    # max_nn 0 failed in numpy ('zero-size array to reduction operation maximum'), a NaN
    # max_nn in int(), a negative radius gave normals from any distance and a negative
    # max_query no query points at all
    with pytest.raises(ValueError, match=msg):
        point_normals(box_front(), SENSOR, **kwargs)


_BOX = box_front()[:200]
_NON_NUMERIC = [lambda a: a.astype(str), lambda a: a.astype('S24'), lambda a: a.astype(object),
                lambda a: a + 0j, lambda a: a > 0, lambda a: a.astype('timedelta64[s]')]
_DTYPE = 'of real numbers, got dtype'


@pytest.mark.parametrize('bad', _NON_NUMERIC)
@pytest.mark.parametrize('which', ['points', 'up', 'sensor_origin'])
def test_non_numeric_input_is_refused_by_name(bad, which):
    # strings were parsed as numbers ('0.5' -> 0.5), complex numbers lost their imaginary
    # part (a warning only), bools and timedeltas passed as numbers
    args = {'points': _BOX, 'up': UP, 'sensor_origin': SENSOR}
    args[which] = bad(args[which])
    with pytest.raises(ValueError, match=f'^{which} must be .* {_DTYPE}'):
        side_normal_descriptors(**args)
    if which != 'up':
        with pytest.raises(ValueError, match=f'^{which} must be .* {_DTYPE}'):
            point_normals(args['points'], args['sensor_origin'])


def test_non_numeric_normals_radius_and_ragged_points_are_refused_by_name():
    from beo_ros.core.normals import descriptors_from_normals
    normals = np.tile([1.0, 0.0, 0.0], (20, 1))
    for bad in _NON_NUMERIC:
        with pytest.raises(ValueError, match=f'^normals must be .* {_DTYPE}'):
            descriptors_from_normals(bad(normals), UP)
        with pytest.raises(ValueError, match=f'^up must be .* {_DTYPE}'):
            descriptors_from_normals(normals, bad(UP))
    # a dict failed in float() with a TypeError, None rows became NaN and were dropped
    with pytest.raises(ValueError, match=f'^points must be .* {_DTYPE} object'):
        side_normal_descriptors({'x': 1}, UP, SENSOR)
    with pytest.raises(ValueError, match=f'^normals must be .* {_DTYPE} object'):
        descriptors_from_normals(np.r_[normals, [[None, 0, 0]]], UP)
    with pytest.raises(ValueError, match='^points must be an .*rows of different lengths'):
        point_normals([[0.0, 0.0, 0.0], [1.0, 0.0]], SENSOR)
    # a numpy complex radius passed isinstance(np.number) and the k-d tree dropped its
    # imaginary part (a warning only)
    with pytest.raises(ValueError, match='^radius must be a finite number > 0'):
        point_normals(_BOX, SENSOR, radius=np.complex128(0.02))


def _normals_by_definition(pts, origin, radius, max_nn):
    """point_normals' documented result at every point, by brute force."""
    normals, svs = np.full((len(pts), 3), np.nan), np.full(len(pts), np.nan)
    for i, p in enumerate(pts):
        d = np.linalg.norm(pts - p, axis=1)
        near = np.argsort(d, kind='stable')[:max_nn]
        near = near[d[near] <= radius]
        q = pts[near]
        cov = (q - q.mean(axis=0)).T @ (q - q.mean(axis=0)) / len(q)
        ev, vec = np.linalg.eigh(cov)
        if len(q) < 3 or ev[1] <= 1e-6 * ev.sum():
            continue
        n = vec[:, 0] if vec[:, 0] @ (origin - p) >= 0 else -vec[:, 0]
        normals[i], svs[i] = n, ev[0] / ev.sum()
    return normals, svs


@pytest.mark.parametrize('max_nn', [30, 6])
def test_point_normals_match_their_definition(max_nn):
    # a curved noisy patch (11 to 63 points within 2 cm of each) and two lone points (2 each,
    # no normal): the covariance over the at most max_nn nearest points within the radius (the
    # missing ones not counted), its smallest eigenvector toward the sensor, l0 / (l0 + l1 + l2)
    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.05, 0.05, (400, 2))
    pts = np.c_[xy, 3 * (xy ** 2).sum(axis=1) + rng.normal(0, 0.002, 400)]
    pts = np.r_[pts, [[0.3, 0.0, 0.0], [0.3, 0.015, 0.0]]]
    idx, normals, sv = point_normals(pts, SENSOR, max_nn=max_nn, max_query=None)
    want_n, want_sv = _normals_by_definition(pts, SENSOR, RADIUS, max_nn)
    np.testing.assert_array_equal(idx, np.arange(len(pts)))
    np.testing.assert_array_equal(np.isnan(normals), np.isnan(want_n))
    assert np.isnan(normals[-2:]).all() and np.isfinite(normals[:-2]).mean() > 0.95
    np.testing.assert_allclose(normals, want_n, atol=1e-6)
    np.testing.assert_allclose(sv, want_sv, rtol=1e-6, atol=1e-12)


def test_a_tilted_line_has_no_normals():
    # off the axes, rounding leaves the line's second eigenvalue a little above 0: still a line
    line = np.linspace(0, 0.2, 200)[:, None] * np.array([1.0, 2.0, 3.0]) / np.sqrt(14) + 0.1
    _, normals, sv = point_normals(line, SENSOR)
    assert np.isnan(normals).all() and np.isnan(sv).all()


def test_query_points_are_at_most_max_query():
    pts = box_front()
    for n, max_query, want in ((1001, 500, 3), (1000, 500, 2), (499, 500, 1), (1501, 1, 1501)):
        idx, _, _ = point_normals(pts[:n], SENSOR, max_query=max_query)
        # every ceil(n / max_query)-th point
        np.testing.assert_array_equal(idx, np.arange(0, n, want))
        assert len(idx) <= max_query


def test_side_normals_are_within_45_degrees_of_horizontal_and_need_ten():
    from beo_ros.core.normals import descriptors_from_normals, horizontal_basis

    def tilted(elev_deg, k):   # k normals at this elevation above the horizontal, theta 0
        e = np.radians(elev_deg)
        return np.tile([np.cos(e), 0.0, np.sin(e)], (k, 1))
    # 44 deg and -44 deg are side normals, 46 deg and -46 deg not
    r4, frac10, ns = descriptors_from_normals(np.r_[tilted(44, 6), tilted(-44, 4),
                                                    tilted(46, 7), tilted(-46, 3)], UP)
    assert ns == 10 and r4 == pytest.approx(1.0) and frac10 == 1.0
    # 9 side normals: undefined
    r4, frac10, ns = descriptors_from_normals(np.r_[tilted(0, 9), tilted(80, 20)], UP)
    assert ns == 9 and np.isnan(r4) and np.isnan(frac10)
    up, e1, e2 = horizontal_basis([0.0, 0.0, 5.0])
    np.testing.assert_allclose(np.c_[e1, e2, up].T @ np.c_[e1, e2, up], np.eye(3), atol=1e-15)
    assert np.linalg.det(np.c_[e1, e2, up]) == pytest.approx(1.0)   # right-handed
