"""Surface-normal descriptors of a segmented object's raw points (box-like vs round sides).

ROS-free, arrays in and out. Used by :meth:`beo_ros.core.bank.ModelBank.estimate_points` when
the bank has a 'points' classifier, and by ``scripts/tabletop_normals.py`` (the measurement),
so the two cannot drift apart.

Per point: the normal is the smallest-eigenvalue eigenvector of the covariance of its
neighbourhood (the at most ``MAX_NN`` = 30 nearest points within ``RADIUS`` = 2 cm, the point
itself included; as open3d's ``estimate_normals`` with ``KDTreeSearchParamHybrid``), oriented
toward the sensor. "Side" points have a normal within 45 deg of horizontal
(``|n . up| < cos 45 deg``); theta is the horizontal direction of a side normal about ``up``.

- ``r4`` = |mean over side points of exp(4 i theta)|: the faces of a box are 90 deg apart, so
  4 theta folds them onto one direction (near 1); the visible front of a cylinder spreads theta
  over about 180 deg (near 0).
- ``frac10`` = the largest fraction of side points whose theta mod 90 deg lies within 10 deg of
  one direction (mode over 1-deg candidates).

Both are invariant to a rotation about ``up`` and to the sign of the normals (theta + 180 deg
gives the same 4 theta and the same theta mod 90), so the orientation toward the sensor does not
change them.
"""
from __future__ import annotations

import numpy as np

from .grid import real_array, unit_vector

RADIUS = 0.02          # metres: neighbourhood radius of a normal
MAX_NN = 30            # at most this many nearest neighbours per normal
SIDE_COS = float(np.cos(np.radians(45.0)))
MODE_TOL_DEG = 10.0
MIN_POINTS = 10        # fewer points: descriptors NaN (undefined)
MIN_SIDE = 10          # fewer side points: descriptors NaN (undefined)
MAX_QUERY = 2000       # normals are computed at most at this many points (evenly strided)
DESCRIPTOR_NAMES = ('r4', 'frac10')


def _check(points, up, sensor_origin):
    pts = real_array(points, 'points', 'an (n, 3) array')
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f'points must be an (n, 3) array, got shape {pts.shape}')
    if not np.isfinite(pts).all():
        raise ValueError('points contain NaN or Inf (drop the non-finite rows first)')
    up = real_array(up, 'up', 'a finite non-zero (3,) vector')
    if up.shape != (3,) or not np.isfinite(up).all() or np.abs(up).max() < 1e-9:
        raise ValueError(f'up must be a finite non-zero (3,) vector, got {up!r}')
    origin = real_array(sensor_origin, 'sensor_origin', 'a finite (3,) vector')
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f'sensor_origin must be a finite (3,) vector, got {origin!r}')
    return pts, unit_vector(up), origin


def horizontal_basis(up):
    """(unit up, e1, e2): a right-handed orthonormal basis with e1, e2 horizontal."""
    up = unit_vector(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - (a @ up) * up
    e1 /= np.linalg.norm(e1)
    return up, e1, np.cross(up, e1)


def point_normals(points, sensor_origin=(0.0, 0.0, 0.0), radius=RADIUS, max_nn=MAX_NN,
                  max_query=MAX_QUERY):
    """Normals at (a strided subset of) the points.

    Args:
        points: (n, 3) finite points in metres, any frame.
        sensor_origin: (3,) sensor position in the same frame (normals are turned toward it).
        radius: neighbourhood radius (metres, > 0); max_nn: at most this many neighbours (>= 1).
        max_query: normals are computed at at most this many points (every ceil(n / max_query)-th
            point; the neighbourhoods still come from all n points); None: at all points.

    Returns (idx (q,) indices of the query points, normals (q, 3) unit vectors or NaN rows where
    fewer than 3 neighbours are within ``radius`` or they lie on a line, surface variation (q,)
    l0 / (l0 + l1 + l2) of the neighbourhood covariance, NaN likewise). Duplicate points count
    as neighbours: pass distinct points (``side_normal_descriptors`` drops the copies).
    """
    from scipy.spatial import cKDTree
    pts, _, origin = _check(points, (0.0, 0.0, 1.0), sensor_origin)
    # else numpy's 'zero-size array to reduction operation' (max_nn 0), an int() error, or
    # normals from any distance (a negative radius)
    # (not np.number: that takes a numpy complex, which fails in 'radius > 0')
    if isinstance(radius, (bool, np.bool_)) \
            or not isinstance(radius, (int, float, np.integer, np.floating)) \
            or not (np.isfinite(radius) and radius > 0):
        raise ValueError(f'radius must be a finite number > 0 (metres), got {radius!r}')
    for name, value in (('max_nn', max_nn), ('max_query', max_query)):
        if not (name == 'max_query' and value is None) and (
                isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer))
                or value < 1):
            raise ValueError(f'{name} must be an integer >= 1'
                             + (' or None' if name == 'max_query' else '') + f', got {value!r}')
    n = len(pts)
    if n == 0:   # cKDTree.query of no points fails in numpy's max()
        return np.zeros(0, dtype=np.intp), np.zeros((0, 3)), np.zeros(0)
    step = 1 if max_query is None or n <= max_query else int(np.ceil(n / max_query))
    idx = np.arange(0, n, step)
    k = min(int(max_nn), n)
    # an unbalanced (sliding-midpoint) tree builds and queries faster on these dense, thin
    # surface clouds; the k nearest neighbours are the same
    tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
    dist, nb = tree.query(pts[idx], k=k, distance_upper_bound=radius)
    dist = dist.reshape(len(idx), k)
    nb = nb.reshape(len(idx), k)
    valid = np.isfinite(dist)
    cnt = valid.sum(axis=1)
    P = pts[np.where(valid, nb, idx[:, None])]           # (q, k, 3); missing -> the point
    w = valid[..., None].astype(np.float64)
    inv = 1.0 / np.maximum(cnt, 1)[:, None]
    mean = (P * w).sum(axis=1) * inv
    D = (P - mean[:, None, :]) * w
    cov = np.matmul(D.transpose(0, 2, 1), D) * inv[:, :, None]
    ev, vec = np.linalg.eigh(cov)                        # ascending eigenvalues
    normals = vec[:, :, 0]
    flip = np.einsum('qi,qi->q', normals, origin - pts[idx]) < 0
    normals[flip] *= -1.0
    sv = ev[:, 0] / np.maximum(ev.sum(axis=1), 1e-30)
    # a line or a single place (rank < 2) has no normal: eigh would return an arbitrary axis,
    # the same at every such point
    bad = (cnt < 3) | (ev[:, 1] <= 1e-6 * ev.sum(axis=1))
    normals[bad] = np.nan
    sv[bad] = np.nan
    return idx, normals, sv


def descriptors_from_normals(normals, up):
    """(r4, frac10, n_side) from (q, 3) normals (NaN rows ignored) and the up vector (3,);
    r4 and frac10 are NaN when fewer than ``MIN_SIDE`` normals are side normals."""
    normals = real_array(normals, 'normals', 'a (q, 3) array')
    normals = normals[np.isfinite(normals).all(axis=1)]
    up, e1, e2 = horizontal_basis(real_array(up, 'up', 'a finite non-zero (3,) vector'))
    side = np.abs(normals @ up) < SIDE_COS
    ns = int(side.sum())
    if ns < MIN_SIDE:
        return np.nan, np.nan, ns
    theta = np.arctan2(normals[side] @ e2, normals[side] @ e1)
    r4 = float(np.abs(np.mean(np.exp(4j * theta))))
    # frac10: the most side normals with theta mod 90 within MODE_TOL_DEG of one of the 1-deg
    # candidates c = 0..89 (circular distance), counted on the sorted angles
    t90 = np.sort(np.degrees(theta) % 90.0)
    ext = np.concatenate([t90 - 90.0, t90, t90 + 90.0])
    cand = np.arange(0.0, 90.0, 1.0)
    counts = (np.searchsorted(ext, cand + MODE_TOL_DEG, side='right')
              - np.searchsorted(ext, cand - MODE_TOL_DEG, side='left'))
    frac10 = float(counts.max() / ns)
    return r4, frac10, ns


def side_normal_descriptors(points, up, sensor_origin=(0.0, 0.0, 0.0), max_query=MAX_QUERY):
    """(r4, frac10) of one segmented object's raw points (see the module docstring).

    Args:
        points: (n, 3) float, metres, any frame (e.g. the camera frame); all rows finite.
        up: (3,) gravity-up direction (e.g. the table normal) in the same frame, any length.
        sensor_origin: (3,) sensor position in the same frame.
        max_query: see :func:`point_normals` (with the default, p50 12 ms per OSD object of
            2k-28k points on 2 cores).

    Returns float64 (2,) = (r4, frac10), both in [0, 1]; NaN for clouds too small to say
    anything (fewer than ``MIN_POINTS`` distinct points or ``MIN_SIDE`` side normals). Raises ValueError
    for a malformed, non-finite or non-numeric (strings, objects, complex numbers, bools, dates)
    input.
    """
    pts, up, origin = _check(points, up, sensor_origin)
    # copies of a point would fill its neighbourhood (max_nn rows) with one place
    # rows as 24-byte keys: np.unique(axis=0) on them is 2.5x slower (12 ms at 28k points)
    rows = np.ascontiguousarray(pts).view(np.dtype((np.void, pts.itemsize * 3))).ravel()
    _, first = np.unique(rows, return_index=True)
    if len(first) < len(pts):
        pts = pts[np.sort(first)]   # keeps the order, so the strided query points
    if len(pts) < MIN_POINTS:
        return np.full(2, np.nan)
    _, normals, _ = point_normals(pts, origin, max_query=max_query)
    r4, frac10, _ = descriptors_from_normals(normals, up)
    return np.array([r4, frac10], dtype=np.float64)
