"""Yaw alignment of a class's training grids by congealing (Learned-Miller 2006; the BEO paper).

Each object is repeatedly re-rotated about +z to the yaw (from a fixed set of candidates) that
minimises the summed voxel-wise binary entropy of the class's mean occupancy, the others held
fixed. With missing data (``masks``: True = observed) the mean of a voxel is taken over the
objects that observe it: p_v = (a + sum_j m_jv x_jv) / (2a + sum_j m_jv), a = ``prior`` pseudo
counts at 1/2, and the objective is the code length sum_v n_v H(p_v) of the observed entries
(n_v = sum_j m_jv), so unknown voxels cost nothing and observations are pulled together.

The entropy is evaluated on 2x-pooled grids (``pool=2``: fractional occupancy and observed
counts per 2^3 block), which smooths the objective and makes it 8x cheaper.
"""
from __future__ import annotations

import sys

import numpy as np

from .grid import rotate_grid, yaw_source_index


def _pool(a, n, p):
    """(r, n^3) -> (r, (n/p)^3) block sums."""
    if p == 1:
        return a
    m = n // p
    # not -1: no rows is (0, m^3) too
    return a.reshape(len(a), m, p, m, p, m, p).sum(axis=(2, 4, 6)).reshape(len(a), m ** 3)


def _h(p):
    p = np.clip(p, 1e-12, 1 - 1e-12)
    return -(p * np.log2(p) + (1 - p) * np.log2(1 - p))


def _cost(S, N, prior):
    # a voxel no object observes costs nothing (with prior 0 it was 0/0: a NaN objective)
    return (N * _h((S + prior) / np.maximum(N + 2 * prior, 1e-12))).sum(axis=-1)


def _check_options(yaw_step_deg, iters, prior, pool):
    """ValueError naming the first congealing option out of range (else a ZeroDivisionError
    for a step or pool of 0, numpy's 'cannot reshape' for a negative step, ...)."""
    def real(v):
        return not isinstance(v, (bool, np.bool_)) and isinstance(v, (int, float, np.number)) \
            and np.isfinite(v)

    def integer(v):
        return not isinstance(v, (bool, np.bool_)) and isinstance(v, (int, np.integer))

    if not (real(yaw_step_deg) and 0 < yaw_step_deg <= 360):
        raise ValueError(f'yaw_step_deg must be a number in (0, 360], got {yaw_step_deg!r}')
    if not (integer(iters) and iters >= 0):
        raise ValueError(f'iters must be an integer >= 0, got {iters!r}')
    if not (real(prior) and prior >= 0):
        raise ValueError(f'prior must be a finite number >= 0, got {prior!r}')
    if not (integer(pool) and pool >= 1):
        raise ValueError(f'pool must be an integer >= 1, got {pool!r}')


def _check_grids(X, masks, n):
    """ValueError unless X (and masks) hold len(X) grids of n^3 voxels: else an IndexError in
    the rotation maps (larger n), yaws from the first n^3 voxels without a word (smaller n),
    or numpy's reshape error after the congealing."""
    for name, a in (('X', X), ('masks', masks)):
        if a is not None and np.shape(a) not in ((len(X), n ** 3), (len(X), n, n, n)):
            raise ValueError(f'{name} must hold {len(X)} grids of n^3 = {n ** 3} voxels (n = {n}),'
                             f' got shape {np.shape(a)}')


def _binary(a):
    return bool(((a == 0) | (a == 1)).all())


def _rotated_counts(X, masks, n, pool, idx):
    """The function i -> (S_i, N_i), object i's pooled occupancy and observed counts at every
    candidate yaw ((Y, (n/pool)^3) each; ``idx`` the (Y, n^3) yaw_source_index maps).

    The cache of these is the congealing's memory (36 yaws of a 64^3 grid: 9 MB an object in
    float32), so an object whose observed occupancy and mask are 0/1 keeps its counts, small
    integers, as uint8, and without masks every object shares one N (the rotated grid's own
    voxels): the same values, so the same costs and yaws. Other objects stay float32.
    """
    pad = lambda a: np.append(a, np.float32(0))  # noqa: E731  outside the grid: unobserved
    small = pool ** 3 <= np.iinfo(np.uint8).max
    ones = np.ones(n ** 3, dtype=np.float32)
    N_all = _pool(pad(ones)[idx], n, pool)
    N_all_small = N_all.astype(np.uint8)

    def rotated(i):
        mf = ones if masks is None else np.asarray(masks[i], dtype=np.float32)
        xo = np.where(mf > 0, X[i], 0)  # not X * Mf: NaN where unobserved made every cost NaN
        S = _pool(pad(xo)[idx], n, pool)
        N = N_all if masks is None else _pool(pad(mf)[idx], n, pool)
        if not (small and _binary(xo) and (masks is None or _binary(mf))):
            return S, N
        return S.astype(np.uint8), N_all_small if masks is None else N.astype(np.uint8)

    return rotated


def congeal_yaws(X, n, masks=None, yaw_step_deg=10.0, iters=6, prior=0.5, pool=2, seed=0,
                 verbose=False):
    """Congeal one class: (yaws (m,) radians to rotate each object by, cost per sweep list).

    X: (m, n^3) occupancy in [0, 1] (anything, NaN too, where unobserved), m >= 1; masks:
    optional bool (m, n^3), True = observed.
    """
    X = np.asarray(X, dtype=np.float32)
    m = len(X)
    if m == 0:   # else "'int' object has no attribute 'astype'" from the empty sums
        raise ValueError('X must hold at least one object, got 0')
    _check_options(yaw_step_deg, iters, prior, pool)
    _check_grids(X, masks, n)
    X = X.reshape(m, n ** 3)
    if masks is not None:
        masks = np.reshape(masks, (m, n ** 3))
    if n % pool:
        pool = 1
    yaws = np.deg2rad(np.arange(0.0, 360.0, yaw_step_deg))
    idx = yaw_source_index(n, yaws)                                  # (Y, n^3)
    rotated = _rotated_counts(X, masks, n, pool, idx)
    cache = [rotated(i) for i in range(m)]
    cur = np.zeros(m, dtype=int)
    # in float32 as the sums of the float32 counts were (the compact ones hold the same values)
    S = sum(c[0][0].astype(np.float32) for c in cache).astype(np.float64)
    N = sum(c[1][0].astype(np.float32) for c in cache).astype(np.float64)
    history = [float(_cost(S, N, prior))]
    rng = np.random.default_rng(seed)
    for sweep in range(iters):
        changed = 0
        for i in rng.permutation(m):
            Si, Ni = cache[i]
            S0, N0 = S - Si[cur[i]], N - Ni[cur[i]]
            c = _cost(S0[None] + Si, N0[None] + Ni, prior)            # (Y,)
            best = int(np.argmin(c))
            if c[best] < c[cur[i]] - 1e-9:
                changed += 1
                cur[i] = best
            S, N = S0 + Si[cur[i]], N0 + Ni[cur[i]]
        history.append(float(_cost(S, N, prior)))
        if verbose:
            print(f'  congeal sweep {sweep + 1}: cost {history[-1]:.1f} bits, {changed} moved',
                  file=sys.stderr)
        if not changed:
            break
    # fix the gauge: the first object keeps its yaw (the class frame follows object 0)
    out = np.mod(yaws[cur] - yaws[cur[0]], 2 * np.pi)
    return out, history


def apply_yaws(X, n, yaws, masks=None):
    """Rotate every row of X (and masks, unknown outside the source grid) by its yaw."""
    X = np.asarray(X)
    Xr = np.stack([rotate_grid(X[i].reshape(n, n, n), yaws[i], fill=0).ravel()
                   for i in range(len(X))]) if len(X) else X.copy()
    if masks is None:
        return Xr, None
    Mr = np.stack([rotate_grid(np.asarray(masks[i], bool).reshape(n, n, n), yaws[i],
                               fill=False).ravel() for i in range(len(X))]) if len(X) else \
        np.zeros((0, n ** 3), dtype=bool)   # np.stack of no arrays fails
    return Xr, Mr


def class_entropy(X, n, masks=None, prior=0.5, pool=2):
    """The congealing objective (bits) of a set of grids as they are."""
    X = np.asarray(X, dtype=np.float32)
    _check_grids(X, masks, n)
    X = X.reshape(len(X), n ** 3)
    Mf = np.ones_like(X) if masks is None else np.reshape(masks, X.shape).astype(np.float32)
    if n % pool:
        pool = 1
    return float(_cost(_pool(np.where(Mf > 0, X, 0), n, pool).sum(0).astype(np.float64),
                       _pool(Mf, n, pool).sum(0).astype(np.float64), prior))


def congeal_classes(X, y, n, masks=None, yaw_step_deg=10.0, iters=6, prior=0.5, pool=2,
                    verbose=False, return_yaws=False):
    """Align the yaw of the objects of each class by congealing (see module doc).

    Returns the aligned X (same dtype and shape), or (X, masks) when ``masks`` is given (masks
    rotated consistently: voxels rotated in from outside the grid are unknown); with
    ``return_yaws`` the per-object yaws (radians, about +z) are appended.
    """
    X = np.asarray(X)
    y = np.asarray(y)
    if len(X) == 0:
        raise ValueError('X must hold at least one object, got 0')
    _check_options(yaw_step_deg, iters, prior, pool)   # also when no class has 2 objects
    if len(y) != len(X):
        raise ValueError(f'y must hold one label per object ({len(X)}), got {len(y)}')
    _check_grids(X, masks, n)
    yaws = np.zeros(len(X))
    for c in np.unique(y):
        sel = np.flatnonzero(y == c)
        if len(sel) < 2:
            continue
        if verbose:
            print(f'congealing class {c}: {len(sel)} objects', file=sys.stderr)
        yaws[sel], _ = congeal_yaws(X[sel], n, None if masks is None else masks[sel],
                                    yaw_step_deg, iters, prior, pool, verbose=verbose)
    Xr, Mr = apply_yaws(X, n, yaws, masks)
    Xr = Xr.astype(X.dtype).reshape(X.shape)   # (m, n, n, n) grids stay grids
    out = (Xr,) if masks is None else (Xr, Mr.reshape(np.shape(masks)))
    if return_yaws:
        out = out + (yaws,)
    return out[0] if len(out) == 1 else out
