"""Voxel grid conventions and yaw rotation of labelled grids.

Conventions used everywhere in beo_ros:
- a grid is an array (N, N, N) indexed [x, y, z], z up;
- labelled grids are int8: 1 occupied, 0 free, -1 unknown;
- voxel centres sit at integer indices; rotations about +z turn about the grid's vertical
  centre line through ``c = (N - 1) / 2``.
"""
from __future__ import annotations

import decimal
import numbers
from dataclasses import asdict, dataclass

import numpy as np

OCCUPIED, FREE, UNKNOWN = 1, 0, -1
UNITS = ('normalized', 'metric')
ANCHORS = ('center', 'bottom')


@dataclass(frozen=True)
class GridSpec:
    """How points in metres map to a model's voxel grid.

    Attributes:
        size: N, the grid is (N, N, N).
        units: 'normalized' scales each object so its largest extent spans ``fill * N`` voxels (as
            the ModelNet training grids); 'metric' uses a fixed ``voxel_size`` in metres.
        voxel_size: metres per voxel, for 'metric' only.
        fill: fraction of the grid the largest extent spans, for 'normalized' only.
        anchor: 'center' puts the object's bounding-box centre at the grid centre; 'bottom' puts
            its lowest point (the support plane) at the bottom of the grid, centred in x, y.
    """

    size: int = 32
    units: str = 'normalized'
    voxel_size: float = 0.0
    fill: float = 1.0
    anchor: str = 'center'

    def __post_init__(self):
        size = _real(self.size)
        if not (4 <= size <= 256 and int(size) == size):   # NaN for non-numbers
            raise ValueError(f'GridSpec.size must be an integer in [4, 256], got {self.size!r}')
        object.__setattr__(self, 'size', int(size))   # 32.0 from a manifest -> 32
        if self.units not in UNITS:
            raise ValueError(f'GridSpec.units must be one of {UNITS}, got {self.units!r}')
        voxel_size = _real(self.voxel_size)
        if self.units == 'metric' and not (np.isfinite(voxel_size) and voxel_size > 0):
            raise ValueError(f'metric GridSpec needs voxel_size > 0, got {self.voxel_size!r}')
        if np.isnan(voxel_size):
            raise ValueError(f'GridSpec.voxel_size must be a number, got {self.voxel_size!r}')
        if not 0 < _real(self.fill) <= 1:
            raise ValueError(f'GridSpec.fill must be in (0, 1], got {self.fill!r}')
        # plain floats: a numpy scalar (np.float32(0.01)) would not go into the JSON manifest
        object.__setattr__(self, 'voxel_size', voxel_size)
        object.__setattr__(self, 'fill', _real(self.fill))
        if self.anchor not in ANCHORS:
            raise ValueError(f'GridSpec.anchor must be one of {ANCHORS}, got {self.anchor!r}')

    @property
    def shape(self) -> tuple:
        return (self.size,) * 3

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> 'GridSpec':
        known = {k: d[k] for k in ('size', 'units', 'voxel_size', 'fill', 'anchor') if k in d}
        return cls(**known)


# what the number checks refuse although isinstance(value, int / np.integer) holds: numpy counts
# timedelta64 as an integer (a step of np.timedelta64(5) raised numpy's UFuncTypeError, a count
# or probe offset of one was taken)
NOT_NUMBERS = (bool, np.bool_, np.timedelta64)


def real_number(value):
    """``value`` as a float if it is a real number, else None. Real numbers: numbers.Real (int,
    float, numpy's, Fraction) and Decimal (which the numbers module leaves out), or a 0-d array
    of one; not a bool, a numpy timedelta64, a complex number or a string. NaN for a real
    number float cannot hold (an int or a Fraction beyond it, a signalling NaN Decimal)."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if isinstance(value, NOT_NUMBERS) or not isinstance(value, (numbers.Real, decimal.Decimal)):
        return None
    try:
        return float(value)
    except (OverflowError, ValueError):
        return np.nan


def check_count(name, value, minimum=0):
    """Raise ValueError unless ``value`` is an integer >= ``minimum`` (numbers.Integral: int,
    numpy's; not a bool, a numpy timedelta64, nor an integral Fraction or Decimal)."""
    if isinstance(value, NOT_NUMBERS) or not isinstance(value, numbers.Integral) \
            or value < minimum:
        raise ValueError(f'{name} must be an integer >= {minimum}, got {value!r}')


def _real(value) -> float:
    """``value`` as a float when it is a real number (see :func:`real_number`), else NaN."""
    x = real_number(value)
    return np.nan if x is None else x


def real_array(value, name, what):
    """float64 array of ``value``; ValueError '``name`` must be ``what``...' unless it holds
    real numbers (integers or floats)."""
    try:
        a = np.asarray(value)
    except ValueError:   # rows of different lengths
        raise ValueError(f'{name} must be {what}, got rows of different lengths') from None
    # strings were parsed as numbers, complex numbers lost their imaginary part, objects
    # failed in float() or became NaN, dates and bools passed as numbers
    if a.dtype.kind not in 'iuf':
        raise ValueError(f'{name} must be {what} of real numbers, got dtype {a.dtype}')
    return a.astype(np.float64, copy=False)


def unit_vector(v) -> np.ndarray:
    """float64 ``v`` / |v| for a finite non-zero vector, without overflow for huge components
    (divided by the largest component first)."""
    v = np.asarray(v, dtype=np.float64)
    v = v / np.abs(v).max()
    return v / np.linalg.norm(v)


def yaw_matrix(yaw: float) -> np.ndarray:
    """(3, 3) right-handed rotation by ``yaw`` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quaternion_matrix(q) -> np.ndarray:
    """float64 (3, 3) rotation of the unit quaternion ``q = (w, x, y, z)``."""
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def yaw_grid(step_deg) -> np.ndarray:
    """(Y,) float64 yaws 0, step, 2 step, ... below 2 pi (radians) for a step in degrees. Every
    search builds its candidates here: the rotation maps are cached by the array's bytes."""
    step = np.deg2rad(step_deg)
    # every multiple below 360 deg (a step that does not divide 360 deg too: 80 -> 0 .. 320);
    # the tolerance keeps a divisor's 360 deg itself out (360 / 0.3 = 1200.0000000000002)
    return np.arange(int(np.ceil(360.0 / step_deg - 1e-6))) * step


def wrap_yaw(yaw) -> float:
    """A yaw in radians as a float in [-pi, pi)."""
    yaw = float(yaw)
    if abs(yaw) > 2 * np.pi:   # whole turns off first: yaw + pi rounds away a huge yaw's angle
        yaw = float(np.mod(yaw, 2 * np.pi))
    y = float(np.mod(yaw + np.pi, 2 * np.pi) - np.pi)
    return -np.pi if y >= np.pi else y   # np.mod rounds a yaw just below -pi up to 2 pi


def yaw_error(a, b):
    """Absolute angular difference of yaws ``a`` and ``b`` (radians, broadcast), in [0, pi]."""
    return np.abs((np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi)


def yaw_column_index(n: int, yaws: np.ndarray) -> np.ndarray:
    """Nearest-neighbour gather maps of the grid columns (x, y) for rotating an (n, n, n) grid
    by each yaw about +z: int64 (len(yaws), n**2), the source column x * n + y of every column
    of the rotated grid, or ``n**2`` where the source lies outside the grid."""
    yaws = np.atleast_1d(np.asarray(yaws, dtype=np.float64))
    c = (n - 1) / 2.0
    ii, jj = np.meshgrid(np.arange(n) - c, np.arange(n) - c, indexing='ij')
    ct, st = np.cos(yaws)[:, None, None], np.sin(yaws)[:, None, None]
    # destination p = R(yaw) q  =>  source q = R(-yaw) p
    sx = np.rint(ct * ii + st * jj + c).astype(np.int64)
    sy = np.rint(-st * ii + ct * jj + c).astype(np.int64)
    inside = (sx >= 0) & (sx < n) & (sy >= 0) & (sy < n)
    return np.where(inside, sx * n + sy, n * n).reshape(len(yaws), n * n)


def yaw_source_index(n: int, yaws: np.ndarray) -> np.ndarray:
    """Nearest-neighbour gather maps for rotating an (n, n, n) grid by each yaw about +z.

    Returns int32 (len(yaws), n**3): flat index into the *source* grid for every voxel of the
    rotated grid, or ``n**3`` (one past the end) where the source lies outside the grid. The
    rotated grid is ``src_padded[idx]`` with ``src_padded = append(src.ravel(), fill)``.
    """
    col = yaw_column_index(n, yaws)
    idx = np.where(col[..., None] < n * n, col[..., None] * n + np.arange(n), n ** 3)
    return idx.reshape(len(col), n ** 3).astype(np.int32)


def rotate_grid(grid: np.ndarray, yaw: float, fill=0) -> np.ndarray:
    """Rotate an (N, N, N) grid by ``yaw`` radians about +z (nearest neighbour).

    Voxels whose source falls outside the grid get ``fill`` (0 = free/empty; use -1 for unknown).
    """
    grid = np.asarray(grid)
    if grid.ndim != 3 or len(set(grid.shape)) != 1:
        raise ValueError(f'grid must be (N, N, N), got shape {grid.shape}')
    n = grid.shape[0]
    idx = yaw_source_index(n, [yaw])[0]
    src = np.append(grid.ravel(), np.asarray(fill, dtype=grid.dtype))
    return src[idx].reshape(grid.shape)


SELF_MATCH_IOU = 0.9
QUARTER_TURNS = (0.5 * np.pi, np.pi, 1.5 * np.pi)


def symmetric_turns(occupied: np.ndarray, min_iou: float = SELF_MATCH_IOU) -> tuple:
    """Quarter turns about +z that map a shape onto itself.

    ``occupied``: bool (N, N, N), axes x, y, z. The shape is turned about the vertical line
    through the centre of its x-y bounding box (the grid centre for a centred object), so an
    object placed off-centre in its grid is judged by its own shape. Returns the turns, radians,
    among pi/2, pi and 3 pi/2, whose turned shape has IoU >= ``min_iou`` with ``occupied``; ()
    for a grid with no occupied voxel. The half turn is exact; a quarter turn of a footprint
    whose x and y extents differ in parity is half a voxel off centre. The set is closed under
    inverse (IoU(R x, x) = IoU(x, R^-1 x)).
    """
    occ = np.asarray(occupied)
    if occ.ndim != 3 or len(set(occ.shape)) != 1:
        raise ValueError(f'occupied must be (N, N, N), got shape {occ.shape}')
    if not 0 < min_iou <= 1:   # also refuses NaN
        raise ValueError(f'min_iou must be in (0, 1], got {min_iou}')
    occ = occ.astype(bool, copy=False)
    total = np.count_nonzero(occ)
    if total == 0:
        return ()
    xs, ys = np.flatnonzero(occ.any(axis=(1, 2))), np.flatnonzero(occ.any(axis=(0, 2)))
    box = occ[xs[0]:xs[-1] + 1, ys[0]:ys[-1] + 1]
    # quarter turns need a square footprint: pad the shorter side on both ends
    side = max(box.shape[:2])
    pads = [((side - w) // 2, side - w - (side - w) // 2) for w in box.shape[:2]]
    square = np.pad(box, pads + [(0, 0)])
    out = []
    for k, turn in enumerate(QUARTER_TURNS, start=1):
        # np.rot90 over axes (0, 1) turns right-handed about +z by k * 90 degrees, as
        # rotate_grid does; the half turn of the unpadded box is exact about its centre
        base = box if k == 2 else square
        inter = np.count_nonzero(base & np.rot90(base, k, axes=(0, 1)))
        if inter >= min_iou * (2 * total - inter):   # IoU = inter / union, both have `total`
            out.append(turn)
    return tuple(out)


def yaw_error_up_to(a, b, turns=()):
    """:func:`yaw_error` of ``a`` against ``b`` and ``b`` + each of ``turns`` (radians), the
    smallest: the yaw error of a shape that the turns map onto itself."""
    err = yaw_error(a, b)
    for t in turns:
        err = np.minimum(err, yaw_error(a, np.asarray(b) + t))
    return err
