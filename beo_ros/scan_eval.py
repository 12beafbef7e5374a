"""Leave-one-scene-out evaluation of class models learned from real partial tabletop scans.

    python -m beo_ros.scan_eval --scans /work/shared/data/osd/learn/*.pcd --out eval_tabletop
    beo-eval --scans learn*.pcd --out DIR [--k 8 --max-iter 40 --no-congeal]

For every scene: refit the class models (VBPCA with the unknown voxels as missing data, yaw
congealed within each class) on the objects of all *other* scenes, then estimate each held-out
object from its labelled grid with the full yaw search and classify it by the class whose model
explains it best (the paper's maximum-likelihood rule). Every held-out object's full (C, F)
features under the models fitted without its scene (out-of-fold features) are saved to
``oof_features.npz``; on them, logistic-regression rules (all C x F features, or the F
differences of two classes; C = 0.1, 1) are compared with the maximum-likelihood rule by a
second-level leave-one-scene-out (``summary['classifier_cv']``), and so is the shipped tabletop
rule, the 'points' classifier (``points_C1``: the C per-class log-likelihoods + the side-normal
descriptors r4, frac10 of the object's raw points, :mod:`beo_ros.core.normals`; the descriptors
are saved in ``oof_features.npz`` as ``point_descriptors``). Caveat of that second level:
the training rows' features came from models that had seen the held-out scene (not nested).
``--from-points``: every held-out object is estimated from its raw camera-frame points with
``bank.estimate_points`` (the deployment path: its own grid without the table floor and the
occluders of the training grid) instead of ``bank.estimate(grid)``; its out-of-fold features are
then the ones a 'points' classifier sees in use (``beo-train --point-classifier`` takes that
``oof_features.npz``).
Reported: accuracy, confusion, and for boxes the yaw
consistency: the estimated yaw against the box's own edge direction from its points (minimum-area
rectangle of the horizontal footprint), modulo 90 degrees, as a circular spread over all boxes.
Writes ``scan_eval.json`` and ``scan_completions.png`` (input points vs completed voxels).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .cli import ArgumentParser, complete_files, count, interruptible, number
from .core.bank import YAW_STEP_RANGE_DEG
from .core.training import check_grid_size


def add_arguments(ap):
    ap.add_argument('--scans', nargs='+', required=True, help='labelled OSD PCD scenes')
    ap.add_argument('--scan-classes', default='box:0-16,cylinder:33-44',
                    help='class:scene ranges, by the number in learnN.pcd')
    # beo-eval's own default: python -m beo_ros.scan_eval --scans ... writes where beo-eval
    # --scans ... does
    ap.add_argument('--out', default='beo_eval_out',
                    help='directory for JSON and PNG (default: %(default)s)')
    ap.add_argument('--k', type=count(1), default=8, help='upper bound on components per class')
    ap.add_argument('--max-iter', type=count(1), default=40, help='VBPCA iterations per refit')
    ap.add_argument('--no-congeal', dest='congeal', action='store_false',
                    help='do not yaw-align the training objects within each class')
    ap.add_argument('--no-mirror', dest='mirror', action='store_false',
                    help='do not add the mirror image (y flip) of every training grid')
    ap.add_argument('--voxel-size', type=number(0, None, lo_open=True), default=0.5 / 32,
                    help='metres per voxel')
    ap.add_argument('--grid', type=count(4, 256), default=32, help='voxels per grid side (even)')
    ap.add_argument('--yaw-step', type=number(*YAW_STEP_RANGE_DEG), default=2.0,
                    help='yaw search step (degrees, %g .. %g)' % YAW_STEP_RANGE_DEG)
    ap.add_argument('--scenes', type=count(0), default=0,
                    help='hold out only this many scenes (spread over the list; 0: all)')
    ap.add_argument('--scene-folds', type=int, default=0,
                    help='hold out groups of scenes: this many folds, every scene held out once '
                         '(0, or as many as the scenes or more: one fold per scene, '
                         'leave-one-scene-out)')
    ap.add_argument('--figures', type=count(0), default=4, help='objects drawn in the PNG')
    ap.add_argument('--from-points', action='store_true',
                    help='estimate every held-out object from its raw camera-frame points with '
                         'bank.estimate_points (the deployment path: its own grid, no table '
                         'floor, no occluders) instead of its training grid; the out-of-fold '
                         "features then fit what a 'points' classifier sees in use")
    return ap


def footprint_angle(points_grid) -> float:
    """Edge direction (radians, in [0, pi/2)) of the minimum-area rectangle around the horizontal
    footprint of points given in grid index coordinates."""
    xy = np.asarray(points_grid)[:, :2]
    xy = xy - xy.mean(axis=0)
    a = np.deg2rad(np.arange(0.0, 90.0, 0.5))
    c, s = np.cos(a), np.sin(a)
    u = xy[:, :1] * c + xy[:, 1:] * s
    v = -xy[:, :1] * s + xy[:, 1:] * c
    area = np.ptp(u, axis=0) * np.ptp(v, axis=0)
    return float(a[np.argmin(area)])


def circular_spread_deg(angles, period_deg=90.0):
    """(circular mean, circular std) in degrees of angles (radians) modulo ``period_deg``."""
    k = 2 * np.pi / np.deg2rad(period_deg)
    z = np.exp(1j * k * np.asarray(angles)).mean()
    r = max(abs(z), 1e-12)
    mean = np.rad2deg(np.angle(z) / k) % period_deg
    return float(mean), float(np.rad2deg(np.sqrt(-2 * np.log(r)) / k))


def fit_models(objs, k, max_iter, congeal=True, mirror=False):
    """Class models (ModelBank without classifier) from ScanObjects, fitted as
    ``beo-train --scans`` fits them (:func:`beo_ros.core.scan_training.fit_scan_models`)."""
    from .core.bank import ModelBank
    from .core.scan_training import fit_scan_models
    return ModelBank(fit_scan_models(objs, k, max_iter, mirror, congeal)[0], objs.spec)


CLASSIFIER_VARIANTS = (('all', 0.1), ('all', 1.0), ('diff', 0.1), ('diff', 1.0))


def classifier_design(F, kind='all'):
    """Classifier input rows from out-of-fold features F (m, C, nf).

    ``kind``: 'all' (the C * nf features, the ``ModelBank`` classifier input) or 'diff' (the
    nf differences class 0 minus class 1; two classes only).
    """
    F = np.asarray(F, dtype=np.float64)
    if F.ndim != 3:
        raise ValueError(f'features must be (objects, classes, features), got {F.shape}')
    if kind == 'all':
        return F.reshape(len(F), -1)
    if kind == 'diff':
        if F.shape[1] != 2:
            raise ValueError(f"'diff' features need exactly 2 classes, got {F.shape[1]}")
        return F[:, 0] - F[:, 1]
    raise ValueError(f"unknown classifier input {kind!r} (use 'all' or 'diff')")


def scene_cv_predictions(F, y, groups, kind='all', C=1.0):
    """Second-level leave-one-group-out predictions of a standardised logistic regression.

    F: (m, C, nf) out-of-fold features (each object's features from class models fitted
    without its scene); y: (m,) labels; groups: (m,) scene ids. Every object's class comes from
    a logistic regression fitted on the objects of the *other* groups only (features
    standardised with their mean and std). For ``kind='all'`` this is
    :func:`beo_ros.core.classifier_training.train_classifier` (the shipped classifier format)
    and the 'unknown' check of ``ModelBank.classify_features`` is applied too.
    Returns (pred (m,), unknown (m,) bool).
    """
    from .core.classifier import classifier_probabilities
    from .core.classifier_training import train_classifier
    F = np.asarray(F, dtype=np.float64)
    y = np.asarray(y)
    groups = np.asarray(groups)
    Z = classifier_design(F, kind)
    pred = np.empty(len(y), dtype=int)
    unknown = np.zeros(len(y), dtype=bool)
    for g in dict.fromkeys(groups.tolist()):
        te = groups == g
        tr = ~te
        if len(np.unique(y[tr])) < 2:        # nothing to discriminate: the only class seen
            pred[te] = y[tr][0] if tr.any() else 0
            continue
        if kind == 'all':
            clf = train_classifier(Z[tr], y[tr], F.shape[1], C)
            p, unknown[te] = classifier_probabilities(clf, Z[te], F[te, :, 0])
            pred[te] = np.argmax(p, axis=1)
        else:
            pred[te] = _logistic_predict(Z[tr], y[tr], Z[te], F.shape[1], C)
    return pred, unknown


def _logistic_predict(Z_train, y_train, Z_test, n_classes, C):
    from .core.classifier_training import fit_logistic
    clf = fit_logistic(Z_train, y_train, n_classes, C)
    z = (Z_test - clf['mean']) / clf['scale']
    return np.argmax(z @ clf['coef'].T + clf['intercept'], axis=1)


def scene_cv_logistic(Z, y, groups, C=1.0):
    """Leave-one-group-out predictions (m,) of a standardised logistic regression on any input
    rows Z (m, n_in) (no 'unknown' check): every row's class from a regression fitted on the
    other groups' rows only; when those hold a single class, that class (as
    :func:`scene_cv_predictions`). ValueError for fewer than 2 groups."""
    Z = np.asarray(Z, dtype=np.float64).reshape(len(y), -1)
    y = np.asarray(y)
    groups = np.asarray(groups)
    if len(np.unique(groups)) < 2:
        raise ValueError(f'leave-one-group-out needs rows of at least 2 groups (scenes), got '
                         f'{len(np.unique(groups))}')
    n_classes = int(y.max()) + 1
    pred = np.empty(len(y), dtype=int)
    for g in dict.fromkeys(groups.tolist()):
        te = groups == g
        if len(np.unique(y[~te])) < 2:   # nothing to discriminate: the only class seen
            pred[te] = y[~te][0]
            continue
        pred[te] = _logistic_predict(Z[~te], y[~te], Z[te], n_classes, C)
    return pred


POINT_CLASSIFIER_CS = (0.1, 1.0)


def scene_cv_point_predictions(F, D, y, groups, C=1.0):
    """Second-level leave-one-group-out predictions of the 'points' classifier.

    F: (m, C, nf) out-of-fold features (only ``F[:, :, 0]``, the log-likelihood, is used);
    D: (m, 2) side-normal descriptors; every object's class from
    :func:`beo_ros.core.scan_training.train_point_classifier` fitted on the other groups'
    objects, applied with ``classifier.apply_point_classifier`` (the code
    ``ModelBank.estimate_points`` runs, 'unknown' check included). Objects with undefined (NaN)
    descriptors take the maximum-likelihood class, as ``estimate_points`` falls back (and are
    left out of the fits).
    Returns (pred (m,), unknown (m,) bool).
    """
    from .core.classifier import apply_point_classifier
    from .core.scan_training import train_point_classifier
    F = np.asarray(F, dtype=np.float64)
    L = F[:, :, 0]
    D = np.asarray(D, dtype=np.float64).reshape(len(F), -1)
    y = np.asarray(y)
    groups = np.asarray(groups)
    ok = np.isfinite(D).all(axis=1)
    pred = np.argmax(L, axis=1)
    unknown = np.zeros(len(y), dtype=bool)
    for g in dict.fromkeys(groups.tolist()):
        te = (groups == g) & ok
        tr = (groups != g) & ok
        if not te.any():
            continue
        if len(np.unique(y[tr])) < 2:
            pred[te] = y[tr][0] if tr.any() else pred[te]
            continue
        clf = train_point_classifier(L[tr], D[tr], y[tr], F.shape[1], C)
        p, unknown[te] = apply_point_classifier(clf, L[te], D[te])
        pred[te] = np.argmax(p, axis=1)
    return pred, unknown


def _rule_report(y, pred, n_classes, unknown=None):
    unknown = np.zeros(len(y), dtype=bool) if unknown is None else np.asarray(unknown)
    ok = (pred == y) & ~unknown
    conf = np.zeros((n_classes, n_classes), dtype=int)
    np.add.at(conf, (y[~unknown], pred[~unknown]), 1)
    return dict(accuracy=round(float(np.mean(ok)), 4), n_correct=int(ok.sum()),
                n_unknown=int(unknown.sum()), confusion=conf.tolist(),
                accuracy_without_unknown_check=round(float(np.mean(pred == y)), 4))


def classifier_comparison(F, y, groups, names=None, variants=CLASSIFIER_VARIANTS,
                          point_descriptors=None):
    """The maximum-likelihood rule (argmax of the log-likelihood feature) against the
    scene-grouped cross-validated logistic-regression variants, on the same out-of-fold features
    (with ``point_descriptors`` (m, 2) also the 'points' classifier, ``points_C<C>``, see
    :func:`scene_cv_point_predictions`).

    Returns {'max_likelihood': report, 'lr_<kind>_C<C>': report, ...}; a report holds accuracy
    (an 'unknown' answer counts as wrong), n_correct, n_unknown, the confusion of the known
    answers and the objects that are wrong (indices).
    """
    F = np.asarray(F, dtype=np.float64)
    y = np.asarray(y)
    n_classes = F.shape[1]
    ml = np.argmax(F[:, :, 0], axis=1)
    out = {'max_likelihood': dict(_rule_report(y, ml, n_classes),
                                  wrong=np.flatnonzero(ml != y).tolist())}
    for kind, C in variants:
        if kind == 'diff' and n_classes != 2:
            continue
        pred, unknown = scene_cv_predictions(F, y, groups, kind, C)
        out[f'lr_{kind}_C{C:g}'] = dict(_rule_report(y, pred, n_classes, unknown),
                                        wrong=np.flatnonzero((pred != y) | unknown).tolist())
    if point_descriptors is not None:
        for C in POINT_CLASSIFIER_CS:
            pred, unknown = scene_cv_point_predictions(F, point_descriptors, y, groups, C)
            out[f'points_C{C:g}'] = dict(
                _rule_report(y, pred, n_classes, unknown),
                wrong=np.flatnonzero((pred != y) | unknown).tolist(),
                n_descriptors_undefined=int((~np.isfinite(point_descriptors).all(axis=1)).sum()))
    return out


def plot_completions(path, items, spec):
    """items: list of (title, points_grid (n, 3), completion (N, N, N)[, class index])."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n = spec.size
    fig, axes = plt.subplots(len(items), 3, figsize=(11, 3.4 * len(items)), squeeze=False)
    for row, (title, pg, comp, *_) in zip(axes, items):
        idx = np.argwhere(comp >= 0.5)
        p = comp[comp >= 0.5]
        for ax, (a, b), lab in zip(row, [(0, 2), (1, 2), (0, 1)],
                                   ['side (x-z)', 'side (y-z)', 'top (x-y)']):
            sc = ax.scatter(idx[:, a], idx[:, b], c=p, cmap='viridis', vmin=0.5, vmax=1.0,
                            s=14, marker='s', alpha=0.35, linewidths=0)
            ax.scatter(pg[:, a], pg[:, b], s=0.3, c='red', alpha=0.5)
            ax.set_xlim(-0.5, n - 0.5)
            ax.set_ylim(-0.5, n - 0.5)
            ax.set_aspect('equal')
            ax.set_title(f'{title}: {lab}', fontsize=8, parse_math=False)   # '$' in a name
        fig.colorbar(sc, ax=row[-1], fraction=0.046, label='P(occupied)')
    fig.suptitle('red: observed points; squares: completed voxels (P >= 0.5), grid index coords')
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run(args) -> dict:
    """The evaluation of parsed ``args``: writes scan_eval.json (and the PNG); the summary."""
    from .core.scan_training import load_scan_objects
    from .cli import output_dir
    t_start = time.time()
    objs = load_scan_objects(args.scans, args.scan_classes, args.grid, args.voxel_size)
    # --out is made once the scans have loaded; a failure or Ctrl-C leaves no empty one behind
    with output_dir(args.out) as out:
        return _run(args, objs, out, t_start)


def _run(args, objs, out, t_start):
    """The folds of :func:`run` on the ScanObjects ``objs``: writes oof_features.npz,
    scan_eval.json (and the PNG) in ``out``, prints the table; the summary."""
    scenes, groups = _scene_groups(args, objs.scenes)
    _check_groups(args, objs, groups)
    recs, figs, oof = [], [], []
    for si, group in enumerate(groups):
        n_held, t_fit = _evaluate_fold(args, objs, group, recs, figs, oof)
        acc = np.mean([r['correct'] for r in recs])
        print(f'[{si + 1}/{len(groups)}] {"+".join(group)}: {n_held} objects, refit '
              f'{t_fit:.0f} s, running accuracy {acc:.3f}', file=sys.stderr)
    summary = _summary(args, objs.names, recs, len(scenes), len(groups))
    # a failure or Ctrl-C in the second-level comparison left oof_features.npz alone in --out
    with complete_files(out, ('oof_features.npz', 'scan_eval.json',
                              'scan_completions.png')) as tmp:
        idx, F, D = _save_oof_features(args, objs, oof, tmp['oof_features.npz'], summary)
        if len(groups) > 1:
            summary['classifier_cv'] = _classifier_cv(objs, idx, F, D)
        summary['seconds'] = round(time.time() - t_start, 1)
        tmp['scan_eval.json'].write_text(json.dumps(dict(summary=summary, objects=recs),
                                                    indent=2) + '\n')
        if figs:
            plot_completions(tmp['scan_completions.png'], figs, objs.spec)
    print_table(summary)
    return summary


def _scene_groups(args, object_scenes):
    """(scenes, groups): the scenes in order of appearance (only --scenes of them, spread over
    the list, if given) and the groups of them held out together (--scene-folds)."""
    scenes = list(dict.fromkeys(object_scenes))
    if args.scenes and args.scenes < len(scenes):
        scenes = [scenes[i] for i in np.linspace(0, len(scenes) - 1, args.scenes).astype(int)]
    groups = [[s] for s in scenes]
    if args.scene_folds and args.scene_folds < len(scenes):
        groups = [scenes[f::args.scene_folds] for f in range(args.scene_folds)]
    return scenes, groups


def _check_groups(args, objs, groups):
    """ValueError, before any fold is fitted, when holding out one of ``groups`` leaves a class
    fewer than the 2 training grids a class model needs (its objects, and with --mirror
    their mirror images, in the other scenes)."""
    for group in groups:
        kept = np.bincount(objs.y[~np.isin(objs.scenes, group)], minlength=len(objs.names))
        for name, m in zip(objs.names, kept):
            if m * (2 if args.mirror else 1) < 2:
                raise ValueError(
                    f'holding out {"+".join(group)} leaves class {name!r} {m} training '
                    f'object(s) in the other scenes; a class model needs 2 grids'
                    f'{" (an object and its mirror image)" if args.mirror else ""}: give the '
                    'class more scenes')


def _evaluate_fold(args, objs, group, recs, figs, oof):
    """Refit the class models without the scenes ``group`` and estimate their objects:
    appends to recs (records), figs (PNG items, up to --figures) and oof ((index, (C, F)
    features)); (held-out objects, refit seconds)."""
    names = objs.names
    held = np.isin(objs.scenes, group)
    te = np.flatnonzero(held)
    t0 = time.time()
    bank = fit_models(objs.subset(~held), args.k, args.max_iter, args.congeal, args.mirror)
    t_fit = time.time() - t0
    for i in te:
        rec, feats, pg, est = _evaluate_object(args, objs, bank, i)
        if feats is not None:
            oof.append((i, feats))
        recs.append(rec)
        wanted = len(figs) < args.figures and (
            sum(r[3] == objs.y[i] for r in figs) < max(
                1, args.figures // len(names)))
        if wanted:
            title = f'{names[objs.y[i]]} {objs.scenes[i]}/{objs.object_ids[i]} -> {est.label}'
            figs.append((title, pg, est.completion, objs.y[i]))
    return len(te), t_fit


def _evaluate_object(args, objs, bank, i):
    """Estimate object i with ``bank`` (from its grid, or its points with --from-points):
    (record, (C, F) features or None, points (n, 3) in grid index coordinates, estimate)."""
    from .core.inference import FEATURE_NAMES
    names = objs.names
    if args.from_points:
        try:
            est = bank.estimate_points(objs.points[i], sensor_origin=(0.0, 0.0, 0.0),
                                       up=objs.ups[i], yaw_step_deg=args.yaw_step)
            T = est.grid_to_input
        except ValueError as e:   # e.g. fewer than 10 points left after the outlier removal
            # nothing voxelized: the estimate of an all-unknown grid ('unknown', counted wrong)
            est = bank.estimate(np.full(objs.spec.shape, -1, dtype=np.int8))
            est.classifier_note = f'estimate_points refused its points: {e}'
            T = objs.grid_to_input[i]
    else:
        est = bank.estimate(objs.grids[i], yaw_step_deg=args.yaw_step)
        T = objs.grid_to_input[i]
    # 'unknown': no occupied voxel in the grid (no features either), counted wrong
    pred = names.index(est.label) if est.label in names else -1
    pts = objs.points[i]
    pg = (np.linalg.inv(T) @ np.c_[pts, np.ones(len(pts))].T).T[:, :3]
    h = pts @ objs.ups[i] + objs.plane_d[i]
    ext = np.ptp(pg, axis=0) * objs.spec.voxel_size
    # the object's full (C, F) features under the models fitted without its scene
    # (out-of-fold): bank.features(grid) with the stage-1 search step of estimate(),
    # i.e. exactly the features its class decision used
    feats = None if est.features is None else np.asarray(est.features, dtype=np.float64)
    if feats is None:
        print(f'{objs.scenes[i]}/{objs.object_ids[i]}: {est.classifier_note}; counted '
              'wrong, left out of the out-of-fold features', file=sys.stderr)
    rec = dict(scene=str(objs.scenes[i]), object=int(objs.object_ids[i]),
               true=names[objs.y[i]], pred=est.label, correct=bool(pred == objs.y[i]),
               n_points=int(len(pts)), extent_cm=[round(float(e) * 100, 1) for e in ext],
               above_table_cm=round(float(h.min()) * 100, 1),
               n_occupied=int((est.grid == 1).sum()),
               unknown_fraction=round(float((est.grid < 0).mean()), 4),
               features=None if feats is None else {
                   names[c]: dict(zip(FEATURE_NAMES, np.round(feats[c], 4).tolist()))
                   for c in range(len(names))},
               scores={k: round(v, 4) for k, v in est.scores.items()},
               yaw_deg=round(float(np.rad2deg(est.yaw)), 1),
               footprint_deg=round(float(np.rad2deg(footprint_angle(pg))), 1),
               seconds=round(est.timings['total'], 3))
    return rec, feats, pg, est


def _summary(args, names, recs, n_scenes, n_folds):
    """The summary of the records: protocol, accuracy, confusion (and the box yaw)."""
    y_true = np.array([names.index(r['true']) for r in recs])
    y_pred = np.array([names.index(r['pred']) if r['pred'] in names else -1 for r in recs])
    conf = np.zeros((len(names), len(names)), dtype=int)   # of the known answers
    np.add.at(conf, (y_true[y_pred >= 0], y_pred[y_pred >= 0]), 1)
    summary = dict(
        protocol=('leave-one-scene-out' if n_folds == n_scenes else
                  f'{n_folds}-fold leave-scenes-out (every scene held out once)') +
                 '; class models refit without the held-out scenes '
                 f'(k={args.k}, max_iter={args.max_iter}, congeal={args.congeal}, '
                 f'mirror={args.mirror}); '
                 'max-likelihood class, full yaw search; held-out objects estimated from ' +
                 ('their raw points (estimate_points)' if args.from_points else
                  'their training grids (estimate)'),
        n_objects=len(recs), n_scenes=n_scenes, n_folds=n_folds, classes=names,
        accuracy=round(float(np.mean(y_true == y_pred)), 4),
        per_class_accuracy={n: round(float(np.mean(y_pred[y_true == c] == c)), 4)
                            for c, n in enumerate(names) if (y_true == c).any()},
        confusion=conf.tolist(), n_unknown=int(np.sum(y_pred < 0)),
        mean_estimate_seconds=round(float(np.mean([r['seconds'] for r in recs])), 3))
    b = [r for r in recs if r['true'] == 'box'] if 'box' in names else []
    if b:
        summary['box_yaw'] = _box_yaw(b)
    return summary


def _box_yaw(b):
    """The yaw consistency of the box records ``b``: estimated yaw against the footprint edge,
    modulo 90 degrees."""
    rel = np.deg2rad([r['footprint_deg'] - r['yaw_deg'] for r in b])
    mean, std = circular_spread_deg(rel, 90.0)
    dev = (np.rad2deg(rel) - mean + 45.0) % 90.0 - 45.0
    return dict(n=len(b), offset_mod90_deg=round(mean, 1), circular_std_mod90_deg=round(std, 1),
                median_abs_dev_deg=round(float(np.median(np.abs(dev))), 1),
                within_10_deg=round(float(np.mean(np.abs(dev) <= 10)), 4))


def _save_oof_features(args, objs, oof, path, summary):
    """Write ``path`` (oof_features.npz: the out-of-fold features and the side-normal
    descriptors of the objects that have features) and note the descriptors' time in summary;
    (idx (m,), F (m, C, F), D (m, 2))."""
    from .core.inference import FEATURE_NAMES
    from .core.scan_training import scan_point_descriptors
    idx = np.array([i for i, _ in oof], dtype=int)
    F = np.array([f for _, f in oof], dtype=np.float64)
    # side-normal descriptors of the raw points (no fitting: the same under any fold)
    t_d = time.perf_counter()
    D = scan_point_descriptors(objs.subset(idx))
    summary['point_descriptor_ms_mean'] = round(
        1e3 * (time.perf_counter() - t_d) / max(len(idx), 1), 2)
    np.savez_compressed(path, features=F, y=objs.y[idx],
                        scenes=objs.scenes[idx], object_ids=objs.object_ids[idx],
                        classes=np.array(objs.names), feature_names=np.array(FEATURE_NAMES),
                        point_descriptors=D,
                        grid_source=np.array('estimate_points' if args.from_points else 'grid'))
    return idx, F, D


def _classifier_cv(objs, idx, F, D):
    """summary['classifier_cv']: the second-level comparison of the rules on the out-of-fold
    features F of the objects idx (wrong objects named scene/object)."""
    comp = classifier_comparison(F, objs.y[idx], objs.scenes[idx], objs.names,
                                 point_descriptors=D)
    for rep in comp.values():
        rep['wrong'] = [f'{objs.scenes[idx[j]]}/{objs.object_ids[idx[j]]}'
                        for j in rep['wrong']]
    return dict(
        protocol='second level, leave-one-scene-out over the out-of-fold features: every '
                 "object's class from a logistic regression (standardised, features of the "
                 'other scenes) that never saw its scene; lr_all: the C x F features '
                 "(with the 'unknown' check, counted wrong), lr_diff: the F differences "
                 "class 0 minus class 1; points: the C loglik + the raw points' side-normal "
                 "descriptors r4, frac10 (the shipped tabletop rule of estimate_points, "
                 "'unknown' check counted wrong); max_likelihood: argmax of loglik",
        **comp)


def print_table(s, file=None):
    print(f'{"objects":>10} {"scenes":>7} {"accuracy":>9}  per class', file=file)
    per = ', '.join(f'{k} {v:.3f}' for k, v in s['per_class_accuracy'].items())
    print(f'{s["n_objects"]:>10} {s["n_scenes"]:>7} {s["accuracy"]:>9.3f}  {per}', file=file)
    print(f'confusion (rows true {s["classes"]}): {s["confusion"]}', file=file)
    for name, rep in s.get('classifier_cv', {}).items():
        if isinstance(rep, dict):
            # of the objects with out-of-fold features (n_objects less those without any)
            n = int(np.sum(rep['confusion'])) + rep['n_unknown']
            print(f'  {name:>16}: accuracy {rep["accuracy"]:.3f} ({rep["n_correct"]}/'
                  f'{n}, {rep["n_unknown"]} unknown), confusion {rep["confusion"]}',
                  file=file)
    if 'box_yaw' in s:
        b = s['box_yaw']
        print(f'box yaw vs footprint edge (mod 90): circular std {b["circular_std_mod90_deg"]} '
              f'deg, median |dev| {b["median_abs_dev_deg"]} deg, within 10 deg '
              f'{b["within_10_deg"]:.2f} (n={b["n"]})', file=file)


@interruptible('beo-eval')
def main(argv=None):
    ap = add_arguments(ArgumentParser(
        prog='beo-eval --scans', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter))
    args = ap.parse_args(argv)
    if args.scene_folds == 1 or args.scene_folds < 0:
        ap.error(f'--scene-folds must be 0 (leave one scene out) or >= 2, got {args.scene_folds}')
    try:
        check_grid_size(args.grid)
    except ValueError as e:
        ap.error(f'--grid: {e}')
    from .cli import out_dir_problem
    problem = out_dir_problem(Path(args.out))
    if problem:
        ap.error(f'--out {args.out}: {problem}')
    try:
        run(args)
    except BrokenPipeError:   # stdout's reader is gone: see cli.interruptible
        raise
    except (ValueError, OSError) as e:
        print(f'beo-eval: error: {e}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())
