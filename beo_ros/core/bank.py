"""Class model bank: per-class VBPCA models plus the classifier, saved as a checked directory.

Layout of a model directory::

    manifest.json          format, version, classes, grid, training settings, file checksums
    class_00_<name>.npz    W (d, k) float32, mean (d,), noise_variance, coarse_noise_variance,
                           loading_covariance (k, k), mean_variance (d,), component_variance (k,)
    verifier.npz           optional: the orientation verifier's trees (``beo_ros.core.verifier``)
    calibration.npz        optional: the completion's occupancy calibration
                           (``beo_ros.core.calibration``)
    classifier.npz         optional: standardisation + multinomial logistic regression per mode
                           ('complete', 'partial': on the (C, F) grid features, with
                           ``descriptors`` also on the first ``descriptor_count`` shape
                           descriptors of the grid (``beo_ros.core.shape``; 12 when the count
                           is not stored, as before 2026-11-23); 'points': on the
                           C per-class log-likelihoods + the 2 side-normal descriptors of the raw
                           points, used by ``estimate_points`` only); every mode may hold
                           ``class_counts`` (C,): its training rows per class, the prior that
                           ``class_prior`` replaces
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .calibration import OccupancyCalibration, check_arrays as check_calibration_arrays
from .estimate import UNKNOWN_LABEL, Estimate, Hypothesis
from .grid import GridSpec, symmetric_turns, unit_vector, wrap_yaw as _wrap, yaw_grid, yaw_matrix
from .inference import FEATURE_NAMES, InferenceEngine, observed_edt, top_modes, top_yaw_modes
from .outliers import OUTLIER_MADS, OUTLIER_NEIGHBORS, clean_points
from .shape import BASIC_NAMES as BASIC_SHAPE_DESCRIPTORS, DESCRIPTOR_NAMES as SHAPE_DESCRIPTORS
from .shape import shape_descriptors
from .verifier import TURNS, OrientationVerifier, check_arrays, quarter_turned_features

FORMAT = 'beo_ros.models'
VERSION = 1
CLASS_KEYS = ('W', 'mean', 'noise_variance', 'coarse_noise_variance', 'loading_covariance',
              'mean_variance', 'component_variance')
OPTIONAL_CLASS_KEYS = ('coarse_noise_map',)
OPTIONAL_FILES = ('classifier.npz', 'verifier.npz', 'calibration.npz')
MODES = ('complete', 'partial')
# optional classifier of estimate_points: inputs are feats[:, 0] (the C per-class exact
# log-likelihoods per known voxel) followed by the descriptors of beo_ros.core.normals
POINTS_MODE = 'points'
POINT_CLASSIFIER_KEYS = ('mean', 'scale', 'coef', 'intercept', 'unknown_threshold')
OPTIONAL_CLASSIFIER_KEYS = ('class_counts',)
# a grid classifier's optional hidden layer (training.fit_mlp): both arrays or neither
HIDDEN_CLASSIFIER_KEYS = ('hidden_coef', 'hidden_intercept')
# named class priors: 'train' keeps the classifier's own probabilities (its training rows'
# class frequencies are its prior); 'uniform' treats every class as equally likely a priori
CLASS_PRIORS = ('train', 'uniform')
# stage 1 (all classes, leading components) searches at this step; the chosen class is then
# refined at the requested resolution, so a finer stage 1 costs time and gains nothing (measured)
SEARCH_STEP_DEG = 2.0
# the refinement's exact probes either side of the pooled optimum (see ModelBank._refine)
PROBE_DEG = (10.0, 20.0)
# the finest step of the pooled re-scoring and of the first climb: the pooled grid does not
# resolve finer yaws, and its rotation maps of every multiple of a finer step cost seconds and
# gigabytes (0.1 deg: 5 s, 1.4 GB); finer returned yaws come from a second, exact climb
STAGE2_MIN_STEP_DEG = 1.0


class ModelError(ValueError):
    """A model directory or file is missing, corrupt or inconsistent."""


@dataclass
class ClassModel:
    """One class's VBPCA model, float32. W: (d, k); mean, mean_variance: (d,);
    coarse_noise_map: optional (d / 8,) noise variance per voxel of the 2x-pooled grid (used by
    the pose refinement; without it the scalar coarse_noise_variance is used everywhere)."""

    name: str
    W: np.ndarray
    mean: np.ndarray
    noise_variance: float
    coarse_noise_variance: float
    loading_covariance: np.ndarray
    mean_variance: np.ndarray
    component_variance: np.ndarray
    coarse_noise_map: np.ndarray | None = None

    @classmethod
    def from_vbpca(cls, name, est, coarse_noise_variance, coarse_noise_map=None):
        return cls(name=name, W=est.components_.T.astype(np.float32),
                   mean=est.mean_.astype(np.float32), noise_variance=float(est.noise_variance_),
                   coarse_noise_variance=float(coarse_noise_variance),
                   coarse_noise_map=None if coarse_noise_map is None else np.asarray(
                       coarse_noise_map, dtype=np.float32),
                   loading_covariance=est.loading_covariance_.astype(np.float32),
                   mean_variance=np.broadcast_to(est.mean_variance_, est.mean_.shape).astype(
                       np.float32),
                   component_variance=est.component_variance_.astype(np.float32))


def coarse_noise(X, est, n, shrink=100.0, floor=1e-4):
    """Residual variance of 2x-pooled training grids X (m, n^3) under the fitted model: the
    scalar over all voxels, and per pooled voxel (n^3 / 8,), shrunk toward the scalar as if
    ``shrink`` extra objects had the scalar variance (few objects: noisy voxel estimates)."""
    from .inference import pool2
    Z = est.transform(X)
    R = (X - est.inverse_transform(Z)).T.reshape(n, n, n, -1)
    r2 = ((pool2(R) / 8.0) ** 2).reshape(-1, len(X))
    v = float(r2.mean()) + 1e-6
    m = r2.shape[1]
    per = (m * r2.mean(axis=1) + shrink * v) / (m + shrink)
    return v, np.maximum(per, floor).astype(np.float32)


def class_name_problem(name):
    """Why ``name`` cannot be a class name ('' when it can): a class is saved as the file
    ``class_XX_<name>.npz``, so a name must be a non-empty string without '/', '\\' or NUL,
    not '.' or '..', and without leading or trailing whitespace."""
    if not isinstance(name, str) or not name:
        return 'class names must be non-empty strings'
    if any(c in name for c in '/\\\0'):
        return "class names cannot contain '/', '\\' or NUL (they name files)"
    if name in ('.', '..'):
        return "class names cannot be '.' or '..'"
    if name != name.strip():
        return 'class names cannot start or end with whitespace'
    return ''


def check_class_names(names, where='classes'):
    """ValueError (a ModelError) naming the first bad or repeated name of ``names``."""
    names = list(names)
    for name in names:
        why = class_name_problem(name)
        if why:
            raise ModelError(f'{where}: {why}, got {name!r} in {names}')
    if len(set(names)) != len(names):
        raise ModelError(f'{where}: class names must be distinct, got {names}')


def is_model_dir(path):
    """True when directory ``path`` holds a beo_ros model (a manifest of this format), which
    ``ModelBank.save`` may replace as a whole."""
    try:
        manifest = json.loads((Path(path) / 'manifest.json').read_text())
    except (OSError, ValueError, RecursionError):   # ValueError: UnicodeDecodeError too
        return False
    return isinstance(manifest, dict) and manifest.get('format') == FORMAT


def check_save_target(path):
    """ValueError unless ``ModelBank.save`` may write directory ``path``: it may not exist yet,
    be empty, or hold a model (replaced as a whole); anything else is never deleted."""
    path = Path(path)
    if path.is_dir():
        if any(path.iterdir()) and not is_model_dir(path):
            raise ValueError(f'{path} is a non-empty directory that holds no beo_ros model: '
                             'not replaced (give a new or empty directory)')
    elif path.exists() or path.is_symlink():
        raise ValueError(f'{path} exists and is not a directory')


def _sha256(path):
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for chunk in iter(lambda: f.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()


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
    with :func:`resolve_class_prior`). Raises ValueError for malformed text."""
    text = str(text).strip()
    if not text:
        return None
    if '=' not in text:
        if text not in CLASS_PRIORS:
            raise ValueError(f"class_prior must be 'train', 'uniform' or 'name=weight,...' with "
                             f'each class once, got {text!r}')
        return text
    prior = {}
    for item in text.split(','):
        name, sep, value = item.partition('=')
        name = name.strip()
        if not sep or not name or name in prior:
            raise ValueError(f"class_prior must be 'train', 'uniform' or 'name=weight,...' with "
                             f'each class once, got {text!r}')
        try:
            prior[name] = float(value)
        except ValueError:
            raise ValueError(f'class_prior: weight of {name!r} is not a number: '
                             f'{value.strip()!r}') from None
    return prior


def prior_offset(counts, prior):
    """Logit offsets (C,) that move a classifier from its training prior (its training rows
    per class, ``counts`` (C,)) to ``prior`` (C,) (Bayes' rule: p'(c|x) ~ p(c|x) prior_c /
    train_c), or None when ``prior`` or ``counts`` is None."""
    if prior is None or counts is None:
        return None
    counts = np.asarray(counts, dtype=np.float64)
    seen = counts > 0
    with np.errstate(divide='ignore'):
        off = np.where(seen, np.log(prior) - np.log(np.where(seen, counts, 1) / counts.sum()),
                       0.0)
    return off


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
    How far below is set where the bounds are fitted (``training.loglik_bounds``).
    """
    L = np.atleast_2d(np.asarray(loglik, dtype=np.float64))
    z = (np.atleast_2d(np.asarray(Z, dtype=np.float64)) - clf['mean']) / clf['scale']
    if 'hidden_coef' in clf:   # one ReLU layer (training.fit_mlp) before the softmax layer
        z = np.maximum(z @ np.asarray(clf['hidden_coef'], dtype=np.float64).T
                       + clf['hidden_intercept'], 0.0)
    logits = z @ np.asarray(clf['coef'], dtype=np.float64).T + clf['intercept']
    if offset is not None:
        logits = logits + offset
    logits -= logits.max(axis=1, keepdims=True)
    p = np.exp(logits)
    p /= p.sum(axis=1, keepdims=True)
    best = np.argmax(p, axis=1)
    explains = L >= clf['unknown_threshold']
    unknown = ~explains[np.arange(len(L)), best] | ((p * explains).sum(axis=1) < 0.5)
    return p, unknown


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
        if a.shape != shape or not np.issubdtype(a.dtype, np.number) or a.dtype == bool:
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
    if a.shape != (n_classes,) or not np.issubdtype(a.dtype, np.number) \
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


def check_class_arrays(arr, d, where, size):
    """Raise ModelError unless the arrays of one class file fit a grid of d voxels: W (d, k),
    mean and mean_variance (d,), loading_covariance (k, k) symmetric positive semi-definite,
    component_variance (k,), scalar noise variances; all numeric and finite, variances >= 0
    and the noise variances > 0. (``coarse_noise_map`` is checked by the caller.)"""
    for key, a in arr.items():
        if not np.issubdtype(a.dtype, np.number) or a.dtype == bool or np.iscomplexobj(a):
            raise ModelError(f'{where}: {key!r} must hold real numbers, got dtype {a.dtype}')
    W = arr['W']
    if W.ndim != 2 or W.shape[0] != d or arr['mean'].shape != (d,):
        raise ModelError(f'{where}: W {W.shape} / mean {arr["mean"].shape} do not fit the '
                         f'{size}^3 grid of the manifest')
    k = W.shape[1]
    shapes = dict(noise_variance=(), coarse_noise_variance=(), loading_covariance=(k, k),
                  mean_variance=(d,), component_variance=(k,))
    for key, shape in shapes.items():
        if arr[key].shape != shape:
            raise ModelError(f'{where}: {key!r} has shape {arr[key].shape}, expected {shape} '
                             f'(W has {k} components)')
    if not all(np.isfinite(a).all() for a in arr.values()):
        raise ModelError(f'{where}: contains NaN or Inf')
    tiny = np.finfo(np.float32).tiny   # the model is used in float32: a subnormal becomes 0
    if not (arr['noise_variance'] >= tiny and arr['coarse_noise_variance'] >= tiny):
        raise ModelError(f'{where}: noise variances must be positive (at least {tiny:.3g}), got '
                         f"{float(arr['noise_variance']):.3g} and "
                         f"{float(arr['coarse_noise_variance']):.3g}")
    if (arr['mean_variance'] < 0).any() or (arr['component_variance'] < 0).any():
        raise ModelError(f'{where}: mean_variance and component_variance must be >= 0')
    C = arr['loading_covariance'].astype(np.float64)
    scale = max(float(np.abs(C).max(initial=0.0)), np.finfo(np.float32).tiny)
    if k and (np.abs(C - C.T).max() > 1e-5 * scale
              or np.linalg.eigvalsh(0.5 * (C + C.T)).min() < -1e-5 * scale):
        raise ModelError(f'{where}: loading_covariance must be symmetric positive semi-definite')


# what np.load raises for a file it cannot read: a truncated or overwritten npz (whose
# checksum may still match a manifest written after it) fails inside zipfile or zlib
UNREADABLE = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)


def _load_npz(fp):
    """``np.load`` of an npz archive (no pickles); ValueError (in UNREADABLE) for a single
    array saved with ``np.save``, which ``np.load`` returns as is."""
    z = np.load(fp, allow_pickle=False)
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError('a single array (an .npy file?), not an npz archive')
    return z


def _optional_arrays(path, files, name, check):
    """The arrays of the optional file ``name`` of model directory ``path``, or None when the
    manifest's ``files`` do not list it; ModelError when it is unreadable or when
    ``check(arrays, where)`` gives a reason."""
    if name not in files:
        return None
    fp = path / name
    try:
        with _load_npz(fp) as z:
            arrays = {k: z[k] for k in z.files}
    except UNREADABLE as e:
        raise ModelError(f'{fp}: unreadable: {type(e).__name__}: {e}') from None
    reason = check(arrays, str(fp))
    if reason:
        raise ModelError(reason)
    return arrays


def _settings_reason(pose_components, training):
    """Why a bank's pose_components / training settings are unusable (None: they are fine)."""
    if isinstance(pose_components, (bool, np.bool_)) \
            or not isinstance(pose_components, (int, np.integer)) or pose_components < 1:
        return f'pose_components must be an integer >= 1, got {pose_components!r}'
    if training is not None and not isinstance(training, dict):
        return f'training settings must be a mapping, got {type(training).__name__}'
    return None


def _read_manifest(path):
    """(manifest path, manifest dict) of model directory ``path`` (a Path); ModelError unless
    it is a directory whose manifest.json parses as this format and version with a grid
    object."""
    mf = path / 'manifest.json'
    if not path.is_dir():
        raise ModelError(f'model directory {path} '
                         + ('is a file' if path.exists() else 'does not exist'))
    if not mf.is_file():
        raise ModelError(f'{mf} is missing: not a beo_ros model directory')
    try:
        manifest = json.loads(mf.read_text())
    except (OSError, ValueError, RecursionError) as e:
        # ValueError: JSONDecodeError, UnicodeDecodeError, integers of over 4300 digits;
        # RecursionError: arrays nested thousands deep
        raise ModelError(f'{mf} is not valid JSON: {type(e).__name__}: {e}') from None
    if not isinstance(manifest, dict) or manifest.get('format') != FORMAT:
        raise ModelError(f'{mf}: format is not {FORMAT!r}')
    if manifest.get('version') != VERSION:
        raise ModelError(f'{mf}: version {manifest.get("version")!r} is not supported '
                         f'(this beo_ros reads version {VERSION})')
    if not isinstance(manifest.get('grid'), dict):
        raise ModelError(f'{mf}: grid must be an object (size, units, ...), got '
                         f'{manifest.get("grid")!r}')
    return mf, manifest


def _manifest_layout(path, mf, manifest):
    """(GridSpec, class names, dict file name -> sha256) of the manifest dict of model
    directory ``path`` (manifest file ``mf``); ModelError for a bad or missing entry, a file
    name outside the directory, an optional part present but unlisted, a bad class name or
    axes other than xyz with up +z."""
    try:
        spec = GridSpec.from_dict(manifest['grid'])
        classes = list(manifest['classes'])
        files = dict(manifest['files'])
    except (KeyError, TypeError, ValueError) as e:
        raise ModelError(f'{mf}: bad or missing entry: {e}') from None
    for fn in files:
        if not isinstance(fn, str) or fn in ('', '.', '..') or Path(fn).name != fn:
            raise ModelError(f'{mf}: files must name files in the model directory, got '
                             f'{fn!r}')
    for fn in OPTIONAL_FILES:
        # a model saved with it lists it; present but unlisted, the model was tampered with
        # and would silently lose a part
        if fn not in files and (path / fn).exists():
            raise ModelError(f'{path / fn} is present but not listed in the manifest')
    check_class_names(classes, str(mf))   # the rule save applies: train and load agree
    if manifest['grid'].get('up', '+z') != '+z' or manifest['grid'].get('axes', 'xyz') != 'xyz':
        raise ModelError(f'{mf}: only axes xyz with up +z are supported')
    return spec, classes, files


def _check_checksums(path, files):
    """ModelError unless every file of ``files`` (name -> sha256) is in directory ``path``
    with that checksum."""
    for fn, digest in files.items():
        fp = path / fn
        if not fp.is_file():
            raise ModelError(f'{fp} is listed in the manifest but missing')
        if _sha256(fp) != digest:
            raise ModelError(f'{fp} is corrupt: checksum does not match the manifest')


def _load_class_models(path, files, classes, spec):
    """The ClassModel (float32) of every class name of ``classes``, in order, from its
    ``class_XX_<name>.npz`` in directory ``path``; ModelError when the file is not listed in
    ``files``, unreadable, lacks an array or its arrays do not fit the grid ``spec``."""
    models = []
    d = spec.size ** 3
    for i, name in enumerate(classes):
        fp = path / f'class_{i:02d}_{name}.npz'
        if fp.name not in files:
            raise ModelError(f'{fp} for class {name!r} is not listed in the manifest')
        try:
            with _load_npz(fp) as z:
                arr = {k: z[k] for k in CLASS_KEYS}
                arr.update({k: z[k] for k in OPTIONAL_CLASS_KEYS if k in z.files})
        except KeyError as e:
            raise ModelError(f'{fp}: missing array {e}') from None
        except UNREADABLE as e:
            raise ModelError(f'{fp}: unreadable: {type(e).__name__}: {e}') from None
        check_class_arrays(arr, d, fp, spec.size)
        W = arr['W']
        noise_map = arr.get('coarse_noise_map')
        if noise_map is not None and (noise_map.shape != (d // 8,) or noise_map.min() <= 0):
            raise ModelError(f'{fp}: coarse_noise_map must be {d // 8} positive values, got '
                             f'shape {noise_map.shape}')
        models.append(ClassModel(
            name=name, W=W.astype(np.float32), mean=arr['mean'].astype(np.float32),
            noise_variance=float(arr['noise_variance']),
            coarse_noise_variance=float(arr['coarse_noise_variance']),
            loading_covariance=arr['loading_covariance'].astype(np.float32),
            mean_variance=arr['mean_variance'].astype(np.float32),
            component_variance=arr['component_variance'].astype(np.float32),
            coarse_noise_map=None if noise_map is None else noise_map.astype(np.float32)))
    return models


def _load_classifier(path, files, n_classes):
    """The classifier dict mode -> arrays of model directory ``path`` for ``n_classes``
    classes, or None when ``files`` does not list classifier.npz; ModelError when it is
    unreadable or a mode is unknown or does not fit (see :func:`_check_grid_classifier`)."""
    if 'classifier.npz' not in files:
        return None
    fp = path / 'classifier.npz'
    try:
        with _load_npz(fp) as z:
            classifier = {}
            for key in z.files:
                mode, name = key.split('__', 1)
                classifier.setdefault(mode, {})[name] = z[key]
    except UNREADABLE as e:
        raise ModelError(f'{fp}: unreadable: {type(e).__name__}: {e}') from None
    for mode, clf in classifier.items():
        if mode == POINTS_MODE:
            check_point_classifier(clf, n_classes, str(fp))
        else:
            _check_grid_classifier(clf, mode, n_classes, fp)
    return classifier


def _check_grid_classifier(clf, mode, n_classes, fp):
    """ModelError (naming file ``fp``) unless ``clf`` is a grid classifier of a known ``mode``
    whose arrays fit ``n_classes`` classes' features and its shape descriptors, and whose row
    standardisation, if any, has the 3 classes it needs."""
    if mode not in MODES:
        raise ModelError(f'{fp}: unknown classifier {mode!r} (known: '
                         f'{", ".join(MODES + (POINTS_MODE,))})')
    try:
        n_d = descriptor_count(clf)
    except ModelError as e:
        raise ModelError(f'{fp}: classifier {mode!r}: {e}') from None
    nf = len(FEATURE_NAMES) * n_classes + n_d
    extra = f' + {n_d} shape descriptors' if n_d else ''
    check_classifier_arrays(clf, n_classes, nf, f'{fp}: classifier {mode!r}',
                            f'{n_classes} classes x {len(FEATURE_NAMES)} '
                            f'features{extra}')
    if bool(clf.get('row_standardize', False)) and n_classes < 3:
        raise ModelError(f'{fp}: classifier {mode!r} standardises features across '
                         f'classes, which needs at least 3 classes')


def _check_manifest_settings(mf, manifest):
    """ModelError (naming manifest file ``mf``) unless the manifest's pose_components,
    training and stage2_noise_map entries are usable."""
    reason = _settings_reason(manifest.get('pose_components', 8), manifest.get('training'))
    if reason:
        raise ModelError(f'{mf}: {reason}')
    if not isinstance(manifest.get('stage2_noise_map', False), bool):
        raise ModelError(f'{mf}: stage2_noise_map must be true or false, got '
                         f'{manifest["stage2_noise_map"]!r}')


class ModelBank:
    """A set of class models over one grid, with pose search, completion and classification.

    Args:
        models: list of ClassModel (same d = spec.size ** 3).
        spec: GridSpec of the training grids.
        classifier: dict mode -> dict(mean, scale, coef, intercept, unknown_threshold), or None
            (then the class with the largest likelihood wins, as in the paper). Mode 'points'
            (optional, see :func:`check_point_classifier`) is used by ``estimate_points``: on
            the per-class log-likelihoods + the raw points' side-normal descriptors.
        training: free-form dict recorded in the manifest.
        pose_components: leading components used by the coarse pose search.
        class_prior: the prior over classes the probabilities assume (see
            :func:`resolve_class_prior`): 'train' (default: the classifier as trained, its
            training rows' class frequencies), 'uniform', or weights per class. Settable; the
            manifest records the one a model directory was built for.
        verifier: optional fitted ``OrientationVerifier``: picks among the refined yaw and its
            90, 180 and 270° turns (``estimate(..., verify=True)``).
        occupancy_calibration: optional fitted ``OccupancyCalibration``: maps the completion's
            model probabilities of the unknown voxels to calibrated ones.
        stage2_noise_map: score the stage-2 refinement with the per-voxel noise variance of
            the pooled model (``coarse_noise_map``) instead of the class scalar. Off: since
            the observed-frame scoring it lowers the yaw accuracy (397 views of fold 0, yaw of
            the true class within 10 deg: 0.728 with the map, 0.768 with the scalar), because
            the log-determinant of a nearest-neighbour-rotated noise map changes with the yaw.
    """

    def __init__(self, models, spec: GridSpec, classifier=None, training=None,
                 pose_components=8, stage2_noise_map=False, class_prior='train',
                 verifier=None, occupancy_calibration=None):
        if not models:
            raise ModelError('a model bank needs at least one class')
        names = [m.name for m in models]
        if len(set(names)) != len(names):
            raise ModelError(f'class names must be unique, got {names}')
        d = spec.size ** 3
        for m in models:
            if m.W.ndim != 2 or m.W.shape[0] != d or m.mean.shape != (d,):
                raise ModelError(f'class {m.name!r}: W {m.W.shape} / mean {m.mean.shape} do not '
                                 f'match the {spec.size}^3 grid')
        if classifier and POINTS_MODE in classifier:
            check_point_classifier(classifier[POINTS_MODE], len(models))
        self.models = list(models)
        self.spec = spec
        self.classifier = classifier
        self.class_prior = class_prior
        if verifier is not None:
            if not hasattr(verifier, 'arrays_'):
                raise ModelError('the orientation verifier is not fitted')
            reason = check_arrays(verifier.arrays_, len(models), spec.size)
            if reason:
                raise ModelError(reason)
        self.verifier = verifier
        if occupancy_calibration is not None:
            if not hasattr(occupancy_calibration, 'probability_'):
                raise ModelError('the occupancy calibration is not fitted')
            reason = check_calibration_arrays(occupancy_calibration.arrays_)
            if reason:
                raise ModelError(reason)
        self.occupancy_calibration = occupancy_calibration
        reason = _settings_reason(pose_components, training)
        if reason:
            raise ModelError(reason)
        self.training = dict(training or {})
        self.pose_components = int(pose_components)
        self.stage2_noise_map = bool(stage2_noise_map)
        k = max(m.W.shape[1] for m in models)
        W = np.zeros((len(models), d, k), dtype=np.float32)
        for i, m in enumerate(models):
            W[i, :, :m.W.shape[1]] = m.W
        self.engine = InferenceEngine(
            W, np.stack([m.mean for m in models]), [m.noise_variance for m in models],
            [m.coarse_noise_variance for m in models], spec.size, pose_components,
            coarse_noise_maps=[m.coarse_noise_map for m in models] if stage2_noise_map else None)

    def __reduce__(self):
        # pickled as its constructor arguments: the inference engine (thread-local scratch,
        # caches) is rebuilt on the other side, e.g. in a worker process
        return (type(self), (self.models, self.spec, self.classifier, self.training,
                             self.pose_components, self.stage2_noise_map, self.class_prior,
                             self.verifier, self.occupancy_calibration))

    def __repr__(self):
        lo, hi = min(m.W.shape[1] for m in self.models), max(m.W.shape[1] for m in self.models)
        modes = [f"{m}: {'mlp' if 'hidden_coef' in self.classifier[m] else 'logistic'}"
                 for m in sorted(self.classifier)] if self.classifier else ['max-likelihood']
        return (f'ModelBank({len(self.models)} classes {self.classes}, grid {self.spec.size}^3 '
                f'{self.spec.units}, k {lo if lo == hi else f"{lo}-{hi}"}, classifier {modes}, '
                f'verifier {"yes" if self.verifier is not None else "no"}, '
                f'calibrated {"yes" if self.occupancy_calibration is not None else "no"}, '
                f'prior {self.class_prior!r})')

    @property
    def classes(self):
        return [m.name for m in self.models]

    @property
    def class_prior(self):
        """'train', 'uniform' or the (C,) normalised weights set (see the class docstring)."""
        return self._class_prior

    @class_prior.setter
    def class_prior(self, prior):
        weights = resolve_class_prior(prior, self.classes)
        self._prior_weights = weights
        self._class_prior = prior if isinstance(prior, str) else weights

    def with_class_prior(self, prior):
        """A copy of the bank with another class prior, sharing models, classifier and inference
        engine (no rebuild); raises ValueError for a bad prior."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.class_prior = prior
        return new

    def _prior_offset(self, clf):
        """Logit offsets (C,) of ``clf`` for the bank's class prior, or None (see
        :func:`prior_offset`)."""
        return prior_offset(clf.get('class_counts'), self._prior_weights)

    def prior_note(self, mode):
        """Why the class prior is not applied to classifier ``mode`` ('' when it is, or when
        the prior is 'train')."""
        clf = (self.classifier or {}).get(mode)
        if self._prior_weights is None or clf is None or 'class_counts' in clf:
            return ''
        return (f'class_prior not applied: the {mode!r} classifier has no class_counts '
                '(trained before they were recorded); its training prior is used')

    @property
    def has_point_classifier(self) -> bool:
        """True when ``estimate_points`` classifies with the raw points' normal descriptors."""
        return bool(self.classifier) and POINTS_MODE in self.classifier

    # ------------------------------------------------------------------ persistence
    def save(self, path):
        """Write the bank to directory ``path`` and return it. ``path`` may be new, empty, or
        hold a model, which is replaced as a whole (see :func:`check_save_target`). The files
        go to a temporary directory beside ``path`` that is renamed into place when complete:
        on any failure (or Ctrl-C) it is removed and a model already at ``path`` is kept."""
        check_class_names(self.classes, 'cannot save the model')
        path = Path(path)
        if path.is_symlink() and path.is_dir():   # replace the directory, keep the link
            path = path.resolve()
        check_save_target(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f'.{path.name}.tmp-', dir=path.parent))
        try:
            umask = os.umask(0)
            os.umask(umask)
            tmp.chmod(0o777 & ~umask)   # mkdtemp's 0o700 would outlive the rename
            self._write(tmp)
            if path.is_dir():
                # two renames: a reader sees the old model or the new one, never a mix (for
                # the instant between them, no directory)
                old = Path(tempfile.mkdtemp(prefix=f'.{path.name}.old-', dir=path.parent))
                try:
                    os.replace(path, old)   # onto the empty directory mkdtemp made
                    try:
                        os.replace(tmp, path)
                    except BaseException:
                        os.replace(old, path)
                        raise
                finally:
                    shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    def _write(self, path):
        """Write the model files and the manifest (last) into the existing directory ``path``."""
        files = {}
        for i, m in enumerate(self.models):
            fn = f'class_{i:02d}_{m.name}.npz'
            np.savez_compressed(path / fn, **{k: np.asarray(getattr(m, k)) for k in
                                              CLASS_KEYS + OPTIONAL_CLASS_KEYS
                                              if getattr(m, k) is not None})
            files[fn] = _sha256(path / fn)
        if self.verifier is not None:
            np.savez_compressed(path / 'verifier.npz', **self.verifier.arrays_)
            files['verifier.npz'] = _sha256(path / 'verifier.npz')
        if self.occupancy_calibration is not None:
            np.savez_compressed(path / 'calibration.npz', **self.occupancy_calibration.arrays_)
            files['calibration.npz'] = _sha256(path / 'calibration.npz')
        if self.classifier:
            arrays = {f'{mode}__{k}': np.asarray(v) for mode, clf in self.classifier.items()
                      for k, v in clf.items()}
            np.savez_compressed(path / 'classifier.npz', **arrays)
            files['classifier.npz'] = _sha256(path / 'classifier.npz')
        manifest = {
            'format': FORMAT, 'version': VERSION, 'classes': self.classes,
            'grid': dict(self.spec.to_dict(), axes='xyz', up='+z'),
            'pose_components': self.pose_components,
            'stage2_noise_map': self.stage2_noise_map,
            'class_prior': (self.class_prior if isinstance(self.class_prior, str)
                            else [float(w) for w in self.class_prior]),  # in class order
            'features': list(FEATURE_NAMES),
            'training': self.training, 'files': files,
        }
        (path / 'manifest.json').write_text(json.dumps(manifest, indent=2) + '\n')

    @classmethod
    def load(cls, path, class_prior=None):
        """Load and check a model directory; raises ModelError naming the bad file.

        ``class_prior``: overrides the manifest's (None: the manifest's; 'train' when it has
        none); a bad value raises ValueError (a bad one in the manifest: ModelError)."""
        path = Path(path)
        mf, manifest = _read_manifest(path)
        spec, classes, files = _manifest_layout(path, mf, manifest)
        _check_checksums(path, files)
        models = _load_class_models(path, files, classes, spec)
        classifier = _load_classifier(path, files, len(classes))
        arrays = _optional_arrays(path, files, 'verifier.npz',
                                  lambda a, where: check_arrays(a, len(classes), spec.size, where))
        verifier = None if arrays is None else OrientationVerifier.from_arrays(arrays)
        arrays = _optional_arrays(path, files, 'calibration.npz', check_calibration_arrays)
        calibration = None if arrays is None else OccupancyCalibration.from_arrays(arrays)
        if class_prior is None:
            class_prior = manifest.get('class_prior', 'train')
            try:
                resolve_class_prior(class_prior, classes)
            except ValueError as e:
                raise ModelError(f'{mf}: {e}') from None
        _check_manifest_settings(mf, manifest)
        return cls(models, spec, classifier, manifest.get('training'),
                   manifest.get('pose_components', 8),
                   stage2_noise_map=manifest.get('stage2_noise_map', False),
                   class_prior=class_prior,
                   verifier=verifier, occupancy_calibration=calibration)

    # ------------------------------------------------------------------ queries
    def check_grid(self, grid):
        grid = np.asarray(grid)
        if grid.shape != self.spec.shape:
            raise ValueError(f'grid must have shape {self.spec.shape}, got {grid.shape}')
        if np.issubdtype(grid.dtype, np.floating):
            # whole values only: a cast would truncate 0.7 to free and NaN to anything
            if not np.isfinite(grid).all() or (grid != np.round(grid)).any():
                raise ValueError('a float grid must hold the whole values 1 (occupied), 0 (free) '
                                 'or -1 (unknown)')
        elif not np.issubdtype(grid.dtype, np.integer) and grid.dtype != bool:
            raise ValueError(f'grid must be an integer array (1 occupied, 0 free, -1 unknown), '
                             f'got dtype {grid.dtype}')
        # checked before the cast to int8, which would wrap 255 to -1 and 257 to 1
        if grid.min() < -1 or grid.max() > 1:
            raise ValueError('grid values must be 1 (occupied), 0 (free) or -1 (unknown)')
        return grid.astype(np.int8)

    def features(self, grid, yaw=None, yaw_step_deg=SEARCH_STEP_DEG, exhaustive=True):
        """Per-class best yaw (stage-1 search every ``yaw_step_deg``), exact posterior and
        features for a labelled grid.

        Returns (features (C, F), list of per-class dicts: yaw, exact, hypotheses, searched,
        search_step_deg, pooled and observed (the grid's pooled weights and its
        ``InferenceEngine.observe`` arrays, shared)).
        """
        grid = self.check_grid(grid)
        check_step('yaw_step_deg', yaw_step_deg)
        yaw = check_yaw(yaw)
        if not (grid == 1).any():   # all free or all unknown: every class would "fit"
            raise ValueError('grid has no occupied voxel: there is no object to estimate')
        eng = self.engine
        pooled = eng.pooled(grid)
        obs = eng.observe(grid)
        if yaw is None:
            best_yaw, best_ll, searched = eng.search(grid, yaw_step_deg, exhaustive=exhaustive,
                                                     pooled=pooled)
        else:
            best_ll = eng.scores(pooled, [float(yaw)])[0]
            best_yaw = np.full(eng.C, float(yaw))
            searched = [(np.array([float(yaw)]), best_ll[c:c + 1]) for c in range(eng.C)]
        edt_pad = np.append(observed_edt(grid).ravel(), 0.0)
        n_pooled = grid.size / 8.0
        feats, per = [], []
        for c in range(eng.C):
            ex = eng.exact(obs, c, float(best_yaw[c]))
            feats.append(eng.features(ex, c, best_ll[c] / n_pooled, edt_pad[ex['idx']]))
            yaws_c, ll_c = searched[c]
            modes = top_yaw_modes(yaws_c, ll_c, 3)   # exhaustive or coarse-to-fine yaws
            per.append(dict(yaw=float(best_yaw[c]), exact=ex, searched=searched[c],
                            search_step_deg=float(yaw_step_deg), pooled=pooled, observed=obs,
                            hypotheses=[(float(yaws_c[i]), float(ll_c[i])) for i in modes]))
        return np.array(feats), per

    def classify_features(self, feats, mode, grid=None):
        """Class probabilities (C,) and the unknown flag from a (C, F) feature array (and the
        labelled grid, for a classifier that also takes its shape descriptors)."""
        if self.classifier and mode in self.classifier:
            clf = self.classifier[mode]
            desc = None
            if uses_descriptors(clf):
                if grid is None:
                    raise ValueError(f'the {mode!r} classifier takes shape descriptors: pass the '
                                     'grid')
                desc = shape_descriptors(grid)[:descriptor_count(clf)]
            x = classifier_input(feats, len(self.models), bool(clf.get('row_standardize', False)),
                                 desc)
            p, unknown = classifier_probabilities(clf, x, feats[:, 0], self._prior_offset(clf))
            return p[0], bool(unknown[0])
        # the paper's rule: the class whose model explains the observation best (times the
        # class prior, when one is set: 'uniform' changes nothing)
        logits = feats[:, 0] * 50.0
        if self._prior_weights is not None:
            with np.errstate(divide='ignore'):
                logits = logits + np.log(self._prior_weights)
        return _softmax(logits), False

    def classify_points(self, feats, point_features):
        """Class probabilities (C,) and the unknown flag of the 'points' classifier from the
        (C, F) grid features and the (2,) finite side-normal descriptors of the raw points."""
        clf = self.classifier[POINTS_MODE]
        p, unknown = apply_point_classifier(clf, np.asarray(feats)[:, 0][None], point_features,
                                            self._prior_offset(clf))
        return p[0], bool(unknown[0])

    def _completion(self, grid, per, probs, best, min_prob=0.1, max_classes=3):
        """Occupancy probability and variance (N, N, N) in the observed frame, averaged over the
        likely classes (Bayesian model averaging: weights = class probabilities >= min_prob);
        the probability of the unknown voxels is then calibrated when the bank has an
        ``occupancy_calibration``. The variance is that of the linear-Gaussian occupancy."""
        order = [int(c) for c in np.argsort(-probs)[:max_classes] if probs[c] >= min_prob]
        order = order or [best]
        w = probs[order] / probs[order].sum()
        prob = np.zeros(grid.shape, np.float64)
        m1 = np.zeros(grid.shape, np.float64)
        m2 = np.zeros(grid.shape, np.float64)
        for wc, c in zip(w, order):
            mc = self.models[c]
            p_c, mean_c, var_c = self.engine.predictive(
                per[c]['exact'], c, mc.loading_covariance.astype(np.float64), mc.mean_variance)
            yaw_c = per[c]['yaw']
            # back to the observed frame; outside the rotated model is empty space
            to_obs = self.engine.to_observed
            prob += wc * to_obs(p_c, yaw_c).reshape(grid.shape)
            mean_c = to_obs(mean_c, yaw_c).reshape(grid.shape)
            var_c = to_obs(var_c, yaw_c).reshape(grid.shape)
            m1 += wc * mean_c
            m2 += wc * (var_c + mean_c.astype(np.float64) ** 2)
        variance = np.maximum(m2 - m1 ** 2, 0)
        if self.occupancy_calibration is not None:
            unknown = grid < 0
            prob[unknown] = self.occupancy_calibration.predict(prob[unknown])
        # what was observed is kept: seen surface occupied, seen space free
        prob = np.where(grid == 1, 1.0, np.where(grid == 0, 0.0, prob))
        variance = np.where(grid >= 0, 0.0, variance)
        return prob.astype(np.float32), variance.astype(np.float32)

    def _refine(self, grid, c, per_c, step_deg=1.0, window_deg=3.0, stage2_step_deg=1.0,
                stage2_modes=6, stage2_window_deg=15.0, probe_deg=PROBE_DEG):
        """Refine the yaw of class ``c``: re-score it on the pooled grid with all its components
        (every ``stage2_step_deg``; None skips this), then re-solve it exactly at full resolution
        at the pooled optimum and at +-``probe_deg`` from it, and climb from the best of those
        to the best yaw within +-window_deg (the pooled grid cannot tell apart yaws a few
        degrees apart, and its optimum is sometimes 10-20 degrees off the full-resolution one).
        ``window_deg`` 0 skips the probes and the climb."""
        best = per_c
        eng = self.engine
        obs = eng.observe(per_c.get('observed', grid))
        if stage2_step_deg:
            step = np.deg2rad(stage2_step_deg)
            yaws = yaw_grid(stage2_step_deg)
            rows = None
            if stage2_modes and stage2_window_deg:
                sy, sl = per_c['searched']
                m0 = top_yaw_modes(sy, sl, stage2_modes)
                r = np.rint(sy[m0] / step).astype(int)
                w = int(round(stage2_window_deg / stage2_step_deg))
                rows = np.unique((r[:, None] + np.arange(-w, w + 1)).ravel() % len(yaws))
            ll = self.engine.scores(self._pooled(grid, per_c), yaws, c, full=True,
                                    rows=rows)[:, 0]
            if rows is not None:
                full_ll = np.full(len(yaws), -np.inf)
                full_ll[rows] = ll
                ll = full_ll
            modes = top_modes(ll, 3, max(1, int(round(20.0 / stage2_step_deg))))
            modes = [i for i in modes if np.isfinite(ll[i])]
            y0 = float(yaws[modes[0]])
            best = dict(per_c, yaw=y0, exact=eng.exact(obs, c, y0, with_prediction=False),
                        hypotheses=[(float(yaws[i]), float(ll[i])) for i in modes])
        if window_deg > 0 and probe_deg:
            # exact solves a little further out: on 794 partial views of fold 0 (true class)
            # the probes at +-10, +-20 deg raised yaw <= 10 deg from 0.783 to 0.795 and with
            # flips from 0.902 to 0.918 for about 5 ms (2 ms since the exact posterior is
            # faster); probes at the other pooled modes, at the 90 and 180 deg turns or also at
            # +-30, +-45 deg did not help (the pooled ranking of distant modes is better)
            y0, top = best['yaw'], best['exact']['loglik']
            for off in probe_deg:
                for sign in (1, -1):
                    y = float(y0 + sign * np.deg2rad(off))
                    ex = eng.exact(obs, c, y, with_prediction=False)
                    if ex['loglik'] > top:
                        top, best = ex['loglik'], dict(best, yaw=y, exact=ex)
        # hill climbing up to +-window_deg in steps of max(step_deg, 1 deg), then below 1 deg
        # in step_deg steps within +-1 deg: 2-4 exact solves per level instead of a scan
        coarse = max(step_deg, STAGE2_MIN_STEP_DEG)
        best = self._climb(obs, c, best, coarse, window_deg)
        if step_deg < coarse and window_deg > 0:
            best = self._climb(obs, c, best, step_deg, min(window_deg, coarse))
        eng.add_prediction(best['exact'], obs, c)
        return best

    def _climb(self, obs, c, best, step_deg, window_deg):
        """Hill climbing of the exact log-likelihood from best['yaw'] in step_deg steps, up
        to +-window_deg, first upward, then downward if that found nothing better (the
        full-resolution likelihood is smooth at this scale, up to the plateaus of the
        nearest-neighbour rotation, which the climb walks across)."""
        step, y0 = np.deg2rad(step_deg), best['yaw']
        for direction in (1, -1):
            top = best['exact']['loglik']
            for i in range(1, int(round(window_deg / step_deg)) + 1):
                y = float(y0 + direction * i * step)
                ex = self.engine.exact(obs, c, y, with_prediction=False)
                if ex['loglik'] < top:
                    break
                top = ex['loglik']
                if top > best['exact']['loglik']:
                    best = dict(best, yaw=y, exact=ex)
            if best['yaw'] != y0:
                break
        return best

    def _pooled_score(self, grid, c, per_c, yaw, step_deg=STAGE2_MIN_STEP_DEG):
        """Pooled log-likelihood of class ``c`` with all its components at ``yaw`` rounded to
        the stage-2 grid of ``step_deg`` (whose rotation maps are cached), as the hypotheses'
        scores."""
        yaws = yaw_grid(step_deg)
        row = int(np.rint(yaw / np.deg2rad(step_deg))) % len(yaws)
        return float(self.engine.scores(self._pooled(grid, per_c), yaws, c, full=True,
                                        rows=[row])[0, 0])

    def _pooled(self, grid, per_c):
        """The 2x-pooled observation: the search's (``per_c['pooled']``), else made now."""
        pooled = per_c.get('pooled')
        return self.engine.pooled(grid) if pooled is None else pooled

    def _verify_turns(self, grid, c, per_c):
        """The refined yaw of class ``c`` or one of its 90, 180, 270° turns: the one with the
        largest exact log-likelihood + weight x log P(turn 0) of the orientation verifier
        (fold 0 of ModelNet10 through ``estimate``, models, classifier and verifier fitted
        without it: yaw within 10° 0.797 -> 0.827 and 0.777 -> 0.811 on two sets of 794
        views, with flips +1.1 / +1.2 points; see ``beo_ros.core.verifier``)."""
        y0 = per_c['yaw']
        yaws = y0 + np.arange(TURNS) * (np.pi / 2)
        logp = self.verifier.predict_log_proba(c, quarter_turned_features(grid, y0))[:, 0]
        # only the turns the verifier prefers to y0 are solved: y0 is the likelihood's own
        # choice, so another turn could win only by a higher likelihood (5 % of the turns on
        # fold 0); skipping them changed 0.5 % of the choices and none of the accuracy, and
        # saves 3 exact solves on most views (0.26 per view instead of 3)
        w = float(self.verifier.weight)
        eng = self.engine
        obs = eng.observe(per_c.get('observed', grid))
        best_k, best_score, best_ex = 0, per_c['exact']['loglik'] + w * logp[0], None
        for k in range(1, TURNS):
            if logp[k] <= logp[0]:
                continue
            ex = eng.exact(obs, c, float(yaws[k]), with_prediction=False)
            if ex['loglik'] + w * logp[k] > best_score:
                best_k, best_score, best_ex = k, ex['loglik'] + w * logp[k], ex
        if best_k == 0:
            return per_c
        return dict(per_c, yaw=float(yaws[best_k]), exact=eng.add_prediction(best_ex, obs, c),
                    turned=best_k)

    def estimate(self, grid, yaw=None, yaw_step_deg=1.0, n_hypotheses=5, exhaustive=True,
                 refine_deg=3.0, stage2_modes=6, stage2_window_deg=15.0, search_step_deg=None,
                 point_features=None, probe_deg=PROBE_DEG, verify=True):
        """Classify, orient and complete one labelled grid (see :class:`Estimate`).

        Args:
            grid: int8 (N, N, N), 1 occupied, 0 free, -1 unknown, axes x, y, z, z up.
            yaw: if given (radians), no pose search is done.
            yaw_step_deg: resolution of the returned yaw, in [0.05, 90]. Below 1° the pooled
                re-scoring stays at 1° and a last exact climb within +-1° gives the finer
                yaw (at 32^3 the nearest-neighbour rotation hardly resolves it).
            search_step_deg: step of the stage-1 search over all classes (default
                max(SEARCH_STEP_DEG, yaw_step_deg)); its features feed the classifier.
            exhaustive: stage 1 scores all 360 / search_step_deg yaws at once (default); False
                searches coarse-to-fine (5 degree steps, then the best modes).
            stage2_modes, stage2_window_deg: the chosen class is re-scored on the pooled grid
                with all its components (not only the leading ``pose_components``) every
                yaw_step_deg within +-stage2_window_deg of its ``stage2_modes`` best stage-1
                modes (either None or 0: all yaws);
            probe_deg: then it is solved exactly at full resolution at the pooled optimum
                and at +- each of these offsets (degrees; () or None: no probes), and
            refine_deg: climbs from the best of those within +-refine_deg
                (0: no refinement at all, the stage-1 yaw is returned).
            verify: with an orientation verifier for the chosen class, the refined yaw may
                then be replaced by one of its quarter turns (``_verify_turns``; False: not).
            point_features: optional (2,) side-normal descriptors of the object's raw points
                (:func:`beo_ros.core.normals.side_normal_descriptors`; ``estimate_points``
                passes them). When the bank has a 'points' classifier and they are finite, that
                classifier decides the class (and so the refined pose and the completion);
                NaN descriptors fall back to the grid rule (``classifier_note`` says so).
                None: the grid rule, exactly as without this argument.
        """
        t0 = time.perf_counter()
        grid = self.check_grid(grid)
        search_step_deg, probe_deg, stage2_window_deg = _check_estimate_options(
            yaw_step_deg, search_step_deg, probe_deg, refine_deg, stage2_window_deg, n_hypotheses,
            stage2_modes)
        yaw = check_yaw(yaw)
        if not (grid == 1).any():
            return self._no_object(grid, yaw, t0)
        feats, per = self.features(grid, yaw, search_step_deg, exhaustive)
        t1 = time.perf_counter()
        probs, unknown, rule, note, point_features = self._classify(feats, grid, point_features)
        best = int(np.argmax(probs))
        t_cls = time.perf_counter()
        if yaw is None and refine_deg > 0:
            per[best] = self._refine(grid, best, per[best], yaw_step_deg, refine_deg,
                                     max(yaw_step_deg, STAGE2_MIN_STEP_DEG), stage2_modes,
                                     stage2_window_deg, probe_deg)
        t_ref = time.perf_counter()
        refined_yaw = per[best]['yaw']
        if yaw is None and refine_deg > 0 and verify and self.verifier is not None \
                and self.verifier.has_class(best):
            per[best] = self._verify_turns(grid, best, per[best])
        t2 = time.perf_counter()
        completion, variance = self._completion(grid, per, probs, best)
        est_yaw = per[best]['yaw']
        turns = symmetric_turns(completion >= 0.5)
        t3 = time.perf_counter()
        hyps = self._hypotheses(grid, per, best, refined_yaw, yaw_step_deg)
        label = UNKNOWN_LABEL if unknown else self.classes[best]
        return Estimate(
            label=label, scores={c: float(p) for c, p in zip(self.classes, probs)},
            yaw=_wrap(est_yaw),
            symmetric_yaws=[_wrap(est_yaw + t) for t in turns],
            completion=completion, variance=variance,
            hypotheses=[Hypothesis(lab, _wrap(y), float(s))
                        for lab, y, s in hyps[:n_hypotheses]],
            timings={'pose_and_features': t1 - t0, 'classify': t_cls - t1,
                     'pose_refinement': t_ref - t_cls, 'orientation_check': t2 - t_ref,
                     'completion': t3 - t2,
                     'total': t3 - t0},
            features=feats, grid=grid, classifier_mode=rule, point_features=point_features,
            classifier_note=note)

    def _classify(self, feats, grid, point_features):
        """Class probabilities (C,) and 'unknown' flag of one grid (N, N, N) from its features
        ``feats`` (C, F): by the 'points' classifier when the bank has one and the optional
        ``point_features`` (2,) are finite, else by the grid rule of the grid's mode.

        Returns (probs, unknown, rule: 'points', 'complete', 'partial' or 'max_likelihood',
        note: why the 'points' classifier was not used and / or the class prior not applied,
        point_features as float64 (2,) or None); ValueError for point_features of another
        shape."""
        mode = 'complete' if (grid < 0).mean() < 0.01 else 'partial'
        rule, note = None, ''
        if point_features is not None:
            point_features = np.asarray(point_features, dtype=np.float64).reshape(-1)
            if point_features.shape != (2,):
                raise ValueError(f'point_features must be 2 values (r4, frac10), got shape '
                                 f'{point_features.shape}')
            if self.has_point_classifier:
                if np.isfinite(point_features).all():
                    probs, unknown = self.classify_points(feats, point_features)
                    rule = POINTS_MODE
                else:
                    note = ("'points' classifier not used: side-normal descriptors undefined "
                            '(too few points or side normals); grid rule')
        if rule is None:
            probs, unknown = self.classify_features(feats, mode, grid)
            rule = mode if self.classifier and mode in self.classifier else 'max_likelihood'
        note = '; '.join(n for n in (note, self.prior_note(rule)) if n)
        return probs, unknown, rule, note, point_features

    def _hypotheses(self, grid, per, best, refined_yaw, yaw_step_deg):
        """The pose hypotheses (class name, yaw, score), best first, of a grid whose chosen
        class ``best`` has the refined (and maybe verifier-turned) search result ``per[best]``
        (``refined_yaw``: its yaw before the verifier): that class's yaw modes (the first at
        ``refined_yaw``; a verifier's quarter turn before them, with its own pooled score), then
        every other class's best mode, by score."""
        est_yaw = per[best]['yaw']
        # the chosen class's yaw modes first (symmetric objects have several), then the others
        hyps = [(self.classes[best], y, ll) for y, ll in per[best]['hypotheses']]
        if hyps:  # the best mode, as refined at full resolution
            hyps[0] = (hyps[0][0], refined_yaw, hyps[0][2])
        if per[best].get('turned'):
            # the verifier's quarter turn goes first, with its own pooled score (it may be
            # lower than the likelihood's choice, which stays listed); modes within 10 degrees
            # of it are the same hypothesis
            score = self._pooled_score(grid, best, per[best], est_yaw,
                                       max(yaw_step_deg, STAGE2_MIN_STEP_DEG))
            hyps = [(self.classes[best], est_yaw, score)] + \
                [h for h in hyps if abs(_wrap(h[1] - est_yaw)) >= np.deg2rad(10.0)]
        hyps += sorted(((self.classes[c], y, ll) for c in range(len(per)) if c != best
                        for y, ll in per[c]['hypotheses'][:1]), key=lambda h: -h[2])
        return hyps

    def _no_object(self, grid, yaw, t0):
        """The estimate of a grid with no occupied voxel (all free or unknown, e.g. the view of
        a one-voxel object that the rotation lost): no object, so label 'unknown', the class
        prior as scores, nothing completed, no pose hypotheses."""
        weights = self._prior_weights
        if weights is None:   # the 'train' prior: the classifier's training rows per class
            counts = ((self.classifier or {}).get('partial') or {}).get('class_counts')
            weights = np.ones(len(self.classes)) if counts is None else \
                np.asarray(counts, dtype=np.float64)
        weights = np.asarray(weights, dtype=np.float64) / np.sum(weights)
        yaw = 0.0 if yaw is None else _wrap(float(yaw))
        zeros = np.zeros(grid.shape, dtype=np.float32)
        return Estimate(label=UNKNOWN_LABEL, scores=dict(zip(self.classes, map(float, weights))),
                        yaw=yaw, completion=zeros, variance=zeros.copy(), grid=grid,
                        timings={'total': time.perf_counter() - t0}, classifier_mode='none',
                        classifier_note='grid has no occupied voxel: no object to estimate')

    def estimate_points(self, points, sensor_origin=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0),
                        yaw_step_deg=1.0, threshold=0.5, center=None,
                        outlier_mads=OUTLIER_MADS, outlier_neighbors=OUTLIER_NEIGHBORS,
                        cluster_tolerance=None):
        """Estimate from an (n, 3) cloud in metres (any frame; the sensor at ``sensor_origin``).

        The pose and completed points come back in the input frame (see :class:`Estimate`).
        Non-finite points are dropped, then statistical outliers
        (:func:`beo_ros.core.outliers.statistical_outliers` with ``outlier_neighbors`` and
        ``outlier_mads``; None: none removed; ``Estimate.n_outliers`` counts them), as the
        extent of the points places and scales the grid. With a ``cluster_tolerance`` (same
        unit as the points; None: off) only the largest cluster of the remaining points is
        kept (:func:`beo_ros.core.outliers.outside_largest_cluster`; counted in
        ``Estimate.n_off_cluster``): for segments that caught part of another surface or
        object. With a 'points' classifier the
        side-normal descriptors of the remaining points are computed too
        (``timings['point_descriptors']``) and passed to :meth:`estimate`. The outlier removal
        grows faster than the points (5 s for a million): downsample big clouds first, as the
        node does (``max_points``).
        """
        from .voxelize import finite_points, grid_to_points, unit_direction, voxelize_view
        if isinstance(threshold, (bool, np.bool_)) or not 0 < threshold <= 1:   # and NaN
            raise ValueError(f'threshold must be an occupancy probability in (0, 1], got '
                             f'{threshold}')
        t0 = time.perf_counter()
        pts_in, n_outliers, n_off_cluster = clean_points(
            finite_points(points), outlier_mads, outlier_neighbors, cluster_tolerance)
        t_out = time.perf_counter()
        view = voxelize_view(pts_in, sensor_origin, up, self.spec, center=center)
        t1 = time.perf_counter()
        up = unit_direction(up, 'up')   # valid: voxelize_view has checked it
        point_features = None
        if self.has_point_classifier:
            from .normals import side_normal_descriptors
            point_features = side_normal_descriptors(pts_in, up, sensor_origin)
        t2 = time.perf_counter()
        est = self.estimate(view.grid, yaw_step_deg=yaw_step_deg, point_features=point_features)
        T = np.asarray(view.grid_to_input, dtype=np.float64)
        R_grid = T[:3, :3] / np.linalg.norm(T[:3, :3], axis=0)
        pose = np.eye(4)
        pose[:3, :3] = R_grid @ yaw_matrix(est.yaw)
        pts, prob = grid_to_points(est.completion, T, threshold)
        c = (self.spec.size - 1) / 2.0
        pose[:3, 3] = object_centre(pts if len(pts) else grid_to_points(view.grid, T, 1)[0],
                                    pose[:3, :3], T @ np.array([c, c, c, 1.0]))
        est.pose = pose
        est.heading_offset = heading_offset(R_grid, up)
        est.grid_to_input = T
        est.completed_points = np.asarray(pts, dtype=np.float32)
        est.completed_probability = np.asarray(prob, dtype=np.float32)
        est.n_outliers = n_outliers
        est.n_off_cluster = n_off_cluster
        est.timings['outliers'] = t_out - t0
        est.timings['voxelize'] = t1 - t_out
        if point_features is not None:
            est.timings['point_descriptors'] = t2 - t1
        est.timings['total'] = time.perf_counter() - t0
        return est


def object_centre(points, rotation, fallback) -> np.ndarray:
    """(3,) middle of the extent of ``points`` (m, 3, input frame) along the object axes
    ``rotation`` (3, 3: axes as columns, input frame); ``fallback`` (3,) when there are none.
    (The grid centre alone is where the voxelization put the view, not the object: on a
    'bottom' grid it lies (N-1)/2 voxels above the support, above a short object.)"""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.asarray(fallback, dtype=np.float64)[:3]
    local = pts @ rotation
    return rotation @ ((local.min(axis=0) + local.max(axis=0)) / 2.0)


def heading_offset(grid_rotation, up) -> float:
    """Radians to add to a grid-frame yaw to get the heading about ``up`` in the input frame:
    the angle from the input frame's x axis projected on the plane normal to ``up`` (its y axis
    when x is within 25 degrees of ``up`` or of down) to the grid's x axis.
    ``grid_rotation`` (3, 3): the grid axes in the input frame, z = up."""
    u = unit_vector(up)
    ref = np.eye(3)[0] - u * u[0]
    if np.linalg.norm(ref) < np.sin(np.deg2rad(25.0)):
        ref = np.eye(3)[1] - u * u[1]
    ref /= np.linalg.norm(ref)
    g = np.asarray(grid_rotation, dtype=np.float64)[:, 0]
    return float(np.arctan2(np.cross(u, ref) @ g, ref @ g))


def check_yaw(yaw):
    """``yaw`` as a float (radians), or None (search it); ValueError unless it is a finite
    real number or None."""
    if yaw is None:
        return None
    if isinstance(yaw, int) and not isinstance(yaw, bool):   # beyond int64 numpy makes objects
        try:
            yaw = float(yaw)
        except OverflowError:
            raise ValueError(f'yaw must be finite, got an integer of {yaw.bit_length()} '
                             'bits') from None
    a = np.asarray(yaw) if not isinstance(yaw, (str, bytes)) else None
    if a is None or a.ndim != 0 or a.dtype == bool or not np.issubdtype(a.dtype, np.number) \
            or np.iscomplexobj(a):
        raise ValueError(f'yaw must be None or a number of radians, got {yaw!r}')
    if not np.isfinite(a):
        raise ValueError(f'yaw must be finite, got {yaw}')
    return float(a)


def check_step(name, value):
    """Raise ValueError unless ``value`` is a real number of degrees in [0.05, 90]."""
    if isinstance(value, (bool, np.bool_)) \
            or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not 0.05 <= value <= 90:   # also refuses NaN
        raise ValueError(f'{name} must be a number of degrees in [0.05, 90], got {value!r}')


def check_count(name, value):
    """Raise ValueError unless ``value`` is an integer >= 0 (bool is not one)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or value < 0:
        raise ValueError(f'{name} must be an integer >= 0, got {value!r}')


def _probe_offsets(probe_deg):
    """``probe_deg`` of :meth:`ModelBank.estimate` (None, one number or several, a list or an
    array) as a tuple of offsets (degrees); ValueError unless each is a number in (0, 180]."""
    if probe_deg is None:
        probe_deg = ()
    elif np.ndim(probe_deg) == 0:
        probe_deg = (probe_deg.item() if isinstance(probe_deg, np.ndarray) else probe_deg,)
    elif isinstance(probe_deg, np.ndarray):
        probe_deg = probe_deg.ravel().tolist()
    try:
        probe_deg = tuple(probe_deg)
    except TypeError:
        raise ValueError(f'probe_deg must be offsets in (0, 180] degrees, got '
                         f'{probe_deg!r}') from None
    if not all(isinstance(p, (int, float, np.floating, np.integer))
               and not isinstance(p, bool) and 0 < p <= 180 for p in probe_deg):
        raise ValueError(f'probe_deg must be offsets in (0, 180] degrees, got {probe_deg}')
    return probe_deg


def _check_estimate_options(yaw_step_deg, search_step_deg, probe_deg, refine_deg,
                            stage2_window_deg, n_hypotheses, stage2_modes):
    """Check the search options of :meth:`ModelBank.estimate` (ValueError naming the first bad
    one) and return (search_step_deg: max(SEARCH_STEP_DEG, yaw_step_deg) when None,
    probe_deg: a tuple (see :func:`_probe_offsets`), stage2_window_deg: 0.0 when None)."""
    check_step('yaw_step_deg', yaw_step_deg)
    if search_step_deg is not None:
        check_step('search_step_deg', search_step_deg)
    probe_deg = _probe_offsets(probe_deg)
    if stage2_window_deg is None:
        stage2_window_deg = 0.0
    for name, value in (('refine_deg', refine_deg), ('stage2_window_deg', stage2_window_deg)):
        if isinstance(value, (bool, np.bool_)) or not 0 <= value <= 180:   # and NaN
            raise ValueError(f'{name} must be in [0, 180] degrees, got {value}')
    check_count('n_hypotheses', n_hypotheses)
    if stage2_modes is not None:
        check_count('stage2_modes', stage2_modes)
    if search_step_deg is None:
        search_step_deg = max(SEARCH_STEP_DEG, yaw_step_deg)
    return search_step_deg, probe_deg, stage2_window_deg


def load_models(path=None, class_prior=None):
    """Load a model directory (default: the shipped ``models/modelnet10_32``; a shipped model's
    bare name such as 'tabletop_32' also works, see :func:`resolve_model_dir`); ``class_prior``
    overrides the manifest's (see :class:`ModelBank`)."""
    return ModelBank.load(resolve_model_dir(path), class_prior)


def default_model_dir(name='modelnet10_32'):
    """The shipped model directory: the installed share dir, else the source tree's models/."""
    try:
        from ament_index_python.packages import get_package_share_directory
        p = Path(get_package_share_directory('beo_ros')) / 'models' / name
        if p.is_dir():
            return p
    except Exception:  # not installed through ament, or ament_index missing
        pass
    return Path(__file__).resolve().parents[2] / 'models' / name


def resolve_model_dir(text) -> Path:
    """A model directory as a user names it: '' or None is the shipped default; a path that
    exists is itself; a bare name that is not a path here (e.g. 'tabletop_32') is that shipped
    model, so an installed package needs no share path. Anything else comes back as given
    (loading it then names it as missing)."""
    if not text:
        return default_model_dir()
    path = Path(text).expanduser()
    if path.exists() or len(path.parts) != 1 or str(text).startswith(('.', '~')):
        return path
    shipped = default_model_dir(str(text))
    return shipped if shipped.is_dir() else path


def shipped_models() -> list:
    """Names of the shipped model directories (those with a manifest)."""
    root = default_model_dir().parent
    return sorted(p.parent.name for p in root.glob('*/manifest.json'))
