"""The files of a model directory: layout, checks and the readers of ``ModelBank.load``
(and the checks of ``ModelBank.save``).

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
import io
import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .class_model import ClassModel, ModelError
from .classifier import POINTS_MODE, check_grid_classifier, check_point_classifier
from .estimate import UNKNOWN_LABEL
from .grid import GridSpec

FORMAT = 'beo_ros.models'
VERSION = 1
CLASS_KEYS = ('W', 'mean', 'noise_variance', 'coarse_noise_variance', 'loading_covariance',
              'mean_variance', 'component_variance')
OPTIONAL_CLASS_KEYS = ('coarse_noise_map',)
OPTIONAL_FILES = ('classifier.npz', 'verifier.npz', 'calibration.npz')
MAX_NAME_BYTES = 200   # 'class_XXX_' + name + '.npz' within a file name's 255 bytes


def class_name_problem(name):
    """Why ``name`` cannot be a class name ('' when it can): a class is saved as the file
    ``class_XX_<name>.npz``, so a name must be a non-empty string without '/', '\\' or NUL
    that the file system encoding can encode (no lone surrogate), not '.' or '..', without
    leading or trailing whitespace and at most ``MAX_NAME_BYTES`` long in UTF-8 (the file name
    within the 255 bytes file systems allow), and not 'unknown' (the label of an estimate that
    names no class)."""
    if not isinstance(name, str) or not name:
        return 'class names must be non-empty strings'
    if any(c in name for c in '/\\\0'):
        return "class names cannot contain '/', '\\' or NUL (they name files)"
    try:
        os.fsencode(name)
    except UnicodeEncodeError:   # a lone surrogate: save failed after training, load too
        return 'class names must be text the file system can encode (they name files)'
    if name in ('.', '..'):
        return "class names cannot be '.' or '..'"
    if name == UNKNOWN_LABEL:   # an object seen as nothing (or rejected) was this class
        return f"class names cannot be {UNKNOWN_LABEL!r}, the label of no class"
    if name != name.strip():
        return 'class names cannot start or end with whitespace'
    if len(name.encode('utf-8', 'surrogatepass')) > MAX_NAME_BYTES:
        # save failed with 'File name too long' after training, load with an OSError
        return f'class names can be at most {MAX_NAME_BYTES} bytes long in UTF-8 (they name files)'
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


def check_class_arrays(arr, d, where, size):
    """Raise ModelError unless the arrays of one class file fit a grid of d voxels: W (d, k),
    mean and mean_variance (d,), loading_covariance (k, k) symmetric positive semi-definite,
    component_variance (k,), scalar noise variances; all numeric and finite, variances >= 0
    and the noise variances > 0, the float32 arrays within float32's range and W and mean
    small enough for the float32 sums of the inference. (``coarse_noise_map`` is checked by
    the caller.)"""
    for key, a in arr.items():
        if a.dtype.kind not in 'iuf':   # numpy counts timedelta64 as a number too
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
    # the model is used in float32: a subnormal becomes 0, beyond float32's range the
    # completion's variance became Inf
    tiny, huge = np.finfo(np.float32).tiny, np.finfo(np.float32).max
    if not all(tiny <= arr[key] <= huge for key in ('noise_variance', 'coarse_noise_variance')):
        raise ModelError(f'{where}: noise variances must be positive (at least {tiny:.3g}) and '
                         f'at most {huge:.3g}, got '
                         f"{float(arr['noise_variance']):.3g} and "
                         f"{float(arr['coarse_noise_variance']):.3g}")
    if (arr['mean_variance'] < 0).any() or (arr['component_variance'] < 0).any():
        raise ModelError(f'{where}: mean_variance and component_variance must be >= 0')
    for key in ('loading_covariance', 'mean_variance', 'component_variance'):
        if np.abs(arr[key]).max(initial=0.0) > np.finfo(np.float32).max:
            raise ModelError(f'{where}: {key!r} has values beyond the float32 range')
    # the pose search sums products of W and mean over the grid in float32: beyond this
    # they overflow to Inf, and the scores to NaN (an IndexError or a silently wrong class)
    limit = float(np.sqrt(np.finfo(np.float32).max / (4 * d)))
    for key in ('W', 'mean'):
        top = float(np.abs(arr[key]).max(initial=0.0))
        if top > limit:
            raise ModelError(f'{where}: {key!r} has values up to {top:.3g}, beyond {limit:.3g} '
                             'the float32 inference overflows')
    C = arr['loading_covariance'].astype(np.float64)
    scale = max(float(np.abs(C).max(initial=0.0)), np.finfo(np.float32).tiny)
    if k and (np.abs(C - C.T).max() > 1e-5 * scale
              or np.linalg.eigvalsh(0.5 * (C + C.T)).min() < -1e-5 * scale):
        raise ModelError(f'{where}: loading_covariance must be symmetric positive semi-definite')


def check_noise_map(noise_map, W, mean, d, where):
    """Raise ModelError unless the optional ``coarse_noise_map`` (None or an array) of a class
    of loadings W (d, k) and mean (d,) is d / 8 values that the float32 stage-2 sums can be
    divided by."""
    if noise_map is None:
        return
    noise_map = np.asarray(noise_map)
    # stage 2 divides the float32 sums of W and mean by it: a map value below this
    # overflows them, as a W beyond the limit of check_class_arrays does
    top = max(float(np.abs(W).max(initial=0.0)), float(np.abs(mean).max()))
    f32 = np.finfo(np.float32)
    low, high = max(4 * (d // 8) * top ** 2 / float(f32.max), float(f32.tiny)), f32.max
    if noise_map.shape != (d // 8,) or not (noise_map.min() >= low
                                            and noise_map.max() <= high):
        raise ModelError(f'{where}: coarse_noise_map must be {d // 8} values in '
                         f'[{low:.3g}, {high:.3g}], got shape {noise_map.shape}'
                         + (f', values {float(noise_map.min()):.3g} to '
                            f'{float(noise_map.max()):.3g}'
                            if noise_map.shape == (d // 8,) else ''))


# what np.load raises for a file it cannot read: a truncated or overwritten npz (whose
# checksum may still match a manifest written after it) fails inside zipfile or zlib
UNREADABLE = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)
# a model file's array header claiming a huge shape (a corrupt file) fails the allocation:
# MemoryError, which training data that does not fit (UNREADABLE's other use) must not hide
_UNREADABLE_MODEL = UNREADABLE + (MemoryError,)


def _load_npz(fp):
    """``np.load`` of an npz archive (no pickles); ValueError (in UNREADABLE) for a single
    array saved with ``np.save``, which ``np.load`` returns as is."""
    z = np.load(fp, allow_pickle=False)
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError('a single array (an .npy file?), not an npz archive')
    return z


def _optional_arrays(path, data, name, check):
    """The arrays of the optional file ``name`` of model directory ``path``, or None when
    ``data`` (file name -> checked bytes, see :func:`_read_checked`) does not hold it;
    ModelError when it is unreadable or when ``check(arrays, where)`` gives a reason."""
    if name not in data:
        return None
    fp = path / name
    try:
        with _load_npz(io.BytesIO(data[name])) as z:
            arrays = {k: z[k] for k in z.files}
    except _UNREADABLE_MODEL as e:
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
    """(manifest path, manifest dict, its text) of model directory ``path`` (a Path);
    ModelError unless it is a directory whose manifest.json parses as this format and version
    with a grid object."""
    mf = path / 'manifest.json'
    if not path.is_dir():
        raise ModelError(f'model directory {path} '
                         + ('is a file' if path.exists() else 'does not exist'))
    if not mf.is_file():
        raise ModelError(f'{mf} is missing: not a beo_ros model directory')
    try:
        text = mf.read_text()
        manifest = json.loads(text)
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
    return mf, manifest, text


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
    if not isinstance(manifest['classes'], list) or not classes:
        # list() of a string gives its letters, of an object its keys
        raise ModelError(f'{mf}: classes must be a non-empty list of class names, got '
                         f'{manifest["classes"]!r}')
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
    if spec.size % 2:   # the inference engine's ValueError named no file
        raise ModelError(f'{mf}: grid size must be even (the pose search pools 2x2x2 voxels), '
                         f'got {spec.size}')
    return spec, classes, files


def _read_checked(path, files):
    """dict file name -> bytes of every file of ``files`` (name -> sha256) in directory
    ``path``; ModelError unless each is there with that checksum. The readers parse these
    bytes, not the files again: what is loaded is what was checked, also when a save replaces
    the directory meanwhile (it was read as checked, then parsed from the new files)."""
    data = {}
    for fn, digest in files.items():
        fp = path / fn
        try:
            data[fn] = fp.read_bytes() if fp.is_file() else None
        except OSError:   # removed since (a save replacing the directory)
            data[fn] = None
        if data[fn] is None:
            raise ModelError(f'{fp} is listed in the manifest but missing')
        if hashlib.sha256(data[fn]).hexdigest() != digest:
            raise ModelError(f'{fp} is corrupt: checksum does not match the manifest')
    return data


def _load_class_models(path, data, classes, spec):
    """The ClassModel (float32) of every class name of ``classes``, in order, from its
    ``class_XX_<name>.npz`` of directory ``path`` in ``data`` (file name -> checked bytes, see
    :func:`_read_checked`); ModelError when the file is not listed in the manifest,
    unreadable, lacks an array or its arrays do not fit the grid ``spec``."""
    models = []
    d = spec.size ** 3
    for i, name in enumerate(classes):
        fp = path / f'class_{i:02d}_{name}.npz'
        if fp.name not in data:
            raise ModelError(f'{fp} for class {name!r} is not listed in the manifest')
        try:
            with _load_npz(io.BytesIO(data[fp.name])) as z:
                arr = {k: z[k] for k in CLASS_KEYS}
                arr.update({k: z[k] for k in OPTIONAL_CLASS_KEYS if k in z.files})
        except KeyError as e:
            raise ModelError(f'{fp}: missing array {e}') from None
        except _UNREADABLE_MODEL as e:
            raise ModelError(f'{fp}: unreadable: {type(e).__name__}: {e}') from None
        check_class_arrays(arr, d, fp, spec.size)
        W = arr['W']
        noise_map = arr.get('coarse_noise_map')
        check_noise_map(noise_map, W, arr['mean'], d, fp)
        models.append(ClassModel(
            name=name, W=W.astype(np.float32), mean=arr['mean'].astype(np.float32),
            noise_variance=float(arr['noise_variance']),
            coarse_noise_variance=float(arr['coarse_noise_variance']),
            loading_covariance=arr['loading_covariance'].astype(np.float32),
            mean_variance=arr['mean_variance'].astype(np.float32),
            component_variance=arr['component_variance'].astype(np.float32),
            coarse_noise_map=None if noise_map is None else noise_map.astype(np.float32)))
    return models


def _load_classifier(path, data, n_classes):
    """The classifier dict mode -> arrays of model directory ``path`` for ``n_classes``
    classes, or None when ``data`` (file name -> checked bytes, see :func:`_read_checked`)
    does not hold classifier.npz; ModelError when it is unreadable or a mode is unknown or
    does not fit (see :func:`check_grid_classifier`)."""
    if 'classifier.npz' not in data:
        return None
    fp = path / 'classifier.npz'
    try:
        with _load_npz(io.BytesIO(data['classifier.npz'])) as z:
            arrays = {k: z[k] for k in z.files}
    except _UNREADABLE_MODEL as e:
        raise ModelError(f'{fp}: unreadable: {type(e).__name__}: {e}') from None
    classifier = {}
    for key, a in arrays.items():
        mode, sep, name = key.partition('__')
        if not sep:   # ValueError inside the try above: called 'unreadable'
            raise ModelError(f"{fp}: array {key!r} is not named '<mode>__<array>'")
        classifier.setdefault(mode, {})[name] = a
    for mode, clf in classifier.items():
        if mode == POINTS_MODE:
            check_point_classifier(clf, n_classes, str(fp))
        else:
            check_grid_classifier(clf, mode, n_classes, str(fp))
    return classifier


def _check_manifest_settings(mf, manifest):
    """ModelError (naming manifest file ``mf``) unless the manifest's pose_components,
    training and stage2_noise_map entries are usable."""
    reason = _settings_reason(manifest.get('pose_components', 8), manifest.get('training'))
    if reason:
        raise ModelError(f'{mf}: {reason}')
    if not isinstance(manifest.get('stage2_noise_map', False), bool):
        raise ModelError(f'{mf}: stage2_noise_map must be true or false, got '
                         f'{manifest["stage2_noise_map"]!r}')
