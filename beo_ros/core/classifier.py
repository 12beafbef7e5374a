"""Classifier plumbing of a model bank: the classifier dicts' inputs, probabilities, class
priors and checks. ROS-free, arrays in and out.

A grid classifier (modes 'complete', 'partial') takes the (C, F) grid features (and optionally
the grid's shape descriptors), a 'points' classifier the C per-class log-likelihoods + the raw
points' side-normal descriptors; both are dicts of standardisation + multinomial logistic
regression arrays (optionally with one hidden layer) as ``ModelBank.classifier`` holds them.
"""
from __future__ import annotations

import json

import numpy as np

from .class_model import ModelError
from .inference import FEATURE_NAMES
from .shape import BASIC_NAMES as BASIC_SHAPE_DESCRIPTORS, DESCRIPTOR_NAMES as SHAPE_DESCRIPTORS

MODES = ('complete', 'partial')
# optional classifier of estimate_points: inputs are feats[:, 0] (the C per-class exact
# log-likelihoods per known voxel) followed by the descriptors of beo_ros.core.normals
POINTS_MODE = 'points'
POINT_CLASSIFIER_KEYS = ('mean', 'scale', 'coef', 'intercept', 'unknown_threshold')
OPTIONAL_CLASSIFIER_KEYS = ('class_counts',)
# a grid classifier's optional hidden layer (classifier_training.fit_mlp): both arrays or neither
HIDDEN_CLASSIFIER_KEYS = ('hidden_coef', 'hidden_intercept')
# a grid classifier's optional input settings (see classifier_input and descriptor_count)
GRID_INPUT_KEYS = ('row_standardize', 'descriptors', 'descriptor_count')
# named class priors: 'train' keeps the classifier's own probabilities (its training rows'
# class frequencies are its prior); 'uniform' treats every class as equally likely a priori
CLASS_PRIORS = ('train', 'uniform')


def classifier_input(F, n_classes, row_standardize=False, descriptors=None):
    """Classifier input rows (r, C*F [+ D]) from feature rows (r, C*F) or one (C, F) array.

    ``row_standardize``: every feature is standardised across the classes of its own row
    (mean 0, std 1 over the C values). That removes what an object does to all classes alike
    (its size, how much of it was seen) and leaves how the classes compare on it: 5-fold CV
    on the ModelNet10 train split, complete 0.863 -> 0.891, partial 0.847 -> 0.869. Needs
    C >= 3 (with two classes it keeps only the sign of each difference).
    ``descriptors``: optional (r, D) or (D,) shape descriptors of the same rows
    (:func:`beo_ros.core.shape.shape_descriptors`), appended as they are.
    """
    F = np.asarray(F, dtype=np.float64).reshape(-1, n_classes * len(FEATURE_NAMES))
    if row_standardize:
        R = F.reshape(len(F), n_classes, len(FEATURE_NAMES))
        R = (R - R.mean(axis=1, keepdims=True)) / (R.std(axis=1, keepdims=True) + 1e-9)
        F = R.reshape(len(F), -1)
    if descriptors is None:
        return F
    D = np.asarray(descriptors, dtype=np.float64).reshape(len(F), -1)
    return np.hstack([F, D])


def uses_descriptors(clf):
    """Whether a grid classifier dict takes the shape descriptors as extra inputs."""
    return bool(clf.get('descriptors', False))


def descriptor_count(clf):
    """How many shape descriptors (the first of ``shape.DESCRIPTOR_NAMES``) a grid classifier
    dict takes: 0 without descriptors; ``descriptor_count`` when stored, else the 12 of the
    first set (classifiers saved before the second). ModelError for a count that is not an
    integer in 1..len(DESCRIPTOR_NAMES)."""
    if not uses_descriptors(clf):
        return 0
    if 'descriptor_count' not in clf:
        return len(BASIC_SHAPE_DESCRIPTORS)
    c = np.asarray(clf['descriptor_count'])
    if c.shape != () or not np.issubdtype(c.dtype, np.integer) or c.dtype == bool \
            or not 1 <= int(c) <= len(SHAPE_DESCRIPTORS):
        raise ModelError(f"'descriptor_count' must be an integer in 1..{len(SHAPE_DESCRIPTORS)}, "
                         f'got {clf["descriptor_count"]!r}')
    return int(c)


def resolve_class_prior(prior, classes):
    """A class prior as None ('train': the classifier's own) or weights (C,) >= 0 summing
    to 1. ``prior``: 'train', 'uniform', a dict class name -> weight >= 0 (every class), or C
    weights >= 0 in class order; weights need not sum to 1. A class of weight 0 is never chosen.
    Raises ValueError naming what is wrong."""
    C = len(classes)
    if isinstance(prior, str):
        if prior == 'train':
            return None
        if prior == 'uniform':
            return np.full(C, 1.0 / C)
        raise ValueError(f'class_prior must be one of {CLASS_PRIORS}, a dict class -> weight or '
                         f'{C} weights, got {prior!r}')
    if isinstance(prior, dict):
        unknown = sorted(set(prior) - set(classes))
        missing = [c for c in classes if c not in prior]
        if unknown or missing:
            raise ValueError(f'class_prior must give a weight for every class {list(classes)}'
                             + (f'; unknown {unknown}' if unknown else '')
                             + (f'; missing {missing}' if missing else ''))
        prior = [prior[c] for c in classes]
    try:
        w = np.asarray(prior, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f'class_prior weights must be numbers, got {prior!r}') from None
    if w.shape != (C,):
        raise ValueError(f'class_prior needs {C} weights (one per class), got shape {w.shape}')
    if not np.isfinite(w).all() or (w < 0).any() or not w.max() > 0:
        raise ValueError(f'class_prior weights must be finite, >= 0 and not all 0, got {w}')
    w = w / w.max()   # first: the sum of weights near the float64 limit would overflow
    return w / w.sum()


def parse_class_prior(text):
    """A class prior from text (a ROS parameter, a command-line flag): '' -> None (keep the
    model directory's), 'train', 'uniform', or 'name=weight,name=weight,...' -> dict (check it
    with :func:`resolve_class_prior`). A name is everything before the item's last '=' (a name
    may hold '='); a name with a ',' (or starting with '"') is written in double quotes, with
    JSON's escapes (``\\"`` and ``\\\\`` inside): '"a,b"=0.3,c=0.7' (see
    :func:`format_class_prior`). Raises ValueError for malformed text."""
    text = str(text).strip()
    if not text:
        return None
    if '=' not in text:
        if text not in CLASS_PRIORS:
            raise ValueError(f"class_prior must be 'train', 'uniform' or 'name=weight,...' with "
                             f'each class once, got {text!r}')
        return text
    prior = {}
    for name, value in _prior_items(text):
        if not name or name in prior:
            raise ValueError(f"class_prior must be 'train', 'uniform' or 'name=weight,...' with "
                             f'each class once (a name with a comma in double quotes), got '
                             f'{text!r}')
        try:
            prior[name] = float(value)
        except ValueError:
            raise ValueError(f'class_prior: weight of {name!r} is not a number: '
                             f'{value.strip()!r}') from None
    return prior


_JSON = json.JSONDecoder()


def _prior_items(text):
    """(name, weight text) of every item of 'name=weight,...' text (see
    :func:`parse_class_prior`); name '' for an item without '='."""
    pos = 0
    while True:
        start = len(text) - len(text[pos:].lstrip())
        name = None
        if text.startswith('"', start):
            # a quoted name followed by '=' and a weight; anything else is read unquoted, as
            # before quoting (e.g. the name '"a' of '"a=1', '"a"=1' of '"a"=1=2')
            try:
                quoted, end = _JSON.raw_decode(text, start)
            except ValueError:
                quoted = None
            rest = text[end:].lstrip() if quoted is not None else ''
            if rest.startswith('='):
                value_start = len(text) - len(rest) + 1
                comma = text.find(',', value_start)
                value = text[value_start:len(text) if comma < 0 else comma]
                if '=' not in value:
                    name = quoted
        if name is None:
            comma = text.find(',', pos)
            item = text[pos:len(text) if comma < 0 else comma]
            name, sep, value = item.rpartition('=')   # the last '=': a name may hold one
            name = name.strip() if sep else ''
        yield name, value
        if comma < 0:
            return
        pos = comma + 1


def format_class_prior(classes, weights):
    """The text 'name=weight,...' of (C,) ``weights`` over ``classes`` that
    :func:`parse_class_prior` reads back: a name with a ',' or starting with '"' is quoted."""
    def name(c):
        return json.dumps(c, ensure_ascii=False) if ',' in c or c.startswith('"') else c
    return ','.join(f'{name(c)}={float(w):.4g}' for c, w in zip(classes, weights))


def prior_offset(counts, prior):
    """Logit offsets (C,) that move a classifier from its training prior (its training rows
    per class, ``counts`` (C,)) to ``prior`` (C,) (Bayes' rule: p'(c|x) ~ p(c|x) prior_c /
    train_c), or None when ``prior`` or ``counts`` is None. A class without training rows gets
    log prior_c (-inf for prior 0: never chosen): it stays at the ~0 probability its head gives
    it (intercept -30), and only when the prior rules out every class with training rows do
    the others share the probability in proportion to their prior."""
    if prior is None or counts is None:
        return None
    counts = np.asarray(counts, dtype=np.float64)
    seen = counts > 0
    # train_c is 0 for a class without rows: Bayes' rule has no likelihood to move (0 * inf),
    # so it is left out (as if train_c were 1, the least any frequency could lift the class);
    # an offset of 0 ignored its prior weight (0.7 and 0.3 for two such classes gave 0.5, 0.5)
    train = np.where(seen, counts / (counts.sum() or 1.0), 1.0)
    with np.errstate(divide='ignore'):
        return np.log(np.asarray(prior, dtype=np.float64)) - np.log(train)


def _softmax(z):
    z = z - z.max()
    e = np.exp(z)
    return e / e.sum()


def classifier_probabilities(clf, Z, loglik, offset=None):
    """Class probabilities (m, C) and 'unknown' flags (m,) of a classifier dict (mean, scale,
    coef, intercept, unknown_threshold; optionally hidden_coef (H, n_in) and hidden_intercept
    (H,): a ReLU layer between the standardised input and the softmax layer, coef then (C, H))
    on its input rows Z (m, n_in), given every row's per-class exact log-likelihood per known
    voxel (m, C); ``offset`` (C,): added to the logits (a class prior, see :func:`prior_offset`).

    'unknown': the winner explains the object far worse than its own training objects, or the
    classes that do explain it hold less than half the probability (the classifier compares
    classes with each other, so random clutter that only one class tolerates can still win).
    How far below is set where the bounds are fitted (``classifier_training.loglik_bounds``).
    ValueError when a row's logits are not finite.
    """
    L = np.atleast_2d(np.asarray(loglik, dtype=np.float64))
    z = (np.atleast_2d(np.asarray(Z, dtype=np.float64)) - clf['mean']) / clf['scale']
    if 'hidden_coef' in clf:   # classifier_training.fit_mlp's ReLU layer before the softmax one
        z = np.maximum(z @ np.asarray(clf['hidden_coef'], dtype=np.float64).T
                       + clf['hidden_intercept'], 0.0)
    logits = z @ np.asarray(clf['coef'], dtype=np.float64).T + clf['intercept']
    bad = ~np.isfinite(logits).all(axis=1)
    if bad.any():   # else NaN probabilities, and argmax named the first class
        raise ValueError(f'the classifier gave non-finite logits for {int(bad.sum())} of '
                         f'{len(bad)} inputs (non-finite features, or its mean, scale or '
                         'weights make them overflow)')
    if offset is not None:   # -inf for a class of prior 0
        logits = logits + offset
    logits -= logits.max(axis=1, keepdims=True)
    p = np.exp(logits)
    p /= p.sum(axis=1, keepdims=True)
    best = np.argmax(p, axis=1)
    explains = L >= clf['unknown_threshold']
    unknown = ~explains[np.arange(len(L)), best] | ((p * explains).sum(axis=1) < 0.5)
    return p, unknown


def check_grid_classifier(clf, mode, n_classes, where='classifier'):
    """Raise ModelError (naming ``where``) unless ``clf`` is a grid classifier of a known
    ``mode`` whose arrays fit ``n_classes`` classes' features and its shape descriptors, and
    whose row standardisation, if any, has the 3 classes it needs."""
    if mode not in MODES:
        raise ModelError(f'{where}: unknown classifier {mode!r} (known: '
                         f'{", ".join(MODES + (POINTS_MODE,))})')
    if not isinstance(clf, dict):
        raise ModelError(f'{where}: classifier {mode!r} must be a dict of arrays')
    # the flags are read with bool(): a (2,) array raised a bare ValueError, 'no' was True
    for flag in ('row_standardize', 'descriptors'):
        a = np.asarray(clf.get(flag, False))
        if a.shape != () or not (a.dtype == bool or (np.issubdtype(a.dtype, np.integer)
                                                     and int(a) in (0, 1))):
            raise ModelError(f'{where}: classifier {mode!r}: {flag!r} must be true or false, '
                             f'got {a!r}')
    try:
        n_d = descriptor_count(clf)
    except ModelError as e:
        raise ModelError(f'{where}: classifier {mode!r}: {e}') from None
    nf = len(FEATURE_NAMES) * n_classes + n_d
    extra = f' + {n_d} shape descriptors' if n_d else ''
    check_classifier_arrays(clf, n_classes, nf, f'{where}: classifier {mode!r}',
                            f'{n_classes} classes x {len(FEATURE_NAMES)} '
                            f'features{extra}')
    if bool(clf.get('row_standardize', False)) and n_classes < 3:
        raise ModelError(f'{where}: classifier {mode!r} standardises features across '
                         f'classes, which needs at least 3 classes')
    # as the 'points' classifier's: a misspelt 'row_standardise' was ignored without a word
    unexpected = sorted(set(clf) - set(POINT_CLASSIFIER_KEYS) - set(OPTIONAL_CLASSIFIER_KEYS)
                        - set(HIDDEN_CLASSIFIER_KEYS) - set(GRID_INPUT_KEYS), key=str)
    if unexpected:
        raise ModelError(f'{where}: classifier {mode!r} has unexpected arrays {unexpected}')


def check_point_classifier(clf, n_classes, where='classifier'):
    """Raise ModelError unless ``clf`` is a usable 'points' classifier for ``n_classes``:
    mean, scale (C+2,), coef (C, C+2), intercept (C,), unknown_threshold (C,), all finite
    (unknown_threshold may be -inf: never 'unknown'), scale > 0."""
    from .normals import DESCRIPTOR_NAMES as POINT_DESCRIPTORS
    check_classifier_arrays(
        clf, n_classes, n_classes + len(POINT_DESCRIPTORS), f"{where}: 'points' classifier",
        f"{n_classes} log-likelihoods + {', '.join(POINT_DESCRIPTORS)}")
    extra = sorted(set(clf) - set(POINT_CLASSIFIER_KEYS) - set(OPTIONAL_CLASSIFIER_KEYS))
    if extra:
        raise ModelError(f"{where}: 'points' classifier has unexpected arrays {extra}")


def check_classifier_arrays(clf, n_classes, n_in, where, inputs):
    """Raise ModelError unless the dict ``clf`` holds mean, scale (n_in,), coef (C, n_in),
    intercept (C,), unknown_threshold (C,), all numeric and finite (unknown_threshold may be
    -inf: never 'unknown'), scale > 0, and valid optional class_counts. With a hidden layer
    (hidden_coef (H, n_in) and hidden_intercept (H,), both or neither) coef is (C, H).
    ``inputs`` describes the n_in inputs for the message."""
    if not isinstance(clf, dict):
        raise ModelError(f'{where} must be a dict of arrays')
    shapes = dict(mean=(n_in,), scale=(n_in,), coef=(n_classes, n_in), intercept=(n_classes,),
                  unknown_threshold=(n_classes,))
    hidden = [k for k in HIDDEN_CLASSIFIER_KEYS if k in clf]
    if hidden:
        if len(hidden) != len(HIDDEN_CLASSIFIER_KEYS):
            raise ModelError(f"{where} has {hidden[0]!r} without "
                             f"{(set(HIDDEN_CLASSIFIER_KEYS) - set(hidden)).pop()!r}")
        h = np.shape(clf['hidden_intercept'])
        if len(h) != 1 or h[0] < 1:
            raise ModelError(f"{where} 'hidden_intercept' has shape {h}, expected (H,) with "
                             'H >= 1 hidden units')
        shapes.update(hidden_coef=(h[0], n_in), hidden_intercept=h, coef=(n_classes, h[0]))
    for key, shape in shapes.items():
        if key not in clf:
            raise ModelError(f'{where} has no {key!r} array')
        a = np.asarray(clf[key])
        if a.shape != shape or a.dtype.kind not in 'iuf':   # not bool nor timedelta64
            raise ModelError(f'{where} {key!r} has shape {a.shape} ({a.dtype}), expected numbers '
                             f'of shape {shape} ({n_classes} classes; inputs: {inputs})')
        ok = (~np.isnan(a) & (a < np.inf)).all() if key == 'unknown_threshold' else \
            np.isfinite(a).all()
        if not ok:
            raise ModelError(f'{where} {key!r} contains NaN or Inf')
    if (np.asarray(clf['scale']) <= 0).any():
        raise ModelError(f"{where} 'scale' must be positive")
    _check_classifier_counts(clf, n_classes, where)


def _check_classifier_counts(clf, n_classes, where):
    """Raise ModelError unless the optional ``class_counts`` of ``clf`` are (C,) finite >= 0."""
    if 'class_counts' not in clf:
        return
    a = np.asarray(clf['class_counts'])
    if a.shape != (n_classes,) or a.dtype.kind not in 'iuf' \
            or not np.isfinite(a).all() or (a < 0).any() or a.sum() <= 0:
        raise ModelError(f'{where}: class_counts must be {n_classes} finite counts >= 0, got '
                         f'shape {a.shape}')


def apply_point_classifier(clf, loglik, descriptors, offset=None):
    """Class probabilities (m, C) and unknown flags (m,) of a 'points' classifier.

    loglik: (m, C) per-class exact log-likelihood per known voxel (``features[:, 0]``);
    descriptors: (m, 2) finite side-normal descriptors (:mod:`beo_ros.core.normals`).
    'unknown' and ``offset`` as for every classifier (:func:`classifier_probabilities`).
    """
    L = np.atleast_2d(np.asarray(loglik, dtype=np.float64))
    D = np.atleast_2d(np.asarray(descriptors, dtype=np.float64))
    return classifier_probabilities(clf, np.hstack([L, D]), L, offset)
