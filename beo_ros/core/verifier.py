"""Orientation verifier: which quarter turn of a pose hypothesis is the class's own orientation.

The class models explain a view about as well after a 180° (or 90°) turn when the object is
nearly symmetric; which turn the training set calls "front" then shows in details the
likelihood of a linear Gaussian model weighs little. The verifier learns them directly: per
class, gradient-boosted trees (scikit-learn's ``HistGradientBoostingClassifier``) on the view
turned into the model's frame (occupied, free and unknown fractions, pooled to 8^3) predict
which of the turns 0, 90, 180 or 270° maps it onto the class's orientation. At query time the
refined yaw and its three turns are scored by exact log-likelihood + ``weight`` x log
P(turn 0) (``ModelBank._verify_turns``; a turn is solved only when the verifier prefers it to
the refined yaw, the likelihood's own choice).

The fitted trees are exported to flat arrays (no pickles in model directories) and evaluated
in numpy; ``predict_log_proba`` equals scikit-learn's ``predict_proba`` (tested).
"""
from __future__ import annotations

import numpy as np

from .grid import rotate_grid

TURNS = 4
# inputs: occupied, free and unknown fractions of the 8^3 pooled cells
CELLS = 8 ** 3
N_FEATURES = 3 * CELLS
# weight of the verifier's log-probability against the exact log-likelihood of the known
# voxels (a sum over thousands of voxels): chosen on 794 fold-0 views (true class, models and
# verifier fitted without fold 0) and checked on 794 others; 300 .. 10000 all gave +2.7 to
# +3.4 points of yaw within 10°, 1000 the most on both
DEFAULT_WEIGHT = 1000.0
# the way out for a grid size the verifier cannot pool to 8^3 (the rest of the model can)
NO_VERIFIER_HINT = ('; train without an orientation verifier (--verifier-views 0, '
                    'verifier_views=0) for this grid size')
ARRAY_KEYS = ('feature', 'threshold', 'left', 'right', 'is_leaf', 'value', 'roots',
              'baseline', 'depth', 'classes', 'weight', 'grid_size')


def verifier_features(canonical):
    """(3 * 512,) float32: fractions of occupied, free and unknown voxels of an int8 (N, N, N)
    labelled grid in the model's frame, pooled to 8^3 (N a multiple of 8)."""
    g = np.asarray(canonical)
    n = g.shape[0]
    if g.ndim != 3 or len(set(g.shape)) != 1 or n % 8:
        raise ValueError(f'verifier features need an (N, N, N) grid with N a multiple of 8, '
                         f'got shape {g.shape}'
                         + (NO_VERIFIER_HINT if g.ndim == 3 and len(set(g.shape)) == 1 else ''))
    f = n // 8
    # one pass: every voxel counts in bin (channel, pooled cell); channel 0 occupied, 1 free,
    # 2 unknown (labels 1, 0, -1)
    cell = _cell_index(n)
    counts = np.bincount((1 - g.ravel().astype(np.int64)) * CELLS + cell, minlength=N_FEATURES)
    return (counts / np.float32(f ** 3)).astype(np.float32)


_CELLS = {}


def _cell_index(n):
    """(n^3,) index of the 8^3 pooled cell of every voxel of an (n, n, n) grid (cached)."""
    if n not in _CELLS:
        i = np.arange(n) // (n // 8)
        _CELLS[n] = (i[:, None, None] * 64 + i[None, :, None] * 8 + i[None, None, :]).ravel()
    return _CELLS[n]


def turned_features(grid, yaws):
    """(len(yaws), 1536) verifier features of ``grid`` turned into the model's frame by each
    hypothesis yaw (radians; the yaw maps the model onto the observation)."""
    return np.stack([verifier_features(rotate_grid(grid, -float(y), fill=-1)) for y in yaws])


def quarter_turned_features(grid, yaw):
    """(4, 1536) verifier features of ``grid`` turned into the model's frame by ``yaw`` and by
    ``yaw`` + 90, 180, 270°: one resampling, then exact quarter turns of the pooled fractions
    (the same as :func:`turned_features` of the four yaws: nearest-neighbour rotation by a
    further 90° is a permutation of the centred grid; except at yaws of exactly 45° + k 90°,
    where voxel centres tie and rounding half to even breaks the ties differently per turn:
    a few of the 1536 features differ there)."""
    P = verifier_features(rotate_grid(grid, -float(yaw), fill=-1)).reshape(3, 8, 8, 8)
    return np.stack([np.rot90(P, k, axes=(2, 1)).ravel() for k in range(TURNS)])


class OrientationVerifier:
    """Per-class gradient-boosted classifiers of the quarter turn, scikit-learn style.

    Args: ``max_iter``, ``learning_rate``, ``max_leaf_nodes``, ``l2_regularization``,
    ``random_state``: those of ``HistGradientBoostingClassifier`` (no early stopping);
    ``weight``: see ``DEFAULT_WEIGHT``.

    Learned attributes: ``classes_`` (the class indices with a verifier), ``arrays_`` (the
    exported trees, see ``ARRAY_KEYS``), ``n_features_in_``.
    """

    def __init__(self, max_iter=300, learning_rate=0.1, max_leaf_nodes=15,
                 l2_regularization=1.0, random_state=0, weight=DEFAULT_WEIGHT):
        self.max_iter = max_iter
        self.learning_rate = learning_rate
        self.max_leaf_nodes = max_leaf_nodes
        self.l2_regularization = l2_regularization
        self.random_state = random_state
        self.weight = weight

    def fit(self, X, turn, y, grid_size):
        """X: (m, 1536) features of canonicalised views; turn: (m,) in 0..3, the quarter turn
        the view was given on top of its true yaw; y: (m,) class index of each row. Classes
        whose rows lack a turn get no verifier. Returns self."""
        from sklearn.ensemble import HistGradientBoostingClassifier
        X = np.asarray(X, dtype=np.float32)
        turn, y = np.asarray(turn), np.asarray(y)
        if X.ndim != 2 or len(X) != len(turn) or len(X) != len(y):
            raise ValueError(f'X (m, F), turn (m,) and y (m,) must have the same m, got '
                             f'{X.shape}, {turn.shape}, {y.shape}')
        if len(X) == 0 or not np.isin(turn, np.arange(TURNS)).all():
            raise ValueError('turn must hold quarter turns 0..3 (and there must be rows)')
        if not (np.isfinite(self.weight) and self.weight >= 0):
            raise ValueError(f'weight must be finite and >= 0, got {self.weight}')
        trees = []
        for c in np.unique(y):
            m = y == c
            if len(np.unique(turn[m])) < TURNS:
                continue
            clf = HistGradientBoostingClassifier(
                max_iter=self.max_iter, learning_rate=self.learning_rate,
                max_leaf_nodes=self.max_leaf_nodes, l2_regularization=self.l2_regularization,
                early_stopping=False, random_state=self.random_state).fit(X[m], turn[m])
            trees.append((int(c), clf))
        if not trees:
            raise ValueError('no class has rows of all four turns')
        self.arrays_ = export_trees(trees, self.weight, grid_size)
        self.classes_ = [c for c, _ in trees]
        self.n_features_in_ = X.shape[1]
        return self

    @classmethod
    def from_arrays(cls, arrays):
        """A fitted verifier from exported arrays (``check_arrays`` them first)."""
        v = cls(weight=float(arrays['weight']))
        v.arrays_ = {k: np.asarray(arrays[k]) for k in ARRAY_KEYS}
        v.classes_ = [int(c) for c in v.arrays_['classes']]
        v.n_features_in_ = N_FEATURES
        return v

    def __getstate__(self):
        # the walk arrays are a cache of arrays_ (rebuilt on first use): not pickled
        state = dict(self.__dict__)
        state.pop('_walk', None)
        return state

    def _walk_arrays(self):
        """(feature, threshold, left, right) with every leaf pointing at itself (threshold
        +max: 'go left' = stay), so a fixed number of steps needs no leaf test."""
        if getattr(self, '_walk', None) is None or self._walk[0] is not self.arrays_:
            a = self.arrays_
            leaf = a['is_leaf'].astype(bool)
            own = np.arange(len(leaf), dtype=np.int32)
            self._walk = (a, np.where(leaf, 0, a['feature']).astype(np.intp),
                          np.where(leaf, np.finfo(np.float32).max, a['threshold']),
                          np.where(leaf, own, a['left']).astype(np.intp),
                          np.where(leaf, own, a['right']).astype(np.intp))
        return self._walk[1:]

    def has_class(self, c):
        return int(c) in self.classes_

    def predict_log_proba(self, c, X):
        """(m, 4) log-probabilities of the quarter turns for rows X (m, 1536) under class c's
        verifier (one row may be given as (1536,)). ValueError for rows of another width."""
        a = self.arrays_
        feature, threshold, left, right = self._walk_arrays()
        j = self.classes_.index(int(c))
        X = np.atleast_2d(np.asarray(X, dtype=np.float32))
        # the walk indexes the rows flattened: a narrower row read the next row's features
        # (or raised numpy's IndexError), a wider one its own first columns, without a word
        if X.ndim != 2 or X.shape[1] != self.n_features_in_:
            raise ValueError(f'X must be (m, {self.n_features_in_}) verifier features, got '
                             f'shape {X.shape}')
        roots = a['roots'][j]                           # (iterations, 4) node indices
        node = np.broadcast_to(roots.ravel(), (len(X), roots.size)).astype(np.intp)
        flat = X.ravel()
        base = (np.arange(len(X)) * X.shape[1])[:, None]
        for _ in range(int(a['depth'][j])):
            go_left = flat[base + feature[node]] <= threshold[node]
            node = np.where(go_left, left[node], right[node])
        raw = a['value'][node].reshape(len(X), *roots.shape).sum(axis=1, dtype=np.float64)
        raw += a['baseline'][j]
        raw -= raw.max(axis=1, keepdims=True)
        return raw - np.log(np.exp(raw).sum(axis=1, keepdims=True))


def export_trees(trees, weight, grid_size):
    """Flat arrays of fitted ``HistGradientBoostingClassifier``s [(class, clf), ...] (4
    classes each; numerical splits only): node arrays over all trees with global child
    indices, per class the root of every (iteration, turn) tree, its baseline and depth."""
    feature, threshold, left, right, is_leaf, value = [], [], [], [], [], []
    roots, baseline, depth = [], [], []
    offset = 0
    for _, clf in trees:
        if clf.n_trees_per_iteration_ != TURNS:
            raise ValueError('each verifier must predict the 4 turns')
        r = np.zeros((len(clf._predictors), TURNS), dtype=np.int32)
        dmax = 0
        for i, per_turn in enumerate(clf._predictors):
            for k, pred in enumerate(per_turn):
                nodes = pred.nodes
                if nodes['is_categorical'].any():
                    raise ValueError('categorical splits are not supported')
                r[i, k] = offset
                feature.append(nodes['feature_idx'].astype(np.int16))
                threshold.append(nodes['num_threshold'].astype(np.float32))
                left.append(nodes['left'].astype(np.int32) + offset)
                right.append(nodes['right'].astype(np.int32) + offset)
                is_leaf.append(nodes['is_leaf'].astype(bool))
                value.append(nodes['value'].astype(np.float32))
                dmax = max(dmax, int(nodes['depth'].max()))
                offset += len(nodes)
        roots.append(r)
        baseline.append(np.asarray(clf._baseline_prediction, dtype=np.float64).reshape(TURNS))
        depth.append(dmax)
    if len({r.shape for r in roots}) != 1:
        raise ValueError('all class verifiers must have the same number of iterations')
    return dict(feature=np.concatenate(feature), threshold=np.concatenate(threshold),
                left=np.concatenate(left), right=np.concatenate(right),
                is_leaf=np.concatenate(is_leaf), value=np.concatenate(value),
                roots=np.stack(roots), baseline=np.stack(baseline),
                depth=np.asarray(depth, dtype=np.int32),
                classes=np.asarray([c for c, _ in trees], dtype=np.int32),
                weight=np.asarray(float(weight)), grid_size=np.asarray(int(grid_size)))


def check_arrays(arrays, n_classes, grid_size, where='verifier'):
    """Reason (str) why exported verifier arrays are unusable with a bank of ``n_classes``
    classes on an N = ``grid_size`` grid, or None when they are fine."""
    missing = [k for k in ARRAY_KEYS if k not in arrays]
    if missing:
        return f'{where}: missing arrays {missing}'
    a = {k: np.asarray(arrays[k]) for k in ARRAY_KEYS}
    # index arrays integers, the rest real numbers, weight and grid_size scalars: a float class
    # index was truncated, a string weight or a (2,) grid_size raised a bare TypeError
    real = (np.integer, np.floating)
    kinds = dict(is_leaf=(np.bool_, np.integer), threshold=real, value=real, baseline=real,
                 weight=real)
    for k in ARRAY_KEYS:
        ok = kinds.get(k, (np.integer,))
        if not any(np.issubdtype(a[k].dtype, t) for t in ok):
            return f'{where}: {k} has dtype {a[k].dtype}, expected ' + \
                ('integers' if ok == (np.integer,) else 'real numbers')
    for k in ('weight', 'grid_size'):
        if a[k].shape != ():
            return f'{where}: {k} must be a scalar, got shape {a[k].shape}'
    if a['feature'].ndim != 1 or a['classes'].ndim != 1:
        return f'{where}: feature and classes must be 1-D'
    n = len(a['feature'])
    if any(a[k].shape != (n,) for k in ('threshold', 'left', 'right', 'is_leaf', 'value')):
        return f'{where}: node arrays differ in length'
    C = len(a['classes'])
    if a['roots'].ndim != 3 or a['roots'].shape[0] != C or a['roots'].shape[2] != TURNS \
            or a['baseline'].shape != (C, TURNS) or a['depth'].shape != (C,):
        return f'{where}: roots, baseline or depth do not fit {C} classes x {TURNS} turns'
    if C == 0 or len(set(a['classes'].tolist())) != C or a['classes'].min() < 0 \
            or a['classes'].max() >= n_classes:
        return f'{where}: classes must be distinct indices below {n_classes}'
    if int(a['grid_size']) != grid_size:
        return f'{where}: made for a {int(a["grid_size"])}^3 grid, the models are {grid_size}^3'
    for k in ('left', 'right', 'roots'):
        if n == 0 or a[k].min() < 0 or a[k].max() >= n:
            return f'{where}: {k} indices outside the {n} nodes'
    if a['feature'].min() < 0 or a['feature'].max() >= N_FEATURES:
        return f'{where}: feature indices outside the {N_FEATURES} inputs'
    if not all(np.isfinite(a[k]).all() for k in ('threshold', 'value', 'baseline', 'weight')) \
            or float(a['weight']) < 0:
        return f'{where}: thresholds, values, baseline and weight must be finite (weight >= 0)'
    if a['depth'].min() < 0 or a['depth'].max() > 64:
        return f'{where}: tree depth out of range'
    return None
