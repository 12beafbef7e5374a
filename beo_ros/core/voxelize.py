"""Cloud-level front end: one segmented partial point cloud -> labelled, gravity-aligned grid.

Frames:
- *input frame*: whatever frame ``points``, ``sensor_origin`` and ``up`` are given in (metres);
- *aligned frame*: z = ``up``; x = horizontal direction from the sensor toward the object's
  centroid (so yaw 0 of the grid means "the grid's +x looks away from the sensor"); y = z x x;
- *grid index coordinates* (i, j, k): voxel centres at integers, voxel (i, j, k) covers
  [i - 0.5, i + 0.5] x ... ; the grid axes are the aligned axes scaled by the voxel size.

``ViewGrid.grid_to_input`` maps homogeneous grid index coordinates to the input frame.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy import ndimage

from .grid import FREE, OCCUPIED, UNKNOWN, GridSpec, real_array, unit_vector

MIN_POINTS = 10
MIN_EXTENT = 1e-6  # input units (m): points spanning no more than this are refused
MAX_COORDINATE = 1e6  # input units (m): points and positions beyond are refused (overflow)
MIN_DIRECTION = 1e-9  # a direction (``up``) whose largest component is below this is refused
_RAY_MARGIN = 0.25  # voxels: a ray stops this short of the voxel centre it is cast at
_RAY_TNEAR = 1e-6  # fraction of a ray: hits nearer its start (the sensor) are not counted
# voxels: points spaced wider than this (median nearest neighbour) also block rays as squares
SPARSE_SPACING = 0.75
SPLAT_SCALE = 0.75  # half-width of those squares, in point spacings


@dataclass
class ViewGrid:
    """A labelled view grid and where it sits.

    Attributes:
        grid: int8 (N, N, N) indexed [x, y, z]: 1 occupied, 0 free, -1 unknown (occluded).
        grid_to_input: float64 (4, 4), homogeneous grid index coords (i, j, k, 1) -> input frame.
        voxel_size_m: edge of one voxel in metres.
        n_points: number of finite input points that fell inside the grid.
        n_below_table: points :func:`~beo_ros.core.scans.object_view` dropped for lying below
            the table plane (0 from :func:`voxelize_view`).
    """

    grid: np.ndarray
    grid_to_input: np.ndarray
    voxel_size_m: float
    n_points: int
    n_below_table: int = 0

    @property
    def input_to_grid(self) -> np.ndarray:
        """float64 (4, 4) inverse of ``grid_to_input``."""
        return np.linalg.inv(self.grid_to_input)


# ----------------------------------------------------------------------------------- validation

def _numbers(value):
    """``value`` as a float64 array if it holds real numbers (integers or floats), else None
    (:func:`~beo_ros.core.grid.real_array`'s rule: a cast to float parsed strings as numbers,
    took bools, dropped an imaginary part with a warning only)."""
    try:
        return real_array(value, 'value', 'an array')
    except ValueError:   # other dtypes, rows of different lengths
        return None


def _check_points(points, min_points: int) -> np.ndarray:
    pts = _numbers(points)
    if pts is None:   # a structured array, text, bools, complex numbers, a dict, ragged rows, ...
        dtype = getattr(points, 'dtype', type(points).__name__)
        raise ValueError(f'points must be an (n, 3) array of numbers, got {dtype}')
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f'points must be an (n, 3) array, got shape {pts.shape}')
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < min_points:
        raise ValueError(f'need at least {min_points} finite points, got {len(pts)}')
    if len(pts) and np.abs(pts).max() > MAX_COORDINATE:
        raise ValueError(f'points must lie within +-{MAX_COORDINATE:g} (input units, m), got '
                         f'a coordinate of {np.abs(pts).max():g}')
    return pts


def finite_points(points, min_points: int = MIN_POINTS) -> np.ndarray:
    """float64 (m, 3) finite rows of (n, 3) ``points``; ValueError for a wrong shape, fewer than
    ``min_points`` finite rows or coordinates beyond +-MAX_COORDINATE."""
    return _check_points(points, min_points)


def unit_direction(v, name: str = 'up') -> np.ndarray:
    """(3,) unit vector along ``v`` (finite, largest component at least MIN_DIRECTION); no
    overflow for huge components. ValueError naming ``name`` otherwise."""
    return _check_vec(v, name, unit=True)


def _check_vec(v, name: str, unit: bool = False) -> np.ndarray:
    a = _numbers(v)
    if a is None:   # e.g. 'abc', ['0', '0', '1'], [1, 'x', 2], None, bools
        raise ValueError(f'{name} must be a finite 3-vector of numbers, got {v!r}')
    v = a
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f'{name} must be a finite 3-vector, got {np.asarray(v)!r}')
    if unit:
        big = np.abs(v).max()
        if big < MIN_DIRECTION:
            raise ValueError(f'{name} must be non-zero (largest component at least '
                             f'{MIN_DIRECTION:g}), got {v!r}')
        v = unit_vector(v)
    elif np.abs(v).max() > MAX_COORDINATE:
        raise ValueError(f'{name} must lie within +-{MAX_COORDINATE:g} (input units, m), got '
                         f'{v!r}')
    return v


def _check_floor(floor) -> float:
    if isinstance(floor, (str, bytes)) or np.ndim(floor) != 0:
        raise ValueError(f'floor must be a finite number, got {floor!r}')
    try:
        floor = float(floor)
    except (TypeError, ValueError):
        raise ValueError(f'floor must be a finite number, got {floor!r}') from None
    if not np.isfinite(floor):
        raise ValueError(f'floor must be finite, got {floor!r}')
    return floor


def aligned_frame(up, sensor_origin, target) -> np.ndarray:
    """(3, 3) rotation whose columns are the aligned x, y, z axes expressed in the input frame.

    z = unit ``up``; x = horizontal (perpendicular to up) direction from ``sensor_origin`` to
    ``target``, or an arbitrary fixed horizontal direction when the sensor is straight above/below.
    """
    z = _check_vec(up, 'up', unit=True)
    h = np.asarray(target, float) - np.asarray(sensor_origin, float)
    h = h - z * (h @ z)
    if np.linalg.norm(h) < 1e-9 * max(1.0, np.linalg.norm(target)):
        h = np.eye(3)[np.argmin(np.abs(z))]  # world axis least parallel to up
        h = h - z * (h @ z)
    x = h / np.linalg.norm(h)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


# ----------------------------------------------------------------------------------- ray casting

_FACES = []  # (axis, side, 4 corner offsets ccw seen from outside) for the 6 cube faces
for _ax in range(3):
    _u, _v = (_ax + 1) % 3, (_ax + 2) % 3
    for _side in (-1, 1):
        _c = np.zeros((4, 3))
        _c[:, _ax] = 0.5 * _side
        _c[:, _u] = [-0.5, 0.5, 0.5, -0.5]
        _c[:, _v] = [-0.5, -0.5, 0.5, 0.5]
        _FACES.append((_ax, _side, _c))


def cube_surface(blocked: np.ndarray) -> tuple:
    """Triangles of the exposed faces of the voxel cubes in bool (N, N, N) ``blocked``.

    Returns (vertices float32 (4F, 3) in grid index coords, triangles uint32 (2F, 3)).
    """
    padded = np.pad(blocked, 1)
    verts, tris = [], []
    base = 0
    for ax, side, corners in _FACES:
        nb = np.roll(padded, -side, axis=ax)[1:-1, 1:-1, 1:-1]
        idx = np.argwhere(blocked & ~nb)
        if len(idx) == 0:
            continue
        v = (idx[:, None, :] + corners[None]).reshape(-1, 3)
        q = base + 4 * np.arange(len(idx))[:, None]
        t = np.concatenate([q + [0, 1, 2], q + [0, 2, 3]], axis=0)
        verts.append(v)
        tris.append(t)
        base += len(v)
    if not verts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    return (np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.uint32))


def cube_soup(voxels: np.ndarray) -> tuple:
    """All 12 triangles of each voxel cube at int (k, 3) indices (no face culling).

    Returns (vertices float32 (24k, 3), triangles uint32 (12k, 3)) in grid index coords.
    """
    corners = np.concatenate([c for _, _, c in _FACES])  # (24, 3), 4 per face
    v = (voxels[:, None, :] + corners[None]).reshape(-1, 3)
    q = 4 * np.arange(6 * len(voxels))[:, None]
    t = np.concatenate([q + [0, 1, 2], q + [0, 2, 3]], axis=0)
    return v.astype(np.float32), t.astype(np.uint32)


def point_spacing(points: np.ndarray, n_queries: int = 2000) -> float:
    """Median distance from a point to its nearest distinct neighbour (inf for one point).

    points: (m, 3); at most ``n_queries`` evenly strided points are queried (deterministic)."""
    from scipy.spatial import cKDTree
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return float('inf')
    q = pts[np.unique(np.linspace(0, len(pts) - 1, min(len(pts), n_queries)).astype(np.intp))]
    k = min(len(pts), 4)
    d = cKDTree(pts).query(q, k=k)[0][:, 1:]
    d = np.where(d > 1e-9, d, np.inf).min(axis=1)   # skip duplicates of the query point
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else float('inf')


def facing_squares(points: np.ndarray, origin: np.ndarray, half: float) -> tuple:
    """A square of half-width ``half`` around each point, facing ``origin`` (same units); a
    point at ``origin`` faces no way and gets a square of no size (it blocks no ray).

    Returns (vertices float32 (4k, 3), triangles uint32 (2k, 3)).
    """
    p = np.asarray(points, dtype=np.float64)
    d = p - np.asarray(origin, dtype=np.float64)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    # any vector not parallel to d: the axis of d's smallest component
    helper = np.zeros_like(d)
    helper[np.arange(len(d)), np.argmin(np.abs(d), axis=1)] = 1.0
    u = np.cross(d, helper)
    # (d = 0 at the origin: u stays 0, not NaN, which would make Embree miss every ray)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    w = np.cross(d, u) * half
    u *= half
    v = np.stack([p - u - w, p + u - w, p + u + w, p - u + w], axis=1).reshape(-1, 3)
    q = 4 * np.arange(len(p))[:, None]
    t = np.concatenate([q + [0, 1, 2], q + [0, 2, 3]], axis=0)
    return v.astype(np.float32), t.astype(np.uint32)


def _relevant_occluders(occ_pts_grid: np.ndarray, origin_grid: np.ndarray, n: int) -> np.ndarray:
    """Unique voxel indices (k, 3) of occluder points that may lie between sensor and grid."""
    c = np.full(3, (n - 1) / 2.0)
    radius = np.sqrt(3) * n / 2.0 + 1.0  # bounding sphere of the grid (+ one voxel)
    to_c = c - origin_grid
    dc = np.linalg.norm(to_c)
    # points beyond the box around the sphere below go first: one 1e300 away has no int64
    # voxel index and overflows the norm (numpy warned about both)
    near = np.all(np.abs(occ_pts_grid - origin_grid) <= dc + radius + 1.0, axis=1)
    idx = np.floor(occ_pts_grid[near] + 0.5).astype(np.int64)
    d = idx - origin_grid
    dist = np.linalg.norm(d, axis=1)
    keep = dist <= dc + radius
    if dc > radius:  # sensor outside the sphere: keep voxels within the sphere's view cone
        # a voxel cube (half-diagonal sqrt(3)/2) at distance r subtends arcsin(0.87 / r)
        own = np.arcsin(np.minimum(1.0, np.sqrt(3) / 2 / np.maximum(dist, 1e-9)))
        half = np.arcsin(radius / dc) + own
        cosang = (d @ to_c) / np.maximum(dist * dc, 1e-12)
        keep &= cosang >= np.cos(np.minimum(half, np.pi))
    idx = idx[keep]
    if len(idx) == 0:
        return idx
    lo = idx.min(axis=0)
    span = tuple(idx.max(axis=0) - lo + 1)  # bounded by the sphere around sensor and grid
    key = np.unique(np.ravel_multi_index(tuple((idx - lo).T), span))
    return np.stack(np.unravel_index(key, span), axis=1) + lo


def _own_voxel(o: np.ndarray, blocked: np.ndarray, occluder_voxels) -> np.ndarray | None:
    """The voxel whose blocking :func:`label_free_unknown` ignores for a sensor at grid coords
    ``o`` (3,): int (3,) the voxel holding it, ``floor(o + 0.5)``; None when the sensor lies
    exactly on a face, edge or corner of a voxel that blocks nothing (it is in free space).

    (``floor`` rounds a sensor on a face into the voxel on its + side: unblocking that one, when
    it is occupied and the - side is free, let rays through it and read what it hides free.)"""
    own = np.floor(o + 0.5).astype(int)
    on_face = o + 0.5 == own
    if not on_face.any():
        return own
    n = blocked.shape[0]
    occ_set = set() if occluder_voxels is None else set(map(tuple, occluder_voxels.tolist()))
    for v in itertools.product(*[(a - 1, a) if f else (a,) for a, f in zip(own, on_face)]):
        inside = all(0 <= a < n for a in v)
        if not (inside and blocked[v]) and v not in occ_set:
            return None
    return own


def label_free_unknown(occupied: np.ndarray, origin_grid, close_holes: bool = True,
                       occluder_voxels=None, splats=None, splat_half: float = 0.0) -> np.ndarray:
    """Label a grid from its occupied voxels and the sensor position by ray casting.

    Args:
        occupied: bool (N, N, N) (any dtype: non-zero is occupied).
        origin_grid: (3,) sensor position in grid index coordinates (may be inside the grid).
        close_holes: block rays with a morphological closing of ``occupied`` (fills one-voxel
            holes of sparse surfaces so they do not leak free space behind the object).
        occluder_voxels: optional int (k, 3) grid indices (may lie outside the grid) of other
            geometry that blocks rays (e.g. neighbouring objects) but is not this object; one at
            the sensor's own voxel is ignored, like occupied voxels and splats there.
        splats: optional (k, 3) grid coordinates of surface points that block rays as squares
            of half-width ``splat_half`` voxels facing the sensor: for surfaces sampled more
            sparsely than the voxels, whose gaps the closing does not bridge.

    Returns int8 (N, N, N): 1 occupied; -1 where the segment from the sensor to the voxel centre
    crosses an occupied cube first (occluded); 0 otherwise (in front of the surface or outside
    the silhouette).
    """
    occupied = np.asarray(occupied)
    if occupied.ndim != 3 or len(set(occupied.shape)) != 1:
        raise ValueError(f'occupied must be an (N, N, N) array, got shape {occupied.shape}')
    occupied = occupied.astype(bool)   # a 0/1 integer array would index, not mask, below
    n = occupied.shape[0]
    o = real_array(origin_grid, 'origin_grid', 'a finite 3-vector')
    if o.shape != (3,) or not np.isfinite(o).all():
        # (NaN read every voxel free; (1, 3) broadcast, (2,) failed in a broadcast)
        raise ValueError(f'origin_grid must be a finite 3-vector (grid index coordinates), got '
                         f'{np.asarray(origin_grid).tolist()!r}')
    blocked = occupied.copy()
    if close_holes and occupied.any():
        nz = np.argwhere(occupied)  # close within the occupied bounding box only (faster)
        lo, hi = nz.min(axis=0), nz.max(axis=0) + 1
        box = tuple(slice(a, b) for a, b in zip(lo, hi))
        closed = ndimage.binary_closing(np.pad(occupied[box], 2), np.ones((3, 3, 3), bool))
        blocked[box] |= closed[2:-2, 2:-2, 2:-2]
    sensor_voxel = np.floor(o + 0.5).astype(int)
    ov = None if occluder_voxels is None else np.asarray(occluder_voxels).reshape(-1, 3)
    own = _own_voxel(o, blocked, ov)
    if own is not None and np.all((own >= 0) & (own < n)):
        blocked[tuple(own)] = False  # never block the sensor's own voxel
    out = np.full(occupied.shape, FREE, dtype=np.int8)
    verts, tris = cube_surface(blocked)
    if ov is not None and len(ov):
        # nor an occluder's (a cube around the sensor would hide the whole grid)
        if own is not None:
            ov = ov[np.any(ov != own, axis=1)]
        ov, ot = cube_soup(ov)
        verts, tris = np.concatenate([verts, ov]), np.concatenate([tris, ot + len(verts)])
    if splats is not None and len(splats) and splat_half > 0:
        # nor do points in it (a self-return would otherwise hide the whole view behind it)
        splats = np.asarray(splats, dtype=np.float64)
        splats = splats[np.any(np.floor(splats + 0.5) != sensor_voxel, axis=1)]
        sv, st = facing_squares(splats, o, splat_half)
        verts, tris = np.concatenate([verts, sv]), np.concatenate([tris, st + len(verts)])
    if len(tris):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris))
        centres = np.indices(occupied.shape, dtype=np.float64).reshape(3, -1).T
        d = centres - o
        dist = np.linalg.norm(d, axis=1)
        # scale so that t = 1 is _RAY_MARGIN voxels short of the centre
        scale = np.maximum(dist - _RAY_MARGIN, 0.0) / np.maximum(dist, 1e-12)
        d *= scale[:, None]
        # Embree works in float32: from a sensor far away (1e5 voxels and more) an origin and
        # end point that large lose the voxel's position. Start each ray where it can first meet
        # the geometry instead (all of it lies within `reach` of the grid centre).
        c = np.full(3, (n - 1) / 2.0)
        reach = np.sqrt(((verts.astype(np.float64) - c) ** 2).sum(axis=1).max()) + 1.0
        t0 = np.maximum(np.linalg.norm(o - c) - reach, 0.0) / np.maximum(dist, 1e-12)
        t0 = np.minimum(t0, 1.0)[:, None]
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = o + t0 * d
        rays[:, 3:] = (1.0 - t0) * d
        # (tnear > 0: a sensor on the face of a blocked voxel is not hidden by it from what lies
        # on its side of the face; Embree counts the hit at t = 0 on every ray leaving it)
        hit = scene.test_occlusions(o3d.core.Tensor(rays), tnear=_RAY_TNEAR, tfar=1.0).numpy()
        hit &= dist > _RAY_MARGIN
        out.reshape(-1)[hit] = UNKNOWN
    out[occupied] = OCCUPIED
    return out


# ----------------------------------------------------------------------------------- front end

def voxelize_view(points, sensor_origin, up, spec: GridSpec, center=None, floor=None,
                  occluders=None, min_points: int = MIN_POINTS,
                  close_holes: bool = True) -> ViewGrid:
    """Voxelize one segmented partial view into a labelled, gravity-aligned grid.

    Args:
        points: (n, 3) object points in the input frame (metres); non-finite rows are dropped.
        sensor_origin: (3,) sensor position in the input frame.
        up: (3,) gravity-up direction in the input frame (any length; its largest component
            must be at least ``MIN_DIRECTION``).
        spec: grid size, units ('normalized' / 'metric') and anchor ('center' / 'bottom').
        center: optional (3,) input-frame point placed at the grid's anchor point: the grid centre
            ((N-1)/2 on all axes) for anchor 'center', the centre of the grid floor
            ((N-1)/2, (N-1)/2, -0.5) for 'bottom'. Overrides the heuristics below.
        floor: optional height of the support plane along unit ``up`` (``up . p = floor``), used
            as the object's bottom for anchor 'bottom' (e.g. ``-d`` of a table plane n.p + d = 0).
        occluders: optional (m, 3) input-frame points of *other* geometry (neighbouring objects,
            not the support plane) that can hide parts of the grid from the sensor; voxels behind
            (or inside) them become unknown instead of free. Non-finite rows are ignored.

    Placement heuristic (without ``center``): only the front of the object is seen, so the
    horizontal footprint is assumed to be as deep (along the aligned x, away from the sensor) as
    its largest observed horizontal extent: the estimated box spans x in
    [x_min, x_min + max(ext_x, ext_y)], y over the observed y range, and z over the observed
    z range (from ``floor`` for 'bottom' when given). That box's centre goes to the grid centre
    ('center'), or its bottom-face centre to the grid floor centre ('bottom'). 'normalized' scales
    the box's largest extent to ``spec.fill * N`` voxels (it equals the observed largest extent);
    'metric' uses ``spec.voxel_size``. Points falling outside the grid are not voxelized, but
    block rays like ``occluders``.

    Occupied voxels are those containing a point; the rest are free/unknown by ray casting from
    the sensor (see :func:`label_free_unknown`).
    """
    pts = _check_points(points, max(min_points, 1))   # (min_points 0: no points, no object)
    origin = _check_vec(sensor_origin, 'sensor_origin')
    upv = _check_vec(up, 'up', unit=True)
    if center is not None:
        center = _check_vec(center, 'center')
    if floor is not None:
        floor = _check_floor(floor)
    o_pts = _check_occluders(occluders)
    rot = aligned_frame(upv, origin, pts.mean(axis=0))
    box_lo, box_hi, largest = _estimated_box(pts @ rot, spec, floor)
    g2i, voxel = _place_grid(rot, box_lo, box_hi, largest, spec, center)
    g = _to_grid(pts, g2i, rot, voxel)
    inside, occ = _occupied_voxels(g, spec, voxel, largest, center)
    origin_grid = _to_grid(origin, g2i, rot, voxel)
    # the object's own points outside the grid (e.g. the top of an object taller than a metric
    # grid) still hide what lies behind them: without them, the inside of the object reads free
    blockers = [g[~inside]]
    if o_pts is not None:
        o_pts = o_pts[np.isfinite(o_pts).all(axis=1)]
        blockers.append(_to_grid(o_pts, g2i, rot, voxel))
    blockers = np.concatenate(blockers)
    occ_vox = _relevant_occluders(blockers, origin_grid, spec.size) if len(blockers) else None
    splats, half = _sparse_splats(g, inside, occ, close_holes)
    grid = label_free_unknown(occ, origin_grid, close_holes=close_holes, occluder_voxels=occ_vox,
                              splats=splats, splat_half=half)
    return ViewGrid(grid=grid, grid_to_input=g2i, voxel_size_m=float(voxel),
                    n_points=int(inside.sum()))


def _check_occluders(occluders) -> np.ndarray | None:
    """float64 (m, 3) ``occluders`` (None stays None; non-finite rows are kept); ValueError for
    another shape."""
    if occluders is None:
        return None
    o_pts = np.asarray(occluders, dtype=np.float64)
    if o_pts.size and (o_pts.ndim != 2 or o_pts.shape[1] != 3):
        raise ValueError(f'occluders must be an (m, 3) array of points, got shape '
                         f'{o_pts.shape}')
    return o_pts.reshape(-1, 3)


def _estimated_box(q: np.ndarray, spec: GridSpec, floor) -> tuple:
    """The object's box estimated from its aligned-frame points ``q`` (m, 3), as the placement
    heuristic of :func:`voxelize_view` says -> (box_lo (3,), box_hi (3,), largest extent).

    ValueError when the points span no more than MIN_EXTENT."""
    lo, hi = q.min(axis=0), q.max(axis=0)
    if not (hi - lo).max() > MIN_EXTENT:   # e.g. every point at one place
        raise ValueError(f'the points span {(hi - lo).max():g} (input units), not more than '
                         f'{MIN_EXTENT:g}: not an object to voxelize')
    if floor is not None and spec.anchor == 'bottom':
        lo[2] = min(lo[2], float(floor))
    ext = hi - lo
    depth = max(ext[0], ext[1])
    box_hi = np.array([lo[0] + depth, hi[1], hi[2]])
    return lo, box_hi, float(max(depth, ext[1], ext[2]))


def _place_grid(rot: np.ndarray, box_lo, box_hi, largest: float, spec: GridSpec,
                center) -> tuple:
    """Put the aligned-frame box's anchor point (or ``center``, input frame) at the grid's ->
    (grid_to_input float64 (4, 4), voxel size in m)."""
    n = spec.size
    if spec.units == 'normalized':
        voxel = largest / (spec.fill * n)
    else:
        voxel = float(spec.voxel_size)
    c = (n - 1) / 2.0
    if spec.anchor == 'center':
        anchor_idx = np.array([c, c, c])
        anchor_al = 0.5 * (box_lo + box_hi)
    else:
        anchor_idx = np.array([c, c, -0.5])
        anchor_al = np.array([0.5 * (box_lo[0] + box_hi[0]), 0.5 * (box_lo[1] + box_hi[1]),
                              box_lo[2]])
    anchor_in = rot @ anchor_al if center is None else center
    g2i = np.eye(4)
    g2i[:3, :3] = voxel * rot
    g2i[:3, 3] = anchor_in - voxel * rot @ anchor_idx
    return g2i, voxel


def _to_grid(p: np.ndarray, g2i: np.ndarray, rot: np.ndarray, voxel: float) -> np.ndarray:
    """Input-frame points (m, 3) (or one (3,)) -> continuous grid index coords."""
    return (p - g2i[:3, 3]) @ rot / voxel


def _occupied_voxels(g: np.ndarray, spec: GridSpec, voxel: float, largest: float,
                     center=None) -> tuple:
    """(inside bool (m,), occupied bool (N, N, N)) for points at grid index coords ``g`` (m, 3);
    ValueError when none falls inside the grid (placed at ``center`` when given)."""
    n = spec.size
    tol = 1e-6
    inside = np.all((g >= -0.5 - tol) & (g <= n - 0.5 + tol), axis=1)
    if not inside.any() and center is not None:   # the caller's placement, not the points
        raise ValueError(f'none of the {len(g)} points fall inside the {n}^3 grid of '
                         f'{n * voxel:g} m placed at center {center.tolist()}; they span '
                         f'{largest:g} (input units)')
    if not inside.any():   # e.g. a metric grid and points in millimetres
        raise ValueError(f'none of the {len(g)} points fall inside the {n}^3 grid of '
                         f'{n * voxel:g} m; they span {largest:g} (input units): '
                         'an object much larger than the grid, or points not in metres')
    idx = np.clip(np.floor(g[inside] + 0.5), 0, n - 1).astype(np.intp)
    occ = np.zeros(spec.shape, dtype=bool)
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return inside, occ


def _sparse_splats(g: np.ndarray, inside: np.ndarray, occ: np.ndarray,
                   close_holes: bool) -> tuple:
    """Squares to block rays with -> (splats (k, 3) grid coords or None, half-width in voxels).

    A surface sampled more sparsely than the voxels (a small or distant object in a normalized
    grid) has gaps the closing does not bridge; squares as wide as the point spacing do."""
    splats, half = None, 0.0
    # (3 points per occupied voxel or more: dense enough, and no KD-tree to build, 20 ms for 50k)
    if close_holes and inside.sum() < 3 * occ.sum():
        spacing = point_spacing(g[inside])
        if SPARSE_SPACING < spacing < np.inf:
            splats, half = g[inside], float(SPLAT_SCALE * spacing)
    return splats, half


def grid_to_points(grid_or_prob, grid_to_input, threshold: float = 0.5,
                   dtype=np.float32) -> tuple:
    """Centres of voxels with value >= ``threshold``, in the input frame.

    Args:
        grid_or_prob: (N, N, N) labelled grid or occupancy probabilities, indexed [x, y, z].
        grid_to_input: (4, 4) homogeneous grid index coords -> input frame.
        dtype: of the points (float32 rounds coordinates of 1e5 m to 8 mm).

    Returns (points ``dtype`` (m, 3), values float32 (m,)).
    """
    g = np.asarray(grid_or_prob)
    if g.ndim != 3:
        raise ValueError(f'grid must be 3-D, got shape {g.shape}')
    t = np.asarray(grid_to_input, dtype=np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise ValueError('grid_to_input must be a finite (4, 4) matrix')
    idx = np.argwhere(g >= threshold)
    pts = idx @ t[:3, :3].T + t[:3, 3]
    return pts.astype(dtype), g[tuple(idx.T)].astype(np.float32)
