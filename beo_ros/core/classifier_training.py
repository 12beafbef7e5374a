"""Training the grid classifier: the logistic regression and the one-layer network, their
cross-validation on out-of-fold features and the choice among inputs and models (the
classifier's use at estimate time is in :mod:`classifier`)."""
from __future__ import annotations

import numpy as np

from .calibration import check_bin_count
from .classifier import classifier_input, prior_offset, resolve_class_prior
from .inference import FEATURE_NAMES


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
    # folds: at most the objects of the smallest class, at least 2: a class of one object
    # (its other views skipped) is classified by folds that never saw it (one fold refused)
    if groups is not None and len(np.unique(groups)) < len(y):
        per_class = min(len(np.unique(groups[y == c])) for c in np.unique(y))
        cv = StratifiedGroupKFold(n_splits=max(2, min(folds, per_class)), shuffle=True,
                                  random_state=seed)
    else:
        groups = None
        # counts of the classes present: a class index without rows (all its views skipped)
        # is not a class of this cross-validation
        per_class = int(np.unique(y, return_counts=True)[1].min())
        cv = StratifiedKFold(n_splits=max(2, min(folds, per_class)), shuffle=True,
                             random_state=seed)
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
    """Expected calibration error: the mean over ``bins`` equal-width confidence bins of
    |mean confidence - accuracy|, weighted by the share of rows in the bin.

    confidence (n,): probabilities in [0, 1]; correct (n,): boolean or 0/1. The bins are
    [0, 1/bins], then (a, b] up to 1. 0 for no rows."""
    check_bin_count(bins)   # else 0 for bins 0 (no bin), numpy's TypeError for 2.5
    confidence, correct = np.asarray(confidence, dtype=np.float64), np.asarray(correct)
    if confidence.shape != correct.shape:
        raise ValueError(f'confidence and correct must have the same shape, got '
                         f'{confidence.shape} and {correct.shape}')
    if not np.all((confidence >= 0) & (confidence <= 1)):   # also False for NaN
        raise ValueError('confidence must be finite probabilities in [0, 1]')
    if correct.dtype != bool and not np.all((correct == 0) | (correct == 1)):
        raise ValueError('correct must be boolean or 0/1')
    if not confidence.size:
        return 0.0
    # bin i holds edges[i] < c <= edges[i + 1]; 0 joins the first bin
    b = np.maximum(np.digitize(confidence.ravel(), np.linspace(0.0, 1.0, bins + 1),
                               right=True), 1) - 1
    gap = np.bincount(b, weights=confidence.ravel(), minlength=bins) - \
        np.bincount(b, weights=correct.ravel().astype(np.float64), minlength=bins)
    return float(np.abs(gap).sum() / confidence.size)


def loglik_bounds(ll, y, n_classes, mads=UNKNOWN_MADS, objects=None):
    """Per-class lower bounds (C,) of the 'unknown' test from out-of-fold log-likelihoods.

    ll: (m, C) per-voxel log-likelihood of every training object under every class; y: (m,);
    ``objects`` (m,): the object of every row when objects have several rows (views).
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
        n_own = len(own) if objects is None else len(np.unique(np.asarray(objects)[y == c]))
        if n_own >= 5:
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
    """(Z standardised per column, mean, scale) of input rows Z (m, n_in). A column constant
    in the rows (to rounding) gets scale 1, as in the cross-validation's StandardScaler: std +
    1e-9 would magnify a query's departure from the constant 1e9 times (a network's hidden
    weights on such a column decay towards 0 but are not 0)."""
    Z = np.asarray(Z, dtype=np.float64)
    mean = Z.mean(axis=0)
    std = Z.std(axis=0)
    scale = np.where(std > 1e-9 * np.maximum(np.abs(mean), 1.0), std + 1e-9, 1.0)
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
                     alpha=MLP_ALPHA, seed=0, objects=None):
    """Standardised multinomial logistic regression (or, with ``hidden`` > 0, the network of
    :func:`fit_mlp`) on features F (r, C*F) [+ shape descriptors (r, D)] -> arrays dict
    (``row_standardize``, ``descriptors``: see ``classifier_input``; ``descriptor_count``: D,
    the first D of ``shape.DESCRIPTOR_NAMES``; ``objects`` (r,): the object of every row, for
    the 'unknown' bounds' count of objects, see :func:`loglik_bounds`)."""
    Z = classifier_input(F, n_classes, row_standardize, descriptors)
    clf = fit_mlp(Z, y, n_classes, hidden, alpha, seed) if hidden else \
        fit_logistic(Z, y, n_classes, C)
    out = dict(clf, unknown_threshold=loglik_bounds(F[:, 0::len(FEATURE_NAMES)], y, n_classes,
                                                    objects=objects),
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
                            descriptors=D if use_d else None, seed=seed, objects=objects,
                            **model_args(m_best)), report
