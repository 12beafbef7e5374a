"""Training sets from real labelled tabletop scans (OSD-style organized PCD scenes).

Every object of a scene becomes one partial training grid: the object's points are voxelized into
the gravity-aligned metric grid standing on the table (:func:`beo_ros.core.scans.object_view`),
free and unknown space come from ray casting from the camera, and the other objects of the scene
are occluders. The class of an object is the class of its scene, by the number N in
``learnN.pcd`` (``--scan-classes 'box:0-16,cylinder:33-44'``).

For VBPCA the unknown voxels are *missing data*: ``X`` holds the occupancy (unknown set to 0) and
``masks`` says which entries were observed (``grid >= 0``).
"""
from __future__ import annotations

import re
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .grid import GridSpec
from .scans import (BELOW_TABLE_TOL, ScanWarning, fit_table_plane, label_summary, load_scene,
                    object_view, scene_occluders, segment_objects)

DEFAULT_SCAN_CLASSES = 'box:0-16,cylinder:33-44'


def parse_scan_classes(text) -> tuple:
    """``'box:0-16,cylinder:33-44'`` -> (class names in order, {scene number: class index}).

    Ranges are inclusive; single numbers and several ranges per class (``box:0-3+7``) work too.
    """
    if isinstance(text, dict):
        text = ','.join(f'{k}:{v}' for k, v in text.items())
    names, table = [], {}
    for part in str(text).split(','):
        part = part.strip()
        if not part:
            continue
        if ':' not in part:
            raise ValueError(f'scan class {part!r} is not name:first-last')
        name, ranges = (s.strip() for s in part.split(':', 1))
        if not name:
            raise ValueError(f'scan class {part!r} has no name')
        if name not in names:
            names.append(name)
        for r in ranges.split('+'):
            m = re.fullmatch(r'\s*(\d+)\s*(?:-\s*(\d+))?\s*', r)
            if not m:
                raise ValueError(f'scan class {part!r}: bad range {r!r}')
            a, b = int(m.group(1)), int(m.group(2) or m.group(1))
            if b < a:
                raise ValueError(f'scan class {part!r}: empty range {r!r}')
            for s in range(a, b + 1):
                if s in table and table[s] != names.index(name):
                    raise ValueError(f'scene {s} is in two classes')
                table[s] = names.index(name)
    if not names:
        raise ValueError(f'no scan classes in {text!r}')
    return names, table


def scene_number(path) -> int | None:
    """The number N of ``...N.pcd`` (e.g. learn33.pcd -> 33), or None."""
    m = re.search(r'(\d+)$', Path(path).stem)
    return int(m.group(1)) if m else None


@dataclass
class ScanObjects:
    """Training objects from labelled scans.

    Attributes:
        X: float32 (m, N^3) occupancy, unknown entries 0.
        y: int (m,) class index.
        names: class names.
        masks: bool (m, N^3) observed (grid >= 0).
        spec: the metric GridSpec of the grids.
        scenes: str (m,) scene name (file stem) of each object, for leave-one-scene-out.
        object_ids: int (m,) OSD object id (label // 10) within its scene.
        points: list of float64 (n_i, 3) camera-frame points of each object.
        ups: float64 (m, 3) table normal (camera frame) of each object's scene.
        plane_d: float64 (m,) table offsets (up . p + d = 0).
        grid_to_input: float64 (m, 4, 4) grid index coords -> camera frame.
        n_outside: int (m,) points of each object outside its grid (not voxelized; those
            dropped below the table plane, see :func:`~beo_ros.core.scans.object_view`, apart).
        scene_notes: scene name -> :func:`~beo_ros.core.scans.label_summary`
            (objects too small to use, points with labels 10-19, table points) of each scene
            of the classes.
    """

    X: np.ndarray
    y: np.ndarray
    names: list
    masks: np.ndarray
    spec: GridSpec
    scenes: np.ndarray
    object_ids: np.ndarray
    points: list = field(default_factory=list)
    ups: np.ndarray = None
    plane_d: np.ndarray = None
    grid_to_input: np.ndarray = None
    n_outside: np.ndarray = None
    scene_notes: dict = field(default_factory=dict)

    @property
    def grids(self) -> np.ndarray:
        """int8 (m, N, N, N) labelled grids: 1 occupied, 0 free, -1 unknown."""
        n = self.spec.size
        g = np.where(self.masks, (self.X > 0.5).astype(np.int8), np.int8(-1)).astype(np.int8)
        return g.reshape(len(g), n, n, n)

    def subset(self, sel) -> 'ScanObjects':
        sel = np.asarray(sel)
        idx = np.flatnonzero(sel) if sel.dtype == bool else sel
        return ScanObjects(self.X[idx], self.y[idx], list(self.names), self.masks[idx], self.spec,
                           self.scenes[idx], self.object_ids[idx],
                           [self.points[i] for i in idx], self.ups[idx], self.plane_d[idx],
                           self.grid_to_input[idx],
                           None if self.n_outside is None else self.n_outside[idx],
                           dict(self.scene_notes))

    def __len__(self):
        return len(self.X)


def grid_spec(grid=32, voxel_size=0.5 / 32) -> GridSpec:
    return GridSpec(size=int(grid), units='metric', voxel_size=float(voxel_size), anchor='bottom')


def load_scan_objects(paths, scan_classes=DEFAULT_SCAN_CLASSES, grid=32, voxel_size=0.5 / 32,
                      verbose=False) -> ScanObjects:
    """Every segmented object of the scans whose scene number has a class, as partial grids.

    Scenes whose number is in no class are skipped (with a note when verbose). Raises ValueError
    for a path that is not a file, when a class ends up with fewer than 2 objects or no scan
    has a class, when two scans of the classes have one file name (a scene is its file stem:
    its objects would count twice, or two scenes be held out as one), or (naming the scan and
    object) when a table plane or an object's grid cannot be made.
    """
    names, table = parse_scan_classes(scan_classes)
    spec = grid_spec(grid, voxel_size)
    paths = list(paths)
    for p in paths:   # a typo (or a glob that matched nothing) is no scene in no class
        if not Path(p).is_file():
            raise ValueError(f'{p}: ' + ('a directory, not a PCD file' if Path(p).is_dir()
                                         else 'no such file'))
    X, M, y, scenes, oids, pts_all, ups, ds, T, outside = [], [], [], [], [], [], [], [], [], []
    notes = {}
    seen = {}
    for p in sorted(paths, key=lambda q: (scene_number(q) is None, scene_number(q) or 0, str(q))):
        num = scene_number(p)
        if num not in table:
            if verbose:
                print(f'{p}: scene {num} is in no class, skipped', file=sys.stderr)
            continue
        stem = Path(p).stem
        if stem in seen:
            raise ValueError(f'{p}: scene {stem!r} given twice (also {seen[stem]}): scenes are '
                             'told apart by their file names')
        seen[stem] = p
        scene = load_scene(p)
        objs = segment_objects(scene)   # warns of small objects and labels 10-19
        notes[Path(p).stem] = label_summary(scene)
        if not objs:   # said even when not verbose: a scene of the classes is not used
            print(f'{p}: no objects (labels >= 20), skipped', file=sys.stderr)
            continue
        try:
            up, d = fit_table_plane(scene)
        except ValueError as exc:   # name the scan: the message alone does not
            raise ValueError(f'{p}: {exc}') from exc
        below = {}
        for oid, pts in objs.items():
            try:
                with warnings.catch_warnings():   # said below, per scene, naming the scan
                    warnings.simplefilter('ignore', ScanWarning)
                    view = object_view(pts, up, d, spec, occluders=scene_occluders(scene, oid))
            except ValueError as exc:
                raise ValueError(f'{p}: object {oid}: {exc}') from exc
            g = view.grid
            X.append((g == 1).ravel())
            M.append((g >= 0).ravel())
            y.append(table[num])
            scenes.append(Path(p).stem)
            oids.append(oid)
            pts_all.append(pts)
            ups.append(up)
            ds.append(d)
            T.append(view.grid_to_input)
            outside.append(len(pts) - view.n_points - view.n_below_table)
            below[oid] = view.n_below_table
        cut = {oid: n for oid, n in zip(oids[-len(objs):], outside[-len(objs):]) if n}
        below = {oid: n for oid, n in below.items() if n}
        if below:   # segmentation leaks under the table: they would have moved the grid floor
            warnings.warn(f'{p}: points more than {BELOW_TABLE_TOL:g} m below the table plane, '
                          'dropped (object id: points dropped/all ' + ', '.join(
                              f'{k}: {n}/{len(objs[k])}' for k, n in below.items()) + ')',
                          ScanWarning, stacklevel=2)
        if cut:   # a grid too small for the objects (e.g. --grid 16 at the default voxel size)
            warnings.warn(f'{p}: points outside the {spec.size}^3 grid of '
                          f'{spec.voxel_size:g} m voxels, not voxelized (object id: points '
                          'outside/all ' + ', '.join(f'{k}: {n}/{len(objs[k])}'
                                                     for k, n in cut.items()) + ')',
                          ScanWarning, stacklevel=2)
        if verbose:
            print(f'{p}: {names[table[num]]}, {len(objs)} objects', file=sys.stderr)
    if not X:
        raise ValueError(f'no objects: no scan matched the scan classes {scan_classes!r}, or '
                         'those that did have no object labels (>= 20)')
    y = np.array(y, dtype=int)
    for c, name in enumerate(names):
        if (y == c).sum() < 2:
            raise ValueError(f'scan class {name!r} has {(y == c).sum()} objects; need >= 2')
    return ScanObjects(np.array(X, dtype=np.float32), y, names, np.array(M, dtype=bool), spec,
                       np.array(scenes), np.array(oids, dtype=int), pts_all,
                       np.array(ups, dtype=np.float64), np.array(ds, dtype=np.float64),
                       np.array(T, dtype=np.float64), np.array(outside, dtype=int), notes)


def mirror_augment(X, y, masks, n, groups=None) -> tuple:
    """Append the left-right mirror image of every training grid (flip of the grid's y axis).

    A scan grid is in the viewer frame (z up, x horizontal from the camera toward the object's
    centroid, y = z x x, the grid's y centre at the middle of the observed y range, within a few
    cm of the camera's vertical plane), so the mirror y -> -y keeps the camera where it was (same
    elevation and distance, azimuth within a few degrees): the mirrored grid, with its mirrored
    mask, is the view of the mirrored object from the same camera.
    Boxes and cylinders are mirror-symmetric classes, so this doubles the training views without
    inventing a viewpoint. Returns (X', y', masks'[, groups']) with the mirrored copies appended
    after the originals (``groups``: e.g. scene ids, repeated so folds keep a pair together).
    """
    X = np.asarray(X)
    m = len(X)

    def flip(a):
        return np.ascontiguousarray(a.reshape(m, n, n, n)[:, :, ::-1, :]).reshape(m, -1)

    out = (np.concatenate([X, flip(X)]), np.concatenate([np.asarray(y), np.asarray(y)]),
           np.concatenate([masks, flip(np.asarray(masks))]))
    if groups is not None:
        out += (np.concatenate([np.asarray(groups), np.asarray(groups)]),)
    return out


def load_scan_training_set(paths, scan_classes=DEFAULT_SCAN_CLASSES, grid=32,
                           voxel_size=0.5 / 32, verbose=False, mirror=False) -> tuple:
    """(X float32 (m, N^3), y (m,), names, masks bool (m, N^3), spec) for ``beo-train --scans``.

    See :func:`load_scan_objects` (which also returns scene ids, points and planes).
    ``mirror``: append the mirror image of every grid (:func:`mirror_augment`); off by default
    because ``beo-train`` folds its out-of-fold features over objects, and an object and its
    mirror image in different folds would leak (use :func:`train_scan_bank`, which keeps pairs
    and scenes together).
    """
    s = load_scan_objects(paths, scan_classes, grid, voxel_size, verbose)
    if mirror:
        X, y, M = mirror_augment(s.X, s.y, s.masks, s.spec.size)
        return X, y, s.names, M, s.spec
    if verbose:
        counts = ', '.join(f'{n} {int((s.y == c).sum())}' for c, n in enumerate(s.names))
        print(f'{len(s)} scan objects ({counts}); {100 * (1 - s.masks.mean()):.0f} % of the '
              f'voxels unknown', file=sys.stderr)
    return s.X, s.y, s.names, s.masks, s.spec


def scan_point_descriptors(objs) -> np.ndarray:
    """(m, 2) side-normal descriptors (r4, frac10) of every object of a :class:`ScanObjects`
    from its camera-frame points (sensor at the origin) and its scene's table normal, as
    ``ModelBank.estimate_points`` computes them with its default outlier removal
    (:mod:`beo_ros.core.normals`, :mod:`beo_ros.core.outliers`)."""
    from .normals import side_normal_descriptors
    from .outliers import clean_points
    out = []
    for p, u in zip(objs.points, objs.ups):
        p = np.asarray(p, dtype=np.float64)
        out.append(side_normal_descriptors(clean_points(p[np.isfinite(p).all(axis=1)])[0], u,
                                           np.zeros(3)))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


def train_point_classifier(loglik, descriptors, y, n_classes, C=1.0):
    """The 'points' classifier of a ModelBank (see ``classifier.check_point_classifier``).

    loglik: (m, C) per-class exact log-likelihood per known voxel of each training object under
    class models that did not see it (out-of-fold, e.g. ``oof_features.npz`` of
    ``beo-eval --scans``: ``features[:, :, 0]``); descriptors: (m, 2) finite side-normal
    descriptors; y: (m,) labels. A standardised logistic regression on the C + 2 inputs
    (``classifier_training.fit_logistic``); ``unknown_threshold`` from
    ``classifier_training.loglik_bounds`` at 6 MADs (the shipped ``tabletop_32`` 'points'
    classifier was measured with it).
    Returns dict(mean, scale, coef (C, C+2), intercept (C,), unknown_threshold (C,)).
    """
    from .classifier_training import fit_logistic, loglik_bounds
    L = np.asarray(loglik, dtype=np.float64).reshape(len(y), n_classes)
    D = np.asarray(descriptors, dtype=np.float64).reshape(len(y), -1)
    y = np.asarray(y)
    if not (np.isfinite(L).all() and np.isfinite(D).all()):
        raise ValueError('point classifier inputs contain NaN or Inf (undefined descriptors?)')
    return dict(fit_logistic(np.hstack([L, D]), y, n_classes, C),
                unknown_threshold=loglik_bounds(L, y, n_classes, mads=6.0))


def point_classifier_from_oof(oof_path, objs, C=1.0):
    """Train the 'points' classifier on every object of ``objs`` (:class:`ScanObjects`) from the
    out-of-fold features of a leave-one-scene-out run (``oof_features.npz`` of
    ``beo-eval --scans``, rows matched by scene and object id; every object must be there; best
    from a ``--from-points`` run, whose features come from ``estimate_points`` like in use) and
    the objects' side-normal descriptors (recomputed from their points).
    Returns (classifier dict, info dict)."""
    with np.load(oof_path, allow_pickle=False) as z:
        F = np.asarray(z['features'], dtype=np.float64)
        rows = {(str(s), int(o)): i for i, (s, o) in enumerate(zip(z['scenes'], z['object_ids']))}
        classes = [str(c) for c in z['classes']]
        source = str(z['grid_source']) if 'grid_source' in z.files else 'grid'
    if classes != list(objs.names):
        raise ValueError(f'{oof_path}: classes {classes} differ from the scans {objs.names}')
    missing = [f'{s}/{o}' for s, o in zip(objs.scenes, objs.object_ids)
               if (str(s), int(o)) not in rows]
    if missing:
        raise ValueError(f'{oof_path}: no out-of-fold features for {len(missing)} objects '
                         f'({", ".join(missing[:5])}...)')
    idx = [rows[(str(s), int(o))] for s, o in zip(objs.scenes, objs.object_ids)]
    L = F[idx][:, :, 0]
    D = scan_point_descriptors(objs)
    bad = ~np.isfinite(D).all(axis=1)
    if bad.any():
        raise ValueError(f'side-normal descriptors undefined for {int(bad.sum())} objects')
    clf = train_point_classifier(L, D, objs.y, len(objs.names), C)
    info = dict(point_classifier=dict(
        oof_features=str(oof_path), oof_grid_source=source, C=float(C),
        n_objects=int(len(objs)),
        inputs='per-class loglik (out-of-fold, leave-one-scene-out) + r4, frac10'))
    return clf, info


def fit_scan_models(objs, k, max_iter, mirror=True, congeal=False, verbose=False):
    """One VBPCA class model per class of a :class:`ScanObjects`, the unknown voxels as missing
    data: ``mirror`` appends the mirror image of every grid (:func:`mirror_augment`),
    ``congeal`` yaw-aligns them within each class. -> (list of ClassModel, training grids)."""
    from .training import fit_class_models
    X, y, M = objs.X, objs.y, objs.masks
    if mirror:
        X, y, M = mirror_augment(X, y, M, objs.spec.size)
    if congeal:
        from .congeal import congeal_classes
        X, M = congeal_classes(X, y, objs.spec.size, masks=M, verbose=verbose)
    return fit_class_models(X, y, objs.names, objs.spec, k, M, max_iter=max_iter), int(len(X))


def train_scan_bank(paths, scan_classes=DEFAULT_SCAN_CLASSES, grid=32, voxel_size=0.5 / 32,
                    k=8, max_iter=200, mirror=True, congeal=False, verbose=False,
                    point_classifier=None, point_C=1.0):
    """Class models from labelled scans, with the maximum-likelihood class rule (no classifier),
    or with a 'points' classifier for ``estimate_points`` (``point_classifier``: the
    ``oof_features.npz`` of a leave-one-scene-out ``beo-eval --scans`` run with the same
    settings, see :func:`point_classifier_from_oof`; ``estimate(grid)`` keeps the
    maximum-likelihood rule).

    The objects are voxelized as in :func:`load_scan_objects`, ``mirror`` appends the mirror image
    of every grid (:func:`mirror_augment`), ``congeal`` yaw-aligns them within each class, and one
    VBPCA model per class is fitted with the unknown voxels as missing data. These are the
    settings the leave-one-scene-out evaluation (``beo-eval --scans``) measures.
    """
    import time
    from .bank import ModelBank
    from .training import OCCUPANCY_MIN_NOISE_VARIANCE
    t0 = time.time()
    paths = list(paths)   # a generator would be consumed by load_scan_objects (manifest inputs)
    s = load_scan_objects(paths, scan_classes, grid, voxel_size, verbose)
    classifier = extra = None
    if point_classifier is not None:  # before the fit: a bad npz fails fast
        clf, extra = point_classifier_from_oof(point_classifier, s, point_C)
        classifier = {'points': clf}
    models, n_grids = fit_scan_models(s, k, max_iter, mirror, congeal, verbose)
    info = dict(inputs=[str(p) for p in paths], scan_classes=str(scan_classes), k=k,
                min_noise_variance=OCCUPANCY_MIN_NOISE_VARIANCE, max_iter=max_iter,
                mirror=bool(mirror), congeal=bool(congeal),
                n_objects=int(len(s)), n_training_grids=n_grids, classifier_views=0,
                rule='maximum likelihood', fit_seconds=round(time.time() - t0, 1))
    if classifier is not None:
        info.update(extra, rule="estimate_points: 'points' classifier (loglik + side-normal "
                                'descriptors); estimate(grid): maximum likelihood')
    return ModelBank(models, s.spec, classifier, info)
