"""Training: per-class VBPCA models, out-of-fold classifier features, data loading."""
from __future__ import annotations

import hashlib
import json
import os
import signal
import sys
import time
import warnings

import numpy as np

from .bank import ModelBank
from .calibration import OccupancyCalibration, calibration_sums, metrics_from_sums
from .class_model import ClassModel, coarse_noise
from .classifier import classifier_input, prior_offset, resolve_class_prior
from .grid import yaw_error
from .inference import FEATURE_NAMES
from .model_files import UNREADABLE, check_class_names
from .shape import shape_descriptors
from .synthetic import random_partial_view
from .verifier import TURNS, OrientationVerifier, turned_features
from .vbpca import VBPCA


def progress_bar(it, desc, total=None, disable=False):
    try:
        from tqdm import tqdm
        return tqdm(it, desc=desc, total=total, disable=disable, file=sys.stderr, leave=False)
    except ImportError:  # pragma: no cover - tqdm is a dependency
        return it


def fit_class_models(X, y, names, spec, k=20, masks=None, max_iter=200, tol=1e-5):
    """One VBPCA ClassModel per class. X: (m, N^3) float32 in [0, 1]; masks: (m, N^3) observed."""
    models = []
    for c, name in enumerate(names):
        sel = y == c
        if sel.sum() < 2:
            raise ValueError(f'class {name!r} has {int(sel.sum())} training objects; need >= 2')
        Xc = X[sel]
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            est = VBPCA(n_components=int(min(k, sel.sum() - 1)), max_iter=max_iter,
                        tol=tol).fit(Xc, mask=None if masks is None else masks[sel])
        Xf = Xc if masks is None else np.where(masks[sel], Xc, est.inverse_transform(
            est.transform(Xc, masks[sel])))
        models.append(ClassModel.from_vbpca(name, est, *coarse_noise(
            Xf.astype(np.float32), est, spec.size)))
    return models


def check_class_counts(y, names, folds=0):
    """ValueError naming the first class of ``names`` with too few objects in labels y: a class
    model needs 2; with ``folds`` >= 2 (out-of-fold classifier features) every fold's training
    part needs 2 as well, i.e. the objects a class keeps when its biggest fold is held out."""
    counts = np.bincount(np.asarray(y, dtype=int), minlength=len(names))
    need = 2
    if folds >= 2:   # stratified_folds holds out up to ceil(m / folds) objects of m
        while need - -(-need // folds) < 2:
            need += 1
    for name, m in zip(names, counts):
        if m < need:
            why = (f'out-of-fold classifier features over {folds} folds need >= {need} per class '
                   "(each fold trains class models on the other folds' objects); "
                   + ('use 3 or more folds' if m >= 3 else
                      'add objects, or train no classifier (views 0)')) \
                if folds >= 2 and m >= 2 else 'a class model needs >= 2'
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


def verifier_training_set(X, n, views=6, seed=0, processes=1, verbose=False):
    """Rows for the orientation verifier from objects X (m, n^3) in their canonical pose:
    ``views`` random partial views of each (the evaluation protocol), each turned into the
    model's frame by its true yaw plus 0, 90, 180 and 270° (+- 5° of jitter).

    Returns (features (m * views * 4, 1536) float32, turn (r,), object index (r,)). The same
    for any ``processes`` (chunks of ``VERIFIER_CHUNK`` objects, each with its own stream).
    """
    X = np.asarray(X)
    chunks = [(X[i:i + VERIFIER_CHUNK], n, views, seed, i // VERIFIER_CHUNK)
              for i in range(0, len(X), VERIFIER_CHUNK)]
    if processes > 1:
        from concurrent.futures import ProcessPoolExecutor
        with ProcessPoolExecutor(processes, initializer=_quiet_on_sigint) as ex:
            parts = list(progress_bar(ex.map(_verifier_chunk, chunks), 'verifier views',
                                      total=len(chunks), disable=not verbose))
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
                              verbose=False):
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
        sub = ModelBank(fit_class_models(X[fold != f], y[fold != f], names, spec, k), spec,
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
        raise ValueError('occupancy calibration: the views gave no unknown voxels of two '
                         'distinct probabilities')
    c = cal.counts_[cal.counts_[:, 2] > 0]
    q = cal.predict(c[:, 0] / c[:, 2]).astype(np.float64)
    qc = np.clip(q, 1e-6, 1 - 1e-6)
    n_occ, n_free, m = c[:, 1], c[:, 2] - c[:, 1], c[:, 2].sum()
    report = dict(views=n_views, folds=folds, knots=len(cal.probability_),
                  raw=metrics_from_sums(raw), calibrated_in_sample=dict(
                      brier=float(np.sum(n_occ * (1 - q) ** 2 + n_free * q ** 2) / m),
                      log_loss=float(-np.sum(n_occ * np.log(qc) + n_free * np.log(1 - qc)) / m)))
    return cal, report


# the network that select_classifier tries beside the logistic regression: one ReLU layer of
# MLP_HIDDEN units, L2 penalty MLP_ALPHA (5-fold CV, mean over 2-3 fold seeds, on the
# ModelNet10 out-of-fold rows, row-standardised + 43 descriptors, complete / partial accuracy:
# logistic C = 0.1 0.911 / 0.895; 128 units at alpha 1 0.917 / 0.898 (ECE 0.01), at 0.1
# 0.915 / 0.893 (ECE 0.04-0.06), at 3 0.911 / 0.894; 256 units at alpha 1 0.916; two layers
# of 64 or the mean of five seeds' networks 0.917-0.918)
MLP_HIDDEN = 128
MLP_ALPHA = 1.0
MLP_MAX_ITER = 1000
CLASSIFIER_KINDS = ('logistic', 'mlp')


def _network(hidden, alpha, seed):
    """The unfitted one-layer ReLU network of :func:`fit_mlp` and of its cross-validation."""
    from sklearn.neural_network import MLPClassifier
    return MLPClassifier((int(hidden),), alpha=alpha, max_iter=MLP_MAX_ITER, random_state=seed)


def _check_kind(kind, name):
    """ValueError unless ``kind`` is one of CLASSIFIER_KINDS or 'auto'."""
    if kind not in CLASSIFIER_KINDS + ('auto',):
        raise ValueError(f"{name} must be one of {CLASSIFIER_KINDS + ('auto',)}, got {kind!r}")


def cross_validated_report(F, y, records, C=1.0, folds=5, seed=0, row_standardize=False,
                           groups=None, descriptors=None, class_prior='train', hidden=0,
                           alpha=MLP_ALPHA):
    """Accuracy (and, for partial views, yaw and IoU) of the classifier on out-of-fold features,
    itself cross-validated: every object's class comes from a classifier that never saw it.

    The classifier is the logistic regression at ``C``, or with ``hidden`` > 0 the one-layer
    ReLU network of :func:`fit_mlp` with that many units and L2 penalty ``alpha``.

    ``groups`` (r,): the object of every row, when objects have several rows (views); all
    rows of an object then fall in the same fold. ``descriptors`` (r, D): shape descriptors
    appended to the classifier input (see ``classifier_input``). ``class_prior``: the prior
    the probabilities are moved to (``classifier.resolve_class_prior``; the rows' own class
    frequencies are the classifier's prior); ``prior_accuracy`` is the accuracy expected when
    classes occur with the prior's frequencies (sum of prior x recall; 'train': the accuracy,
    'uniform': the balanced accuracy). Every other number is on these rows as they are.
    """
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import StratifiedGroupKFold, StratifiedKFold, cross_val_predict
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    if hidden:
        clf = make_pipeline(StandardScaler(), _network(hidden, alpha, seed))
    else:
        clf = make_pipeline(StandardScaler(), LogisticRegression(C=C, max_iter=2000))
    if groups is not None and len(np.unique(groups)) < len(y):
        per_class = min(len(np.unique(groups[y == c])) for c in np.unique(y))
        cv = StratifiedGroupKFold(n_splits=min(folds, per_class), shuffle=True, random_state=seed)
    else:
        groups = None
        # counts of the classes present: a class index without rows (all its views skipped)
        # is not a class of this cross-validation
        cv = StratifiedKFold(n_splits=min(folds, int(np.unique(y, return_counts=True)[1].min())),
                             shuffle=True, random_state=seed)
    nf = len(FEATURE_NAMES)
    P = cross_val_predict(clf, classifier_input(F, F.shape[1] // nf, row_standardize,
                                                descriptors), y, cv=cv, groups=groups,
                          method='predict_proba')
    classes = np.unique(y)
    n_classes = F.shape[1] // nf
    counts = np.bincount(y, minlength=n_classes).astype(np.float64)
    weights = resolve_class_prior(class_prior, range(n_classes))

    def under(prior):  # the cross-validated probabilities moved to another class prior
        if prior is None:
            return P
        Q = P * np.exp(prior_offset(counts, prior))[classes]
        return Q / Q.sum(axis=1, keepdims=True)

    uniform = np.full(n_classes, 1.0 / n_classes)
    train_pred, uniform_pred = (classes[np.argmax(under(w), axis=1)] for w in (None, uniform))
    P = under(weights)
    pred = classes[np.argmax(P, axis=1)]
    ml = np.argmax(F[:, 0::nf], axis=1)
    recall = np.array([np.mean(pred[y == c] == c) for c in classes])
    prior = counts[classes] / counts.sum() if weights is None else weights[classes]
    p_true = P[np.arange(len(y)), np.searchsorted(classes, y)]
    rep = dict(n=int(len(y)), accuracy=float(np.mean(pred == y)),
               balanced_accuracy=float(np.mean(recall)),
               prior_accuracy=float(prior @ recall / prior.sum()),
               accuracy_max_likelihood=float(np.mean(ml == y)),
               log_loss=float(-np.mean(np.log(np.maximum(p_true, 1e-12)))),
               ece=expected_calibration_error(P.max(axis=1), pred == y))
    # the same classifier under the two named priors, whichever was asked for
    for name, pr in (('train', train_pred), ('uniform', uniform_pred)):
        rep[f'accuracy_{name}_prior'] = float(np.mean(pr == y))
        rep[f'balanced_accuracy_{name}_prior'] = float(np.mean([np.mean(pr[y == c] == c)
                                                                for c in classes]))
    if records and 'yaw_err' in records[0]:
        err = np.rad2deg([r['yaw_err'][p] for r, p in zip(records, pred)])
        err_true = np.rad2deg([r['yaw_err'][t] for r, t in zip(records, y)])
        rep.update(yaw_within_10=float(np.mean(err <= 10)),
                   yaw_within_10_or_flip=float(np.mean((err <= 10) | (err >= 170))),
                   yaw_median_deg=float(np.median(err)),
                   yaw_within_10_true_class=float(np.mean(err_true <= 10)),
                   iou=float(np.mean([r['iou'][p] for r, p in zip(records, pred)])))
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in rep.items()}


# regularisation strengths of the logistic regression that fit_bank cross-validates: with the
# 72 inputs of the 12-descriptor classifier C = 1 overfits a little (5-fold CV on the
# ModelNet10 out-of-fold features, complete / partial: C = 1 0.900 / 0.883, ECE 0.022 / 0.029;
# C = 0.1 0.909 / 0.887, ECE 0.017 / 0.013); with the 103 inputs of the 43 descriptors
# C = 1 0.909 / 0.889, C = 0.1 0.913 / 0.894)
C_OPTIONS = (0.1, 0.3, 1.0)
# the grid classifiers' 'unknown' bound, in scaled MADs below the median (see loglik_bounds)
UNKNOWN_MADS = 8.0


def expected_calibration_error(confidence, correct, bins=10):
    """Expected calibration error: the mean over 10 equal-width confidence bins of
    |mean confidence - accuracy|, weighted by the share of rows in the bin."""
    confidence, correct = np.asarray(confidence, dtype=np.float64), np.asarray(correct)
    edges = np.linspace(0.0, 1.0, bins + 1)
    ece = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        m = (confidence > a) & (confidence <= b)
        if m.any():
            ece += m.mean() * abs(confidence[m].mean() - correct[m].mean())
    return float(ece)


def loglik_bounds(ll, y, n_classes, mads=UNKNOWN_MADS):
    """Per-class lower bounds (C,) of the 'unknown' test from out-of-fold log-likelihoods.

    ll: (m, C) per-voxel log-likelihood of every training object under every class; y: (m,).
    The winning class must explain an object about as well as its own out-of-fold objects: a
    robust bound (median - ``mads`` scaled MADs of their log-likelihood), so a single outlier
    among them cannot drag it down; -inf for a class with fewer than 5 objects.
    Every 'unknown' answer for an object of a known class is an error, so the bound is set by
    how many of those it makes: on the ModelNet10 out-of-fold rows (shape-descriptor
    classifier) 8 MADs flag 0.6 % of the complete objects and 0.3 % of the partial views,
    6 MADs 1.4 % and 0.9 % (four fifths of them classified right), and both reject the same
    random grids (10 % and >= 20 % of the voxels occupied; 15 % reads as night stand).
    """
    thr = np.full(n_classes, -np.inf)
    for c in range(n_classes):
        own = ll[y == c, c]
        if len(own) >= 5:
            med = np.median(own)
            mad = 1.4826 * np.median(np.abs(own - med))
            thr[c] = med - mads * max(mad, 1e-3)
    return thr


def fit_logistic(Z, y, n_classes, C=1.0):
    """Standardised logistic regression on input rows Z (m, n_in) with labels y (m,) ->
    dict(mean, scale (n_in,), coef (n_classes, n_in), intercept (n_classes,), class_counts
    (n_classes,): the rows per class, its prior) in the softmax form of
    ``classifier.classifier_probabilities``. Classes absent from y get intercept -30 (never
    chosen); a binary fit becomes the two-class softmax with logits -z/2, +z/2: the regression's
    own probabilities (logits -z, +z would square the odds).
    """
    from sklearn.linear_model import LogisticRegression
    Z, mean, scale = _standardized(Z)
    lr = LogisticRegression(C=C, max_iter=2000).fit(Z, y)
    return dict(mean=mean, scale=scale,
                **_softmax_head(lr.classes_, lr.coef_, lr.intercept_, n_classes, y))


def _standardized(Z):
    """(Z standardised per column, mean, scale) of input rows Z (m, n_in)."""
    Z = np.asarray(Z, dtype=np.float64)
    mean = Z.mean(axis=0)
    scale = Z.std(axis=0) + 1e-9
    return (Z - mean) / scale, mean, scale


def _softmax_head(classes, coef_, intercept_, n_classes, y):
    """coef (n_classes, n_in), intercept (n_classes,) and class_counts of a fitted scikit-learn
    linear output layer (coef_ (K, n_in), intercept_ (K,) over the K ``classes`` present; one
    row for a binary fit). Absent classes get intercept -30 (never chosen); a binary fit's one
    logit z becomes the two-class softmax with logits -z/2, +z/2 (its own probabilities:
    logits -z, +z would square the odds)."""
    coef = np.zeros((n_classes, coef_.shape[1]))
    intercept = np.full(n_classes, -30.0)
    if len(classes) > 2:
        coef[classes], intercept[classes] = coef_, intercept_
    else:
        coef[classes] = np.vstack([-coef_, coef_]) / 2
        intercept[classes] = np.hstack([-intercept_, intercept_]) / 2
    return dict(coef=coef, intercept=intercept,
                class_counts=np.bincount(np.asarray(y), minlength=n_classes).astype(np.float64))


def fit_mlp(Z, y, n_classes, hidden=MLP_HIDDEN, alpha=MLP_ALPHA, seed=0):
    """A one-layer ReLU network (scikit-learn's MLPClassifier, ``hidden`` units, L2 penalty
    ``alpha``) on standardised input rows Z (m, n_in) with labels y (m,) -> the dict of
    :func:`fit_logistic` plus hidden_coef (hidden, n_in) and hidden_intercept (hidden,); coef
    (n_classes, hidden) is then the softmax layer on the hidden units (see
    ``classifier.classifier_probabilities``). Absent classes and a binary fit as in fit_logistic."""
    Z, mean, scale = _standardized(Z)
    net = _network(hidden, alpha, seed).fit(Z, y)
    (w1, w2), (b1, b2) = net.coefs_, net.intercepts_
    return dict(mean=mean, scale=scale, hidden_coef=w1.T.copy(), hidden_intercept=b1.copy(),
                **_softmax_head(net.classes_, w2.T, b2, n_classes, y))


def train_classifier(F, y, n_classes, C=1.0, row_standardize=False, descriptors=None, hidden=0,
                     alpha=MLP_ALPHA, seed=0):
    """Standardised multinomial logistic regression (or, with ``hidden`` > 0, the network of
    :func:`fit_mlp`) on features F (r, C*F) [+ shape descriptors (r, D)] -> arrays dict
    (``row_standardize``, ``descriptors``: see ``classifier_input``; ``descriptor_count``: D,
    the first D of ``shape.DESCRIPTOR_NAMES``)."""
    Z = classifier_input(F, n_classes, row_standardize, descriptors)
    clf = fit_mlp(Z, y, n_classes, hidden, alpha, seed) if hidden else \
        fit_logistic(Z, y, n_classes, C)
    out = dict(clf, unknown_threshold=loglik_bounds(F[:, 0::len(FEATURE_NAMES)], y, n_classes),
               row_standardize=np.asarray(bool(row_standardize)),
               descriptors=np.asarray(descriptors is not None))
    if descriptors is not None:
        out['descriptor_count'] = np.asarray(np.shape(descriptors)[1], dtype=np.int64)
    return out


def select_classifier(F, y, records, objects, D, n_classes, C=C_OPTIONS, seed=0,
                      row_standardize='auto', descriptors='auto', class_prior='train',
                      kind='auto'):
    """Cross-validate every classifier input (raw or row-standardised features, with or
    without the shape descriptors D (r, D)) and model (the logistic regression at each
    regularisation strength in ``C``, a number or a sequence, and the one-layer network of
    :func:`fit_mlp`; ``kind``: 'logistic', 'mlp' or 'auto' for both) on out-of-fold features
    F (r, C*F) with labels y and the object of every row, keep the most accurate under
    ``class_prior`` (its ``prior_accuracy``; the first of equals, in that order: logistic
    before the network), train it on all rows.

    Returns (classifier dict, report dict: the winner's ``cross_validated_report`` plus its
    row_standardize, descriptors, kind and C (logistic) or hidden and alpha (network), and
    every option's accuracy).
    """
    _check_kind(kind, 'kind')
    if row_standardize == 'auto':
        rs_options = [False, True] if n_classes >= 3 else [False]
    else:
        rs_options = [row_standardize]
    c_options = [float(c) for c in np.atleast_1d(C)]
    models = ([('logistic', c) for c in c_options] if kind in ('auto', 'logistic') else []) \
        + ([('mlp', MLP_ALPHA)] if kind in ('auto', 'mlp') else [])
    options = [(r, d, m) for d in ([False, True] if descriptors == 'auto' else [descriptors])
               for r in rs_options for m in models]

    def model_args(m):
        return dict(C=m[1]) if m[0] == 'logistic' else dict(hidden=MLP_HIDDEN, alpha=m[1])

    reports = [cross_validated_report(F, y, records, seed=seed, row_standardize=r,
                                      groups=objects, descriptors=D if d else None,
                                      class_prior=class_prior, **model_args(m))
               for r, d, m in options]
    accs = [r['prior_accuracy'] for r in reports]
    best = int(np.argmax(accs))
    rs, use_d, m_best = options[best]
    report = dict(reports[best], row_standardize=rs, descriptors=use_d, kind=m_best[0],
                  **model_args(m_best),
                  class_prior=class_prior if isinstance(class_prior, str) else
                  [float(w) for w in resolve_class_prior(class_prior, range(n_classes))])
    if len(options) > 1:
        def label(r, d, m):
            name = ('row-standardised' if r else 'raw') + (' + descriptors' if d else '')
            if m[0] == 'mlp':
                return name + f', MLP {MLP_HIDDEN} alpha={m[1]:g}'
            return name + (f', C={m[1]:g}' if len(c_options) > 1 else '')
        report['accuracy_other_input'] = max(a for j, a in enumerate(accs) if j != best)
        report['accuracy_by_input'] = {label(*o): a for o, a in zip(options, accs)}
    return train_classifier(F, y, n_classes, row_standardize=rs,
                            descriptors=D if use_d else None, seed=seed,
                            **model_args(m_best)), report


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
                         f'got {n}')


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
        verifier_views, classifier_kind, calibration_views, grids, oof_path)
    weights = resolve_class_prior(class_prior, names)
    cv_prior = class_prior if isinstance(class_prior, str) else weights
    X = np.asarray(X, dtype=np.float32)
    y = np.asarray(y)
    check_class_counts(y, names, folds if classifier_views > 0 or calibration_views else 0)
    t0 = time.time()
    if verbose:   # minutes with missing data (scans), and no bar of its own
        print(f'fitting {len(names)} class models on {len(X)} objects (k {k}'
              f'{", unknown voxels as missing data" if masks is not None else ""}) ...',
              file=sys.stderr, flush=True)
    models = fit_class_models(X, y, names, spec, k, masks)
    info = dict(training or {}, k=k, n_objects=int(len(X)), folds=folds, seed=seed,
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
                       oof_path):
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
    if verifier_views and (masks is not None or spec.size % 8):
        raise ValueError('the orientation verifier needs whole objects in their canonical pose '
                         f'(no masks) on a grid of a multiple of 8 (got {spec.size})')
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
    np.savez(path, **arrays)


# ---------------------------------------------------------------------- data loading
def _decode_voxels(path, vox, shape):
    """(m, N^3) voxel rows and N from the 'voxels' array (and the 'shape' key, or None) of a
    voxel npz: bit-packed (m, ceil(N^3 / 8)) uint8 rows when 'shape' says (N, N, N) is more
    than the row holds; otherwise unpacked (m, N^3) or (m, N, N, N) values in {0, 1}."""
    if not (vox.dtype == np.bool_ or np.issubdtype(vox.dtype, np.integer)
            or np.issubdtype(vox.dtype, np.floating)):
        raise ValueError(f'{path}: voxels must be numbers, got dtype {vox.dtype}')
    if vox.ndim not in (2, 4):
        raise ValueError(f'{path}: voxels must be (n, N^3) (bit-packed or not) or (n, N, N, N), '
                         f'got shape {vox.shape}')
    if shape is not None:
        if len(shape) != 3 or len(set(shape)) != 1 or shape[0] < 1:
            raise ValueError(f"{path}: 'shape' key must be (N, N, N), got {shape}")
        n = shape[0]
        packed_len = -(-n ** 3 // 8)
        if vox.ndim == 2 and vox.dtype == np.uint8 and vox.shape[1] == packed_len and \
                packed_len != n ** 3:
            return np.unpackbits(vox, axis=1, count=n ** 3), n
        if vox.shape[1:] not in ((n ** 3,), (n, n, n)):
            raise ValueError(f"{path}: 'shape' key {shape} does not match voxels of shape "
                             f'{vox.shape} (bit-packed: (n, {packed_len}) uint8; unpacked: '
                             f'(n, {n ** 3}) or (n, {n}, {n}, {n}))')
    elif vox.ndim == 4:
        n = vox.shape[1]
        if vox.shape[2:] != (n, n):
            raise ValueError(f'{path}: voxel grids of shape {vox.shape[1:]} are not cubes')
    else:
        n = int(round(vox.shape[1] ** (1 / 3)))
        if n ** 3 != vox.shape[1]:
            hint = ''
            if vox.dtype == np.uint8:
                hint = (" (bit-packed voxels need the 'shape' key (N, N, N); this file has "
                        "no 'shape' key)")
            raise ValueError(f'{path}: voxel rows of {vox.shape[1]} values are not a cube{hint}')
    X = vox.reshape(len(vox), -1)
    bad = (X != 0) & (X != 1)
    if bad.any():
        v = X[bad][0].item()
        hint = ''
        if vox.dtype == np.uint8 and vox.ndim == 2:
            hint = (" (bit-packed rows? they need the 'shape' key (N, N, N), which this file "
                    "does not have)" if shape is None else
                    f" (bit-packed rows? the 'shape' key {shape} makes rows of "
                    f'{vox.shape[1]} values unpacked)')
        raise ValueError(f'{path}: voxel values must be 0 or 1, found {v!r} in '
                         f'{int(bad.any(axis=1).sum())} of {len(X)} objects{hint}')
    return X, n


def _check_labels(path, labels, names, m):
    """labels as an int array after checking they index ``names``, one per object (m)."""
    if labels.ndim != 1:
        raise ValueError(f'{path}: labels must be a 1-D array, got shape {labels.shape}')
    if len(labels) != m:
        raise ValueError(f'{path}: {len(labels)} labels for {m} objects (voxels); need one '
                         'label per object')
    if labels.dtype == np.bool_ or np.issubdtype(labels.dtype, np.integer):
        pass
    elif np.issubdtype(labels.dtype, np.floating):
        if not (np.isfinite(labels).all() and (labels == np.round(labels)).all()):
            raise ValueError(f'{path}: labels must be integers (class indices), got '
                             'non-integral values')
    else:
        raise ValueError(f'{path}: labels must be integers (class indices), got dtype '
                         f'{labels.dtype}')
    bad = (labels < 0) | (labels >= len(names))
    if bad.any():
        raise ValueError(f'{path}: labels must be in [0, {len(names)}) (indices into its '
                         f'{len(names)} classes), found {labels[bad][0].item()!r} in '
                         f'{int(bad.sum())} of {m} objects (first: object '
                         f'{int(np.flatnonzero(bad)[0])})')
    return labels.astype(int)


def _head(path, n=8):
    """The first ``n`` bytes of a file, or None when it cannot be read."""
    try:
        with open(path, 'rb') as f:
            return f.read(n)
    except OSError:
        return None


def load_voxel_npz(path, classes=None):
    """(X (m, N^3) float32, labels (m,), class names, N) from a voxel npz in the shared format.

    Keys: 'voxels', bit-packed (m, N^3 / 8) uint8 rows with a 'shape' key (N, N, N), or
    unpacked (m, N^3) or (m, N, N, N) values in {0, 1} ('shape', if given, must match);
    'labels', m integers in [0, len(classes)); 'classes', the class names. ValueError naming
    the file for anything else.
    """
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):   # np.save output: one bare array
            raise ValueError(f'{path}: holds a single array (an .npy file?), not a voxel npz '
                             "with keys 'voxels', 'labels', 'classes'")
        with z:
            for key in ('voxels', 'labels', 'classes'):
                if key not in z.files:
                    raise ValueError(f'{path}: missing key {key!r} (has {z.files})')
            vox, labels = z['voxels'], z['labels']
            names = [str(c) for c in np.atleast_1d(z['classes'])]
            shape = z['shape'] if 'shape' in z.files else None
    except UNREADABLE as e:
        if str(path) in str(e):
            raise
        head = _head(path)
        if head is not None and not head.startswith((b'PK', b'\x93NUMPY')):
            # numpy's own message here is about pickles, which says nothing useful
            raise ValueError(f'{path}: not an npz file (it starts with {head!r})') from None
        raise ValueError(f'{path}: not a readable voxel npz ({type(e).__name__}: {e})') from None
    if shape is not None:
        if not (np.issubdtype(shape.dtype, np.number) and np.isfinite(shape).all()
                and (shape == np.round(shape)).all()):
            raise ValueError(f"{path}: 'shape' key must be integers (N, N, N), got {shape!r}")
        shape = tuple(int(s) for s in shape.ravel())
    X, n = _decode_voxels(path, vox, shape)
    labels = _check_labels(path, labels, names, len(X))
    X = X.astype(np.float32)
    if classes:
        X, labels, names = select_classes(X, labels, names, classes, path)
    return X, labels, names, n


def drop_empty_objects(X, y, names):
    """(X, y, dropped) without the objects that have no occupied voxel (nothing to learn a
    shape from); ``dropped``: {class name: count} of the classes that lost objects. ValueError
    when a class has no object left."""
    empty = ~(np.asarray(X) > 0.5).any(axis=1)
    counts = np.bincount(np.asarray(y, dtype=int)[empty], minlength=len(names))
    dropped = {name: int(c) for name, c in zip(names, counts) if c}
    left = np.bincount(np.asarray(y, dtype=int)[~empty], minlength=len(names))
    gone = [name for name, c, e in zip(names, left, counts) if e and not c]
    if gone:
        raise ValueError(f'classes {gone} have no object with an occupied voxel '
                         f'(empty objects per class: {dropped})')
    return X[~empty], y[~empty], dropped


def training_data_hash(X, y, names):
    """SHA-256 (hex) of a training set's occupancy (X > 0.5), labels and class names: recorded
    in the manifest so that ``beo-train --calibrate-only`` can tell other data apart."""
    X = np.asarray(X)
    h = hashlib.sha256(json.dumps([list(map(str, names)), list(X.shape)]).encode())
    h.update(np.packbits(X > 0.5, axis=-1).tobytes())
    h.update(np.asarray(y, dtype='<i8').tobytes())
    return h.hexdigest()


def select_classes(X, labels, names, classes, where):
    """(X, labels, names) of only the objects of ``classes``, labels renumbered in that order;
    ValueError naming ``where`` for a class not in ``names`` or given twice."""
    twice = sorted({c for c in classes if list(classes).count(c) > 1})
    if twice:
        raise ValueError(f'{where}: classes {twice} given more than once')
    keep = [names.index(c) if c in names else None for c in classes]
    missing = [c for c, k in zip(classes, keep) if k is None]
    if missing:
        raise ValueError(f'{where}: classes {missing} not in {names}')
    remap = {old: new for new, old in enumerate(keep)}
    sel = np.isin(labels, keep)
    return X[sel], np.array([remap[v] for v in labels[sel]], dtype=int), list(classes)


def mesh_class_name(path) -> str:
    """The class of a mesh file: the name before a last '_' followed by digits only, as in
    ModelNet's ``chair_0001.off`` (``night_stand_0001.off`` -> 'night_stand'), else the name
    of the folder holding it (``mugs/red_mug.off`` -> 'mugs')."""
    from pathlib import Path
    path = Path(path)
    head, sep, tail = path.stem.rpartition('_')
    if sep and head and tail.isdigit():
        return head
    return path.absolute().parent.name


def load_meshes(paths, size):
    """Voxelize mesh files; the class of each is :func:`mesh_class_name`."""
    from pathlib import Path
    from .meshes import load_mesh, voxelize_mesh
    X, names_of = [], []
    for p in paths:
        p = Path(p)
        X.append(voxelize_mesh(load_mesh(p), size).ravel())
        names_of.append(mesh_class_name(p))
    names = sorted(set(names_of))
    return np.array(X, dtype=np.float32), np.array([names.index(s) for s in names_of]), names
