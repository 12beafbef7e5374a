"""Synthetic partial views (the evaluation protocol), rendered clouds and generated shapes.

Partial view protocol: rotate the object about +z by a yaw, look at it orthographically from
(azimuth, elevation); along each ray the first occupied voxel is 1, voxels in front of it 0,
voxels behind it -1; rays that miss leave their voxels at 0. A voxel seen free by any ray is 0,
seen as a first hit by any ray is 1, otherwise -1 if it is behind a hit.
"""
from __future__ import annotations

import numpy as np

from .grid import _real, rotate_grid

RAY_SAMPLES = 1 << 20   # ray samples of partial_view held at a time


def view_direction(azimuth, elevation):
    """Unit (3,) vector from the object toward the viewer (grid frame, z up)."""
    ce = np.cos(elevation)
    return np.array([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)])


def _check_view(*angles, **spacings):
    """ValueError unless the ``angles`` (radians) are finite and the ``spacings`` (voxels)
    positive and finite (NaN angles made NaN rays cast to garbage voxels, a zero spacing an
    endless arange, a negative step a division by zero)."""
    for a in angles:
        if not np.isfinite(_real(a)):
            raise ValueError(f'view angles must be finite numbers (radians), got {a!r}')
    for name, v in spacings.items():
        if not 0 < _real(v) < np.inf:
            raise ValueError(f'{name} must be a positive number of voxels, got {v!r}')


def partial_view(occ, azimuth, elevation, ray_spacing=0.5, step=0.5):
    """Label an (N, N, N) bool occupancy as seen orthographically from (azimuth, elevation).

    Returns int8 (N, N, N): 1 first hit, 0 free, -1 unknown (behind a hit).
    """
    occ = np.asarray(occ, dtype=bool)
    if occ.ndim != 3 or len(set(occ.shape)) != 1:   # an IndexError deep in the rays before
        raise ValueError(f'occ must be (N, N, N), got shape {occ.shape}')
    _check_view(azimuth, elevation, ray_spacing=ray_spacing, step=step)
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


def render_surface_points(field, level, yaw, azimuth, elevation, distance=2.0, size=1.0,
                          ray_spacing=0.5, step=0.25, noise=0.0, rng=None):
    """Points where the rays of a pinhole sensor first reach ``level`` in an occupancy field.

    ``field`` (N, N, N) float (a mean shape, a drawn instance, or a bool occupancy) is
    interpolated trilinearly (0 outside the grid), so the surface is smooth and turned by
    ``yaw`` exactly; ``render_view_points`` gives voxel centres jittered over whole voxels
    instead, whose normals (2 cm neighbourhoods at 15.6 mm voxels) are noise. The object is
    turned by ``yaw`` about +z, scaled so the grid spans ``size`` metres and centred at the
    origin of a z-up world frame; the sensor sits ``distance`` metres away toward (azimuth,
    elevation) and looks at the origin, its rays ``ray_spacing`` voxels apart there. A ray's
    crossing is interpolated between its samples ``step`` voxels apart; ``noise`` (metres) is
    Gaussian depth noise along the ray. Returns (points (m, 3) float32 in the world frame,
    sensor origin (3,)), as ``render_view_points``.
    """
    from scipy.ndimage import map_coordinates
    f = np.asarray(field, dtype=np.float32)
    if f.ndim != 3 or len(set(f.shape)) != 1:
        raise ValueError(f'field must be (N, N, N), got shape {f.shape}')
    _check_view(yaw, azimuth, elevation, ray_spacing=ray_spacing, step=step)
    n = f.shape[0]
    scale = size / n
    c = (n - 1) / 2.0
    half = np.sqrt(3) * n / 2   # the grid's bounding sphere, voxels
    if not distance / scale > half + 1:
        raise ValueError(f'distance {distance} m puts the sensor inside the grid (its bounding '
                         f'sphere has radius {half * scale:.3g} m)')
    cy, sy = np.cos(yaw), np.sin(yaw)
    to_grid = np.array([[cy, sy, 0.0], [-sy, cy, 0.0], [0.0, 0.0, 1.0]])   # R(-yaw)
    to_viewer = view_direction(azimuth, elevation)
    origin = to_viewer * distance
    eye = to_grid @ to_viewer * (distance / scale)          # grid frame, voxels from the centre
    dist = np.linalg.norm(eye)
    fwd = -eye / dist
    u = np.cross(fwd, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(u, fwd)
    inside = np.argwhere(f >= level)
    if not len(inside):
        return np.zeros((0, 3), dtype=np.float32), origin
    # rays and samples only through the box around the surface (a voxel wider), not the grid
    lo, hi = inside.min(axis=0) - c - 1.5, inside.max(axis=0) - c + 1.5
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - eye
    ahead = corners @ fwd                                   # > 0: the sensor is outside
    su_c, sw_c = corners @ u / ahead * dist, corners @ w / ahead * dist
    s_u = np.arange(su_c.min(), su_c.max() + ray_spacing, ray_spacing)
    s_w = np.arange(sw_c.min(), sw_c.max() + ray_spacing, ray_spacing)
    su, sw = np.meshgrid(s_u, s_w, indexing='ij')
    dirs = su.ravel()[:, None] * u + sw.ravel()[:, None] * w + dist * fwd
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    reach = np.linalg.norm(corners + eye, axis=1).max()    # the box within reach of the centre
    t = np.arange(max(dist - reach, step), dist + reach + step, step)
    rng = rng or np.random.default_rng(0)
    hits = []
    chunk = max(1, RAY_SAMPLES // len(t))
    for a in range(0, len(dirs), chunk):
        d = dirs[a:a + chunk]
        pts = eye + t[None, :, None] * d[:, None, :]                       # (r, S, 3)
        vals = map_coordinates(f, (pts + c).reshape(-1, 3).T, order=1, mode='constant',
                               cval=0.0).reshape(pts.shape[:2])
        above = vals >= level
        r = np.flatnonzero(above.any(axis=1) & ~above[:, 0])
        i = above[r].argmax(axis=1)
        v0, v1 = vals[r, i - 1], vals[r, i]
        depth = t[i - 1] + (level - v0) / np.maximum(v1 - v0, 1e-12) * step
        if noise > 0:
            depth = depth + rng.normal(0.0, noise / scale, len(depth))
        hits.append(eye + depth[:, None] * d[r])
    p = np.concatenate(hits)
    return (p * scale @ to_grid).astype(np.float32), origin


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
