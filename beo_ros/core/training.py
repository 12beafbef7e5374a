"""Training: per-class VBPCA models, out-of-fold classifier features, the occupancy
calibration and the orientation verifier, put together by :func:`fit_bank`. The classifier's
fitting and choice are in :mod:`classifier_training`, data loading in :mod:`datasets`; their
names are re-exported here."""
from __future__ import annotations

import os
import signal
import sys
import time
import warnings

import numpy as np

from .bank import ModelBank
from .calibration import OccupancyCalibration, calibration_sums, metrics_from_sums
from .class_model import ClassModel, coarse_noise
from .classifier import resolve_class_prior
from .classifier_training import (C_OPTIONS, CLASSIFIER_KINDS, MLP_ALPHA, MLP_HIDDEN,
                                  MLP_MAX_ITER, UNKNOWN_MADS, _check_kind,
                                  cross_validated_report, expected_calibration_error,
                                  fit_logistic, fit_mlp, loglik_bounds, select_classifier,
                                  train_classifier)
from .datasets import (drop_empty_objects, load_meshes, load_voxel_npz, mesh_class_name,
                       select_classes, training_data_hash)
from .grid import yaw_error
from .model_files import _settings_reason, check_class_names
from .shape import shape_descriptors
from .synthetic import random_partial_view
from .verifier import NO_VERIFIER_HINT, TURNS, OrientationVerifier, turned_features
from .vbpca import VBPCA

__all__ = [
    # defined here
    'progress_bar', 'OCCUPANCY_MIN_NOISE_VARIANCE', 'fit_class_models', 'check_class_counts',
    'stratified_folds', 'VERIFIER_CHUNK', 'verifier_training_set', 'fit_verifier', 'view_features',
    'fit_occupancy_calibration', 'check_grid_size', 'fit_bank',
    # re-exported from classifier_training
    'MLP_HIDDEN', 'MLP_ALPHA', 'MLP_MAX_ITER', 'CLASSIFIER_KINDS', 'cross_validated_report',
    'C_OPTIONS', 'UNKNOWN_MADS', 'expected_calibration_error', 'loglik_bounds', 'fit_logistic',
    'fit_mlp', 'train_classifier', 'select_classifier',
    # re-exported from datasets
    'load_voxel_npz', 'drop_empty_objects', 'training_data_hash', 'select_classes',
    'mesh_class_name', 'load_meshes',
]

# seconds between the progress lines of a loop when stderr is a file or a pipe
PROGRESS_LINE_S = 30.0

# Floor of a class model's noise variance. Occupancies are in [0, 1] and no voxelisation is
# exact to better than about 1% per voxel (std 0.01, so v >= 1e-4); without it a class of a
# few near noise-free objects fits v ~ 1e-8 and is absurdly sure of itself, so that its
# likelihood against another such class hangs on numerical noise. The shipped models fit
# v = 5e-4 (tabletop_32) to 0.04 (modelnet10_32), above it: their training is unchanged.
OCCUPANCY_MIN_NOISE_VARIANCE = 1e-4


def progress_bar(it, desc, total=None, disable=False):
    """``it``, with progress on stderr: a tqdm bar on a terminal; in a file or a pipe (a log),
    where a bar's carriage returns and cursor moves are garbage, whole lines ``DESC: i/total``
    at most every :data:`PROGRESS_LINE_S` seconds and ``DESC: total/total in T s`` at the end."""
    if disable:
        return it
    try:
        tty = sys.stderr.isatty()
    except (AttributeError, ValueError):   # no stderr (None), or a closed one
        return it
    if not tty:
        return _progress_lines(it, desc, len(it) if total is None and hasattr(it, '__len__')
                               else total)
    try:
        from tqdm import tqdm
        return tqdm(it, desc=desc, total=total, file=sys.stderr, leave=False)
    except ImportError:  # pragma: no cover - tqdm is a dependency
        return it


def _progress_lines(it, desc, total):
    """``progress_bar`` in a file or a pipe: see there."""
    t0 = last = time.monotonic()
    of = '' if total is None else f'/{total}'
    i = 0
    for i, item in enumerate(it, 1):
        yield item
        if time.monotonic() - last >= PROGRESS_LINE_S:
            last = time.monotonic()
            print(f'{desc}: {i}{of}', file=sys.stderr, flush=True)
    print(f'{desc}: {i}{of} in {time.monotonic() - t0:.1f} s', file=sys.stderr, flush=True)


def fit_class_models(X, y, names, spec, k=20, masks=None, max_iter=200, tol=1e-5,
                     min_noise_variance=OCCUPANCY_MIN_NOISE_VARIANCE):
    """One VBPCA ClassModel per class. X: (m, N^3) float32 in [0, 1]; masks: (m, N^3) observed;
    ``min_noise_variance``: floor of each model's noise variance (see
    ``OCCUPANCY_MIN_NOISE_VARIANCE``)."""
    models = []
    for c, name in enumerate(names):
        sel = y == c
        if sel.sum() < 2:
            raise ValueError(f'class {name!r} has {int(sel.sum())} training objects; need >= 2')
        Xc = X[sel]
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            est = VBPCA(n_components=int(min(k, sel.sum() - 1)), max_iter=max_iter, tol=tol,
                        min_noise_variance=min_noise_variance).fit(
                            Xc, mask=None if masks is None else masks[sel])
        Xf = Xc if masks is None else np.where(masks[sel], Xc, est.inverse_transform(
            est.transform(Xc, masks[sel])))
        models.append(ClassModel.from_vbpca(name, est, *coarse_noise(
            Xf.astype(np.float32), est, spec.size, min_noise_variance=min_noise_variance)))
    return models


def check_class_counts(y, names, folds=0, no_classifier='views 0', leave_out=None):
    """ValueError naming the first class of ``names`` with too few objects in labels y: a class
    model needs 2; with ``folds`` >= 2 (out-of-fold classifier features) every fold's training
    part needs 2 as well, i.e. the objects a class keeps when its biggest fold is held out
    (``no_classifier``: the caller's option that trains no classifier, ``leave_out``: its
    option that leaves a class out, if any, for the message).
    Labels that are not class indices into ``names`` are refused (a label past the names was
    left out of every model without a word, a negative one failed in numpy's bincount)."""
    y = np.asarray(y)
    if y.ndim != 1 or not np.isin(y, np.arange(len(names))).all():
        bad = sorted(set(np.unique(y).tolist()) - set(range(len(names))))[:5]
        raise ValueError(f'labels must be class indices 0..{len(names) - 1} into the '
                         f'{len(names)} class names, got {bad}')
    counts = np.bincount(y.astype(int), minlength=len(names))
    need = 2
    if folds >= 2:   # stratified_folds holds out up to ceil(m / folds) objects of m
        while need - -(-need // folds) < 2:
            need += 1
    for name, m in zip(names, counts):
        if m < need:
            why = (f'out-of-fold classifier features over {folds} folds need >= {need} per class '
                   "(each fold trains class models on the other folds' objects); "
                   + ('use 3 or more folds' if m >= 3 else
                      f'add objects, or train no classifier ({no_classifier})')) \
                if folds >= 2 and m >= 2 else ('a class model needs >= 2: add objects of it, '
                                                'or leave the class out'
                                                + (f' ({leave_out})' if leave_out else ''))
            raise ValueError(f'class {name!r} has {int(m)} training objects; {why}')


def stratified_folds(y, k, rng):
    """(m,) fold index in 0..k-1 of labels y (m,): every class dealt round-robin over the
    folds in a random order drawn from ``rng``."""
    fold = np.empty(len(y), dtype=int)
    for c in np.unique(y):
        idx = np.flatnonzero(y == c)
        fold[idx] = rng.permutation(len(idx)) % k
    return fold


# objects per chunk of the verifier's training views: every chunk has its own random stream,
# so the views do not depend on how many processes make them
VERIFIER_CHUNK = 64


def _verifier_chunk(args):
    """Verifier training rows of one chunk of objects (see ``verifier_training_set``)."""
    X, n, views, seed, chunk = args
    rng = np.random.default_rng([seed, chunk])
    F, turn, obj = [], [], []
    for i in range(len(X)):
        occ = X[i].reshape(n, n, n) > 0.5
        for _ in range(views):
            grid, yaw, _, _, _ = random_partial_view(occ, rng)
            jitter = np.deg2rad(rng.uniform(-5.0, 5.0, TURNS))
            F.append(turned_features(grid, yaw + np.arange(TURNS) * np.pi / 2 + jitter))
            turn += list(range(TURNS))
            obj += [i] * TURNS
    return np.vstack(F), np.array(turn), np.array(obj)


def _quiet_on_sigint():
    """Process-pool initializer: Ctrl-C (sent to the whole process group) ends the worker at
    once and without a traceback; the parent reports the interruption in one line."""
    signal.signal(signal.SIGINT, lambda signum, frame: os._exit(128 + signal.SIGINT))


def _kill_pool(ex):
    """Kill the processes of ProcessPoolExecutor ``ex`` at once and drop its queued work."""
    for p in list((getattr(ex, '_processes', None) or {}).values()):
        if p.is_alive():
            p.kill()
    ex.shutdown(wait=False, cancel_futures=True)


def verifier_training_set(X, n, views=6, seed=0, processes=1, verbose=False):
    """Rows for the orientation verifier from objects X (m, n^3) in their canonical pose:
    ``views`` random partial views of each (the evaluation protocol), each turned into the
    model's frame by its true yaw plus 0, 90, 180 and 270° (+- 5° of jitter).

    Returns (features (m * views * 4, 1536) float32, turn (r,), object index (r,)). The same
    for any ``processes`` (chunks of ``VERIFIER_CHUNK`` objects, each with its own stream).
    ValueError for no views or no objects (numpy's 'need at least one array to concatenate').
    """
    if not (isinstance(views, (int, np.integer)) and views >= 1):
        raise ValueError(f'verifier views must be an integer >= 1, got {views!r}')
    X = np.asarray(X)
    if X.ndim != 2 or not len(X):
        raise ValueError(f'the verifier needs objects X (m >= 1, n^3), got shape {X.shape}')
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) \
            or X.shape[1] != n ** 3:   # else numpy's 'cannot reshape' in every worker
        raise ValueError(f'the verifier needs objects X of n^3 = {n!r}^3 voxels, got shape '
                         f'{X.shape}')
    chunks = [(X[i:i + VERIFIER_CHUNK], n, views, seed, i // VERIFIER_CHUNK)
              for i in range(0, len(X), VERIFIER_CHUNK)]
    # at most a process per chunk: the pool forks all it is given at once, idle or not
    processes = min(processes, len(chunks))
    if processes > 1:
        from concurrent.futures import ProcessPoolExecutor
        ex = ProcessPoolExecutor(processes, initializer=_quiet_on_sigint)
        try:
            parts = list(progress_bar(ex.map(_verifier_chunk, chunks), 'verifier views',
                                      total=len(chunks), disable=not verbose))
        except BaseException:
            # SIGTERM to this process alone (kill PID, docker stop) or a failure: leaving a
            # 'with' block would make every chunk still queued first (minutes)
            _kill_pool(ex)
            raise
        ex.shutdown()
    else:
        parts = [_verifier_chunk(c) for c in progress_bar(chunks, 'verifier views',
                                                          disable=not verbose)]
    offsets = np.arange(len(chunks)) * VERIFIER_CHUNK
    return (np.vstack([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] + o for p, o in zip(parts, offsets)]))


def fit_verifier(X, y, n, views=6, seed=0, processes=1, verbose=False, **params):
    """An ``OrientationVerifier`` fitted on ``verifier_training_set`` rows of objects X
    (m, n^3) with class labels y (m,); ``params`` go to the verifier."""
    F, turn, obj = verifier_training_set(X, n, views, seed, processes, verbose)
    return OrientationVerifier(**params).fit(F, turn, np.asarray(y)[obj], n)


def view_features(bank, X, rng, n_views=1, complete=True):
    """Features of objects X (m, N^3) under ``bank``: complete grids at yaw 0 and random partial
    views at unknown yaw (the evaluation protocol).

    Returns (dict mode -> (feature rows (r, C*F), object index (r,), records, shape descriptors
    (r, D)), number of views skipped); a partial-view record holds, per class hypothesis, the
    yaw error (rad) and the completion IoU (C,) each. A view is skipped when it has no
    occupied voxel (the rotation can lose an object of a few voxels).
    """
    n = bank.spec.size
    out = {'complete': ([], [], [], []), 'partial': ([], [], [], [])}
    skipped = 0
    for i in range(len(X)):
        occ = X[i].reshape(n, n, n) > 0.5
        if complete:
            f, _ = bank.features(occ.astype(np.int8), yaw=0.0)
            out['complete'][0].append(f.ravel())
            out['complete'][1].append(i)
            out['complete'][2].append({})
            out['complete'][3].append(shape_descriptors(occ.astype(np.int8)))
        for _ in range(n_views):
            grid, yaw, _, _, rotated = random_partial_view(occ, rng)
            if not (grid == 1).any():
                skipped += 1
                continue
            f, per = bank.features(grid)
            # the pose refinement estimate() applies to the chosen class, here for the three
            # classes that explain the view best (the classifier is trained later)
            for c in np.argsort(-f[:, 0])[:3]:
                per[c] = bank._refine(grid, int(c), per[c])
            out['partial'][0].append(f.ravel())
            out['partial'][1].append(i)
            out['partial'][2].append(_hypothesis_quality(bank.engine, grid, per, yaw, rotated))
            out['partial'][3].append(shape_descriptors(grid))
    return {m: (np.array(a), np.array(b, dtype=int), r, np.array(d))
            for m, (a, b, r, d) in out.items() if a}, skipped


def _hypothesis_quality(engine, grid, per, yaw, rotated):
    """Yaw error and completion IoU of every class's best hypothesis for one partial view."""
    errs, ious = [], []
    for p in per:
        errs.append(float(yaw_error(p['yaw'], yaw)))
        comp = engine.to_observed(p['exact']['pred'] >= 0.5, p['yaw'], fill=False)
        comp = np.where(grid >= 0, grid == 1, comp.reshape(grid.shape))
        union = (comp | rotated).sum()
        ious.append((comp & rotated).sum() / union if union else 1.0)
    return dict(yaw_err=np.array(errs), iou=np.array(ious))


def fit_occupancy_calibration(X, y, names, spec, k=20, folds=5, seed=0, views=1,
                              classifier=None, class_prior='train', pose_components=8,
                              verbose=False, min_noise_variance=OCCUPANCY_MIN_NOISE_VARIANCE):
    """Calibrate the completion's occupancy probabilities on out-of-fold views.

    For each of ``folds`` stratified folds (those of ``fit_bank`` with the same ``seed``),
    class models fitted without the fold complete ``views`` random protocol views of each of
    its whole objects X (m, N^3), classified by ``classifier`` (as the bank will be); the
    model probability and the truth of every unknown voxel, in the observed frame, go into an
    :class:`OccupancyCalibration`. The views use their own random stream, so the classifier's
    out-of-fold views do not change.

    Returns (calibration, report): the report has the views counted, the number of knots,
    the Brier score, log loss and 10-bin ECE of the model probabilities ('raw'), and the
    Brier score and log loss of the calibrated ones ('calibrated_in_sample': on the same
    voxels, each at its bin's mean probability; held-out figures come from ``beo-eval``).
    ``min_noise_variance``: that of the class models (``fit_class_models``).
    """
    if not (isinstance(views, (int, np.integer)) and views >= 1):
        raise ValueError(f'views must be an integer >= 1, got {views!r}')
    if not (isinstance(folds, (int, np.integer)) and folds >= 2):
        raise ValueError(f'the occupancy calibration needs folds >= 2, got {folds!r}')
    X = np.asarray(X, dtype=np.float32)
    y = np.asarray(y)
    n = spec.size
    fold = stratified_folds(y, folds, np.random.default_rng(seed))
    rng = np.random.default_rng([seed, 1])
    cal = OccupancyCalibration()
    raw, n_views = [], 0
    for f in progress_bar(range(folds), 'occupancy calibration', disable=not verbose):
        # the class models of fit_bank's own fold f again: a few seconds, where keeping all
        # folds' models from its classifier loop would hold ~130 MB for ModelNet10
        sub = ModelBank(fit_class_models(X[fold != f], y[fold != f], names, spec, k,
                                         min_noise_variance=min_noise_variance), spec,
                        classifier, pose_components=pose_components, class_prior=class_prior)
        ps, ts = [], []
        for i in np.flatnonzero(fold == f):
            occ = X[i].reshape(n, n, n) > 0.5
            for _ in range(views):
                grid, _, _, _, rotated = random_partial_view(occ, rng)
                unknown = grid < 0
                if not (grid == 1).any() or not unknown.any():
                    continue
                ps.append(sub.estimate(grid).completion[unknown])
                ts.append(rotated[unknown])
        if ps:   # one count and one map fit per fold, not per view
            p, t = np.concatenate(ps), np.concatenate(ts)
            cal.partial_fit(p, t)
            raw.append(calibration_sums(p, t))
            n_views += len(ps)
    if not hasattr(cal, 'probability_'):
        raise ValueError('occupancy calibration: the views gave no unknown voxels in two '
                         'bins of distinct probabilities')
    c = cal.counts_[cal.counts_[:, 2] > 0]
    q = cal.predict(c[:, 0] / c[:, 2]).astype(np.float64)
    qc = np.clip(q, 1e-6, 1 - 1e-6)
    n_occ, n_free, m = c[:, 1], c[:, 2] - c[:, 1], c[:, 2].sum()
    report = dict(views=n_views, folds=folds, knots=len(cal.probability_),
                  raw=metrics_from_sums(raw), calibrated_in_sample=dict(
                      brier=float(np.sum(n_occ * (1 - q) ** 2 + n_free * q ** 2) / m),
                      log_loss=float(-np.sum(n_occ * np.log(qc) + n_free * np.log(1 - qc)) / m)))
    return cal, report


def check_grid_size(n, verifier=False):
    """ValueError unless a model can use grid size N = ``n``: an integer in [4, 256] and even
    (the coarse pose search pools 2x2x2 voxels); a multiple of 8 with the orientation
    ``verifier``."""
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) \
            or not 4 <= n <= 256 or n % 2:
        raise ValueError(f'the grid size must be an even integer in [4, 256] (the coarse pose '
                         f'search pools 2x2x2 voxels), got {n!r}')
    if verifier and n % 8:
        raise ValueError(f'the orientation verifier needs a grid size that is a multiple of 8, '
                         f'got {n}{NO_VERIFIER_HINT}')


def fit_bank(X, y, names, spec, k=20, masks=None, pose_components=8, classifier_views=1,
             folds=5, seed=0, C=None, verbose=False, training=None, grids=None,
             oof_path=None, row_standardize='auto', descriptors='auto', class_prior='train',
             verifier_views=0, processes=1, classifier_kind='auto', calibration_views='auto'):
    """Fit class models on all of X and a classifier on out-of-fold features.

    ``classifier_views``: random partial views per training object for the partial-view
    classifier (0: no classifier, the paper's max-likelihood rule).
    ``grids``: optional int8 (m, N, N, N) labelled training grids (real partial scans, in their
    original, un-congealed pose); then the out-of-fold 'partial' features come from these grids
    with pose search (``bank.features(grid)``) instead of synthetic random views.
    ``oof_path``: also save the out-of-fold features, labels and per-hypothesis yaw errors and
    IoUs there (npz) for analysis.
    ``row_standardize``: True, False or 'auto' (per mode, whichever gives the higher
    cross-validated accuracy under ``class_prior``; never with fewer than 3 classes). See
    ``classifier_input``.
    ``C``: the logistic regression's regularisation strength, or several (default
    ``C_OPTIONS``), cross-validated like the inputs below (``select_classifier``).
    ``descriptors``: True, False or 'auto': also give the classifier the grid's shape
    descriptors (:func:`beo_ros.core.shape.shape_descriptors`); 'auto' tries both, per mode,
    together with the ``row_standardize`` options, and keeps the input with the highest
    cross-validated accuracy (the first of equals: raw before standardised, without
    descriptors before with them).
    ``classifier_kind``: 'logistic', 'mlp' or 'auto' (both, cross-validated with the inputs;
    see ``select_classifier``).
    ``class_prior``: the prior over classes the bank assumes (``ModelBank.class_prior``;
    default 'train': the training set's class frequencies; 'uniform': no class is favoured for
    being common in the training set); inputs are chosen by the accuracy expected under it
    (uniform: the balanced accuracy). The report gives the accuracy under both priors.
    ``verifier_views``: random views per object for the orientation verifier
    (``fit_verifier``; 0: none, needs the objects in their canonical pose and N a multiple
    of 8); ``processes`` make its views.
    ``calibration_views``: random views per object for the completion's occupancy calibration
    (``fit_occupancy_calibration``, after the classifier, which classifies them; 0: none, the
    model probabilities are published as they are). 'auto': 1 when a classifier is trained on
    whole objects, else 0 (partial training data have no truth for their unknown voxels).
    """
    C, calibration_views = _check_fit_options(
        names, spec, k, masks, classifier_views, folds, C, row_standardize, descriptors,
        verifier_views, classifier_kind, calibration_views, grids, oof_path, seed)
    reason = _settings_reason(pose_components, training)
    if reason:   # else the bank's ModelError after all the fits
        raise ValueError(reason)
    weights = resolve_class_prior(class_prior, names)
    cv_prior = class_prior if isinstance(class_prior, str) else weights
    X = np.asarray(X, dtype=np.float32)
    y = np.asarray(y)
    # before the fits: an IndexError of the first class's rows, or a ModelError about W after
    # all of them
    if X.ndim != 2 or X.shape[1] != spec.size ** 3 or y.shape != (len(X),):
        raise ValueError(f'X must be (objects, {spec.size ** 3}) (flattened {spec.size}^3 grids) '
                         f'and y one label per object, got X {X.shape} and y {y.shape}')
    check_class_counts(y, names, folds if classifier_views > 0 or calibration_views else 0)
    t0 = time.time()
    if verbose:   # minutes with missing data (scans), and no bar of its own
        print(f'fitting {len(names)} class models on {len(X)} objects (k {k}'
              f'{", unknown voxels as missing data" if masks is not None else ""}) ...',
              file=sys.stderr, flush=True)
    models = fit_class_models(X, y, names, spec, k, masks)
    info = dict(training or {}, k=k, min_noise_variance=OCCUPANCY_MIN_NOISE_VARIANCE,
                n_objects=int(len(X)), folds=folds, seed=seed,
                classifier_views=classifier_views, fit_seconds=round(time.time() - t0, 1))
    classifier = None
    if classifier_views > 0:
        rows, skipped = _out_of_fold_rows(X, y, names, spec, k, masks, grids, pose_components,
                                          classifier_views, folds, seed, verbose)
        classifier, cv_report = _select_classifiers(rows, len(names), C, seed, row_standardize,
                                                    descriptors, cv_prior, classifier_kind)
        info['cross_validation'] = cv_report
        info['skipped_views'] = skipped
        if skipped:
            print(f'out-of-fold features: {skipped} partial view(s) skipped: no occupied voxel '
                  '(objects of a few voxels lost to the rotation)', file=sys.stderr)
        if oof_path:
            _save_out_of_fold_rows(oof_path, rows)
        if verbose:
            print(f'cross-validated (out-of-fold features, {folds} folds): {cv_report}',
                  file=sys.stderr)
        info['classifier_seconds'] = round(time.time() - t0 - info['fit_seconds'], 1)
    calibration = None
    if calibration_views:
        t1 = time.time()
        calibration, info['occupancy_calibration'] = fit_occupancy_calibration(
            X, y, names, spec, k, folds, seed, calibration_views, classifier, class_prior,
            pose_components, verbose)
        info['occupancy_calibration'].update(seconds=round(time.time() - t1, 1))
        if verbose:
            print(f"occupancy calibration: {info['occupancy_calibration']}", file=sys.stderr)
    verifier = None
    if verifier_views > 0:
        t1 = time.time()
        verifier = fit_verifier(X, y, spec.size, verifier_views, seed, processes, verbose)
        info.update(verifier_views=int(verifier_views),
                    verifier_seconds=round(time.time() - t1, 1))
    return ModelBank(models, spec, classifier, info, pose_components, class_prior=class_prior,
                     verifier=verifier, occupancy_calibration=calibration)


def _check_fit_options(names, spec, k, masks, classifier_views, folds, C, row_standardize,
                       descriptors, verifier_views, classifier_kind, calibration_views, grids,
                       oof_path, seed=0):
    """Check the options of :func:`fit_bank` before its long fits (ValueError naming the first
    bad one, in fit_bank's order) and return (C: ``C_OPTIONS`` when None,
    calibration_views: an integer, 'auto' resolved as fit_bank documents)."""
    if C is None:
        C = C_OPTIONS
    if not (np.size(C) and np.all(np.asarray(C, dtype=np.float64) > 0)):
        raise ValueError(f'C must be a positive number or a sequence of them, got {C!r}')
    if row_standardize not in (True, False, 'auto'):
        raise ValueError(f"row_standardize must be True, False or 'auto', got {row_standardize!r}")
    if descriptors not in (True, False, 'auto'):
        raise ValueError(f"descriptors must be True, False or 'auto', got {descriptors!r}")
    _check_kind(classifier_kind, 'classifier_kind')
    if row_standardize is True and len(names) < 3:
        raise ValueError('row_standardize needs at least 3 classes')
    if not (isinstance(verifier_views, (int, np.integer)) and verifier_views >= 0):
        raise ValueError(f'verifier_views must be an integer >= 0, got {verifier_views!r}')
    # else a TypeError after the class models were fitted; with folds 1 'class ... has 0
    # training objects', with folds 0 no classifier at all, without a word
    if isinstance(classifier_views, (bool, np.bool_)) or not (
            isinstance(classifier_views, (int, np.integer)) and classifier_views >= 0):
        raise ValueError(f'classifier_views must be an integer >= 0, got {classifier_views!r}')
    if classifier_views and not (isinstance(folds, (int, np.integer)) and folds >= 2):
        raise ValueError(f'the out-of-fold classifier features need folds >= 2, got {folds!r}')
    if verifier_views and (masks is not None or spec.size % 8):
        raise ValueError('the orientation verifier needs whole objects in their canonical pose '
                         f'(no masks) on a grid of a multiple of 8 (got {spec.size})'
                         + (NO_VERIFIER_HINT if spec.size % 8 else ''))
    if calibration_views == 'auto':
        calibration_views = int(classifier_views > 0 and masks is None and grids is None)
    if isinstance(calibration_views, (bool, np.bool_)) or not (
            isinstance(calibration_views, (int, np.integer)) and calibration_views >= 0):
        raise ValueError("calibration_views must be 'auto' or an integer >= 0, got "
                         f'{calibration_views!r}')
    if calibration_views and not (isinstance(folds, (int, np.integer)) and folds >= 2):
        raise ValueError(f'the occupancy calibration needs folds >= 2, got {folds!r}')
    if calibration_views and (masks is not None or grids is not None):
        raise ValueError('the occupancy calibration needs whole training objects (no masks, '
                         'no scans): their unknown voxels have no truth')
    if oof_path and classifier_views <= 0:
        raise ValueError('oof_path needs classifier_views >= 1: without a classifier there are '
                         'no out-of-fold features to save')
    if len(set(names)) != len(names):
        raise ValueError(f'class names must be unique, got {list(names)}')
    check_class_names(names)   # the names save writes and load accepts
    check_grid_size(spec.size)
    if not (isinstance(k, (int, np.integer)) and k >= 1):
        raise ValueError(f'k must be an integer >= 1, got {k!r}')
    if isinstance(seed, (bool, np.bool_)) or not (isinstance(seed, (int, np.integer))
                                                  and seed >= 0):
        # else numpy's 'expected non-negative integer', or with None a TypeError after the
        # class models and the classifier were fitted
        raise ValueError(f'seed must be an integer >= 0, got {seed!r}')
    if classifier_views > 0 and len(names) < 2:
        raise ValueError(f'a classifier needs 2 or more classes, got {len(names)} '
                         f'({list(names)}); train none (classifier_views=0) for a one-class '
                         'model')
    return C, calibration_views


def _out_of_fold_rows(X, y, names, spec, k, masks, grids, pose_components, classifier_views,
                      folds, seed, verbose):
    """Classifier training rows of objects X (m, N^3) with labels y (m,), each from class
    models fitted on the other folds (``folds`` stratified folds drawn with ``seed``, whose
    stream then draws the views): ``classifier_views`` protocol views of each object (see
    :func:`view_features`; the complete grid too without ``masks``), or with ``grids`` each
    object's own labelled grid (a real scan: no ground-truth yaw).

    Returns (dict mode ('complete', 'partial') -> dict of lists: 'features' (r_i, C*F) and
    'descriptors' (r_i, D) blocks, 'labels' and 'objects' per row, 'records' (dicts) per row;
    the number of views skipped: no occupied voxel)."""
    rng = np.random.default_rng(seed)
    fold = stratified_folds(y, folds, rng)
    rows = {mode: dict(features=[], labels=[], records=[], objects=[], descriptors=[])
            for mode in ('complete', 'partial')}
    skipped = 0
    for f in progress_bar(range(folds), 'out-of-fold features', disable=not verbose):
        tr, te = fold != f, np.flatnonzero(fold == f)
        sub = ModelBank(fit_class_models(X[tr], y[tr], names, spec, k,
                                         None if masks is None else masks[tr]),
                        spec, pose_components=pose_components)
        for i in progress_bar(te, f'fold {f}', disable=not verbose):
            if grids is not None:
                part = rows['partial']
                F, _ = sub.features(np.asarray(grids[i], dtype=np.int8))
                part['features'].append(F.ravel()[None])
                part['descriptors'].append(shape_descriptors(np.asarray(grids[i]))[None])
                part['labels'].append(y[i])
                part['objects'].append(i)
                part['records'].append({})  # no ground-truth yaw for real scans
                continue
            out, lost = view_features(sub, X[i:i + 1], rng, classifier_views,
                                      complete=masks is None)
            skipped += lost
            for mode, (F, _, recs, D) in out.items():
                rows[mode]['features'].append(F)
                rows[mode]['descriptors'].append(D)
                rows[mode]['labels'] += [y[i]] * len(F)
                rows[mode]['objects'] += [i] * len(F)
                rows[mode]['records'] += recs
    return rows, skipped


def _select_classifiers(rows, n_classes, C, seed, row_standardize, descriptors, class_prior,
                        kind):
    """(classifier dict mode -> arrays, report dict mode -> cross-validation report): the
    :func:`select_classifier` choice for every mode of ``rows`` (see
    :func:`_out_of_fold_rows`) that has rows."""
    classifier, cv_report = {}, {}
    for mode, r in rows.items():
        if r['features']:
            classifier[mode], cv_report[mode] = select_classifier(
                np.vstack(r['features']), np.array(r['labels']), r['records'],
                np.array(r['objects']), np.vstack(r['descriptors']), n_classes, C, seed,
                row_standardize, descriptors, class_prior, kind)
    return classifier, cv_report


def _save_out_of_fold_rows(path, rows):
    """Save the out-of-fold ``rows`` (see :func:`_out_of_fold_rows`) to npz ``path``: per mode
    with rows, <mode>_features, _labels, _objects, _descriptors and each record key (e.g.
    <mode>_yaw_err (r, C), <mode>_iou (r, C))."""
    arrays = {}
    for mode, r in rows.items():
        if r['features']:
            arrays[f'{mode}_features'] = np.vstack(r['features'])
            arrays[f'{mode}_labels'] = np.array(r['labels'])
            arrays[f'{mode}_objects'] = np.array(r['objects'])
            arrays[f'{mode}_descriptors'] = np.vstack(r['descriptors'])
            if r['records'] and r['records'][0]:
                for key in r['records'][0]:
                    arrays[f'{mode}_{key}'] = np.array([rec[key] for rec in r['records']])
    from pathlib import Path
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'wb') as f:   # the name given: np.savez appends '.npz' to a name without it
        np.savez(f, **arrays)
