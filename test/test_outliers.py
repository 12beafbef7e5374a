"""Outlier removal (beo_ros.core.outliers: statistical, largest cluster) and its use by
estimate_points."""
import numpy as np
import pytest

from beo_ros.core.bank import ModelBank
from beo_ros.core.outliers import clean_points, outside_largest_cluster, statistical_outliers
from beo_ros.core.synthetic import make_tiny_bank, render_view_points


def _patch(n=5000, seed=0):
    """(n, 3) points on a 0.3 m square, 1 mm of depth noise, 1 m ahead (a flat object face)."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(0, 0.3, n), rng.uniform(0, 0.3, n), rng.normal(0, 0.001, n)] \
        + [1.0, 0.0, 0.0]


def test_stray_points_at_every_distance_are_removed_and_nothing_else():
    # with the mean and standard deviation the 100 km point inflates both, and the points
    # 1 km, 10 m and 0.5 m out would stay; the median and MAD catch all four
    pts = _patch()
    strays = np.array([[1e5, 0, 0], [1e3, 0, 0], [10.0, 0, 0], [1.5, 0, 0]])
    out = statistical_outliers(np.r_[pts, strays])
    assert out[-4:].all()
    assert not out[:-4].any()


def test_a_clean_cloud_loses_nothing_and_a_lattice_nothing_either():
    assert not statistical_outliers(_patch()).any()
    # voxel centres: more than half the points have the same neighbour distance (MAD 0), the
    # corners and edges a little more; none is an outlier
    g = np.stack(np.meshgrid(*[np.arange(10.0)] * 3, indexing='ij'), -1).reshape(-1, 3)
    assert not statistical_outliers(g).any()


def test_repeated_points_do_not_make_everything_an_outlier():
    # every point 3 times: three of the 8 neighbour distances are 0; a lone stray is found
    pts = np.repeat(_patch(500), 3, axis=0)
    out = statistical_outliers(np.r_[pts, [[5.0, 0, 0]]])
    assert out[-1] and not out[:-1].any()
    # every point 12 times: all distances 0, no spread to judge by (and no stray among them)
    assert not statistical_outliers(np.repeat(_patch(500), 12, axis=0)).any()
    assert not statistical_outliers(np.zeros((50, 3))).any()   # one place


def test_many_copies_of_one_point_do_not_make_the_others_outliers():
    # 600 copies of one point of the patch (d = 0) are left out of the median and MAD: with
    # them the median is 0, the scale 0 and every other point of the patch an outlier
    p = _patch(500)
    pts = np.r_[p, np.tile(p[0], (600, 1)), [[5.0, 0, 0]]]
    assert np.flatnonzero(statistical_outliers(pts)).tolist() == [1100]


def test_neighbors_or_fewer_points_with_spread_are_never_outliers():
    # 20 copies of one point and 8 others (d > 0), one of them 3 m out: the documented limit
    # ("with neighbors or fewer points with d > 0 nothing is an outlier"), although 8 points
    # would give a median and MAD by which the far one is out
    ring = 0.01 * np.c_[np.cos(np.arange(8)), np.sin(np.arange(8)), np.zeros(8)]
    ring[-1] = [3.0, 0, 0]
    pts = np.r_[np.zeros((20, 3)), ring]
    assert not statistical_outliers(pts, neighbors=8).any()
    # one neighbour fewer: 8 points to judge by, and the far one is out
    assert np.flatnonzero(statistical_outliers(pts, neighbors=7)).tolist() == [27]


def test_a_cluster_of_strays_stays():
    # documented limit: twenty points together far away (as dense as the object) explain
    # each other
    rng = np.random.default_rng(1)
    cluster = rng.normal([5.0, 0, 0], 0.003, size=(20, 3))
    out = statistical_outliers(np.r_[_patch(), cluster])
    assert not out[-20:].any()


def test_few_points_are_never_outliers():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1e5, 0, 0]], float)
    assert not statistical_outliers(pts, neighbors=8).any()
    assert statistical_outliers(np.zeros((0, 3))).shape == (0,)


@pytest.mark.parametrize('kw, match', [
    ({'neighbors': 0}, 'neighbors must be'), ({'neighbors': True}, 'neighbors must be'),
    ({'neighbors': 2.5}, 'neighbors must be'), ({'mads': 0}, 'mads must be'),
    ({'mads': -1.0}, 'mads must be'), ({'mads': float('nan')}, 'mads must be'),
    ({'mads': float('inf')}, 'mads must be'), ({'mads': 'x'}, 'mads must be'),
    ({'mads': True}, 'mads must be'), ({'mads': None}, 'mads must be'),
    ({'mads': [1.0, 2.0]}, 'mads must be'), ({'mads': 1j}, 'mads must be'),
])
def test_bad_arguments_are_named(kw, match):
    with pytest.raises(ValueError, match=match):
        statistical_outliers(_patch(100), **kw)


@pytest.mark.parametrize('pts', [np.zeros((10, 2)), np.full((10, 3), np.nan), np.zeros(3)])
def test_bad_points_are_named(pts):
    with pytest.raises(ValueError, match='finite'):
        statistical_outliers(pts)


@pytest.fixture(scope='module')
def tiny():
    return make_tiny_bank()


def _view(bank):
    occ = bank.models[0].mean.reshape(bank.spec.shape) > 0.5
    return render_view_points(occ, 0.5, 0.3, np.deg2rad(30), distance=2.0, size=0.4)


def test_estimate_points_is_not_spoilt_by_a_stray_point(tiny):
    pts, origin = _view(tiny)
    clean = tiny.estimate_points(pts, sensor_origin=origin)
    stray = np.r_[pts, [[300.0, 0.0, 0.0]]]
    e = tiny.estimate_points(stray, sensor_origin=origin)
    assert e.n_outliers >= 1 and clean.n_outliers == e.n_outliers - 1
    assert e.label == clean.label and e.yaw == pytest.approx(clean.yaw)
    np.testing.assert_allclose(e.pose, clean.pose, atol=1e-9)
    np.testing.assert_allclose(e.grid_to_input, clean.grid_to_input, atol=1e-9)
    assert 'outliers' in e.timings
    # without the removal the stray point sets the grid's scale: the object shrinks
    raw = tiny.estimate_points(stray, sensor_origin=origin, outlier_mads=None)
    assert raw.n_outliers == 0
    assert np.abs(raw.grid).sum() != 0 and (raw.grid == 1).sum() < (clean.grid == 1).sum() / 4


def test_estimate_points_names_bad_outlier_arguments(tiny):
    pts, origin = _view(tiny)
    # under the names estimate_points (and the node's parameters) give them
    with pytest.raises(ValueError, match='^outlier_mads must be'):
        tiny.estimate_points(pts, sensor_origin=origin, outlier_mads=0.0)
    with pytest.raises(ValueError, match='^outlier_neighbors must be'):
        tiny.estimate_points(pts, sensor_origin=origin, outlier_neighbors=0)
    with pytest.raises(ValueError, match='^cluster_tolerance must be'):
        tiny.estimate_points(pts, sensor_origin=origin, cluster_tolerance=-0.01)


def test_a_voxelization_refusal_after_the_cleaning_names_the_cleaning(tiny):
    """100 copies of one point and a stray one: the removal leaves points that span 0; the
    refusal says that the cleaning left them (it named only the span)."""
    origin = np.array([0.0, 0.0, 2.0])
    pts = np.vstack([np.tile([0.1, 0.2, 0.0], (100, 1)), [[0.6, -0.3, 0.2]]])
    with pytest.raises(ValueError, match=r'span 0.*after removing 1 outliers'):
        tiny.estimate_points(pts, sensor_origin=origin, outlier_neighbors=100)
    with pytest.raises(ValueError, match='span 0') as e:   # nothing removed: as it was
        tiny.estimate_points(pts[:100], sensor_origin=origin, outlier_mads=None)
    assert 'removing' not in str(e.value)


def test_estimate_points_on_a_metric_grid_keeps_a_stray_point_out_of_the_placement():
    # a metric (tabletop) grid: without the removal the stray point 3 m behind moves the box
    # off the object (no point inside the grid: refused); with it the answer is the same
    import beo_ros
    from pathlib import Path
    bank = beo_ros.load_models(Path(__file__).resolve().parents[1] / 'models' / 'tabletop_32')
    assert isinstance(bank, ModelBank) and bank.spec.units == 'metric'
    rng = np.random.default_rng(0)
    top = np.c_[rng.uniform(-0.08, 0.08, 800), rng.uniform(-0.05, 0.05, 800), np.full(800, 0.12)]
    front = np.c_[np.full(800, -0.08), rng.uniform(-0.05, 0.05, 800), rng.uniform(0, 0.12, 800)]
    pts = np.r_[top, front]
    clean = bank.estimate_points(pts, sensor_origin=(-0.8, 0.0, 0.5))
    e = bank.estimate_points(np.r_[pts, [[3.0, 0.0, 0.05]]], sensor_origin=(-0.8, 0.0, 0.5))
    assert e.label == clean.label
    np.testing.assert_allclose(e.pose, clean.pose, atol=1e-9)
    with pytest.raises(ValueError, match='none of the'):
        bank.estimate_points(np.r_[pts, [[3.0, 0.0, 0.05]]], sensor_origin=(-0.8, 0.0, 0.5),
                             outlier_mads=None)


def test_estimate_points_counts_the_points_outside_a_metric_grid():
    # a box 0.8 m tall in the 0.5 m tabletop grid: its top part was dropped without a count
    # (load_scan_objects warns of the same in training)
    import beo_ros
    from pathlib import Path
    bank = beo_ros.load_models(Path(__file__).resolve().parents[1] / 'models' / 'tabletop_32')
    rng = np.random.default_rng(0)
    front = np.c_[np.full(3000, -0.08), rng.uniform(-0.05, 0.05, 3000), rng.uniform(0, 0.8, 3000)]
    tall = bank.estimate_points(front, sensor_origin=(-0.8, 0.0, 0.5), outlier_mads=None)
    # the grid floor at the box's bottom, its top 0.5 m above
    top = front[:, 2].min() + bank.spec.size * bank.spec.voxel_size
    assert tall.n_outside_grid == int((front[:, 2] > top + 1e-6).sum()) > 1000
    low = bank.estimate_points(front[front[:, 2] < 0.3], sensor_origin=(-0.8, 0.0, 0.5))
    assert low.n_outside_grid == 0


# ---------------------------------------------------------------- largest cluster

def test_the_largest_cluster_is_kept_and_a_dense_cluster_of_strays_goes():
    # the cluster the statistical removal keeps (see test_a_cluster_of_strays_stays)
    rng = np.random.default_rng(1)
    cluster = rng.normal([5.0, 0, 0], 0.003, size=(20, 3))
    pts = np.r_[_patch(), cluster]
    off = outside_largest_cluster(pts, 0.02)
    assert off[-20:].all() and not off[:-20].any()
    # order does not matter: the largest wins, wherever it is
    off = outside_largest_cluster(np.r_[cluster, _patch()], 0.02)
    assert off[:20].all() and not off[20:].any()


def test_cluster_tolerance_bounds():
    # two lines of points 1 cm apart along x; the lines are `gap` apart along y
    line = np.c_[np.arange(0, 1, 0.01), np.zeros(100), np.zeros(100)]
    small = np.c_[np.arange(0, 0.3, 0.01), np.zeros(30), np.zeros(30)]
    tol = 0.02
    # closer than the tolerance: joined; beyond 2 sqrt(3) tolerances (0.0693), in any
    # direction: apart
    for shift, joined in (([0, 0.0199, 0], True), ([0, 0.0694, 0], False),
                          ([0, 0.04, 0.057], False), ([0.0401, 0.0401, 0.0401], False),
                          ([0, 0.1, 0], False)):
        assert joined or np.linalg.norm(shift) > 2 * np.sqrt(3) * tol
        off = outside_largest_cluster(np.r_[line, small + shift], tol)
        assert not off[:100].any()
        assert (not off[100:].any()) if joined else off[100:].all(), shift
    # between the two bounds the cells decide: lines 2.25 tolerances apart along y lie in
    # cells 0 and 2, which do not touch (a neighbour radius of 2+ cells joined them)
    off = outside_largest_cluster(np.r_[line, small + [0, 0.045, 0]], tol)
    assert not off[:100].any() and off[100:].all()
    # closer than the tolerance along a diagonal: the cells touch at an edge or a corner only
    # (the neighbour radius reaches sqrt(3) cells); the first point puts the cells' corner
    for step in ([0.5, 0.5, 0.0], [0.5, 0.5, 0.5]):
        pts = np.array([[0, 0, 0], np.multiply(step, 1.4), np.multiply(step, 2.4)]) * tol
        assert np.linalg.norm(pts[2] - pts[1]) < tol
        assert not outside_largest_cluster(pts, tol).any(), step
    # a chain of points each closer than the tolerance is one cluster, however long
    chain = np.c_[np.arange(0, 10, 0.019), np.zeros(527), np.zeros(527)]
    assert not outside_largest_cluster(chain, tol).any()


def test_clusters_do_not_depend_on_where_the_cloud_is():
    # the cells start at the points' minimum, so moving the cloud moves its cells with it: a
    # point 1.5 tolerances beyond the minimum is always in the next cell (joined); with cells
    # fixed in space it fell two cells away (apart) for some positions
    pts = np.array([[0, 0, 0], [0, 0, 0], [1.5, 0, 0]])
    for shift in (0.0, 0.25, 0.5, 0.75, -0.25, 100.25, -100.75):
        moved = pts + [shift, shift, -shift]
        assert not outside_largest_cluster(moved, 1.0).any(), shift
    # and a point 2.5 tolerances beyond is always two cells away
    apart = np.r_[pts[:2], [[2.5, 0, 0]]]
    for shift in (0.0, 0.25, 0.5, 0.75, -0.25, 100.25, -100.75):
        assert outside_largest_cluster(apart + shift, 1.0).tolist() == [False, False, True]


def test_equal_clusters_keep_the_one_with_the_first_point():
    a = np.zeros((10, 3))
    b = np.full((10, 3), 5.0)
    off = outside_largest_cluster(np.r_[b, a], 0.1)
    assert not off[:10].any() and off[10:].all()
    off = outside_largest_cluster(np.r_[a[:5], b, a[5:]], 0.1)
    assert off[5:15].all() and not off[:5].any() and not off[15:].any()


def test_cluster_of_few_points_and_one_place():
    assert outside_largest_cluster(np.zeros((0, 3)), 0.1).shape == (0,)
    assert not outside_largest_cluster(np.zeros((1, 3)), 0.1).any()
    assert not outside_largest_cluster(np.zeros((7, 3)), 0.1).any()
    assert outside_largest_cluster(np.array([[0, 0, 0], [1.0, 0, 0]]), 0.1).tolist() == \
        [False, True]


@pytest.mark.parametrize('tol', [0, -1.0, float('nan'), float('inf'), True, 'x', None,
                                 [0.1, 0.2], 1j])
def test_bad_cluster_tolerance_is_named(tol):
    with pytest.raises(ValueError, match='tolerance must be'):
        outside_largest_cluster(_patch(100), tol)


def test_a_tolerance_too_small_for_the_extent_is_named():
    with pytest.raises(ValueError, match='too small'):
        outside_largest_cluster(np.array([[0, 0, 0], [1e3, 0, 0]]), 1e-300)
    # 1e16 cells: past 2**52 a float no longer holds every cell index (neighbours merge)
    with pytest.raises(ValueError, match='too small'):
        outside_largest_cluster(np.array([[0, 0, 0], [1e3, 0, 0]]), 1e-13)
    # 1e15 cells: still exact
    assert outside_largest_cluster(np.array([[0, 0, 0], [1e3, 0, 0]]), 1e-12).tolist() == \
        [False, True]


@pytest.mark.parametrize('pts', [np.zeros((10, 2)), np.full((10, 3), np.inf), np.zeros(3)])
def test_bad_points_are_named_by_the_clustering(pts):
    with pytest.raises(ValueError, match='finite'):
        outside_largest_cluster(pts, 0.1)


def test_estimate_points_keeps_the_largest_cluster_on_request(tiny):
    # a dense blob 1 m beside the object survives the statistical removal and spoils the
    # grid; with a cluster_tolerance the answer is the clean cloud's
    pts, origin = _view(tiny)
    clean = tiny.estimate_points(pts, sensor_origin=origin)
    rng = np.random.default_rng(3)
    blob = rng.normal(pts.mean(axis=0) + [0.0, 1.0, 0.0], 0.005, size=(40, 3))
    spoilt = tiny.estimate_points(np.r_[pts, blob], sensor_origin=origin)
    assert spoilt.n_off_cluster == 0 and not np.allclose(spoilt.grid_to_input,
                                                         clean.grid_to_input)
    e = tiny.estimate_points(np.r_[pts, blob], sensor_origin=origin, cluster_tolerance=0.05)
    assert e.n_off_cluster == 40 and e.n_outliers == clean.n_outliers
    assert clean.n_off_cluster == 0
    assert e.label == clean.label and e.yaw == pytest.approx(clean.yaw)
    np.testing.assert_allclose(e.grid_to_input, clean.grid_to_input, atol=1e-9)
    np.testing.assert_allclose(e.pose, clean.pose, atol=1e-9)
    with pytest.raises(ValueError, match='tolerance must be'):
        tiny.estimate_points(pts, sensor_origin=origin, cluster_tolerance=0.0)


@pytest.mark.parametrize('name, value', [
    ('sensor_origin', 'abc'), ('sensor_origin', None), ('sensor_origin', [0, 0]),
    ('up', [1, 'x', 2]), ('up', (0, 0, 10 ** 400)), ('up', (0, 0, 0))])
def test_estimate_points_names_a_bad_sensor_origin_or_up(tiny, name, value):
    # 'abc' was numpy's "could not convert string to float", naming neither
    pts, origin = _view(tiny)
    kw = {'sensor_origin': origin, name: value}
    with pytest.raises(ValueError, match=name + ' must be'):
        tiny.estimate_points(pts, **kw)


_PATCH = np.random.default_rng(0).normal(size=(30, 3))


@pytest.mark.parametrize('pts', [
    _PATCH.astype(str), _PATCH.astype('S24'), _PATCH.astype(object),
    np.array([[None, 1.0, 2.0]] * 20, dtype=object), _PATCH + 0j, _PATCH.astype(complex) + 1j,
    _PATCH > 0, np.ones((20, 3), dtype='timedelta64[s]'),
    np.full((20, 3), '2020-01-01', dtype='datetime64[D]'), {'x': 1}, [[0.0, 1.0, 2.0], [3.0]],
])
@pytest.mark.parametrize('clean', [
    statistical_outliers, lambda p: outside_largest_cluster(p, 0.5), clean_points])
def test_non_numeric_points_are_refused_by_name(pts, clean):
    # strings were parsed as numbers ('1.5' -> 1.5), complex numbers lost their imaginary
    # part (a warning only), a dict failed in float() with a TypeError, None became NaN (and
    # the message named the shape (20, 3))
    with pytest.raises(ValueError, match=r'^points must be a finite \(n, 3\) array( of real '
                                         r'numbers, got dtype|, got rows of different lengths)'):
        clean(pts)


def test_complex_scalar_arguments_are_refused_by_name():
    # numpy's complex 8+0j passed as mads 8.0 (float() drops the imaginary part, a warning only)
    with pytest.raises(ValueError, match='^mads must be'):
        statistical_outliers(_PATCH, mads=np.complex128(8.0))
    with pytest.raises(ValueError, match='^tolerance must be'):
        outside_largest_cluster(_PATCH, np.complex64(0.5))
    with pytest.raises(ValueError, match='^outlier_mads must be'):
        clean_points(_PATCH, outlier_mads=np.complex128(8.0))
