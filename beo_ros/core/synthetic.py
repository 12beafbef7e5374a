"""Synthetic partial views (the evaluation protocol), rendered clouds and generated shapes.

Partial view protocol: rotate the object about +z by a yaw, look at it orthographically from
(azimuth, elevation); along each ray the first occupied voxel is 1, voxels in front of it 0,
voxels behind it -1; rays that miss leave their voxels at 0. A voxel seen free by any ray is 0,
seen as a first hit by any ray is 1, otherwise -1 if it is behind a hit.
"""
from __future__ import annotations

import numpy as np

from .grid import rotate_grid

RAY_SAMPLES = 1 << 20   # ray samples of partial_view held at a time


def view_direction(azimuth, elevation):
    """Unit (3,) vector from the object toward the viewer (grid frame, z up)."""
    ce = np.cos(elevation)
    return np.array([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)])


def partial_view(occ, azimuth, elevation, ray_spacing=0.5, step=0.5):
    """Label an (N, N, N) bool occupancy as seen orthographically from (azimuth, elevation).

    Returns int8 (N, N, N): 1 first hit, 0 free, -1 unknown (behind a hit).
    """
    occ = np.asarray(occ, dtype=bool)
    n = occ.shape[0]
    c = (n - 1) / 2.0
    to_viewer = view_direction(azimuth, elevation)
    ray_dir = -to_viewer
    # image plane basis
    up = np.array([0.0, 0.0, 1.0])
    u = np.cross(up, to_viewer)
    u /= np.linalg.norm(u)
    w = np.cross(to_viewer, u)
    half = np.sqrt(3) * n / 2 + 1
    s = np.arange(-half, half + 1e-9, ray_spacing)
    t = np.arange(-half, half + 1e-9, step)
    su, sw = np.meshgrid(s, s, indexing='ij')
    origins = c + su.ravel()[:, None] * u + sw.ravel()[:, None] * w + half * to_viewer  # (R, 3)
    free = np.zeros(n ** 3, dtype=bool)
    first_hit = np.zeros(n ** 3, dtype=bool)
    pos = np.arange(len(t))[None, :]
    # the rays RAY_SAMPLES samples at a time: all at once took 0.9 GB at 64^3, 7 GB at 128^3
    chunk = max(1, RAY_SAMPLES // len(t))
    for a in range(0, len(origins), chunk):
        pts = origins[a:a + chunk, None, :] + (t + half)[None, :, None] * ray_dir   # (r, S, 3)
        ijk = np.rint(pts).astype(np.int64)
        inside = ((ijk >= 0) & (ijk < n)).all(axis=2)
        flat = np.where(inside, (ijk[..., 0] * n + ijk[..., 1]) * n + ijk[..., 2], -1)
        hit = np.zeros(flat.shape, dtype=bool)
        hit[inside] = occ.ravel()[flat[inside]]
        first = np.where(hit.any(axis=1), hit.argmax(axis=1), flat.shape[1])
        free[flat[inside & (pos < first[:, None])]] = True
        first_hit[flat[inside & (pos == first[:, None])]] = True
    labels = np.full(n ** 3, -1, dtype=np.int8)
    labels[free] = 0
    labels[first_hit] = 1
    return labels.reshape(occ.shape)


def random_partial_view(occ, rng, elevation_deg=(10.0, 50.0)):
    """The evaluation protocol: random yaw, random view.

    Returns (grid int8 (N, N, N), yaw, az, el, rotated bool (N, N, N): the whole object after
    the yaw, i.e. the ground truth of the view).
    """
    yaw = rng.uniform(0, 2 * np.pi)
    az = rng.uniform(0, 2 * np.pi)
    el = np.deg2rad(rng.uniform(*elevation_deg))
    rotated = rotate_grid(np.asarray(occ, dtype=np.uint8), yaw).astype(bool)
    return partial_view(rotated, az, el), yaw, az, el, rotated


def render_view_points(occ, yaw, azimuth, elevation, distance=2.0, size=1.0, ray_spacing=0.5,
                       noise=0.0, rng=None):
    """Points on the visible surface of a voxel object, as a depth sensor would see them.

    The object (N, N, N) bool is rotated by ``yaw``, scaled so the grid spans ``size`` metres,
    centred at the origin of a z-up world frame, and viewed from ``distance`` metres away at
    (azimuth, elevation). Returns (points (m, 3) float32 in the world frame, sensor origin (3,)).
    """
    rotated = rotate_grid(np.asarray(occ, dtype=np.uint8), yaw).astype(bool)
    labels = partial_view(rotated, azimuth, elevation, ray_spacing=ray_spacing)
    n = occ.shape[0]
    vox = np.argwhere(labels == 1).astype(np.float64)
    scale = size / n
    pts = (vox - (n - 1) / 2.0) * scale
    rng = rng or np.random.default_rng(0)
    # a few samples per visible voxel face, jittered within the voxel, like a dense scan
    reps = np.repeat(pts, 4, axis=0) + rng.uniform(-0.5, 0.5, (len(pts) * 4, 3)) * scale
    if noise > 0:
        reps += rng.normal(0, noise, reps.shape)
    origin = view_direction(azimuth, elevation) * distance
    return reps.astype(np.float32), origin


def primitive_shapes(n=16, count=20, rng=None):
    """Generated training shapes of two classes, 'box' and 'cylinder': (X (m, n^3) float32,
    labels (m,), class names). Random sizes, centred, z up. For tests and the tiny bank."""
    rng = rng or np.random.default_rng(0)
    c = (n - 1) / 2.0
    ii, jj, kk = np.meshgrid(*(np.arange(n) - c,) * 3, indexing='ij')
    X, y = [], []
    for i in range(count):
        for label in (0, 1):
            a, b, h = rng.uniform(0.25, 0.45, 3) * n
            if label == 0:
                occ = (np.abs(ii) <= a) & (np.abs(jj) <= b * 0.6) & (np.abs(kk) <= h)
            else:
                occ = (ii ** 2 + jj ** 2 <= (0.7 * a) ** 2) & (np.abs(kk) <= h)
            X.append(occ.ravel())
            y.append(label)
    return np.array(X, dtype=np.float32), np.array(y), ['box', 'cylinder']


def make_tiny_bank(path=None, n=16, k=4, seed=0):
    """A small real bank (boxes and cylinders at n^3) for tests and demos; saved if ``path``."""
    from .training import fit_bank
    from .grid import GridSpec
    X, y, names = primitive_shapes(n, 15, np.random.default_rng(seed))
    bank = fit_bank(X, y, names, GridSpec(size=n), k=k, pose_components=min(k, 4),
                    classifier_views=0, seed=seed)
    if path is not None:
        bank.save(path)
    return bank
