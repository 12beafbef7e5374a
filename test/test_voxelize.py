"""voxelize_view: occupied/free/unknown labelling, frame conventions, placement, validation."""
import warnings

import numpy as np
import pytest

from beo_ros.core.grid import FREE, OCCUPIED, UNKNOWN, GridSpec
from beo_ros.core.voxelize import (
    aligned_frame, grid_to_points, label_free_unknown, voxelize_view)

N = 32
C = (N - 1) / 2


def box_front(m=3000, seed=0, x=0.9):
    """Points of the face x = ``x`` (|y| <= 0.15, 0 <= z <= 0.4) of a box, seen from the origin."""
    rng = np.random.default_rng(seed)
    return np.c_[np.full(m, x), rng.uniform(-0.15, 0.15, m), rng.uniform(0.0, 0.4, m)]


def rot_about(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def counts(g):
    return {k: int((g == k).sum()) for k in (OCCUPIED, FREE, UNKNOWN)}


def test_box_seen_from_one_side():
    v = voxelize_view(box_front(), np.zeros(3), [0, 0, 1], GridSpec(N))
    g = v.grid
    assert g.shape == (N, N, N) and g.dtype == np.int8
    occ = np.argwhere(g == OCCUPIED)
    # the face is one voxel layer thick, perpendicular to the grid's x axis (the view direction)
    assert np.ptp(occ[:, 0]) == 0
    fx = occ[0, 0]
    # largest extent 0.4 m (height) spans the grid; the 0.3 m width spans 24 voxels
    assert np.ptp(occ[:, 2]) == N - 1 and np.ptp(occ[:, 1]) == 23
    assert v.voxel_size_m == pytest.approx(0.4 / N, rel=1e-3)
    # assumed depth = width 0.3 m: the face sits ~12 voxels in front of the grid centre
    assert fx == pytest.approx(C - 12, abs=1)
    ys, zs = slice(occ[:, 1].min() + 2, occ[:, 1].max() - 1), slice(2, N - 2)
    assert np.all(g[fx + 1:, ys, zs] == UNKNOWN)  # inside and behind the box: occluded
    assert np.all(g[:fx, ys, zs] == FREE)  # between the sensor and the face: seen free
    assert np.all(g[:, 0, :][:fx] == FREE)  # outside the silhouette
    assert v.n_points == 3000


def test_invariant_to_rotation_about_up_and_translation():
    rng = np.random.default_rng(3)
    pts = np.r_[box_front(2000), np.c_[rng.uniform(0.9, 1.1, 800), np.full(800, -0.15),
                                       rng.uniform(0, 0.4, 800)]]  # two faces visible
    origin = np.array([0.0, 0.4, 0.6])
    up = np.array([0.0, 0.0, 1.0])
    for spec in (GridSpec(N), GridSpec(N, units='metric', voxel_size=0.02, anchor='bottom')):
        ref = voxelize_view(pts, origin, up, spec)
        for angle, t in ((0.7, [1, -2, 0.3]), (-2.5, [0, 0, 0]), (np.pi, [5, 5, 5])):
            # rotate the whole scene about an arbitrary vertical axis, then also tilt the world
            # so 'up' is no longer z: the grid must not change
            r = rot_about(up, angle)
            tilt = rot_about([1, 2, 0], 1.1)
            p2 = (pts @ r.T + t) @ tilt.T
            o2 = (origin @ r.T + t) @ tilt.T
            v = voxelize_view(p2, o2, 3.0 * (tilt @ up), spec)
            np.testing.assert_array_equal(v.grid == OCCUPIED, ref.grid == OCCUPIED)
            assert np.mean(v.grid != ref.grid) < 2e-3  # grazing rays may differ
            assert v.voxel_size_m == pytest.approx(ref.voxel_size_m)
            # grid_to_input follows the scene
            m = np.eye(4)
            m[:3, :3], m[:3, 3] = tilt @ r, tilt @ np.asarray(t, float)
            np.testing.assert_allclose(v.grid_to_input, m @ ref.grid_to_input, atol=1e-9)


def test_x_axis_points_away_from_sensor():
    pts = box_front(x=0.0)
    for origin in ([-1.0, 0, 0.2], [1.0, 0, 0.2], [0, 1.0, 0.3]):
        v = voxelize_view(pts, origin, [0, 0, 1], GridSpec(N))
        ex = v.grid_to_input[:3, 0] / v.voxel_size_m
        to_obj = pts.mean(axis=0) - origin
        to_obj[2] = 0
        np.testing.assert_allclose(ex, to_obj / np.linalg.norm(to_obj), atol=1e-12)
        occ = np.argwhere(v.grid == OCCUPIED)
        unk = np.argwhere(v.grid == UNKNOWN)
        assert unk[:, 0].mean() > occ[:, 0].mean()  # occluded space lies behind, at larger x
        np.testing.assert_allclose(v.grid_to_input[:3, 2] / v.voxel_size_m, [0, 0, 1])


def test_aligned_frame_fallback_when_sensor_straight_above():
    r = aligned_frame([0, 0, 2], [0, 0, 5], [0, 0, 0])
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0)
    np.testing.assert_allclose(r[:, 2], [0, 0, 1])
    # straight above a target far from the origin, with rounding noise in the sensor's
    # position: the same fixed axis, not the noise's direction
    far = aligned_frame([0, 0, 1], [1e3 + 1e-7, -2e-8, 5.0], [1e3, 0.0, 0.0])
    np.testing.assert_allclose(far, aligned_frame([0, 0, 1], [0, 0, 5], [0, 0, 0]), atol=1e-12)
    np.testing.assert_allclose(far[:, 0], [1, 0, 0])   # the world axis least parallel to up
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.1, 0.1, (500, 3)) * [1, 1, 0] + [0, 0, 0.0]
    v = voxelize_view(pts, [0, 0, 1], [0, 0, 1], GridSpec(N))
    assert counts(v.grid)[OCCUPIED] > 0 and counts(v.grid)[UNKNOWN] > 0  # below the plate


def test_fill_scales_the_largest_extent_to_that_fraction_of_the_grid():
    v = voxelize_view(box_front(), np.zeros(3), [0, 0, 1], GridSpec(N, fill=0.5))
    assert v.voxel_size_m == pytest.approx(0.4 / (N / 2), rel=1e-3)
    occ = np.argwhere(v.grid == OCCUPIED)
    # 0.4 m over 16 voxels, 0.3 m over 12 (the ends may fall on a voxel face)
    assert np.ptp(occ[:, 2]) in (15, 16) and np.ptp(occ[:, 1]) in (11, 12)


def test_grid_to_input_and_grid_to_points():
    pts = box_front()
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], GridSpec(N))
    centres, values = grid_to_points(v.grid, v.grid_to_input, threshold=0.5)
    assert centres.dtype == np.float32 and centres.shape == (counts(v.grid)[OCCUPIED], 3)
    assert np.all(values == 1)
    # every occupied voxel centre is within half a voxel diagonal of an input point
    d = np.linalg.norm(centres[:, None, :] - pts[None, :, :], axis=2).min(axis=1)
    assert d.max() <= v.voxel_size_m * np.sqrt(3) / 2 + 1e-6
    # and every input point is inside an occupied voxel
    g = (pts - v.grid_to_input[:3, 3]) @ np.linalg.inv(v.grid_to_input[:3, :3]).T
    idx = np.clip(np.floor(g + 0.5), 0, N - 1).astype(int)
    assert np.all(v.grid[tuple(idx.T)] == OCCUPIED)
    np.testing.assert_allclose(v.input_to_grid @ v.grid_to_input, np.eye(4), atol=1e-9)
    prob = np.zeros((N, N, N), np.float32)
    prob[1, 2, 3], prob[4, 5, 6] = 0.9, 0.3
    p, val = grid_to_points(prob, np.eye(4), threshold=0.5)
    np.testing.assert_array_equal(p, [[1, 2, 3]])
    np.testing.assert_allclose(val, [0.9])
    # the threshold is inclusive: a labelled grid at threshold 1 gives its occupied voxels
    p, val = grid_to_points(prob, np.eye(4), threshold=np.float32(0.3))
    np.testing.assert_array_equal(p, [[1, 2, 3], [4, 5, 6]])
    assert len(grid_to_points(v.grid, v.grid_to_input, threshold=1)[0]) == len(centres)
    # (a 2-D grid failed in numpy's matmul, also a ValueError, naming no grid)
    with pytest.raises(ValueError, match=r'grid must be 3-D, got shape \(4, 4\)'):
        grid_to_points(np.zeros((4, 4)), np.eye(4))
    with pytest.raises(ValueError, match=r'grid_to_input must be a finite \(4, 4\)'):
        grid_to_points(prob, np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match=r'grid_to_input must be a finite \(4, 4\)'):
        grid_to_points(prob, bad)


def test_metric_bottom_anchor_floor_and_center_override():
    pts = box_front()
    spec = GridSpec(N, units='metric', voxel_size=0.02, anchor='bottom')
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    occ = np.argwhere(v.grid == OCCUPIED)
    assert v.voxel_size_m == 0.02
    assert occ[:, 2].min() == 0 and occ[:, 2].max() == 19  # 0.4 m / 0.02 m = 20 layers
    assert np.ptp(occ[:, 1]) == 14 or np.ptp(occ[:, 1]) == 15
    # the floor plane lies 0.1 m below the lowest point: the object floats 5 voxels up
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, floor=-0.1)
    assert np.argwhere(v.grid == OCCUPIED)[:, 2].min() == 5
    np.testing.assert_allclose(v.grid_to_input @ [C, C, -0.5, 1], [1.05, 0, -0.1, 1], atol=3e-3)
    # center: the given point goes to the anchor point
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], GridSpec(N, units='metric', voxel_size=0.02),
                      center=[1.0, 0.1, 0.2])
    np.testing.assert_allclose(v.grid_to_input @ [C, C, C, 1], [1.0, 0.1, 0.2, 1], atol=1e-9)
    # points outside a small metric grid are not voxelized and not counted: inside means grid
    # coordinates in [-0.5, N - 0.5] (the outer faces of the outer voxels), and every occupied
    # voxel holds an inside point
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], GridSpec(8, units='metric', voxel_size=0.04))
    g = (pts - v.grid_to_input[:3, 3]) @ v.input_to_grid[:3, :3].T
    inside = np.all((g >= -0.5) & (g <= 8 - 0.5), axis=1)
    assert 0 < inside.sum() < len(pts) and v.n_points == inside.sum()
    want = np.zeros((8, 8, 8), bool)
    want[tuple(np.floor(g[inside] + 0.5).astype(int).T)] = True
    np.testing.assert_array_equal(v.grid == OCCUPIED, want)


def test_floor_lowers_the_bottom_only_and_only_for_the_bottom_anchor():
    pts = box_front()   # lowest point near z = 0
    spec = GridSpec(N, units='metric', voxel_size=0.02, anchor='bottom')
    ref = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    # a floor above the lowest point (points below a fitted table plane) does not cut the
    # object: the grid floor stays at its lowest point
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, floor=0.1)
    assert v.n_points == len(pts)
    np.testing.assert_array_equal(v.grid, ref.grid)
    np.testing.assert_allclose(v.grid_to_input, ref.grid_to_input, atol=1e-12)
    # the centre anchor takes no floor
    spec = GridSpec(N, units='metric', voxel_size=0.02)
    ref = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, floor=-0.3)
    np.testing.assert_array_equal(v.grid, ref.grid)
    np.testing.assert_allclose(v.grid_to_input, ref.grid_to_input, atol=1e-12)


def test_sensor_inside_grid():
    pts = box_front()
    spec = GridSpec(N, units='metric', voxel_size=0.1)  # 3.2 m grid contains the sensor
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    o = (np.zeros(3) - v.grid_to_input[:3, 3]) @ np.linalg.inv(v.grid_to_input[:3, :3]).T
    assert np.all((o > 0) & (o < N - 1))
    oi = tuple(np.floor(o + 0.5).astype(int))
    assert v.grid[oi] == FREE
    assert counts(v.grid)[UNKNOWN] > 0
    occ = np.argwhere(v.grid == OCCUPIED)
    fx = occ[:, 0].max()
    assert v.grid[fx + 2, occ[:, 1].min() + 1, occ[:, 2].min() + 1] == UNKNOWN


def test_occluders_hide_space_behind_them():
    pts = box_front()
    rng = np.random.default_rng(4)
    wall = np.c_[np.full(3000, 0.5), rng.uniform(-0.6, 0.0, 3000), rng.uniform(-0.2, 0.6, 3000)]
    spec = GridSpec(N, units='metric', voxel_size=0.02)
    a = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    b = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, occluders=wall)
    np.testing.assert_array_equal(a.grid == OCCUPIED, b.grid == OCCUPIED)
    assert counts(b.grid)[UNKNOWN] > counts(a.grid)[UNKNOWN] + 1000
    assert np.all(b.grid[a.grid == UNKNOWN] == UNKNOWN)  # occluders only add unknowns
    # far-away occluders behind the sensor change nothing
    c = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, occluders=wall * [-1, 1, 1] - [5, 0, 0])
    np.testing.assert_array_equal(c.grid, a.grid)


def test_occluders_anywhere_in_front_of_a_grid_voxel_hide_it():
    # the occluders are culled to those that can lie between the sensor and the grid: that
    # cull must keep small blobs near the sensor on the way to the grid's corners (the corners
    # lie sqrt(3) N / 2 from the centre) and a wall inside the grid beyond its centre
    pts = box_front()
    spec = GridSpec(N, units='metric', voxel_size=0.02)
    a = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    g2i = a.grid_to_input
    corners = [(N - 1, N - 1, N - 1), (N - 1, 0, N - 1), (N - 1, N - 1, 0), (0, N - 1, N - 1)]
    off = np.stack(np.meshgrid(*[np.arange(-1, 2) * 0.004] * 3), -1).reshape(-1, 3)
    blobs = np.concatenate([0.4 * (g2i @ [*c, 1])[:3] + off for c in corners])
    b = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, occluders=blobs)
    for c in corners:
        assert a.grid[c] == FREE and b.grid[c] == UNKNOWN, c
    rng = np.random.default_rng(0)
    wall = np.c_[np.full(2000, 1.25), rng.uniform(0.2, 0.3, 2000), rng.uniform(0.0, 0.4, 2000)]
    assert 1.25 > (g2i @ [C, C, C, 1])[0]   # beyond the grid centre
    w = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, occluders=wall)
    xyz = np.indices(a.grid.shape).reshape(3, -1).T @ g2i[:3, :3].T + g2i[:3, 3]
    behind = ((xyz[:, 0] > 1.27) & (np.abs(xyz[:, 1] / xyz[:, 0] - 0.2) < 0.03)
              & (xyz[:, 2] > 0.05) & (xyz[:, 2] / xyz[:, 0] < 0.3 / 1.25))
    assert behind.sum() > 200 and (a.grid.reshape(-1)[behind] == FREE).sum() > 200
    assert (w.grid.reshape(-1)[behind] == UNKNOWN).all()


def test_occluder_points_too_far_for_a_voxel_index_change_nothing():
    # 1e300 m has no int64 voxel index: the cast warned ("invalid value encountered in cast")
    # before the distance test dropped the point
    pts = box_front()
    spec = GridSpec(N, units='metric', voxel_size=0.02)
    a = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    far = np.array([[1e300, 0.0, 0.0], [0.0, -1e300, 1e300]])
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        b = voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, occluders=far)
    np.testing.assert_array_equal(b.grid, a.grid)


def test_points_outside_the_grid_still_hide_what_is_behind_them():
    # a 0.3 x 0.3 x 0.8 m box standing at x = 1 m, seen from (0, 0, 1.6): its top face and the
    # upper part of its front lie above the 0.64 m metric grid. They must still block the rays,
    # or the inside of the box reads as seen-free (before: 1235 of its voxels did).
    s = np.arange(-0.15, 0.1501, 0.005)
    h = np.arange(0.0, 0.8001, 0.005)
    front = np.array([(0.85, y, z) for y in s for z in h])
    top = np.array([(1.0 + x, y, 0.8) for x in s for y in s])
    pts = np.r_[front, top]
    sensor = np.array([0.0, 0.0, 1.6])
    v = voxelize_view(pts, sensor, [0, 0, 1], GridSpec(N, units='metric', voxel_size=0.02,
                                                          anchor='bottom'))
    assert v.n_points < len(front)          # part of the object is outside the grid
    centres = np.indices(v.grid.shape).reshape(3, -1).T
    xyz = centres @ v.grid_to_input[:3, :3].T + v.grid_to_input[:3, 3]
    inside = ((np.abs(xyz[:, 0] - 1.0) < 0.13) & (np.abs(xyz[:, 1]) < 0.13)
              & (xyz[:, 2] > 0.02) & (xyz[:, 2] < 0.78))
    labels = v.grid.reshape(-1)[inside]
    assert len(labels) > 2000
    assert (labels == FREE).sum() == 0, (labels == FREE).sum()
    # and the space in front of the box, in the grid, is still seen free
    before = (xyz[:, 0] < 0.8) & (xyz[:, 0] > v.grid_to_input[0, 3] + 0.05)
    assert (v.grid.reshape(-1)[before] == FREE).mean() > 0.9


def _sparse_box_view(spacing):
    """Points on the faces of a 8 x 6 x 10 cm box at 3 m (yawed 0.5 rad) that face the sensor
    at (0, 0, 0.8), on a regular grid of ``spacing`` m per face; -> points, sensor, inside()."""
    c0, half, yaw = np.array([3.0, 0.2, 0.05]), np.array([0.04, 0.03, 0.05]), 0.5
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    sensor = np.array([0.0, 0.0, 0.8])
    pts = []
    for axis in range(3):
        for sign in (-1, 1):
            normal = R[:, axis] * sign
            if normal @ (sensor - (c0 + normal * half[axis])) <= 0:
                continue
            a, b = [i for i in range(3) if i != axis]
            ua = np.arange(-half[a], half[a] + 1e-9, spacing)
            ub = np.arange(-half[b], half[b] + 1e-9, spacing)
            A, B = np.meshgrid(ua, ub)
            local = np.zeros((A.size, 3))
            local[:, axis], local[:, a], local[:, b] = sign * half[axis], A.ravel(), B.ravel()
            pts.append(local @ R.T + c0)

    def inside(xyz, margin):
        return np.all(np.abs((xyz - c0) @ R) < half - margin, axis=1)
    return np.concatenate(pts), sensor, inside


def test_sparsely_sampled_surfaces_do_not_leak_free_space(monkeypatch):
    # a small object far away in a normalized grid: its points are ~1.4 voxels apart, and the
    # one-voxel closing left gaps through which the inside of the box read as seen-free
    import beo_ros.core.voxelize as vx
    pts, sensor, inside = _sparse_box_view(0.0045)
    spec = GridSpec(N)

    def inside_labels():
        v = voxelize_view(pts, sensor, [0, 0, 1], spec)
        centres = np.indices(v.grid.shape).reshape(3, -1).T
        xyz = centres @ v.grid_to_input[:3, :3].T + v.grid_to_input[:3, 3]
        spacing = vx.point_spacing((pts - v.grid_to_input[:3, 3]) @ v.input_to_grid[:3, :3].T)
        return v.grid.reshape(-1)[inside(xyz, 1.5 * v.voxel_size_m)], spacing

    labels, spacing = inside_labels()
    assert 1.2 < spacing < 1.6
    assert len(labels) > 5000 and (labels == FREE).sum() == 0
    monkeypatch.setattr(vx, 'SPARSE_SPACING', np.inf)       # the closing alone
    before, _ = inside_labels()
    assert (before == FREE).sum() > 500


def test_point_spacing_and_facing_squares():
    from beo_ros.core.voxelize import facing_squares, point_spacing
    g = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0) * 2, [0.0]), -1).reshape(-1, 3)
    assert point_spacing(g) == 1.0
    assert point_spacing(np.r_[g, g]) == 1.0           # duplicates are not neighbours
    assert point_spacing(g[:1]) == np.inf
    v, t = facing_squares(np.array([[5.0, 0, 0], [0, 0, 3.0]]), np.zeros(3), 0.5)
    assert v.shape == (8, 3) and t.shape == (4, 3)
    for k, p in enumerate(([5.0, 0, 0], [0, 0, 3.0])):
        quad = v[4 * k:4 * k + 4].astype(float)
        normal = np.asarray(p) / np.linalg.norm(p)
        np.testing.assert_allclose((quad - p) @ normal, 0, atol=1e-6)   # faces the origin
        np.testing.assert_allclose(np.abs(quad - p).max(axis=0).max(), 0.5, atol=1e-6)


def test_label_free_unknown_single_voxel_and_hole_closing():
    occ = np.zeros((8, 8, 8), bool)
    occ[3, 4, 4] = True
    g = label_free_unknown(occ, [-20.0, 4.0, 4.0])
    assert g[3, 4, 4] == OCCUPIED
    assert np.all(g[4:, 4, 4] == UNKNOWN) and np.all(g[:3, 4, 4] == FREE)
    assert g[5, 6, 4] == FREE
    assert np.all(label_free_unknown(np.zeros((4, 4, 4), bool), [0, 0, 0]) == FREE)
    # a wall x = 2 with a one-voxel hole: closing stops the leak
    wall = np.zeros((8, 8, 8), bool)
    wall[2, 1:7, 1:7] = True
    wall[2, 4, 4] = False
    leaky = label_free_unknown(wall, [-30.0, 4.0, 4.0], close_holes=False)
    closed = label_free_unknown(wall, [-30.0, 4.0, 4.0])
    assert leaky[6, 4, 4] == FREE and closed[6, 4, 4] == UNKNOWN
    assert closed[2, 4, 4] == UNKNOWN and closed[1, 4, 4] == FREE


def test_far_sensor_keeps_voxel_precision():
    # Embree's rays are float32: cast from 1e7 voxels away, origin and end point used to lose
    # about a voxel (342 labels differed from the sensor at 1e4 on this object; 72 from 1e3,
    # from the perspective alone, so 1e4 is the reference).
    occ = np.zeros((N, N, N), bool)
    occ[8:24, 10:22, 4:20] = True
    occ[12:20, 14:18, 20:28] = True
    d = np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62])
    near = label_free_unknown(occ, C + d * 1e4)
    assert np.count_nonzero(near == UNKNOWN) > 4000
    for r in (1e5, 1e6, 1e7):
        np.testing.assert_array_equal(label_free_unknown(occ, C + d * r), near)


@pytest.mark.parametrize('kwargs,match', [
    (dict(points=np.zeros((5, 2))), r'\(n, 3\)'),
    (dict(points=np.zeros(30)), r'\(n, 3\)'),
    (dict(points=np.full((50, 3), np.nan)), 'at least 10 finite'),
    (dict(up=[0, 0, 0]), 'non-zero'),
    (dict(up=[0, np.nan, 1]), 'up'),
    (dict(up=[0, 1]), 'up'),
    (dict(sensor_origin=[np.inf, 0, 0]), 'sensor_origin'),
    (dict(center=[0, 0]), 'center'),
    (dict(floor=np.nan), 'floor'),
    (dict(floor='0'), 'floor must be a finite number'),            # a TypeError before
    (dict(floor=np.array([0.0])), 'floor must be a finite number'),
    (dict(up=[0, 0, 1e-10]), 'largest component at least 1e-09'),
    (dict(occluders=np.ones(4)), r'occluders must be an \(m, 3\)'),   # a reshape error before
    (dict(occluders=np.ones((20, 6))), r'occluders must be an \(m, 3\)'),  # XYZRGB rows
    (dict(points=box_front(100) * 1e7), r'within \+-1e\+06'),
    (dict(sensor_origin=[-1e300, 0, 0]), 'sensor_origin must lie within'),
    (dict(center=[0, 0, 1e9]), 'center must lie within'),
    (dict(points=np.ones((100, 3))), 'not an object'),                  # all at one place
    (dict(points=np.ones((100, 3)), floor=-1.0), 'not an object'),      # floor adds no extent
    # a TypeError (cannot cast) before: x, y, z records, as a PCD or PointCloud2 reader gives
    (dict(points=np.rec.fromarrays(box_front(100).T, names='x,y,z')), 'array of numbers'),
    (dict(points={'x': 1.0}), 'points must be an'),
    # min_points 0 and no finite point: numpy's 'zero-size array to reduction operation' before
    (dict(points=np.zeros((0, 3)), min_points=0), 'need at least 1 finite points, got 0'),
    (dict(points=np.full((5, 3), np.nan), min_points=0), 'need at least 1 finite points'),
])
def test_validation(kwargs, match):
    args = dict(points=box_front(100), sensor_origin=np.zeros(3), up=[0, 0, 1], spec=GridSpec(8))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        voxelize_view(**args)


@pytest.mark.parametrize('kwargs, match', [
    # parsed as numbers, taken as 0/1, or the imaginary part dropped with a warning only
    (dict(points=box_front(100).astype(str)), 'points must be an'),
    (dict(points=box_front(100) > 0.1), r'points must be an \(n, 3\) array of numbers, got bool'),
    (dict(points=box_front(100) + 1j), 'points must be an'),
    (dict(sensor_origin=['0', '0', '0']), 'sensor_origin must be a finite 3-vector'),
    (dict(up=[False, False, True]), 'up must be a finite 3-vector'),
    (dict(center=np.array([0.9, 0.0, 0.2]) + 0j), 'center must be a finite 3-vector'),
])
def test_values_that_are_no_real_numbers_are_refused(kwargs, match):
    args = dict(points=box_front(100), sensor_origin=np.zeros(3), up=[0, 0, 1], spec=GridSpec(8))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        voxelize_view(**args)
    # integer and half-precision points are numbers
    pts = np.round(box_front(100) * 1000).astype(np.int32)
    assert voxelize_view(pts, np.zeros(3), [0, 0, 1], GridSpec(8)).n_points == 100
    assert voxelize_view(pts.astype(np.float16), np.zeros(3), [0, 0, 1], GridSpec(8)).n_points


def test_finite_points_of_none_with_min_points_0():
    from beo_ros.core.voxelize import finite_points
    for pts in (np.zeros((0, 3)), np.full((5, 3), np.nan)):
        assert finite_points(pts, min_points=0).shape == (0, 3)


def test_empty_occluders_are_none():
    args = (box_front(100), np.zeros(3), [0, 0, 1], GridSpec(8))
    a = voxelize_view(*args)
    for empty in ([], np.zeros((0, 3))):
        np.testing.assert_array_equal(voxelize_view(*args, occluders=empty).grid, a.grid)


def test_label_free_unknown_integer_occupancy_is_a_mask():
    # a uint8 0/1 array used to index whole slabs (128 occupied voxels instead of 4)
    occ = np.zeros((8, 8, 8), bool)
    occ[4, 3:5, 3:5] = True
    a = label_free_unknown(occ, [-10, 3.5, 3.5])
    b = label_free_unknown(occ.astype(np.uint8), [-10, 3.5, 3.5])
    assert (b == OCCUPIED).sum() == 4
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match=r'occupied must be an \(N, N, N\)'):
        label_free_unknown(np.zeros((8, 8)), [0, 0, 0])


@pytest.mark.parametrize('origin', [
    (np.nan, 8.0, 8.0), (np.inf, 8.0, 8.0),   # every voxel read free
    [[-10.0, 3.5, 3.5]],                       # broadcast as if (3,)
    (-10.0, 3.5),                              # numpy's broadcast error
    ('-10', '3.5', '3.5'),                     # strings parsed as numbers
])
def test_label_free_unknown_refuses_an_origin_that_is_no_point(origin):
    occ = np.zeros((8, 8, 8), bool)
    occ[4, 3:5, 3:5] = True
    with pytest.raises(ValueError, match='origin_grid must be a finite 3-vector'):
        label_free_unknown(occ, origin)


def test_points_outside_a_metric_grid_are_refused():
    # millimetres for metres: every point fell outside the grid, which came back empty
    spec = GridSpec(16, units='metric', voxel_size=0.05)
    pts = box_front(100)
    assert voxelize_view(pts, np.zeros(3), [0, 0, 1], spec).n_points > 0
    with pytest.raises(ValueError, match='not in metres'):
        voxelize_view(pts * 1000 + [0, 0, 500], np.zeros(3), [0, 0, 1], spec)


def test_points_outside_the_grid_message_says_what_they_span():
    spec = GridSpec(16, units='metric', voxel_size=0.05)
    pts = box_front(100) * 1000 + [0, 0, 500]   # aligned frame = input frame: up z, sensor at 0
    span = (pts.max(axis=0) - pts.min(axis=0)).max()
    with pytest.raises(ValueError) as e:
        voxelize_view(pts, np.zeros(3), [0, 0, 1], spec)
    assert str(e.value) == (f'none of the 100 points fall inside the 16^3 grid of 0.8 m; they '
                            f'span {span:g} (input units): an object much larger than the '
                            'grid, or points not in metres')


def test_huge_up_vector_is_a_direction():
    # (0, 0, 1e300) is a valid direction: its norm must not overflow to inf (up -> 0)
    args = (box_front(100), np.zeros(3))
    a = voxelize_view(*args, [0, 0, 1e300], GridSpec(8))
    b = voxelize_view(*args, [0, 0, 1], GridSpec(8))
    np.testing.assert_array_equal(a.grid, b.grid)


def test_non_finite_points_are_dropped():
    pts = box_front(100)
    pts[::2] = np.nan
    v = voxelize_view(pts, np.zeros(3), [0, 0, 1], GridSpec(16))
    assert v.n_points == 50
    pts[1::4, 2] = np.inf   # one coordinate is enough
    assert voxelize_view(pts, np.zeros(3), [0, 0, 1], GridSpec(16)).n_points == 25
    with pytest.raises(ValueError, match='at least 60'):
        voxelize_view(pts, np.zeros(3), [0, 0, 1], GridSpec(16), min_points=60)


def test_sensor_in_an_occupied_voxel_still_sees_free_space():
    # a point in the sensor's own voxel (dust on the lens, a self-return) must not blind it
    occ = np.zeros((16, 16, 16), bool)
    occ[12, 4:12, 4:12] = True         # a wall in front of the sensor
    occ[3, 8, 8] = True                # the sensor's own voxel
    g = label_free_unknown(occ, (3.0, 8.0, 8.0))
    assert (g[5:11, 6:10, 6:10] == FREE).all()
    assert (g[13:, 6:10, 6:10] == UNKNOWN).all()
    assert g[12, 8, 8] == OCCUPIED


def test_sensor_on_the_face_of_an_occupied_voxel_still_sees_free_space():
    # the sensor exactly on a voxel face (its own voxel on one side, an occupied one on the
    # other): Embree hit that face at t = 0 on every ray leaving it, all unknown but behind it
    occ = np.zeros((16, 16, 16), bool)
    occ[12, 4:12, 4:12] = True         # a wall in front of the sensor
    occ[3, 8, 8] = True                # the sensor sits on its +x face
    for sensor in ((3.5, 8.0, 8.0), (3.5, 8.3, 7.9), (3.5 + 1e-6, 8.0, 8.0)):
        g = label_free_unknown(occ, sensor)
        assert (g[5:11, 6:10, 6:10] == FREE).all()
        assert (g[13:, 6:10, 6:10] == UNKNOWN).all()
        assert (g[:3, 7:10, 7:10] == UNKNOWN).all()   # behind the voxel it sits on
        assert g[3, 8, 8] == OCCUPIED


def test_sensor_on_the_near_face_of_an_occupied_voxel_does_not_see_through_it():
    # floor(o + 0.5) puts a sensor on a face into the voxel on its + side; that voxel, occupied
    # with free space on the - side where the sensor is, was unblocked as the sensor's own
    # voxel and what it hides read free
    occ = np.zeros((16, 16, 16), bool)
    occ[12, 4:12, 4:12] = True         # a wall behind the voxel
    occ[3, 8, 8] = True                # the sensor sits on its -x face
    shadow = (slice(4, 12), slice(7, 10), slice(7, 10))   # behind it (toward the wall)
    for sensor in ((2.5, 8.0, 8.0), (2.5, 7.5, 8.0), (2.5, 8.5, 8.5)):
        # a micron off the face, on the free side, the sensor sees the voxel's shadow
        ref = label_free_unknown(occ, np.subtract(sensor, (1e-6, 0, 0)))
        assert (ref[shadow] == UNKNOWN).sum() >= 24
        g = label_free_unknown(occ, sensor)
        np.testing.assert_array_equal(g[shadow], ref[shadow])
        assert (g[:2, 6:10, 6:10] == FREE).all()   # in front of the sensor's free side
    ref = label_free_unknown(occ, (2.5 - 1e-6, 8.0, 8.0))
    # the same voxel as another object's (an occluder voxel) hides as much
    wall = np.zeros_like(occ)
    wall[12, 4:12, 4:12] = True
    g = label_free_unknown(wall, (2.5, 8.0, 8.0), occluder_voxels=np.array([[3, 8, 8]]))
    np.testing.assert_array_equal(g[shadow], ref[shadow])
    # occupied on both sides (inside the object): the + side voxel is still its own, unblocked
    solid = np.zeros_like(occ)
    solid[2:4, 6:11, 6:11] = True
    g = label_free_unknown(solid, (2.5, 8.0, 8.0))
    assert (g[4:, 8, 8] == FREE).all() and (g[:2, 8, 8] == UNKNOWN).all()


def test_a_self_return_does_not_blind_the_splats():
    # a sparse wall blocks rays as squares facing the sensor; a point in the sensor's own voxel
    # made a square right at the sensor that hid the whole view (0.1 voxel off), or, exactly at
    # the sensor, NaN vertices with which Embree missed every ray (nothing unknown behind)
    from beo_ros.core.voxelize import facing_squares
    yy, zz = np.meshgrid(np.arange(4, 12, 1.5), np.arange(4, 12, 1.5))
    wall = np.c_[np.full(yy.size, 12.0), yy.ravel(), zz.ravel()]
    sensor = np.array([3.0, 8.0, 8.0])
    for extra in (sensor, sensor + [0.1, 0, 0]):
        pts = np.r_[wall, [extra]]
        occ = np.zeros((16, 16, 16), bool)
        occ[tuple(np.floor(pts + 0.5).astype(int).T)] = True
        g = label_free_unknown(occ, sensor, splats=pts, splat_half=1.0)
        assert (g[5:11, 6:10, 6:10] == FREE).all()
        assert (g[13:, 6:10, 6:10] == UNKNOWN).all()
    v, _ = facing_squares(np.array([[0.0, 0, 0], [2.0, 0, 0]]), np.zeros(3), 0.5)
    assert np.isfinite(v).all() and (v[:4] == 0).all()


def test_an_occluder_point_at_the_sensor_does_not_blind_it():
    # a point of another object in the sensor's own voxel (a self-return, a driver's (0, 0, 0)
    # for no return) became a cube around the sensor that hid the whole grid
    spec = GridSpec(N, units='metric', voxel_size=0.02)
    rng = np.random.default_rng(4)
    wall = np.c_[np.full(3000, 0.5), rng.uniform(-0.6, 0.0, 3000), rng.uniform(-0.2, 0.6, 3000)]
    a = voxelize_view(box_front(), np.zeros(3), [0, 0, 1], spec, occluders=wall)
    for extra in ([0.0, 0.0, 0.0], [0.004, 0.0, 0.0]):
        b = voxelize_view(box_front(), np.zeros(3), [0, 0, 1], spec,
                          occluders=np.r_[wall, [extra]])
        np.testing.assert_array_equal(b.grid, a.grid)
    occ = np.zeros((16, 16, 16), bool)
    occ[12, 4:12, 4:12] = True
    g = label_free_unknown(occ, (3.0, 8.0, 8.0), occluder_voxels=np.array([[3, 8, 8]]))
    assert (g[5:11, 6:10, 6:10] == FREE).all()
    assert (g[13:, 6:10, 6:10] == UNKNOWN).all()


def test_points_outside_a_grid_placed_at_center_blame_the_center():
    # a 5 cm object 10 m from the given center: the message blamed the object's size or unit
    spec = GridSpec(16, units='metric', voxel_size=0.05)
    pts = box_front(100) * 0.1 + [2.0, 0, 0]
    assert voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, center=pts.mean(axis=0)).n_points
    with pytest.raises(ValueError) as e:
        voxelize_view(pts, np.zeros(3), [0, 0, 1], spec, center=[12.0, 0.0, 0.0])
    assert 'placed at center [12.0, 0.0, 0.0]' in str(e.value)
    assert 'not in metres' not in str(e.value)
