"""Peer estimators for ``beo-bench`` (ROS-free): the paper's plain method and an ICP database.

Both take the same labelled query grids as :meth:`ModelBank.estimate` (int8 (N, N, N): 1
occupied, 0 free, -1 unknown; object rotated about +z by an unknown yaw) and return
``(label index, yaw radians)`` with the yaw convention of the bank: the rotation about +z that
maps the canonical (training) object onto the observed one.

- :class:`PaperPCA` is a deliberately plain implementation of the original BEO method: plain PCA
  per class; for each of 36 yaw candidates (a Python loop) and each class, rotate the query back,
  solve the least squares ``A o = b`` with ``A = W_K^T W_K``, ``b = W_K^T (y_K - mu_K)`` over the
  known voxels K, and keep the (class, yaw) of the smallest residual on the known voxels.
- :class:`ICPDatabase` keeps surface point clouds of training objects and aligns the query's
  occupied voxels to each of them (open3d point-to-plane ICP) from several initial yaws; the
  best fitness (tie-break: smaller inlier RMSE) gives class and yaw.
"""
from __future__ import annotations

import numbers

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils.validation import check_is_fitted

from .grid import rotate_grid


def _check_int(name, value, low):
    """``value`` as an int, after checking it is an integer >= ``low``."""
    if not (isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
            and value >= low):
        raise ValueError(f'{name} must be an integer >= {low}, got {value!r}')
    return int(value)


def _check_number(name, value, low, strict):
    """``value`` as a float, after checking it is a finite number > ``low`` (>= if not
    ``strict``)."""
    if not (isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
            and np.isfinite(value) and (value > low if strict else value >= low)):
        raise ValueError(f'{name} must be a finite number {">" if strict else ">="} {low}, '
                         f'got {value!r}')
    return float(value)


def _check_training(X, y, names, n):
    """(X (m, n^3), y (m,) int, n) as arrays after checking they describe labelled grids:
    one row of X per label, the labels class indices into ``names``."""
    n = _check_int('n', n, 1)
    X, y = np.asarray(X), np.asarray(y)
    if X.ndim != 2 or X.shape[1] != n ** 3:
        raise ValueError(f'X must have shape (objects, {n ** 3}) (flattened {n}^3 grids), '
                         f'got {X.shape}')
    if y.shape != (len(X),):
        raise ValueError(f'y must have shape ({len(X)},) (one label per row of X), '
                         f'got {y.shape}')
    if len(names) == 0:
        raise ValueError('names must name at least one class')
    if len(y) and not np.isin(y, np.arange(len(names))).all():
        raise ValueError(f'y must hold class indices 0..{len(names) - 1} (into names), got '
                         f'{sorted(set(np.unique(y).tolist()) - set(range(len(names))))[:5]}')
    return X, y, n


def _check_query(grid, n):
    """The labelled query grid as an array, after checking its shape and that it has an object."""
    grid = np.asarray(grid)
    if grid.shape != (n,) * 3:
        raise ValueError(f'grid must have shape {(n,) * 3} (the fitted size), got {grid.shape}')
    if not (grid == 1).any():   # all free or all unknown: nothing to classify or align
        raise ValueError('grid has no occupied voxel: there is no object to estimate')
    return grid


class PaperPCA(BaseEstimator):
    """The paper's method, written plainly (per-candidate and per-class Python loops).

    Args:
        k: PCA components per class.
        n_yaws: yaw candidates, evenly spaced over 360 degrees.
        ridge: tiny Tikhonov term so ``A`` stays invertible (0: a singular ``A``, fewer known
            voxels than components, is solved by least squares).

    Learned attributes: ``n_`` (grid size), ``classes_`` (class names), ``W_`` and ``mu_``
    (per class: the (d, k) components and the (d,) mean, d = n^3).
    """

    def __init__(self, k=20, n_yaws=36, ridge=1e-6):
        self.k = k
        self.n_yaws = n_yaws
        self.ridge = ridge

    def fit(self, X, y, names, n):
        """X: (m, n^3) occupancy of the training objects, y: (m,) class indices into ``names``,
        n: the grid size. Returns self."""
        from sklearn.decomposition import PCA
        k = _check_int('k', self.k, 1)
        _check_int('n_yaws', self.n_yaws, 1)
        _check_number('ridge', self.ridge, 0, strict=False)
        X, y, n = _check_training(X, y, names, n)
        X = X.astype(np.float32, copy=False)
        W, mu = [], []
        for c in range(len(names)):
            Xc = X[y == c]
            if len(Xc) < 2:
                raise ValueError(f'class {names[c]!r} has {len(Xc)} training objects; need >= 2')
            pca = PCA(n_components=int(min(k, len(Xc) - 1)), svd_solver='randomized',
                      random_state=0).fit(Xc)
            W.append(pca.components_.T.astype(np.float32))   # (d, k)
            mu.append(pca.mean_.astype(np.float32))          # (d,)
        self.n_, self.classes_, self.W_, self.mu_ = n, list(names), W, mu
        return self

    @property
    def nbytes(self):
        check_is_fitted(self, 'W_')
        return int(sum(w.nbytes + m.nbytes for w, m in zip(self.W_, self.mu_)))

    def predict(self, grid):
        """(class index, yaw radians, completion (N, N, N) float32 in the canonical frame).

        Raises ValueError for a grid of another size than the fitted one or with no occupied voxel.
        """
        check_is_fitted(self, 'W_')
        grid = _check_query(grid, self.n_).astype(np.int8)
        n_yaws, ridge = int(self.n_yaws), float(self.ridge)
        best = (np.inf, 0, 0.0, None)
        for j in range(n_yaws):
            yaw = 2 * np.pi * j / n_yaws
            canon = rotate_grid(grid, -yaw, fill=np.int8(-1)).ravel()   # undo the candidate yaw
            K = canon >= 0
            if not K.any():
                continue
            yK = (canon[K] == 1).astype(np.float32)
            for c in range(len(self.classes_)):
                WK = self.W_[c][K]
                muK = self.mu_[c][K]
                A = WK.T @ WK + ridge * np.eye(WK.shape[1], dtype=np.float32)
                b = WK.T @ (yK - muK)
                try:
                    o = np.linalg.solve(A, b)
                except np.linalg.LinAlgError:
                    # ridge 0 and fewer known voxels than components: the least-norm solution
                    o = np.linalg.lstsq(A, b, rcond=None)[0]
                r = WK @ o + muK - yK
                resid = float(r @ r) / len(yK)
                if resid < best[0]:
                    best = (resid, c, yaw, o)
        _, c, yaw, o = best
        completion = (self.W_[c] @ o + self.mu_[c]).reshape((self.n_,) * 3)
        return c, float(yaw), completion


def surface_points(occ):
    """Centred (m, 3) float64 points of the surface voxels of a bool (N, N, N) occupancy."""
    from scipy.ndimage import binary_erosion
    occ = np.asarray(occ, dtype=bool)
    surf = occ & ~binary_erosion(occ, border_value=0)
    n = occ.shape[0]
    return np.argwhere(surf).astype(np.float64) - (n - 1) / 2.0


def _yaw_T(yaw):
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


class ICPDatabase(BaseEstimator):
    """Nearest training object under point-to-plane ICP.

    Args:
        per_class: training objects kept per class (random subsample, seeded); None keeps all.
        n_init_yaws: initial yaws tried per database object (evenly spaced).
        max_dist: correspondence distance in voxels.
        max_iter: ICP iterations per alignment.
        seed: seed of the subsample (an integer >= 0, or None).

    Learned attributes: ``n_`` (grid size), ``classes_`` (class names), ``db_`` (the open3d
    point clouds with normals), ``db_labels_`` (their class indices), ``n_points_`` (their
    points in all).
    """

    def __init__(self, per_class=20, n_init_yaws=4, max_dist=2.0, max_iter=30, seed=0):
        self.per_class = per_class
        self.n_init_yaws = n_init_yaws
        self.max_dist = max_dist
        self.max_iter = max_iter
        self.seed = seed

    def fit(self, X, y, names, n):
        """X: (m, n^3) occupancy of the training objects, y: (m,) class indices into ``names``,
        n: the grid size. Returns self."""
        per_class = None if self.per_class is None else _check_int('per_class',
                                                                    self.per_class, 1)
        _check_int('n_init_yaws', self.n_init_yaws, 1)
        _check_number('max_dist', self.max_dist, 0, strict=True)
        _check_int('max_iter', self.max_iter, 1)
        if self.seed is not None:
            _check_int('seed', self.seed, 0)
        X, y, n = _check_training(X, y, names, n)
        import open3d as o3d
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        rng = np.random.default_rng(self.seed)
        db, db_labels, n_points = [], [], 0
        for c in range(len(names)):
            idx = np.flatnonzero(y == c)
            if per_class is not None and len(idx) > per_class:
                idx = np.sort(rng.choice(idx, per_class, replace=False))
            for i in idx:
                pts = surface_points(np.asarray(X[i]).reshape((n,) * 3) > 0.5)
                if len(pts) < 4:
                    continue
                pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
                pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5, max_nn=20))
                db.append(pc)
                db_labels.append(c)
                n_points += len(pts)
        if not db:   # predict would answer class 0, yaw 0 for anything
            raise ValueError('no training object has 4 or more surface voxels: the database '
                             'would be empty')
        self.n_, self.classes_ = n, list(names)
        self.db_, self.db_labels_, self.n_points_ = db, np.array(db_labels), n_points
        return self

    @property
    def size(self):
        check_is_fitted(self, 'db_')
        return len(self.db_)

    @property
    def nbytes(self):
        check_is_fitted(self, 'db_')
        return int(self.n_points_ * 6 * 8)   # points + normals, float64

    def predict(self, grid):
        """(class index, yaw radians, best fitness) for a labelled grid.

        Raises ValueError for a grid of another size than the fitted one or with no occupied voxel.
        """
        check_is_fitted(self, 'db_')
        import open3d as o3d
        grid = _check_query(grid, self.n_)
        n_init_yaws, max_dist = int(self.n_init_yaws), float(self.max_dist)
        pts = np.argwhere(grid == 1).astype(np.float64) - (self.n_ - 1) / 2.0
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
        crit = o3d.pipelines.registration.ICPConvergenceCriteria(
            max_iteration=int(self.max_iter))
        best = (-1.0, np.inf, 0, 0.0)
        for i, tgt in enumerate(self.db_):
            for j in range(n_init_yaws):
                # source (observed) -> target (canonical): a rotation by minus the object yaw
                init = _yaw_T(-2 * np.pi * j / n_init_yaws)
                r = o3d.pipelines.registration.registration_icp(src, tgt, max_dist, init,
                                                                est, crit)
                key = (r.fitness, -r.inlier_rmse)
                if key > (best[0], -best[1]):
                    T = np.asarray(r.transformation)
                    best = (r.fitness, r.inlier_rmse, int(self.db_labels_[i]),
                            float(np.arctan2(T[0, 1], T[0, 0])))
        return best[2], best[3], best[0]
