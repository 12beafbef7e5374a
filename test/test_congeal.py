"""Yaw congealing: randomly rotated copies of one asymmetric shape are re-aligned."""
import numpy as np
import pytest

from beo_ros.core.congeal import apply_yaws, class_entropy, congeal_classes, congeal_yaws
from beo_ros.core.grid import rotate_grid


def l_shape(n=16):
    g = np.zeros((n, n, n), dtype=np.float32)
    g[3:13, 5:8, 0:6] = 1      # long arm
    g[3:6, 8:12, 0:6] = 1      # short arm at one end: no rotational symmetry
    g[10:13, 2:5, 0:3] = 1     # a foot
    return g


def test_congeal_realigns_rotated_copies():
    n = 16
    rng = np.random.default_rng(0)
    base = l_shape(n)
    rot = np.deg2rad(rng.choice(np.arange(0, 360, 30), size=8))
    X = np.stack([rotate_grid(base, r).ravel() for r in rot])
    masks = np.ones(X.shape, bool)
    masks[::2, : n * n * 4] = False  # some unknown voxels: ignored by the objective
    before = class_entropy(X, n, masks)
    yaws, hist = congeal_yaws(X, n, masks, yaw_step_deg=10.0, iters=8)
    assert hist[-1] < hist[0]
    # aligned: yaw_i + rot_i is the same for all i (up to the 10 deg candidate step)
    tot = np.rad2deg(yaws + rot)
    d = (tot[:, None] - tot[None] + 180) % 360 - 180
    assert np.abs(d).max() <= 15, np.round(tot)
    Xa, Ma, ya = congeal_classes(X, np.zeros(len(X), int), n, masks=masks, return_yaws=True)
    assert Xa.shape == X.shape and Ma.dtype == bool
    assert class_entropy(Xa, n, Ma) < before
    # voxels rotated in from outside the grid are unknown: a fully known object turned by a
    # yaw that is no quarter turn comes back with unknown corners
    odd = [i for i in range(1, len(X), 2)
           if abs((np.rad2deg(ya[i]) + 45) % 90 - 45) > 5]
    assert odd and all((~Ma[i]).any() for i in odd), np.rad2deg(ya).round()


def test_congeal_without_masks_returns_x_only():
    n = 16
    base = l_shape(n)
    X = np.stack([rotate_grid(base, r).ravel() for r in np.deg2rad([0, 90, 200, 270])])
    y = np.array([0, 0, 1, 1])
    Xa = congeal_classes(X, y, n, yaw_step_deg=10.0)
    assert isinstance(Xa, np.ndarray) and Xa.shape == X.shape
    Xa, yaws = congeal_classes(X, y, n, return_yaws=True)
    assert yaws[0] == 0 and yaws[2] == 0  # the first object of each class keeps its yaw


def test_congeal_classes_refuses_no_objects():
    n = 16
    empty = np.zeros((0, n ** 3), np.float32)
    with pytest.raises(ValueError, match='at least one object'):   # np.stack's error before
        congeal_classes(empty, np.zeros(0, int), n, masks=np.zeros((0, n ** 3), bool))
    with pytest.raises(ValueError, match='one label per object'):
        congeal_classes(np.zeros((2, n ** 3), np.float32), np.zeros(3, int), n)


@pytest.mark.parametrize('n, masks_n', [(32, 16), (8, 16), (16, 8)])
def test_congeal_classes_names_grids_of_another_size(n, masks_n):
    # X of 16^3 with n = 32 was an IndexError in the rotation maps, with n = 8 numpy's
    # 'cannot reshape' after the congealing, masks of another size a broadcast error
    X = np.stack([rotate_grid(l_shape(16), r).ravel() for r in np.deg2rad([0, 90, 200])])
    masks = np.ones((3, masks_n ** 3), bool)
    which = 'X' if n != 16 else 'masks'
    with pytest.raises(ValueError, match=f'{which} must hold 3 grids of n\\^3'):
        congeal_classes(X, np.zeros(3, int), n, masks=masks)


def test_congeal_yaws_refuses_no_objects_and_bad_options_by_name():
    # no objects was "'int' object has no attribute 'astype'", a step or pool of 0 a
    # ZeroDivisionError, a negative step numpy's 'cannot reshape'
    n = 16
    X = np.stack([rotate_grid(l_shape(n), r).ravel() for r in np.deg2rad([0, 90])])
    with pytest.raises(ValueError, match='at least one object'):
        congeal_yaws(np.zeros((0, n ** 3), np.float32), n)
    for kwargs, msg in [(dict(yaw_step_deg=0), 'yaw_step_deg'),
                        (dict(yaw_step_deg=-10.0), 'yaw_step_deg'),
                        (dict(yaw_step_deg=float('nan')), 'yaw_step_deg'),
                        (dict(pool=0), 'pool'), (dict(iters=-1), 'iters'),
                        (dict(prior=-0.5), 'prior')]:
        with pytest.raises(ValueError, match=msg):
            congeal_yaws(X, n, **kwargs)
        # also when no class has two objects to congeal
        with pytest.raises(ValueError, match=msg):
            congeal_classes(X, np.array([0, 1]), n, **kwargs)
    # the objective of no grids is 0 bits (was numpy's 'cannot reshape')
    assert class_entropy(np.zeros((0, n ** 3), np.float32), n) == 0.0


def test_prior_zero_with_voxels_nobody_observes_still_congeals():
    # prior 0 (no pseudo counts) made a voxel that no object observes 0/0: the objective was
    # NaN, no object ever moved and the history was all NaN
    n = 16
    base = l_shape(n)
    rot = np.deg2rad([0, 90, 180, 270])
    X = np.stack([rotate_grid(base, r).ravel() for r in rot])
    masks = np.ones(X.shape, bool)
    masks[:, : 2 * n * n] = False      # the first two x slices: unknown in every object
    yaws, hist = congeal_yaws(X, n, masks, prior=0.0, yaw_step_deg=90.0)
    assert np.isfinite(hist).all() and hist[-1] < hist[0]
    assert np.isfinite(class_entropy(X, n, masks, prior=0.0))


def test_congeal_classes_keeps_the_shape_of_grids():
    # (m, n, n, n) grids, which the shape check accepts, came back as (m, n^3) rows
    n = 16
    X = np.stack([rotate_grid(l_shape(n), r) for r in np.deg2rad([0, 90, 200])])
    masks = np.ones(X.shape, bool)
    Xa, Ma = congeal_classes(X, np.zeros(3, int), n, masks=masks)
    assert Xa.shape == X.shape and Ma.shape == masks.shape
    assert congeal_classes(X, np.zeros(3, int), n).shape == X.shape
    flat = congeal_classes(X.reshape(3, -1), np.zeros(3, int), n)
    np.testing.assert_array_equal(flat, Xa.reshape(3, -1))


def test_apply_yaws_of_no_objects_with_masks():
    # no objects passed without masks but failed with numpy's 'need at least one array to
    # stack' with them
    n = 8
    Xr, Mr = apply_yaws(np.zeros((0, n ** 3), np.float32), n, np.zeros(0),
                        masks=np.zeros((0, n ** 3), bool))
    assert Xr.shape == (0, n ** 3) and Mr.shape == (0, n ** 3) and Mr.dtype == bool


def test_nan_where_unobserved_does_not_poison_the_objective():
    # X * mask kept NaN (the VBPCA convention for unknown entries): every cost was NaN, no
    # object moved and the yaws came back all 0
    n = 16
    rot = np.deg2rad([0, 90, 180, 270])
    X = np.stack([rotate_grid(l_shape(n), r).ravel() for r in rot])
    masks = np.ones(X.shape, bool)
    masks[:, :300] = False
    Xn = np.where(masks, X, np.nan)
    yaws, hist = congeal_yaws(Xn, n, masks, yaw_step_deg=90.0)
    np.testing.assert_array_equal(yaws, congeal_yaws(X, n, masks, yaw_step_deg=90.0)[0])
    assert np.isfinite(hist).all() and hist[-1] < hist[0]
    assert class_entropy(Xn, n, masks) == class_entropy(X, n, masks)


@pytest.mark.parametrize('n', [8, 32])
def test_congeal_yaws_and_class_entropy_name_grids_of_another_size(n):
    # 16^3 grids with n = 8 gave yaws from their first 512 voxels without a word, with
    # n = 32 an IndexError in the rotation maps; class_entropy numpy's 'cannot reshape'
    X = np.stack([rotate_grid(l_shape(16), r).ravel() for r in np.deg2rad([0, 90, 200])])
    for fn in (congeal_yaws, class_entropy):
        with pytest.raises(ValueError, match=r'X must hold 3 grids of n\^3'):
            fn(X, n)
    with pytest.raises(ValueError, match=r'masks must hold 3 grids of n\^3'):
        congeal_yaws(X, 16, masks=np.ones((3, n ** 3), bool))
    # (m, n, n, n) grids are grids too
    assert class_entropy(X.reshape(3, 16, 16, 16), 16) == class_entropy(X, 16)


def _rotated_set(n, m, seed=0):
    """m copies of the L shape (scaled to n) turned by random yaws, (m, n^3) float32."""
    base = l_shape(16).repeat(n // 16, 0).repeat(n // 16, 1).repeat(n // 16, 2)
    rot = np.random.default_rng(seed).uniform(0, 2 * np.pi, m)
    return np.stack([rotate_grid(base, r).ravel() for r in rot])


def _peak_bytes(X, n, masks):
    import tracemalloc
    tracemalloc.start()
    try:
        congeal_yaws(X, n, masks, iters=1)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize('with_masks', [False, True])
def test_congealing_memory_per_object_is_about_a_byte_per_pooled_voxel_and_yaw(with_masks):
    # every object's pooled occupancy and observed counts at all 36 yaws were cached as
    # float32: 8 bytes per pooled voxel and yaw (9 MB an object at 64^3), plus float32 copies
    # of X and the masks; 0/1 grids now keep uint8 counts and share N without masks
    n, yaw_count = 32, 36
    entries = yaw_count * (n // 2) ** 3
    X = _rotated_set(n, 24)
    masks = np.ones(X.shape, bool) if with_masks else None
    if with_masks:
        masks[::2, : n * n * 8] = False
    few = _peak_bytes(X[:8], n, None if masks is None else masks[:8])
    many = _peak_bytes(X, n, masks)
    per_object = (many - few) / 16
    assert per_object < (2.5 if with_masks else 1.5) * entries, per_object / entries


@pytest.mark.parametrize('with_masks', [False, True])
def test_compact_counts_give_the_float32_counts_yaws(monkeypatch, with_masks):
    # the uint8 cache holds the same values as the float32 one: the same costs, the same yaws
    from beo_ros.core import congeal
    n = 16
    X = _rotated_set(n, 10, seed=3)
    masks = None
    if with_masks:
        masks = np.ones(X.shape, bool)
        masks[1::3, : n * n * 5] = False
    X[4] *= 0.75   # a fractional object: float32 counts beside the others' uint8 ones
    compact = congeal_yaws(X, n, masks, yaw_step_deg=15.0)
    monkeypatch.setattr(congeal, '_binary', lambda a: False)   # every object in float32
    wide = congeal_yaws(X, n, masks, yaw_step_deg=15.0)
    np.testing.assert_array_equal(compact[0], wide[0])
    assert compact[1] == wide[1] and wide[1][-1] < wide[1][0]


def test_class_entropy_by_hand():
    # sum over voxels of n_v H(p_v), p_v = (a + occupied) / (2a + observed), a = prior: the
    # other tests only compared costs with each other (lower after congealing)
    n = 2
    X = np.stack([np.ones(8), np.zeros(8)]).astype(np.float32)
    assert class_entropy(X, n, pool=1) == pytest.approx(16.0)       # p = 1/2 everywhere
    masks = np.ones(X.shape, bool)
    masks[1, 4:] = False      # the empty object observes half the voxels
    h = -(0.75 * np.log2(0.75) + 0.25 * np.log2(0.25))               # p = 1.5 / 2
    assert class_entropy(X, n, masks, pool=1) == pytest.approx(4 * 2 + 4 * h)
    # prior 0: the observed-by-one voxels are certain (0 bits)
    assert class_entropy(X, n, masks, prior=0.0, pool=1) == pytest.approx(8.0)
    # pooled: 2^3 blocks of a 4^3 grid, occupied counts 8 and 0 out of 16 observed
    X4 = np.stack([np.ones(64), np.zeros(64)]).astype(np.float32)
    X4[1, :32] = 1   # the second object full in its lower half of x: blocks 16/16 or 8/16
    full = -(16.5 / 17 * np.log2(16.5 / 17) + 0.5 / 17 * np.log2(0.5 / 17))
    assert class_entropy(X4, 4, pool=2) == pytest.approx(16 * (4 * full + 4 * 1.0))


def test_congeal_history_starts_at_the_objective_of_the_grids_as_given():
    n = 16
    X = _rotated_set(n, 5, seed=1)
    masks = np.ones(X.shape, bool)
    masks[::2, : n * n * 3] = False
    for prior in (0.5, 0.0):
        _, hist = congeal_yaws(X, n, masks, iters=1, prior=prior)
        assert hist[0] == pytest.approx(class_entropy(X, n, masks, prior=prior), rel=1e-6)


def test_objects_do_not_move_between_yaws_of_equal_cost_and_the_sweeps_stop():
    # a cube centred in the grid costs the same at every quarter turn: no object moves (an
    # equal cost is no gain), so the first sweep changes nothing and is the last
    n = 16
    g = np.zeros((n,) * 3, np.float32)
    g[4:12, 4:12, 0:6] = 1
    X = np.stack([g.ravel()] * 4)
    yaws, hist = congeal_yaws(X, n, yaw_step_deg=90.0, iters=6)
    np.testing.assert_array_equal(yaws, 0.0)
    assert len(hist) == 2 and hist[1] == hist[0]
