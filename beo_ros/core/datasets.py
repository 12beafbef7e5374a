"""Training data: voxel npz files (checked, with errors naming the file), meshes voxelized
with their class from the file name, class selection, empty objects and the data hash."""
from __future__ import annotations

import hashlib
import json
import os
from collections import Counter

import numpy as np

from .model_files import UNREADABLE


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
    X = vox.reshape(len(vox), n ** 3)   # not -1: a file of no objects is (0, N^3) too
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


def npz_class_names(classes, path):
    """The class names of a voxel npz's 'classes' array (0-D or 1-D; str, or bytes decoded
    as UTF-8, as numpy saves ``np.array([b'chair'])``, where ``str()`` would give "b'chair'");
    ValueError naming ``path`` otherwise."""
    classes = np.asarray(classes)
    if classes.ndim > 1:
        raise ValueError(f"{path}: 'classes' must be a 1-D array of names, got shape "
                         f'{classes.shape}')
    if classes.dtype.kind != 'S':
        return [str(c) for c in np.atleast_1d(classes)]
    try:
        return [bytes(c).decode('utf-8') for c in np.atleast_1d(classes)]
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: 'classes' holds bytes that are not UTF-8 ({e})") from None


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
    'labels', m integers in [0, len(classes)); 'classes', the class names (distinct).
    ValueError naming the file for anything else.
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
            names = npz_class_names(z['classes'], path)
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
    twice = sorted(c for c, k in Counter(names).items() if k > 1)
    if twice:   # selecting such a class kept only the objects of its first index
        raise ValueError(f"{path}: 'classes' names {twice} more than once; class names must "
                         'be distinct')
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
    # abspath, not Path.absolute: that keeps '..', so ../mug.off was of class '..'
    return Path(os.path.abspath(path)).parent.name


def load_meshes(paths, size, classes=None):
    """Voxelize mesh files: (X (m, size^3) float32, labels (m,), sorted class names), the class
    of each file :func:`mesh_class_name`. With ``classes``, the files of other classes are not
    read (their classes stay in the names, with no objects)."""
    from pathlib import Path
    from .meshes import MeshError, load_mesh, voxelize_mesh
    paths = [Path(p) for p in paths]
    names_of = [mesh_class_name(p) for p in paths]
    names = sorted(set(names_of))
    X, labels = [], []
    for p, name in zip(paths, names_of):
        if classes is not None and name not in classes:
            continue
        mesh = load_mesh(p)
        try:
            X.append(voxelize_mesh(mesh, size).ravel())
        except MeshError as e:   # named the mesh, not the file
            raise MeshError(f'{p}: {e}') from None
        labels.append(names.index(name))
    X = np.array(X, dtype=np.float32).reshape(len(X), size ** 3)   # no meshes: (0, size^3)
    return X, np.array(labels, dtype=int), names
