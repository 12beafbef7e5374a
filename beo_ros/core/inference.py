"""Pose search, Bayesian completion and classification features for a labelled voxel grid.

Everything is batched: the pose search scores every (yaw, class) pair with two matrix products
over a 2x-pooled grid, then the best yaws of each class are re-scored exactly at full resolution.

Every score is a likelihood of the *observation as it is*: the model is rotated into the observed
frame (nearest neighbour), each observed voxel counted once. Resampling the observation into the
model's frame instead drops and duplicates observed voxels differently at every yaw (thin parts
such as chair legs vanish at some angles), so the scores of different yaws would describe
different data; that made the likelihood landscape jagged and its maximum often 10-40 degrees
off for thin objects.

Notation (per class): W (d, k) loadings, mu (d,) mean, v noise variance. Given known voxels K
with values y_K, the coefficient posterior is N(m, S) with
    S^-1 = G = I + W_K^T W_K / v,     m = S W_K^T (y_K - mu_K) / v,
and the log marginal likelihood of y_K is
    -1/2 [ |K| log(2 pi v) + ||y_K - mu_K||^2 / v - b^T S b + log|G| ],  b = W_K^T (y_K - mu_K) / v.
"""
from __future__ import annotations

import threading

import numpy as np
from scipy import ndimage
from scipy.linalg import lapack
from scipy.special import ndtr

from .grid import yaw_column_index, yaw_grid, yaw_source_index

LOG2PI = float(np.log(2 * np.pi))
FEATURE_NAMES = ('loglik', 'coarse_loglik', 'rmse', 'recall', 'false_occupied', 'dt_error')
# pooled-grid rotation maps kept per engine (those of the default search take ~20 MB)
MAP_CACHE_BYTES = 256 * 2**20
# full-resolution rotation maps kept per engine: 720 at 32^3 (94 MB), fewer on larger grids
# (one map of 64^3 takes 1 MB, of 128^3 8 MB)
FULL_MAP_CACHE_BYTES = 128 * 2**20


def batched_cholesky_terms(G, b):
    """For SPD G (B, k, k) and b (B, k): returns (b^T G^-1 b (B,), log|G| (B,), G^-1 b (B, k)).

    A column loop over k with the batch vectorised: far faster than B LAPACK calls for k ~ 10
    (one system: ``cholesky_terms``; the two agree to rounding, which matters where G is
    ill-conditioned, so each caller sticks to one).
    """
    B, k, _ = G.shape
    L = np.zeros_like(G)
    for j in range(k):
        d = G[:, j, j] - np.einsum('bi,bi->b', L[:, j, :j], L[:, j, :j])
        d = np.sqrt(np.maximum(d, 1e-12))
        L[:, j, j] = d
        if j + 1 < k:
            L[:, j + 1:, j] = (G[:, j + 1:, j] - np.einsum('bri,bi->br', L[:, j + 1:, :j],
                                                          L[:, j, :j])) / d[:, None]
    z = np.zeros_like(b)
    for j in range(k):
        z[:, j] = (b[:, j] - np.einsum('bi,bi->b', L[:, j, :j], z[:, :j])) / L[:, j, j]
    x = np.zeros_like(b)
    for j in range(k - 1, -1, -1):
        x[:, j] = (z[:, j] - np.einsum('bi,bi->b', L[:, j + 1:, j], x[:, j + 1:])) / L[:, j, j]
    logdet = 2 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1)
    return (z ** 2).sum(axis=1), logdet, x


def yaw_key(yaw):
    """The cache key of a yaw (radians): its value in [0, 2 pi) rounded to 1e-9."""
    return round(float(np.mod(yaw, 2 * np.pi)), 9) % round(2 * np.pi, 9)


def cholesky_terms(G, b):
    """For one SPD G (k, k) float64 and b (k,): (b^T G^-1 b, log|G|, G^-1 b (k,)) by LAPACK
    (called directly: the wrappers of numpy and scipy cost more than the solve at k ~ 20).

    Raises numpy.linalg.LinAlgError when G is not positive definite."""
    if not len(b):   # a model of no components (LAPACK refuses empty arrays)
        return 0.0, 0.0, np.zeros(0)
    L, info = lapack.dpotrf(G, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f'matrix is not positive definite (LAPACK potrf info {info})')
    z, _ = lapack.dtrtrs(L, b, lower=1)
    x, _ = lapack.dpotrs(L, b, lower=1)
    return float(z @ z), float(2 * np.log(np.diagonal(L)).sum()), x


def pool2(a):
    """Sum-pool the first three axes of a (n, n, n, ...) array by 2: (n/2, n/2, n/2, ...)."""
    n = a.shape[0]
    h = n // 2
    return a.reshape(h, 2, h, 2, h, 2, *a.shape[3:]).sum(axis=(1, 3, 5))


class InferenceEngine:
    """Precomputed arrays for the batched pose search and the exact posteriors over a set of
    class models (caches per yaw: rotation maps and the yaw's model sums; thread-safe to use).

    Args:
        W: (C, d, k) loadings, zero-padded to a common k; mu: (C, d); v: (C,) noise variances;
        v_coarse: (C,) noise variances of the 2x-pooled model; n: grid size (d = n**3);
        pose_components: how many leading components the coarse search uses;
        coarse_noise_maps: optional per class None or (d / 8,) noise variance per pooled voxel,
            used when one class is scored with all its components (``scores(..., full=True)``).
    """

    def __init__(self, W, mu, v, v_coarse, n, pose_components=8, coarse_noise_maps=None):
        self.C, self.d, self.k = W.shape
        if n % 2 or n ** 3 != self.d:
            raise ValueError(f'grid size must be even (the pose search pools it by 2) and '
                             f'n^3 = d; got n={n}, d={self.d}')
        self.n = n
        # W is a view of [W | mu] (C, d, k + 1): the exact posterior's weighted sums over voxels
        # are the blocks of one augmented gram A^T diag(w) A (see ``exact``)
        W = np.asarray(W)
        self._Wmu = np.empty(W.shape[:2] + (W.shape[2] + 1,), dtype=np.float32)
        self._Wmu[:, :, :-1] = W
        self._Wmu[:, :, -1] = mu
        self.W = self._Wmu[:, :, :-1]
        self.mu = np.ascontiguousarray(mu, dtype=np.float32)
        self.v = np.asarray(v, dtype=np.float64)
        self.v_coarse = np.asarray(v_coarse, dtype=np.float64)
        # voxels where a class model is not exactly zero (never-occupied voxels have W = 0 and
        # mu = 0): the exact posterior only needs these rows
        self.support = np.any(self.W != 0, axis=2) | (self.mu != 0)               # (C, d)
        # coarse model: 2x pooled mean of the first kp components (stage 1: all classes) and
        # of all k components (stage 2: one class at a time)
        self.nc = n // 2
        self.kp = int(min(pose_components, self.k))
        self._PD, self._PT, self._iu = self._pooled_terms(range(self.C), self.kp)
        self._PD_c = [np.ascontiguousarray(self._PD[:, c]) for c in range(self.C)]
        self._PT_c = [np.ascontiguousarray(self._PT[:, c]) for c in range(self.C)]
        # built here, not on first use: no slow first queries
        self._full_terms = [self._full_class_terms(c, noise) for c, noise in
                            enumerate(coarse_noise_maps or [None] * self.C)]
        # per class and grid column (x, y): the sums over z of the upper triangle of A A^T
        # (float64), so the sums over all voxels for a yaw are one (n^2,) product: the
        # nearest-neighbour rotation moves whole columns, each canonical column showing in
        # 0, 1, 2 or 3 observed ones
        self._tri = np.triu_indices(self.k + 1)
        self._col_terms = [self._column_terms(c) for c in range(self.C)]
        self._supp_cols = self.support.reshape(self.C, n * n, n).sum(axis=2).astype(np.float64)
        self._maps = {}
        self._maps_bytes = 0
        self._full_maps = {}
        self._col_counts = {}
        self._yaw_terms = {}
        self._local = threading.local()
        # the yaw terms of every whole degree (what searches and refinements ask for), also
        # built here rather than on first use
        self._fill_yaw_terms(-np.deg2rad(np.arange(360.0)))

    def _column_terms(self, c):
        """(n^2, (k+1)(k+2)/2) float64: per grid column of class c the sums over z of the upper
        triangle of a a^T, a = [W | mu] of the column's voxels."""
        n = self.n
        A = self._Wmu[c].astype(np.float64).reshape(n * n, n, self.k + 1)
        return np.einsum('rza,rzb->rab', A, A)[:, self._tri[0], self._tri[1]]

    def _fill_yaw_terms(self, yaws):
        """Cache the column counts and ``_class_yaw_terms`` of the yaws' keys for every class."""
        keys = [yaw_key(y) for y in yaws]
        counts = self._counts_of(keys)
        self._col_counts.update(zip(keys, counts))
        for c in range(self.C):
            self._yaw_terms.update(zip(((key, c) for key in keys),
                                       self._terms_of(c, counts)))

    def _counts_of(self, keys):
        """(Y, n^2) int64: for the model rotated into the observed frame by minus the yaw of
        each key (the map ``_full_map(key)``, not made here), how many observed grid columns
        show each canonical column."""
        n2 = self.n ** 2
        cols = yaw_column_index(self.n, -np.asarray(keys, dtype=np.float64))   # n^2: outside
        Y = len(cols)
        return np.bincount((cols + (np.arange(Y) * (n2 + 1))[:, None]).ravel(),
                           minlength=Y * (n2 + 1)).reshape(Y, n2 + 1)[:, :n2]

    def _terms_of(self, c, counts):
        """``_class_yaw_terms`` of class c for column counts (Y, n^2): a list of Y pairs."""
        counts = np.asarray(counts, dtype=np.float64)
        out = []
        for tot, shown in zip(counts @ self._col_terms[c], (counts > 0) @ self._supp_cols[c]):
            aug = np.zeros((self.k + 1, self.k + 1))
            aug[self._tri] = tot
            out.append((aug + np.triu(aug, 1).T, int(round(float(shown)))))
        return out

    def _class_yaw_terms(self, c, key):
        """For class c rotated into the observed frame by minus the yaw of ``key``
        (``yaw_key``; the map ``_full_map(key)``): (k+1, k+1) float64 sum_p cM[p] a_p a_p^T
        over canonical voxels p, a = [W | mu], cM[p] the number of observed voxels showing p;
        and the count of support voxels shown at least once. Cached per (key, class)."""
        out = self._yaw_terms.get((key, c))
        if out is None:
            out = self._terms_of(c, self._column_counts(key)[None])[0]
            if len(self._yaw_terms) < 2 * 360 * self.C:
                self._yaw_terms[(key, c)] = out
        return out

    def _pooled_terms(self, classes, kp, noise=None):
        """Per pooled voxel and class: [pairs | mu*W | mu^2] (dc, C', m) to be weighted by D and
        [W | mu] (dc, C', kp+1) to be weighted by T, so two products score every (yaw, class).

        ``noise`` (dc,) (one class): every term is divided by the voxel's noise variance and D
        also weighs a last column log(2 pi noise)."""
        n, classes = self.n, list(classes)
        Wg = self.W[classes, :, :kp].reshape(len(classes), n, n, n, kp).transpose(1, 2, 3, 0, 4)
        Wc = (pool2(Wg) / 8.0).reshape(self.nc ** 3, len(classes), kp)
        muc = (pool2(self.mu[classes].T.reshape(n, n, n, len(classes))) / 8.0).reshape(
            -1, len(classes))
        iu = np.triu_indices(kp)
        pairs = Wc[:, :, iu[0]] * Wc[:, :, iu[1]]
        PD = np.concatenate([pairs, muc[:, :, None] * Wc, muc[:, :, None] ** 2], axis=2)
        PT = np.concatenate([Wc, muc[:, :, None]], axis=2)
        if noise is not None:
            noise = np.asarray(noise, dtype=np.float64)[:, None, None]
            PD = np.concatenate([PD / noise, np.log(2 * np.pi * noise)], axis=2)
            PT = PT / noise
        return (np.ascontiguousarray(PD, dtype=np.float32),
                np.ascontiguousarray(PT, dtype=np.float32), iu)

    def _full_class_terms(self, c, noise):
        """Stage-2 arrays of class c: all k components, per-voxel noise (dc,) if given; returns
        (PD, PT, iu, 1 / noise or None, noise outside the grid or None)."""
        PD, PT, iu = self._pooled_terms([c], self.k, noise)
        if noise is None:
            return PD[:, 0].copy(), PT[:, 0].copy(), iu, None, None
        noise = np.asarray(noise, np.float64)
        # observed cells beyond the rotated model's grid get the noise of its outer shell
        # (empty space, like the grid's corners), not the class scalar: the scalar is far
        # larger, and a yaw that turns the corners out of the grid would lose by it
        nc = self.nc
        shell = np.ones((nc,) * 3, dtype=bool)
        shell[1:-1, 1:-1, 1:-1] = False
        return (PD[:, 0].copy(), PT[:, 0].copy(), iu, 1.0 / noise,
                float(np.median(noise[shell.ravel()])))

    # ------------------------------------------------------------------ pose search
    def _rotation_maps(self, yaws):
        """Scatter maps of the pooled grid's columns for ``yaws``, the model rotated into the
        observed frame: observed cell q shows canonical cell R(-yaw) q, so a canonical cell sums
        the weights of 0, 1, 2 or 3 observed cells. The rotation moves whole (x, y) columns (z
        is kept), so the maps are of columns: cell (column p, z) shows the cells (q, z) of the
        columns q that show p. Returns (first (Y, nc^2) int index into the pooled observation's
        columns padded with a zero column, so a gather gives each canonical column one of its
        observed columns; extra: a list of (flat position in (Y, nc^2), observed column)
        arrays, one per further column, positions unique within each array)."""
        key = np.asarray(yaws, dtype=np.float64).tobytes()
        if key in self._maps:
            return self._maps[key]
        m = self.nc ** 2
        inv = yaw_column_index(self.nc, np.asarray(yaws))    # (Y, m), m: outside
        Y = len(inv)
        flat = (inv + (np.arange(Y) * (m + 1))[:, None]).ravel()   # (yaw, canonical column)
        order = np.argsort(flat, kind='stable')
        sflat = flat[order]
        rank = np.arange(len(sflat)) - np.searchsorted(sflat, sflat, side='left')
        col = sflat % (m + 1)
        inside = col < m        # observed columns beyond the canonical grid show empty space
        pos = (sflat // (m + 1)) * m + col                    # flat position in (Y, m)
        src = order % m
        first = np.full(Y * m, m, dtype=np.intp)
        sel = inside & (rank == 0)
        first[pos[sel]] = src[sel]
        extra = []
        for r in range(1, int(rank[inside].max(initial=0)) + 1):
            sel = inside & (rank == r)
            extra.append((pos[sel].astype(np.intp), src[sel].astype(np.intp)))
        out = (first.reshape(Y, m), extra)
        size = first.nbytes + sum(p.nbytes + c.nbytes for p, c in extra)
        # keep the regular search grids only, within a memory budget: a user sweeping fine
        # steps would otherwise pin many MB per step
        if (len(self._maps) < 16 and len(yaws) >= 36
                and self._maps_bytes + size <= MAP_CACHE_BYTES):
            self._maps[key] = out
            self._maps_bytes += size
        return out

    def _full_map(self, yaw):
        """Full-resolution gather map (d,) int32 rotating the observation by -yaw, or the
        canonical frame into the observed one for -yaw (cached per ``yaw_key``: every map,
        count and term of a key is made from the key's yaw, so they always agree)."""
        key = yaw_key(yaw)
        idx = self._full_maps.get(key)
        if idx is None:
            idx = yaw_source_index(self.n, [-key])[0]   # int32
            if len(self._full_maps) < min(720, FULL_MAP_CACHE_BYTES // idx.nbytes):
                self._full_maps[key] = idx
        return idx

    def _column_counts(self, key):
        """(n^2,) int64: for the model rotated into the observed frame by minus the yaw of
        ``key`` (the map ``_full_map(key)``), how many observed grid columns show each
        canonical column (cached)."""
        counts = self._col_counts.get(key)
        if counts is None:
            counts = self._counts_of([key])[0]
            if len(self._col_counts) < 720:
                self._col_counts[key] = counts
        return counts

    def to_observed(self, values, yaw, fill=0.0):
        """Rotate canonical-frame voxel values (d,) by ``yaw`` into the observed frame (d,)."""
        return np.take(np.append(values, np.asarray(fill, dtype=values.dtype)),
                       self._full_map(-yaw))

    def pooled(self, grid):
        """2x-pooled observation: weights D (known fraction), T (D * occupied fraction), and
        T^2 / D, each (dc + 1,) float32 with a last zero entry (the padding of the gathers)."""
        known = (grid >= 0).astype(np.float32)
        occ = (grid == 1).astype(np.float32)
        D = (pool2(known) / 8.0).ravel()
        T = (pool2(occ) / 8.0).ravel()
        TT = np.where(D > 0, T * T / np.maximum(D, 1e-6), 0.0)
        # float32 throughout (D and T are multiples of 1/8: exact), so the gathers in scores()
        # write into their float32 buffers without a cast
        zero = np.float32(0.0)
        return (np.append(D, zero), np.append(T, zero), np.append(TT, zero).astype(np.float32))

    def scores(self, pooled, yaws, c=None, full=False, rows=None):
        """Pooled log-likelihood (Y, C) of every yaw for all classes, or (Y, 1) for class c.

        ``full`` (with ``c``): use all k components of class c instead of the leading
        ``pose_components`` (slower, sharper: the pose refinement of the chosen class).
        ``rows``: score only these indices into ``yaws`` (whose maps stay cached).
        """
        D, T, TT = pooled
        yaws = np.atleast_1d(np.asarray(yaws, dtype=np.float64))
        first, extra = self._rotation_maps(yaws)
        dc, nc = len(D) - 1, self.nc
        m = nc * nc
        if rows is not None:
            rows = np.asarray(rows)
            # a row named twice is scored once: the extra cells below go to one copy only
            uniq, back = np.unique(rows % len(yaws), return_inverse=True)
            if len(uniq) < len(rows):
                return self.scores(pooled, yaws, c, full, uniq)[back.ravel()]
            keep = np.full(len(yaws), -1, dtype=np.intp)
            keep[rows] = np.arange(len(rows))
            sub = []
            for pos, src in extra:
                new = keep[pos // m]
                ok = new >= 0
                sub.append((new[ok] * m + pos[ok] % m, src[ok]))
            yaws, first, extra = yaws[rows], first[rows], sub
        Y = len(yaws)
        # the observed cells summed per canonical cell: one gather of whole columns (np.take
        # into reused buffers, 'clip' so that numpy does not buffer the output: the indices
        # are in range), then the few extra columns; D and T are multiples of 1/8, so their
        # sums are exact in any order
        n = Y * dc
        buf = getattr(self._local, 'buf', None)
        if buf is None or buf.shape[1] < n:
            buf = self._local.buf = np.empty((2, n), dtype=np.float32)
        zcol = np.zeros((1, nc), dtype=np.float32)
        Dcol = np.concatenate([D[:dc].reshape(m, nc), zcol])       # (m + 1, nc)
        Tcol = np.concatenate([T[:dc].reshape(m, nc), zcol])
        Dr3 = np.take(Dcol, first, axis=0, out=buf[0, :n].reshape(Y, m, nc), mode='clip')
        Tr3 = np.take(Tcol, first, axis=0, out=buf[1, :n].reshape(Y, m, nc), mode='clip')
        for pos, src in extra:
            Dr3.reshape(Y * m, nc)[pos] += Dcol[src]
            Tr3.reshape(Y * m, nc)[pos] += Tcol[src]
        Dr, Tr = Dr3.reshape(Y, dc), Tr3.reshape(Y, dc)
        inv = None
        if c is None:
            PD, PT, iu, kp, C = (self._PD.reshape(dc, -1), self._PT.reshape(dc, -1), self._iu,
                                 self.kp, self.C)
        elif full:
            PD, PT, iu, inv, v_out = self._full_terms[c]
            kp, C = self.k, 1
        else:
            PD, PT, iu, kp, C = self._PD_c[c], self._PT_c[c], self._iu, self.kp, 1
        AD = (Dr @ PD).reshape(Y, C, -1).astype(np.float64)
        AT = (Tr @ PT).reshape(Y, C, -1).astype(np.float64)
        # every observed cell counts once, whatever the yaw: the TT and D totals are constants;
        # cells that show nothing of the canonical grid are explained by empty space
        D_all = float(D[:dc].sum(dtype=np.float64))
        TT_all = float(TT[:dc].sum(dtype=np.float64))
        if inv is not None:   # per-voxel noise, already divided into the terms
            TTcol = np.concatenate([TT[:dc].reshape(m, nc), zcol])
            TTr = np.take(TTcol, first, axis=0).astype(np.float64)   # (Y, m, nc)
            for pos, src in extra:
                TTr.reshape(Y * m, nc)[pos] += TTcol[src]
            TTr = TTr.reshape(Y, dc)
            D_out = D_all - Dr.sum(axis=1, dtype=np.float64)
            TT_out = TT_all - TTr.sum(axis=1)
            return self._loglik(AD[:, :, :-1], AT, (TTr @ inv + TT_out / v_out)[:, None],
                                AD[:, :, -1] + (D_out * np.log(2 * np.pi * v_out))[:, None],
                                iu, kp)
        vc = self.v_coarse[None, :] if c is None else self.v_coarse[None, c:c + 1]
        return self._loglik(AD / vc[..., None], AT / vc[..., None],
                            np.full((Y, 1), TT_all) / vc,
                            np.full((Y, 1), D_all) * np.log(2 * np.pi * vc), iu, kp)

    @staticmethod
    def _loglik(AD, AT, tt, lognoise, iu, kp):
        """Log-likelihood (Y, C) from noise-scaled sums over the rotated pooled cells:
        AD (Y, C, npair + kp + 1) of D * [pairs | mu*W | mu^2] / noise, AT (Y, C, kp + 1) of
        T * [W | mu] / noise, tt (Y, C) of TT / noise and lognoise (Y, C) of D log(2 pi noise)."""
        Y, C = AD.shape[:2]
        npair = len(iu[0])
        # both triangles written directly (the same sums as mirroring the upper one with triu,
        # four times faster at 180 yaws x 10 classes)
        G = np.zeros((Y, C, kp, kp))
        G[:, :, iu[0], iu[1]] = AD[:, :, :npair]
        G[:, :, iu[1], iu[0]] = AD[:, :, :npair]
        G += np.eye(kp)
        b = AT[:, :, :kp] - AD[:, :, npair:npair + kp]
        quad, logdet, _ = batched_cholesky_terms(G.reshape(Y * C, kp, kp), b.reshape(Y * C, kp))
        rr = tt - 2 * AT[:, :, kp] + AD[:, :, npair + kp]
        return -0.5 * (lognoise + rr - quad.reshape(Y, C) + logdet.reshape(Y, C))

    def search(self, grid, step_deg=1.0, coarse_step_deg=5.0, n_modes=2, window_deg=None,
               exhaustive=False, pooled=None):
        """Best yaw of every class on the pooled grid.

        Scores every class at ``coarse_step_deg`` in one batched product, then each class's
        ``n_modes`` best modes at ``step_deg`` within +-``window_deg`` (default: the coarse
        step); ``exhaustive`` scores all 360 / step_deg yaws instead.
        ``pooled``: ``self.pooled(grid)`` if the caller has it already.
        Returns (best yaw (C,), best log-likelihood (C,), list of per-class (yaws, ll)).
        """
        P = self.pooled(grid) if pooled is None else pooled
        step = np.deg2rad(step_deg)
        if exhaustive or coarse_step_deg <= step_deg:
            yaws = yaw_grid(step_deg)
            ll = self.scores(P, yaws)
            per = [(yaws, ll[:, c]) for c in range(self.C)]
        else:
            yaws0 = yaw_grid(coarse_step_deg)
            ll0 = self.scores(P, yaws0)
            half = np.deg2rad(coarse_step_deg if window_deg is None else window_deg)
            nw = int(round(half / step))
            offs = np.arange(-nw, nw + 1) * step     # includes the coarse mode itself
            per = []
            min_sep = max(1, int(round(30.0 / coarse_step_deg)))
            for c in range(self.C):
                modes = top_modes(ll0[:, c], n_modes, min_sep)
                cand = np.concatenate([yaws0[m] + offs for m in modes])
                per.append((cand, self.scores(P, cand, c)[:, 0]))
        best = [int(np.argmax(llc)) for _, llc in per]
        return (np.array([y[i] for (y, _), i in zip(per, best)]),
                np.array([llc[i] for (_, llc), i in zip(per, best)]), per)

    # ------------------------------------------------------------------ exact posterior
    def observe(self, grid):
        """The per-grid arrays that every ``exact`` call on ``grid`` (N, N, N) int8 needs."""
        if isinstance(grid, Observation):
            return grid
        g = np.ascontiguousarray(grid, dtype=np.int8).ravel()
        if g.size != self.d:
            raise ValueError(f'grid must have {self.d} voxels, got {g.size}')
        return Observation(g)

    def exact(self, grid, c, yaw, with_prediction=True):
        """Exact full-resolution posterior of class ``c`` at ``yaw``.

        ``grid``: (N, N, N) int8 labels or ``self.observe(grid)`` (faster for repeated calls).
        Returns a dict: loglik, n_known, m (k,), G (k, k), rr, b, idx, and (with_prediction) the
        rotated canonical labels ``canon`` (d,) int8 and prediction ``pred`` (d,) in the
        canonical frame (``add_prediction`` adds them later).
        """
        obs = self.observe(grid)
        k, n, d, v = self.k, self.n, self.d, self.v[c]
        A = self._Wmu[c]
        # the likelihood is of the observation as it is: observed voxel q is explained by
        # canonical voxel inv[q] (the model rotated by yaw; d: outside, explained as empty).
        # Canonical voxel p explains cK[p] = cM[p] - cU[p] known voxels: cM[p] observed voxels
        # show it (0-3, the same along a grid column), cU[p] of them are unknown
        key = yaw_key(-yaw)
        inv = self._full_map(key)
        aug_M, n_shown = self._class_yaw_terms(c, key)
        col_M = self._column_counts(key)
        cU = np.bincount(np.take(inv, obs.unknown), minlength=d + 1)[:d]
        supp = self.support[c]
        U = np.flatnonzero(cU)
        U = U[supp[U]]
        wU = cU[U]
        n_known_rows = n_shown - int(np.count_nonzero(wU == col_M[U // n]))
        # the augmented gram of the known voxels, sum_p cK[p] a_p a_p^T: the cM-weighted one
        # (column sums, float64) minus the unknown rows, or directly over the known rows,
        # whichever touches fewer rows. A long direct sum runs in float32 (BLAS) and is added
        # to float64; a difference is taken in float64 throughout: in float32 its rounding,
        # divided by a small v, made G indefinite (few known voxels) or many times too sure
        # of components that only the unknown voxels carry (e.g. an object's hidden back)
        from_total = len(U) <= n_known_rows
        if from_total:
            rows, w = U, wU
        else:
            cK = np.repeat(col_M, n) - cU
            rows = np.flatnonzero(cK * supp)
            w = cK[rows]
        AR = np.take(A, rows, axis=0)
        if from_total or len(rows) < 4096:   # short sums are cheap in float64 anyway
            AR = AR.astype(np.float64)
        AR *= np.sqrt(w, dtype=AR.dtype)[:, None]
        aug = (AR.T @ AR).astype(np.float64)
        if from_total:
            aug = aug_M - aug
        gram, wmu, mu2 = aug[:k, :k], aug[:k, k], aug[k, k]
        O, wO = np.unique(np.take(inv, obs.occupied), return_counts=True)
        if len(O) and O[-1] == d:
            O, wO = O[:-1], wO[:-1]
        occ = wO.astype(np.float64) @ np.take(A, O, axis=0).astype(np.float64)
        b = (occ[:k] - wmu) / v
        rr = obs.n_occupied - 2 * occ[k] + mu2
        G = np.eye(k) + gram / v
        quad, logdet, m = cholesky_terms(G, b)
        nk = obs.n_known
        ll = -0.5 * (nk * np.log(2 * np.pi * v) + rr / v - quad + logdet)
        out = dict(loglik=float(ll), n_known=int(nk), m=m, G=G, rr=float(rr), b=b,
                   idx=self._full_map(yaw))
        if with_prediction:
            self.add_prediction(out, obs, c)
        return out

    def add_prediction(self, ex, grid, c):
        """Add ``canon`` (the observation rotated into the canonical frame, free outside) and
        ``pred`` (W m + mu) (d,) to the result ``ex`` of ``exact(grid, c, ...)``; returns it."""
        if 'pred' not in ex:
            obs = self.observe(grid)
            ex['canon'] = np.take(obs.padded, ex['idx'])
            ex['pred'] = self.W[c] @ ex['m'].astype(np.float32) + self.mu[c]
        return ex

    def features(self, ex, c, coarse_ll, edt_obs_canon):
        """Classification features of one exact posterior (see FEATURE_NAMES)."""
        canon, pred = ex['canon'], ex['pred']
        nk = max(ex['n_known'], 1)
        v = self.v[c]
        m, G = ex['m'], ex['G']
        sq = ex['rr'] - 2 * v * m @ ex['b'] + v * m @ (G - np.eye(self.k)) @ m
        occ = canon == 1
        free = canon == 0
        p_occ = pred >= 0.5
        n_occ = max(int(occ.sum()), 1)
        recall = float((p_occ & occ).sum()) / n_occ
        false_occ = float((p_occ & free).sum()) / max(int(free.sum()), 1)
        # one-sided distance-transform error: predicted occupied known voxels to the observed
        # surface (the paper's EDT L2 error restricted to what was seen)
        sel = p_occ & (canon >= 0)
        dt = float(np.sqrt((edt_obs_canon[sel] ** 2).mean())) if sel.any() else float(self.n)
        return np.array([ex['loglik'] / nk, coarse_ll, np.sqrt(max(sq, 0) / nk), recall,
                         false_occ, dt], dtype=np.float64)

    def predictive(self, ex, c, Sw=None, mu_var=None):
        """Occupancy probability, predictive mean and variance (d,) in the canonical frame.

        ``Sw`` (k_c, k_c): posterior covariance of a row of W (loading uncertainty);
        ``mu_var`` (d,): posterior variance of mu.
        """
        W = self.W[c].astype(np.float64)
        S = np.linalg.inv(ex['G'])
        mean = ex['pred'].astype(np.float64)
        var = ((W @ S) * W).sum(axis=1) + self.v[c]
        if Sw is not None:
            ks = Sw.shape[0]
            m = ex['m'][:ks]
            var += m @ Sw @ m + np.trace(Sw @ S[:ks, :ks])
        if mu_var is not None:
            var += mu_var
        prob = ndtr((mean - 0.5) / np.sqrt(var))
        return prob.astype(np.float32), mean.astype(np.float32), var.astype(np.float32)


class Observation:
    """What ``InferenceEngine.exact`` needs of a labelled grid, flattened (d,) int8: the flat
    indices of its unknown and occupied voxels, the counts of known and occupied voxels, and
    the labels padded with a free voxel (the gathers' outside)."""

    __slots__ = ('padded', 'unknown', 'occupied', 'n_known', 'n_occupied')

    def __init__(self, labels):
        self.padded = np.append(labels, np.int8(0))
        self.unknown = np.flatnonzero(labels < 0)
        self.occupied = np.flatnonzero(labels == 1)
        self.n_known = labels.size - len(self.unknown)
        self.n_occupied = len(self.occupied)


def observed_edt(grid):
    """Euclidean distance (voxels) from every voxel to the nearest observed occupied voxel."""
    occ = grid == 1
    if not occ.any():
        return np.full(grid.shape, float(grid.shape[0]), dtype=np.float32)
    return ndimage.distance_transform_edt(~occ).astype(np.float32)


def top_yaw_modes(yaws, scores, n_modes, min_sep_deg=20.0):
    """Indices of the ``n_modes`` best ``scores`` (Y,) whose ``yaws`` (Y,) radians are at least
    ``min_sep_deg`` apart on the circle, best first (any set of yaws, e.g. the windows of a
    coarse-to-fine search, not only a regular grid). ValueError unless ``n_modes`` is an
    integer >= 1 (0 used to return every separated mode)."""
    if isinstance(n_modes, (bool, np.bool_)) or not isinstance(n_modes, (int, np.integer)) \
            or n_modes < 1:
        raise ValueError(f'n_modes must be an integer >= 1, got {n_modes!r}')
    yaws = np.asarray(yaws, dtype=np.float64)
    sep = np.deg2rad(min_sep_deg) - 1e-9
    alive = np.ones(len(yaws), dtype=bool)
    picked = []
    for i in np.argsort(-np.asarray(scores)):
        if not alive[i]:
            continue
        picked.append(int(i))
        if len(picked) == n_modes:
            break
        alive &= np.abs((yaws - yaws[i] + np.pi) % (2 * np.pi) - np.pi) >= sep
    return picked


def top_modes(scores, n_modes, min_sep):
    """Indices of the ``n_modes`` best circular local maxima of ``scores`` (Y,) over a regular
    grid of Y yaws, at least ``min_sep`` grid steps apart, best first (``top_yaw_modes``)."""
    scores = np.asarray(scores)
    Y = len(scores)
    # local maxima only: else the best yaw min_sep steps down the slope of the best mode
    # passed for a second mode
    peaks = np.flatnonzero((scores >= np.roll(scores, 1)) & (scores >= np.roll(scores, -1)))
    picked = top_yaw_modes(peaks * (2 * np.pi / Y), scores[peaks], n_modes, min_sep * 360.0 / Y)
    return [int(peaks[i]) for i in picked]
