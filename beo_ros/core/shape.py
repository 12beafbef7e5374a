"""Yaw-invariant global shape descriptors of the occupied voxels of a labelled grid.

They complement the per-class BEO features in the classifier: the class models explain an
object's *shape* class by class, while these describe the seen occupied voxels once, the same
for every class (height, horizontal extent and its elongation, how the voxels spread over
height and radius, how they stand on each other). All are invariant to a rotation about +z
(up to the voxel resampling), so they need no pose. On ModelNet10 out-of-fold features (5
folds) the first 12 raised the accuracy 0.891 -> 0.900 (complete objects) and the balanced
accuracy 0.813 -> 0.831; the 31 of the second set (2026-11-23) 0.909 -> 0.913 (balanced
0.837 -> 0.848) and, on one partial view, 0.888 -> 0.894 (balanced 0.806 -> 0.821).
"""
from __future__ import annotations

import numpy as np

# the first set; classifiers saved before the second set take only these
BASIC_NAMES = ('height', 'extent_major', 'extent_minor', 'elongation', 'log_count',
               'height_q1', 'height_q2', 'height_q3', 'radius_q1', 'radius_q2',
               'radius_q3', 'mean_height')
PROFILE_BINS = 8     # height profile over the grid
JOINT_BINS = 4       # (relative height, relative radius) histogram, per axis
DESCRIPTOR_NAMES = BASIC_NAMES + tuple(
    [f'z_profile_{i}' for i in range(PROFILE_BINS)]
    + [f'height_radius_{i}_{j}' for i in range(JOINT_BINS) for j in range(JOINT_BINS)]
    + ['supported', 'column_fill', 'columns']
    + [f'spread_q{i}' for i in range(JOINT_BINS)])


def shape_descriptors(grid):
    """Descriptors (43,) float64 (see DESCRIPTOR_NAMES) of the voxels == 1 of an (N, N, N)
    grid (axes x, y, z, z up); lengths in units of the grid size N.

    First set (12): height: z extent / N; extent_major/minor: square roots of the eigenvalues
    of the covariance of the voxels' (x, y) / (N / 2); elongation: minor / major; log_count:
    log of the number of voxels; height_q1..3: fraction of the voxels in the lower three
    quarters of their z extent; radius_q1..3: the same over the horizontal distance from their
    (x, y) centroid, relative to its maximum; mean_height: mean z / N.
    Second set (31), fractions of the voxels unless said otherwise: z_profile_i: in the i-th
    eighth of the grid's height; height_radius_i_j: in quarter i of their z extent and
    quarter j of that radius; supported: with an occupied voxel right below (the share with one
    right above is the same number);
    column_fill: mean over the occupied (x, y) columns of their voxels / (top - bottom + 1);
    columns: occupied columns per voxel; spread_qi: RMS radius / (N / 2) of the voxels in
    quarter i of the z extent (0 if none). Fewer than 3 voxels: all zeros.
    """
    g = np.asarray(grid)
    if g.ndim != 3 or len(set(g.shape)) != 1:
        raise ValueError(f'grid must be (N, N, N), got shape {g.shape}')
    n = g.shape[0]
    occ = g == 1
    p = np.argwhere(occ).astype(np.float64)
    if len(p) < 3:
        return np.zeros(len(DESCRIPTOR_NAMES))
    m = len(p)
    z = p[:, 2]
    xy = p[:, :2] - p[:, :2].mean(axis=0)
    ev = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(xy.T)), 0.0))[::-1]
    h = z.max() - z.min() + 1.0
    zr = (z - z.min()) / h
    hq = np.histogram(zr, bins=4, range=(0.0, 1.0))[0][:3] / m
    r = np.linalg.norm(xy, axis=1)
    rr = r / (r.max() + 1e-9)
    rq = np.histogram(rr, bins=4, range=(0.0, 1.0))[0][:3] / m
    half = n / 2.0
    basic = [h / n, ev[0] / half, ev[1] / half, ev[1] / (ev[0] + 1e-9), np.log(m)]

    profile = np.histogram(z / n, bins=PROFILE_BINS, range=(0.0, 1.0))[0] / m
    joint = np.histogram2d(zr, rr, bins=JOINT_BINS, range=((0.0, 1.0), (0.0, 1.0)))[0] / m
    supported = (occ[:, :, 1:] & occ[:, :, :-1]).sum() / m   # voxel pairs stacked in z
    cols = occ.any(axis=2)
    zz = np.arange(n)
    top = np.where(occ, zz, -1).max(axis=2)[cols]
    bottom = np.where(occ, zz, n).min(axis=2)[cols]
    column_fill = np.mean(occ.sum(axis=2)[cols] / (top - bottom + 1.0))
    quarter = np.minimum((zr * JOINT_BINS).astype(int), JOINT_BINS - 1)
    spread = np.array([np.sqrt(np.mean(r[quarter == i] ** 2)) / half
                       if (quarter == i).any() else 0.0 for i in range(JOINT_BINS)])
    return np.concatenate([basic, hq, rq, [z.mean() / n], profile, joint.ravel(),
                           [supported, column_fill, cols.sum() / m], spread])
