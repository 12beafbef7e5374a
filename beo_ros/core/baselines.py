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

import numpy as np

from .grid import rotate_grid


def _check_query(grid, n):
    """The labelled query grid as an array, after checking its shape and that it has an object."""
    grid = np.asarray(grid)
    if grid.shape != (n,) * 3:
        raise ValueError(f'grid must have shape {(n,) * 3} (the fitted size), got {grid.shape}')
    if not (grid == 1).any():   # all free or all unknown: nothing to classify or align
        raise ValueError('grid has no occupied voxel: there is no object to estimate')
    return grid


class PaperPCA:
    """The paper's method, written plainly (per-candidate and per-class Python loops).

    Args:
        k: PCA components per class.
        n_yaws: yaw candidates, evenly spaced over 360 degrees.
        ridge: tiny Tikhonov term so ``A`` stays invertible.
    """

    def __init__(self, k=20, n_yaws=36, ridge=1e-6):
        self.k = int(k)
        self.n_yaws = int(n_yaws)
        self.ridge = float(ridge)

    def fit(self, X, y, names, n):
        from sklearn.decomposition import PCA
        X = np.asarray(X, dtype=np.float32)
        y = np.asarray(y)
        self.n = int(n)
        self.classes = list(names)
        self.W, self.mu = [], []
        for c in range(len(names)):
            Xc = X[y == c]
            if len(Xc) < 2:
                raise ValueError(f'class {names[c]!r} has {len(Xc)} training objects; need >= 2')
            pca = PCA(n_components=int(min(self.k, len(Xc) - 1)), svd_solver='randomized',
                      random_state=0).fit(Xc)
            self.W.append(pca.components_.T.astype(np.float32))   # (d, k)
            self.mu.append(pca.mean_.astype(np.float32))          # (d,)
        return self

    @property
    def nbytes(self):
        return int(sum(w.nbytes + m.nbytes for w, m in zip(self.W, self.mu)))

    def predict(self, grid):
        """(class index, yaw radians, completion (N, N, N) float32 in the canonical frame).

        Raises ValueError for a grid of another size than the fitted one or with no occupied voxel.
        """
        grid = _check_query(grid, self.n).astype(np.int8)
        best = (np.inf, 0, 0.0, None)
        for j in range(self.n_yaws):
            yaw = 2 * np.pi * j / self.n_yaws
            canon = rotate_grid(grid, -yaw, fill=np.int8(-1)).ravel()   # undo the candidate yaw
            K = canon >= 0
            if not K.any():
                continue
            yK = (canon[K] == 1).astype(np.float32)
            for c in range(len(self.classes)):
                WK = self.W[c][K]
                muK = self.mu[c][K]
                A = WK.T @ WK + self.ridge * np.eye(WK.shape[1], dtype=np.float32)
                b = WK.T @ (yK - muK)
                o = np.linalg.solve(A, b)
                r = WK @ o + muK - yK
                resid = float(r @ r) / len(yK)
                if resid < best[0]:
                    best = (resid, c, yaw, o)
        _, c, yaw, o = best
        completion = (self.W[c] @ o + self.mu[c]).reshape((self.n,) * 3)
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


class ICPDatabase:
    """Nearest training object under point-to-plane ICP.

    Args:
        per_class: training objects kept per class (random subsample, seeded); None keeps all.
        n_init_yaws: initial yaws tried per database object (evenly spaced).
        max_dist: correspondence distance in voxels.
        max_iter: ICP iterations per alignment.
    """

    def __init__(self, per_class=20, n_init_yaws=4, max_dist=2.0, max_iter=30, seed=0):
        self.per_class = per_class
        self.n_init_yaws = int(n_init_yaws)
        self.max_dist = float(max_dist)
        self.max_iter = int(max_iter)
        self.seed = seed

    def fit(self, X, y, names, n):
        import open3d as o3d
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        self.o3d = o3d
        rng = np.random.default_rng(self.seed)
        self.n = int(n)
        self.classes = list(names)
        self.db, self.db_labels = [], []
        self.n_points = 0
        for c in range(len(names)):
            idx = np.flatnonzero(np.asarray(y) == c)
            if self.per_class is not None and len(idx) > self.per_class:
                idx = np.sort(rng.choice(idx, self.per_class, replace=False))
            for i in idx:
                pts = surface_points(np.asarray(X[i]).reshape((n,) * 3) > 0.5)
                if len(pts) < 4:
                    continue
                pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
                pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5, max_nn=20))
                self.db.append(pc)
                self.db_labels.append(c)
                self.n_points += len(pts)
        self.db_labels = np.array(self.db_labels)
        return self

    @property
    def size(self):
        return len(self.db)

    @property
    def nbytes(self):
        return int(self.n_points * 6 * 8)   # points + normals, float64

    def predict(self, grid):
        """(class index, yaw radians, best fitness) for a labelled grid.

        Raises ValueError for a grid of another size than the fitted one or with no occupied voxel.
        """
        o3d = self.o3d
        grid = _check_query(grid, self.n)
        pts = np.argwhere(grid == 1).astype(np.float64) - (self.n - 1) / 2.0
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
        crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=self.max_iter)
        best = (-1.0, np.inf, 0, 0.0)
        for i, tgt in enumerate(self.db):
            for j in range(self.n_init_yaws):
                # source (observed) -> target (canonical): a rotation by minus the object yaw
                init = _yaw_T(-2 * np.pi * j / self.n_init_yaws)
                r = o3d.pipelines.registration.registration_icp(src, tgt, self.max_dist, init,
                                                                est, crit)
                key = (r.fitness, -r.inlier_rmse)
                if key > (best[0], -best[1]):
                    T = np.asarray(r.transformation)
                    best = (r.fitness, r.inlier_rmse, int(self.db_labels[i]),
                            float(np.arctan2(T[0, 1], T[0, 0])))
        return best[2], best[3], best[0]
