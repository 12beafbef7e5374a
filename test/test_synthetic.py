"""Synthetic partial views (the evaluation protocol), rendered clouds and generated shapes."""
import numpy as np
import pytest

from beo_ros.core.grid import rotate_grid
from beo_ros.core.synthetic import (partial_view, primitive_shapes, random_partial_view,
                                    render_surface_points, render_view_points, view_direction)

N = 16


def cube(lo=5, hi=11):
    occ = np.zeros((N,) * 3, dtype=bool)
    occ[lo:hi, lo:hi, lo:hi] = True
    return occ


def test_cube_seen_from_plus_x():
    occ = cube()
    lab = partial_view(occ, azimuth=0.0, elevation=0.0)
    assert lab.dtype == np.int8 and lab.shape == occ.shape
    s = slice(5, 11)
    assert (lab[10, s, s] == 1).all()          # the face toward +x is the first hit
    assert (lab[11:, s, s] == 0).all()         # in front of it: seen free
    assert (lab[:10, s, s] == -1).all()        # interior and behind: unknown
    sil = np.zeros((N, N), dtype=bool)
    sil[s, s] = True
    assert (lab[:, ~sil] == 0).all()           # rays that miss: free
    assert (lab == 1).sum() == 36


def test_cube_seen_from_plus_y():
    occ = cube()
    lab = partial_view(occ, azimuth=np.pi / 2, elevation=0.0)
    s = slice(5, 11)
    assert (lab[s, 10, s] == 1).all()
    assert (lab[s, 11:, s] == 0).all()
    assert (lab[s, :10, s] == -1).all()


def test_view_direction_is_unit_toward_viewer():
    np.testing.assert_allclose(view_direction(0.0, 0.0), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(view_direction(np.pi / 2, 0.0), [0, 1, 0], atol=1e-12)
    d = view_direction(0.3, 0.4)
    assert abs(np.linalg.norm(d) - 1) < 1e-12 and d[2] > 0


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_labels_are_consistent_with_the_truth(seed):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(seed))
    rng = np.random.default_rng(seed)
    for row in X:
        occ = row.reshape((N,) * 3) > 0.5
        lab = partial_view(occ, rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(10, 50)))
        assert set(np.unique(lab)) <= {-1, 0, 1}
        assert (lab == 1).any() and (lab == -1).any() and (lab == 0).any()
        assert occ[lab == 1].all()             # first hits are occupied
        assert not occ[lab == 0].any()         # nothing seen free is occupied
        # every occupied voxel is either seen or hidden behind a hit
        assert np.isin(lab[occ], [1, -1]).all()


def test_partial_view_of_a_large_grid_holds_the_rays_in_chunks():
    # every ray sample was held at once: 0.8 GB at 64^3, about 7 GB at 128^3 (GridSpec takes
    # up to 256^3); the rays go RAY_SAMPLES samples at a time, with the same labels
    import tracemalloc
    n = 64
    occ = np.zeros((n,) * 3, dtype=bool)
    occ[16:48, 16:48, :32] = True
    tracemalloc.start()
    try:
        lab = partial_view(occ, 0.3, 0.5)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 250e6, peak
    assert occ[lab == 1].all() and not occ[lab == 0].any() and np.isin(lab[occ], [1, -1]).all()
    assert (lab[:, :, 40:] == 0).all()   # above the box, seen from above: free


def test_random_partial_view_returns_rotated_truth():
    X, _, _ = primitive_shapes(N, 2, np.random.default_rng(3))
    occ = X[0].reshape((N,) * 3) > 0.5         # a box: not yaw-symmetric
    rng = np.random.default_rng(7)
    grid, yaw, az, el, rotated = random_partial_view(occ, rng)
    assert 0 <= yaw < 2 * np.pi and 0 <= az < 2 * np.pi
    assert np.deg2rad(10) <= el <= np.deg2rad(50)
    np.testing.assert_array_equal(rotated, rotate_grid(occ.astype(np.uint8), yaw).astype(bool))
    np.testing.assert_array_equal(grid, partial_view(rotated, az, el))
    assert rotated[grid == 1].all()
    assert not rotated[grid == 0].any()
    # the yaw is actually applied (a box rotated by a non-multiple of 180 deg differs)
    d = np.rad2deg(yaw) % 180
    if 10 < d < 170:
        assert not np.array_equal(rotated, occ)
    # the same rng state gives the same view
    g2 = random_partial_view(occ, np.random.default_rng(7))
    np.testing.assert_array_equal(g2[0], grid)
    assert g2[1] == yaw


def test_render_view_points_lie_on_the_visible_surface():
    occ = cube()
    pts, origin = render_view_points(occ, 0.0, 0.0, 0.0, distance=2.0, size=1.0)
    assert pts.dtype == np.float32 and pts.shape[1] == 3 and len(pts) == 4 * 36
    np.testing.assert_allclose(origin, [2.0, 0, 0], atol=1e-12)
    scale = 1.0 / N
    # the +x face of the cube: voxel x = 10, centre at (10 - 7.5) / 16 m, jitter +-half a voxel
    xc = (10 - (N - 1) / 2) * scale
    assert np.all(np.abs(pts[:, 0] - xc) <= 0.5 * scale + 1e-6)
    lo, hi = (5 - 7.5 - 0.5) * scale, (10 - 7.5 + 0.5) * scale
    assert pts[:, 1:].min() >= lo - 1e-6 and pts[:, 1:].max() <= hi + 1e-6


def assert_on_cube(pts, half=3.0 / N):
    """Points (m, 3) on the cube of half side ``half`` about the origin: on its faces where
    they are half a voxel or more from an edge, else on the rounded edge within half a voxel;
    to 0.05 voxel (the crossing is interpolated linearly between samples along the ray)."""
    a = np.sort(np.abs(pts), axis=1)
    tol = 0.05 / N
    assert (a[:, 2] <= half + tol).all() and (a[:, 2] >= half - 0.5 / N - tol).all()
    face = a[:, 1] < half - 0.5 / N
    assert face.mean() > 0.5
    np.testing.assert_allclose(a[face, 2], half, atol=tol)


def test_render_surface_points_lie_on_the_visible_face():
    occ = cube()   # voxels 5-10: the faces at 4.5 and 10.5 voxels, 3 voxels from the centre 7.5
    pts, origin = render_surface_points(occ, 0.5, 0.0, 0.0, 0.0, distance=2.0, size=1.0)
    assert pts.dtype == np.float32 and pts.shape[1] == 3 and len(pts) > 50
    np.testing.assert_allclose(origin, [2.0, 0, 0], atol=1e-12)
    # a plane, not voxel centres jittered over whole voxels (trilinear interpolation rounds
    # the edges within half a voxel)
    assert_on_cube(pts)
    assert (pts[:, 0] > 2.5 / N - 1e-5).all()


def test_render_surface_points_turns_the_object_exactly():
    # rotate_grid's nearest-neighbour turn made staircases of the faces of a turned box
    occ = cube()
    yaw = np.deg2rad(30.0)
    pts, _ = render_surface_points(occ, 0.5, yaw, 0.3, 0.4, distance=2.0, size=1.0,
                                   noise=0.0)
    c, s = np.cos(yaw), np.sin(yaw)
    assert_on_cube(pts.astype(np.float64) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]))
    assert render_surface_points(occ, 0.5, yaw, 0.3, 0.4, distance=2.0,
                                 noise=0.01, rng=np.random.default_rng(0))[0].shape == pts.shape


def test_render_surface_points_refuses_a_sensor_inside_and_renders_nothing_of_nothing():
    with pytest.raises(ValueError, match='inside the grid'):
        render_surface_points(cube(), 0.5, 0.0, 0.0, 0.0, distance=0.5, size=1.0)
    pts, _ = render_surface_points(np.zeros((N,) * 3), 0.5, 0.0, 0.0, 0.0)
    assert pts.shape == (0, 3)


def test_primitive_shapes():
    X, y, names = primitive_shapes(N, 3)
    assert X.shape == (6, N ** 3) and X.dtype == np.float32
    assert names == ['box', 'cylinder'] and list(y) == [0, 1] * 3
    assert set(np.unique(X)) == {0.0, 1.0}
    assert (X.sum(axis=1) > 50).all()
    X2, _, _ = primitive_shapes(N, 3)
    np.testing.assert_array_equal(X, X2)       # deterministic by default


@pytest.mark.parametrize('call, match', [
    (lambda occ: partial_view(occ[:, :, :4], 0.1, 0.3), r'occ must be \(N, N, N\)'),   # IndexError
    (lambda occ: partial_view(occ, np.nan, 0.3), 'view angles must be finite'),   # garbage
    (lambda occ: partial_view(occ, 0.1, 0.3, step=-1.0), 'step must be a positive'),
    # numpy counts timedelta64 as an integer: it was taken as 1 radian / 0.5 voxels
    (lambda occ: partial_view(occ, np.timedelta64(1), 0.3), 'view angles must be finite'),
    (lambda occ: partial_view(occ, 0.1, 0.3, step=np.timedelta64(1, 's')),
     'step must be a positive'),
    (lambda occ: render_view_points(occ, 0.0, 0.1, np.nan), 'view angles must be finite'),
    (lambda occ: render_surface_points(occ.astype(float), 0.5, np.nan, 0.1, 0.3),
     'view angles must be finite'),                                     # 'arange: cannot ...'
    (lambda occ: render_surface_points(occ.astype(float), 0.5, 0.0, 0.1, 0.3, ray_spacing=0),
     'ray_spacing must be a positive'),                                 # divide by zero
    (lambda occ: partial_view(occ, 0.1, 0.3, ray_spacing=np.inf), 'ray_spacing must be a positive'),
    (lambda occ: render_surface_points(occ[:, :, :4].astype(float), 0.5, 0.0, 0.1, 0.3),
     r'field must be \(N, N, N\)'),
    # the grid's bounding sphere is 0.87 m (sqrt(3) * 4 voxels of 0.125 m): 0.9 m is less than
    # a voxel beyond it
    (lambda occ: render_surface_points(occ.astype(float), 0.5, 0.0, 0.1, 0.3, distance=0.9),
     'inside the grid'),
])
def test_views_refuse_what_is_no_view(call, match):
    occ = np.zeros((8, 8, 8), bool)
    occ[3:5, 3:5, 3:5] = True
    with pytest.raises(ValueError, match=match):
        call(occ)


# ---------------------------------------------------------------- mutation audit
def box(lo, hi):
    occ = np.zeros((N,) * 3, dtype=bool)
    occ[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    return occ


def test_render_view_points_turns_the_object_by_the_yaw():
    # a bar along x, turned by 90 deg about +z: along y
    occ = box((2, 7, 7), (14, 9, 9))
    pts, _ = render_view_points(occ, np.pi / 2, 0.3, 0.4)
    extent = np.ptp(pts, axis=0)
    assert extent[1] > 0.6 and extent[0] < 0.25, extent


def test_render_view_points_noise_is_in_metres():
    occ = cube()
    ref, _ = render_view_points(occ, 0.0, 0.3, 0.4, rng=np.random.default_rng(0))
    noisy, _ = render_view_points(occ, 0.0, 0.3, 0.4, noise=0.01, rng=np.random.default_rng(0))
    assert noisy.shape == ref.shape
    dev = (noisy - ref).astype(np.float64)
    assert 0.008 < dev.std() < 0.012, dev.std()


def test_render_surface_points_depth_noise_is_in_metres_along_the_ray():
    occ = cube()
    ref, origin = render_surface_points(occ, 0.5, 0.0, 0.0, 0.0, distance=2.0)
    noisy, _ = render_surface_points(occ, 0.5, 0.0, 0.0, 0.0, distance=2.0, noise=0.01,
                                     rng=np.random.default_rng(0))
    assert noisy.shape == ref.shape
    ray = ref - origin
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    dev = (noisy - ref).astype(np.float64)
    along = np.einsum('ij,ij->i', dev, ray)
    assert 0.008 < along.std() < 0.012, along.std()
    np.testing.assert_allclose(dev - along[:, None] * ray, 0, atol=1e-5)


def test_render_surface_points_reaches_a_surface_beyond_the_centre():
    # a block on the far side of the grid centre from the sensor (+x): its face toward the
    # sensor is at x = 5.5 voxels, 2 voxels behind the centre 7.5
    occ = box((2, 5, 5), (6, 11, 11))
    pts, _ = render_surface_points(occ, 0.5, 0.0, 0.0, 0.0, distance=2.0, size=1.0)
    assert len(pts) > 50
    np.testing.assert_allclose(np.median(pts[:, 0]), (5.5 - 7.5) / N, atol=0.05 / N)


def test_partial_view_of_nothing_is_all_free_from_any_direction():
    # the rays cover the grid's bounding sphere: its corners too
    for az, el in ((0.0, 0.0), (0.3, 0.5), (np.pi / 4, np.arctan(1 / np.sqrt(2)))):
        assert (partial_view(np.zeros((N,) * 3, bool), az, el) == 0).all()


def test_random_partial_view_draws_yaw_and_azimuth_over_the_whole_turn():
    draws = [random_partial_view(cube(), np.random.default_rng(s))[1:3] for s in range(30)]
    yaws, azs = np.array(draws).T
    assert yaws.max() > 1.5 * np.pi and azs.max() > 1.5 * np.pi


def test_primitive_shapes_are_boxes_and_upright_cylinders():
    X, y, _ = primitive_shapes(N, 5)
    for row, label in zip(X, y):
        occ = row.reshape((N,) * 3) > 0.5
        idx = np.argwhere(occ)
        lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
        full = occ[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].all()
        assert full == (label == 0)               # a box fills its bounding box
        assert hi[2] - lo[2] < N                  # bounded in height
        # every horizontal slice is the same (a prism along z)
        assert (occ[:, :, lo[2]:hi[2]] == occ[:, :, lo[2]:lo[2] + 1]).all()
