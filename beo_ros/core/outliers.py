"""Statistical outlier removal for segmented clouds (ROS-free, arrays in and out).

The grid of :func:`beo_ros.core.voxelize.voxelize_view` is placed (and for 'normalized' grids
scaled) by the extent of the points, so one stray point far away shrinks the object to a voxel
or pushes it out of a metric grid; :meth:`beo_ros.core.bank.ModelBank.estimate_points` removes
such points first.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

OUTLIER_NEIGHBORS = 8   # neighbours per point
OUTLIER_MADS = 8.0      # the cut: this many scaled MADs above the median neighbour distance
MIN_SCALE = 0.1         # the scale is at least this fraction of the median (MAD 0 on a lattice)


def statistical_outliers(points, neighbors: int = OUTLIER_NEIGHBORS,
                         mads: float = OUTLIER_MADS) -> np.ndarray:
    """bool (n,) mask of the outliers among (n, 3) finite ``points`` (any frame and unit).

    Each point's distance d is the mean distance to its ``neighbors`` nearest other points. A
    point is an outlier when d > median(d) + ``mads`` * s, with s = max(1.4826 MAD(d),
    0.1 median(d)) (median and MAD over the points with d > 0): the statistical outlier removal
    of PCL and open3d's ``remove_statistical_outlier``, with the median and MAD in place of the
    mean and standard deviation, so that one stray point far away does not hide another (with
    the mean and standard deviation a point 100 km out inflates them past a point 1 km out).
    It removes isolated points (flying pixels, a stray return metres away); a *cluster* of
    stray points (or one point repeated more than ``neighbors`` times) explains itself and
    stays. With ``neighbors`` or fewer points (with d > 0) nothing is an outlier. About 12 ms
    for 10 000 points (k-d tree, one thread).

    Raises ValueError for points that are not a finite (n, 3) array, ``neighbors`` that is
    not a positive integer or ``mads`` that is not a positive finite number.
    """
    if isinstance(neighbors, (bool, np.bool_)) or not isinstance(neighbors, (int, np.integer)) \
            or neighbors < 1:
        raise ValueError(f'neighbors must be a positive integer, got {neighbors!r}')
    try:
        cut = float(mads) if np.ndim(mads) == 0 else np.nan
    except (TypeError, ValueError):
        cut = np.nan
    if isinstance(mads, (bool, np.bool_, str, bytes)) or not (np.isfinite(cut) and cut > 0):
        raise ValueError(f'mads must be a positive finite number, got {mads!r}')
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.isfinite(pts).all():
        raise ValueError(f'points must be a finite (n, 3) array, got shape {pts.shape}')
    if len(pts) <= neighbors:
        return np.zeros(len(pts), dtype=bool)
    dist, _ = cKDTree(pts).query(pts, k=int(neighbors) + 1)   # the first is the point itself
    d = dist[:, 1:].mean(axis=1)
    spread = d[d > 0]   # a point repeated more than ``neighbors`` times has d = 0
    if len(spread) <= neighbors:
        return np.zeros(len(pts), dtype=bool)
    med = np.median(spread)
    scale = max(1.4826 * np.median(np.abs(spread - med)), MIN_SCALE * med)
    return d > med + cut * scale
