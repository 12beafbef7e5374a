"""Tabletop scenes (OSD-style organized PCD scans): load, segment objects, fit the table, voxelize.

Camera frame (PCL/Kinect optical): x right, y down, z forward, sensor at the origin, metres.
A file whose ``VIEWPOINT`` (the sensor's pose in the cloud's frame, ``tx ty tz qw qx qy qz``) is
not the identity has its points moved into that sensor frame by :func:`load_scene`.
OSD labels: 0 invalid, 1-9 the supporting table, >= 20 object parts with object id = label // 10
(so the first object has id 2).
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from .grid import GridSpec, _real, quaternion_matrix
from .pcd import PCDError, read_pcd
from .voxelize import MIN_POINTS, ViewGrid, finite_points, voxelize_view

TABLE_LABELS = (1, 9)  # inclusive range
MIN_VIEW_ANGLE_DEG = 5.0  # a support plane seen at a shallower angle is refused
# support points narrower than this many distance thresholds across (a strip of a few image
# rows or columns) leave the plane's tilt about the strip free: refused
MIN_WIDTH_THRESHOLDS = 3.0
FIRST_OBJECT_LABEL = 20
# metres: object points lower than this below the table plane are dropped (object_view)
BELOW_TABLE_TOL = 0.01
TABLETOP_SPEC = GridSpec(size=32, units='metric', voxel_size=0.5 / 32, anchor='bottom')
IDENTITY_VIEWPOINT = np.array([0, 0, 0, 1, 0, 0, 0], dtype=np.float64)


class ScanWarning(UserWarning):
    """Part of a scan is left out (small objects, labels 10-19, points outside a grid) or the
    table is not fitted from table labels."""


@dataclass
class Scene:
    """One organized scan.

    Attributes:
        points: float32 (H*W, 3) camera frame, NaN where invalid (row-major, index = r * W + c).
        labels: uint32 (H*W,), 0 where the file has no label field.
        rgb: uint8 (H*W, 3), zeros where the file has no colour.
        width, height: W, H.
        path: file it came from ('' if built in memory).
        viewpoint: float64 (7,) the file's VIEWPOINT ``tx ty tz qw qx qy qz`` (the sensor's
            pose in the file's frame), already applied to ``points``.
    """

    points: np.ndarray
    labels: np.ndarray
    rgb: np.ndarray
    width: int
    height: int
    path: str = ''
    viewpoint: np.ndarray = field(default_factory=lambda: IDENTITY_VIEWPOINT.copy())


def load_scene(path, require_labels: bool = True) -> Scene:
    """Read an OSD-style PCD (fields x y z, label, optional rgba/rgb). Raises PCDError, also
    for a file without a label field unless ``require_labels`` is False (labels then 0).

    The points are returned in the sensor frame: a VIEWPOINT ``t, q`` other than the identity
    (the sensor at ``t`` with orientation ``q`` in the file's frame, as PCL writes it) maps a
    file point ``p`` to ``R(q)^T (p - t)``, so the sensor is at the origin like in OSD files.
    """
    pcd = read_pcd(path)
    if not all(k in pcd for k in 'xyz'):
        raise PCDError(f'{path}: no x/y/z fields')
    if require_labels and 'label' not in pcd:
        # without labels every point would be "invalid": no table, no objects
        raise PCDError(f'{path}: no label field (a segmented scene is needed: labels 1-9 the '
                       f'table, >= {FIRST_OBJECT_LABEL} the objects)')
    n = pcd.n_points
    try:
        pts = pcd.xyz()   # float32 once in the sensor frame: F 8 map coordinates keep their mm
    except PCDError as e:
        raise PCDError(f'{path}: {e}') from None
    for key in ('label', 'rgba', 'rgb'):
        if key in pcd and pcd[key].ndim != 1:
            raise PCDError(f'{path}: field {key!r} has COUNT {pcd[key].shape[1]}, not 1')
    viewpoint = np.asarray(pcd.viewpoint, dtype=np.float64)
    if not (viewpoint == IDENTITY_VIEWPOINT).all():   # identity: the points as they are
        pts = _to_sensor_frame(pts, viewpoint, path)
    pts = pts.astype(np.float32)
    labels = _labels(pcd['label'], path) if 'label' in pcd else np.zeros(n, np.uint32)
    rgb = np.zeros((n, 3), np.uint8)
    for key in ('rgba', 'rgb'):
        if key in pcd:
            v = pcd[key]
            v = v.view(np.uint32) if v.dtype.itemsize == 4 else v.astype(np.uint32)
            rgb = np.stack([(v >> 16) & 255, (v >> 8) & 255, v & 255], axis=1).astype(np.uint8)
            break
    return Scene(points=pts, labels=labels, rgb=rgb, width=pcd.width, height=pcd.height,
                 path=os.fspath(path), viewpoint=viewpoint)


def _to_sensor_frame(points, viewpoint, path) -> np.ndarray:
    """(n, 3) file points -> float64 points in the frame of the sensor whose pose is
    ``viewpoint``."""
    t, q = viewpoint[:3], viewpoint[3:]
    norm = float(np.linalg.norm(q))
    if not np.isfinite(viewpoint).all() or norm < 1e-6:
        raise PCDError(f'{path}: VIEWPOINT {viewpoint.tolist()} is not a pose (non-finite '
                       'numbers or a zero quaternion)')
    R = quaternion_matrix(q / norm)   # sensor axes in the file's frame (columns)
    return (points.astype(np.float64) - t) @ R   # rows: R^T (p - t)


def _labels(values, path) -> np.ndarray:
    """uint32 labels from a label field of any numeric type; PCDError for values that are not
    integers in [0, 2^32) (a cast would wrap -1 to 4294967295, an object label)."""
    v = np.asarray(values)
    if v.dtype.kind == 'f':
        bad = ~np.isfinite(v) | (v != np.round(v))
    else:
        bad = np.zeros(v.shape, bool)
    with np.errstate(invalid='ignore'):
        # a float64 bound: in float32 the uint32 maximum rounds to 2^32, which then passed
        bad |= (v < 0) | (v >= np.float64(2 ** 32))
    if bad.any():
        raise PCDError(f'{path}: label field has {int(bad.sum())} value(s) that are not integers '
                       f'in [0, 2^32), e.g. {v[bad][0]!r}')
    return v.astype(np.uint32)


def _finite(points) -> np.ndarray:
    return np.isfinite(points).all(axis=1)


def label_summary(scene: Scene, min_points: int = MIN_POINTS) -> dict:
    """What :func:`segment_objects` and :func:`fit_table_plane` leave out of ``scene``:
    dict(small_objects={object id: finite points} of the objects with fewer than ``min_points``,
    unassigned_points=finite points with labels 10-19 (neither table nor object),
    table_points=finite points with table labels 1-9)."""
    ok = _finite(scene.points)
    lab = scene.labels[ok]
    ids, counts = np.unique(lab[lab >= FIRST_OBJECT_LABEL] // 10, return_counts=True)
    return dict(small_objects={int(i): int(c) for i, c in zip(ids, counts) if c < min_points},
                unassigned_points=int(((lab >= 10) & (lab < FIRST_OBJECT_LABEL)).sum()),
                table_points=int(((lab >= TABLE_LABELS[0]) & (lab <= TABLE_LABELS[1])).sum()))


def _name(scene) -> str:
    return scene.path or 'scene'


def segment_objects(scene: Scene, min_points: int = MIN_POINTS) -> dict:
    """Object id (label // 10) -> float64 (n, 3) finite camera-frame points, ids ascending.

    Objects with fewer than ``min_points`` finite points are left out, and points with labels
    10-19 (neither table nor object) are ignored; both with a :class:`ScanWarning` naming the
    scene and the numbers (:func:`label_summary` returns them).
    """
    ok = _finite(scene.points) & (scene.labels >= FIRST_OBJECT_LABEL)
    ids = scene.labels[ok] // 10
    pts = scene.points[ok].astype(np.float64)
    out = {}
    for oid in np.unique(ids):
        sel = pts[ids == oid]
        if len(sel) >= min_points:
            out[int(oid)] = sel
    info = label_summary(scene, min_points)
    notes = []
    if info['small_objects']:
        notes.append(f"left out {len(info['small_objects'])} object(s) with fewer than "
                     f'{min_points} points (id: points ' + ', '.join(
                         f'{k}: {v}' for k, v in info['small_objects'].items()) + ')')
    if info['unassigned_points']:
        notes.append(f"ignored {info['unassigned_points']} points with labels 10-19 (neither "
                     'table nor object)')
    if notes:
        warnings.warn(f'{_name(scene)}: ' + '; '.join(notes), ScanWarning, stacklevel=2)
    return out


def fit_table_plane(scene_or_points, labels=None, distance_threshold: float = 0.01,
                    iterations: int = 500, sensor_origin=(0.0, 0.0, 0.0)) -> tuple:
    """Fit the support plane by RANSAC (open3d ``segment_plane``) + least-squares refinement.

    Args:
        scene_or_points: a :class:`Scene`, or (n, 3) points (camera frame).
        labels: (n,) labels for raw points; table points are labels 1-9. With no labels all
            finite points are used and the dominant plane is taken; so too, with a
            :class:`ScanWarning`, when the labels hold fewer than 3 finite table points.
        sensor_origin: finite (3,) sensor position, same frame as the points.

    Returns (up float64 (3,), d float): unit plane normal oriented toward the sensor side and
    offset with ``up . p + d = 0`` on the plane; ``up . sensor_origin + d > 0`` is the sensor's
    height above the table. Raises ValueError when the points hold no plane, when the plane's
    inliers form a strip narrower than ``MIN_WIDTH_THRESHOLDS`` x ``distance_threshold`` (the
    width of a uniform strip with their spread across; a few image rows or columns of a table:
    the plane could tilt about the strip) or when the sensor sees the plane at less than
    ``MIN_VIEW_ANGLE_DEG`` (edge-on) from its centre.
    """
    if isinstance(scene_or_points, Scene):
        pts, labels = scene_or_points.points, scene_or_points.labels
    else:
        pts = np.asarray(scene_or_points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f'points must be (n, 3), got shape {pts.shape}')
    pts = np.asarray(pts, dtype=np.float64)
    origin = np.asarray(sensor_origin, dtype=np.float64)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f'sensor_origin must be a finite 3-vector, got {sensor_origin!r}')
    # (open3d took 0, negative or NaN for no plane, and negative iterations for vector::reserve)
    if isinstance(distance_threshold, (bool, np.bool_)) or not isinstance(
            distance_threshold, (int, float, np.integer, np.floating)) \
            or not 0 < distance_threshold < np.inf:
        raise ValueError(f'distance_threshold must be a positive number of metres, got '
                         f'{distance_threshold!r}')
    if isinstance(iterations, (bool, np.bool_)) or not isinstance(iterations, (int, np.integer)) \
            or iterations < 1:
        raise ValueError(f'iterations must be a positive integer, got {iterations!r}')
    ok = _finite(pts)
    if labels is not None:
        labels = np.asarray(labels).reshape(-1)
        if len(labels) != len(pts):
            raise ValueError(f'labels must hold one label per point ({len(pts)}), got '
                             f'{len(labels)}')
        table = ok & (labels >= TABLE_LABELS[0]) & (labels <= TABLE_LABELS[1])
        if table.sum() >= 3:
            ok = table
        else:
            where = _name(scene_or_points) if isinstance(scene_or_points, Scene) else 'points'
            warnings.warn(f'{where}: {int(table.sum())} table points (labels 1-9), fewer than '
                          f'3: the table is the dominant plane of all {int(ok.sum())} finite '
                          'points', ScanWarning, stacklevel=2)
    sel = pts[ok]
    if len(sel) < 3:
        raise ValueError(f'need at least 3 finite points to fit a plane, got {len(sel)}')
    o3d.utility.random.seed(0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sel))
    _, inliers = cloud.segment_plane(distance_threshold, 3, iterations)
    if len(inliers) < 3:   # open3d finds no plane in collinear or identical points
        raise ValueError(f'no plane among the {len(sel)} support points (collinear or all at '
                         'one place?)')
    # least squares on the inliers, re-selected by the refined plane until they stop changing:
    # open3d's multithreaded RANSAC is not reproducible even when seeded, its refined plane is
    keep = np.zeros(len(sel), dtype=bool)
    keep[np.asarray(inliers)] = True
    for _ in range(20):
        inl = sel[keep]
        centroid = inl.mean(axis=0)
        _, sv, vt = np.linalg.svd(inl - centroid, full_matrices=False)
        if len(sv) < 3 or sv[1] <= 1e-6 * sv[0]:   # a line: any normal across it would do
            raise ValueError(f'no plane among the {len(sel)} support points (they lie on a '
                             'line)')
        normal = vt[2]
        again = np.abs((sel - centroid) @ normal) <= distance_threshold
        if again.sum() < 3 or (again == keep).all():
            break
        keep = again
    # width of a uniform strip with the inliers' spread along the plane's narrower axis: RANSAC
    # and the refit can tilt a plane about a strip little wider than the inlier band at will
    # (OSD tables cut to their last 3-10 image rows: 38-116 deg off, no error)
    width = np.sqrt(12.0) * sv[1] / np.sqrt(len(inl))
    if width < MIN_WIDTH_THRESHOLDS * distance_threshold:
        raise ValueError(f'the support points form a strip {100 * width:.1f} cm wide (less than '
                         f'{MIN_WIDTH_THRESHOLDS:g} x distance_threshold {distance_threshold:g} '
                         'm): the tilt of a plane through it is not determined (too little of '
                         'the table visible?)')
    d = -float(normal @ centroid)
    height = normal @ origin + d
    seen_deg = np.degrees(np.arcsin(min(1.0, abs(height) / max(
        float(np.linalg.norm(centroid - origin)), 1e-12))))
    if seen_deg < MIN_VIEW_ANGLE_DEG:
        # a few image rows of the table lie close to the plane of their own rays: RANSAC finds
        # that plane, which passes (nearly) through the sensor and is not the table
        raise ValueError(f'the fitted support plane is seen edge-on ({seen_deg:.1f} deg from '
                         'the sensor, too few table rows to fit it?)')
    if height < 0:
        normal, d = -normal, -d
    return normal, d


def object_view(points, up, plane_d: float, spec: GridSpec = TABLETOP_SPEC,
                sensor_origin=(0.0, 0.0, 0.0), occluders=None, stacked_tol: float = 0.03,
                below_tol: float = BELOW_TABLE_TOL, **kw) -> ViewGrid:
    """Voxelize one tabletop object standing on the table plane ``up . p + plane_d = 0``.

    Args:
        points: (n, 3) object points, camera frame.
        up, plane_d: the table plane as returned by :func:`fit_table_plane`
            (``object_view(pts, *plane)``).
        occluders: optional (m, 3) points of the *other* objects (see :func:`scene_occluders`);
            voxels they hide from the camera become unknown.
        stacked_tol: metres; when the object's lowest point is higher than this above the table
            (it stands on another object), its own lowest point is the grid floor instead.
        below_tol: metres (>= 0); object points lower than this below the table plane
            (segmentation leaks, noise) are dropped, with a :class:`ScanWarning`, and counted in
            ``ViewGrid.n_below_table``; points less low are kept and the grid floor goes down to
            the lowest of them (the plane fit's noise: 1 cm is ``fit_table_plane``'s band).
            0 keeps the floor on the table.
        kw: passed to :func:`~beo_ros.core.voxelize.voxelize_view`.

    The grid floor is the table plane (for anchor 'bottom'); x, y follow the
    :func:`~beo_ros.core.voxelize.voxelize_view` placement heuristic; free/unknown come from ray
    casting from ``sensor_origin`` (the camera).
    """
    up = np.asarray(up, dtype=np.float64)
    norm = np.linalg.norm(up)
    if up.shape != (3,) or not np.isfinite(up).all() or norm < 1e-9:
        raise ValueError(f'up must be a finite non-zero 3-vector, got {up!r}')
    if not 0 <= _real(below_tol) < np.inf:   # NaN for what is no real number
        raise ValueError(f'below_tol must be a finite number of metres >= 0, got {below_tol!r}')
    # (NaN stacked_tol called no object stacked; a NaN plane_d was blamed on 'floor', an array
    # or None failed in float())
    if not 0 <= _real(stacked_tol) < np.inf:
        raise ValueError(f'stacked_tol must be a finite number of metres >= 0, got '
                         f'{stacked_tol!r}')
    if not np.isfinite(_real(plane_d)):
        raise ValueError(f'plane_d must be a finite number (the table plane up . p + plane_d '
                         f'= 0), got {plane_d!r}')
    floor = -float(plane_d) / norm  # height of the plane along the unit up vector
    min_points = max(kw.get('min_points', MIN_POINTS), 1)
    pts = finite_points(points, min_points)
    h = pts @ (up / norm)
    # a point further below the table than its noise is no part of an object standing on it:
    # it would move the grid floor (and the object) down with it
    low = h < floor - below_tol
    n_below = int(low.sum())
    if n_below:
        depth = floor - float(h.min())
        if len(pts) - n_below < min_points:
            raise ValueError(f'{n_below} of the {len(pts)} points lie more than {below_tol:g} m '
                             f'below the table plane (down to {depth:.3g} m), leaving fewer '
                             f'than {min_points}: not an object on this table (the wrong plane?)')
        warnings.warn(f'dropped {n_below} of {len(pts)} object points lying more than '
                      f'{below_tol:g} m below the table plane (down to {depth:.3g} m; '
                      'segmentation leaks or noise)', ScanWarning, stacklevel=2)
        pts, h = pts[~low], h[~low]
    if h.min() - floor > stacked_tol:
        floor = None
    view = voxelize_view(pts, sensor_origin, up, spec, floor=floor, occluders=occluders, **kw)
    view.n_below_table = n_below
    return view


def scene_occluders(scene: Scene, object_id: int) -> np.ndarray:
    """float64 (m, 3) finite points of every other object (labels >= 20, id != ``object_id``)."""
    ok = _finite(scene.points) & (scene.labels >= FIRST_OBJECT_LABEL)
    ok &= scene.labels // 10 != object_id
    return scene.points[ok].astype(np.float64)
