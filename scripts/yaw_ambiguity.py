#!/usr/bin/env python
"""Measurement: how often does one partial view not determine an object's yaw at all?

Not imported by the package or the tests. No model is involved: for objects of a voxel npz
(the shared format), a view is made by the evaluation protocol
(``beo_ros.core.synthetic.random_partial_view``: random yaw, azimuth U[0, 360), elevation
U[10, 50] deg), then the *same* object is turned by a further 90, 180 and 270 deg and viewed
from the same direction. When a turned view labels the grid as the original view does, no
method that sees only the view can tell the two yaws apart; the yaw is uniform, so it is right
on such a view with probability at most 1 / m, m = 1 + the number of such turns. The mean of
1 / m over the views is an upper bound of "yaw within 10 deg" for *any* estimator (on objects
that are their own image under a turn at IoU 1; the looser thresholds count near-images).

It is a bound on the object, not on what a class model can learn: a night stand seen from the
back differs from the same night stand seen from the front, but it may look like another night
stand's front. The second table measures that on whole objects, again without a model: for
every object that is not its own image under a quarter or half turn (IoU < 0.8), do its 3
nearest objects of the same class (IoU of the aligned grids, the object left out) match it
better after a turn of 90, 180 or 270 deg than as it is? If so, the class's own labelled
orientations disagree with the object's, and a model learned from them will turn it.

The third table is a learned bound: the orientation verifier itself
(``beo_ros.core.verifier.OrientationVerifier``, same features and trees) fitted under k-fold
cross-validation on *whole* objects at their labelled orientation and turned by 90, 180 and
270 deg. An object counts as decided when the turn the verifier finds most likely to be the
labelled orientation gives the labelled grid (so a turn that maps the object onto itself
counts as right). A partial view shows less than the whole object and its yaw must also be
found to within 10 deg first, so this is a generous ceiling for the verifier's part of "yaw
within 10 deg" on partial views (``--folds 0`` skips it).

Usage (from the repository root):

    .venv/bin/python scripts/yaw_ambiguity.py $BEO_DATA_DIR/modelnet10/modelnet10_vox32_train.npz \
        [--every 5] [--seed 5] [--folds 5] [--json out.json]
"""
import argparse
import json
import sys

import numpy as np

from beo_ros.core.synthetic import partial_view, random_partial_view, rotate_grid
from beo_ros.core.training import load_voxel_npz, progress_bar, stratified_folds
from beo_ros.core.verifier import TURNS, OrientationVerifier, quarter_turned_features

THRESHOLDS = (1.0, 0.95, 0.9, 0.8)


def turned_view_iou(occ, rng):
    """One protocol view of ``occ`` (N, N, N) bool and the IoU (3,) of its occupied voxels with
    those of the views of the object turned by a further 90, 180, 270 deg (same direction)."""
    grid, yaw, az, el, _ = random_partial_view(occ, rng)
    ious = []
    for k in (1, 2, 3):
        turned = rotate_grid(occ.astype(np.uint8), yaw + k * np.pi / 2).astype(bool)
        g2 = partial_view(turned, az, el)
        a, b = grid == 1, g2 == 1
        union = (a | b).sum()
        same_labels = np.array_equal(grid, g2)
        ious.append(1.0 if same_labels else float((a & b).sum() / union) if union else 1.0)
    return np.array(ious)


def neighbour_turns(X, n, k=3):
    """For objects X (m, n^3) of one class: self-IoU (m, 3) under turns of 90, 180, 270 deg and
    the mean IoU (m, 4) with the k nearest other objects of X after turns of 0, 90, 180, 270."""
    G = X.reshape(-1, n, n, n) > 0.5
    A = G.reshape(len(G), -1).astype(np.float32)
    size = A.sum(axis=1)
    self_iou = np.zeros((len(G), 3))
    nn = np.zeros((len(G), 4))
    for t in range(4):
        R = np.rot90(G, t, axes=(1, 2)).reshape(len(G), -1)   # exact quarter turns about z
        inter = R.astype(np.float32) @ A.T                     # turned object i vs object j
        iou = inter / np.maximum(size[:, None] + size[None, :] - inter, 1)
        if t:
            self_iou[:, t - 1] = np.diagonal(iou)
        np.fill_diagonal(iou, -1.0)
        nn[:, t] = np.sort(iou, axis=1)[:, -k:].mean(axis=1)
    return self_iou, nn


def learned_turn_decided(X, y, n, folds=5, seed=0, max_iter=300):
    """(m,) bool: for objects X (m, n^3) with labels y (m,), is the labelled orientation the
    quarter turn the orientation verifier, fitted on whole objects of the other folds, finds
    most likely (or a turn giving the same grid)?"""
    G = X.reshape(-1, n, n, n) > 0.5
    # (m, 4, features): each object turned by exact quarter turns t (the pooled fractions
    # turned, as at query time); same[i, t]: the turn leaves the object as it is
    F = np.stack([quarter_turned_features(g.astype(np.int8), 0.0) for g in G])
    same = np.stack([(np.rot90(G, t, axes=(2, 1)) == G).all(axis=(1, 2, 3))
                     for t in range(TURNS)], axis=1)
    fold = stratified_folds(y, folds, np.random.default_rng(seed))
    decided = np.zeros(len(X), dtype=bool)
    for f in progress_bar(range(folds), 'learned bound folds'):
        tr, te = np.flatnonzero(fold != f), np.flatnonzero(fold == f)
        ver = OrientationVerifier(max_iter=max_iter).fit(
            F[tr].reshape(-1, F.shape[2]), np.tile(np.arange(TURNS), len(tr)),
            np.repeat(y[tr], TURNS), n)
        for c in np.unique(y[te]):
            rows = te[y[te] == c]
            if not ver.has_class(int(c)):
                continue
            # log P(this grid is the labelled orientation) of each of the four turned grids
            logp0 = ver.predict_log_proba(int(c), F[rows].reshape(-1, F.shape[2]))[:, 0]
            pick = logp0.reshape(-1, TURNS).argmax(axis=1)
            decided[rows] = same[rows, pick]
    return decided


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('data', help='voxel npz (keys voxels, labels, classes)')
    ap.add_argument('--every', type=int, default=5, help='use every n-th object (default 5)')
    ap.add_argument('--seed', type=int, default=5)
    ap.add_argument('--folds', type=int, default=5,
                    help='folds of the learned bound on whole objects (0: skip it)')
    ap.add_argument('--json', help='also write the numbers here')
    args = ap.parse_args(argv)
    if args.every < 1:
        ap.error('--every must be >= 1')
    if args.folds == 1 or args.folds < 0:
        ap.error('--folds must be 0 (skip) or >= 2')
    X, y, names, n = load_voxel_npz(args.data)
    idx = np.arange(0, len(X), args.every)
    rng = np.random.default_rng(args.seed)
    iou = np.array([turned_view_iou(X[i].reshape(n, n, n) > 0.5, rng)
                    for i in progress_bar(idx, 'views')])
    labels = y[idx]
    out = {'views': int(len(idx)), 'thresholds': {}}
    print(f'{len(idx)} views (every {args.every}th object, seed {args.seed})')
    print(f'{"IoU >=":>8} {"ambiguous":>10} {"bound":>6}  per-class bound')
    for th in THRESHOLDS:
        m = 1 + (iou >= th - 1e-12).sum(axis=1)
        per = {names[c]: round(float(np.mean(1.0 / m[labels == c])), 3)
               for c in np.unique(labels)}
        out['thresholds'][str(th)] = dict(ambiguous=round(float(np.mean(m > 1)), 4),
                                         bound=round(float(np.mean(1.0 / m)), 4), per_class=per)
        print(f'{th:8.2f} {np.mean(m > 1):10.3f} {np.mean(1.0 / m):6.3f}  '
              + ' '.join(f'{k} {v:.2f}' for k, v in per.items()))
    print('\nwhole objects: do the 3 nearest objects of the class prefer a turn (objects with '
          'self-IoU < 0.8 under every turn)?')
    out['neighbours_prefer_turn'] = {}
    for c in np.unique(y):
        self_iou, nn = neighbour_turns(X[y == c], n)
        asym = (self_iou < 0.8).all(axis=1)
        prefer = nn[:, 1:].max(axis=1) > nn[:, 0]
        frac = float(np.mean(prefer[asym])) if asym.any() else float('nan')
        flip = float(np.mean(nn[asym, 2] > np.maximum(nn[asym, 0], nn[asym][:, [1, 3]].max(
            axis=1)))) if asym.any() else float('nan')
        out['neighbours_prefer_turn'][names[c]] = dict(
            objects=int((y == c).sum()), asymmetric=int(asym.sum()), prefer_turn=round(frac, 3),
            prefer_half_turn=round(flip, 3))
        print(f'  {names[c]:12s} {int(asym.sum()):4d} of {int((y == c).sum()):4d} asymmetric; '
              f'neighbours prefer a turn {frac:.2f} (the half turn {flip:.2f})')
    if args.folds:
        decided = learned_turn_decided(X, y, n, args.folds, args.seed)
        out['learned_turn_decided'] = dict(
            folds=args.folds, all=round(float(decided.mean()), 4),
            per_class={names[c]: round(float(decided[y == c].mean()), 3) for c in np.unique(y)})
        print(f'\nwhole objects, learned ({args.folds}-fold; the orientation verifier fitted on '
              f'whole objects): labelled quarter turn found for {decided.mean():.3f}')
        print('  ' + ' '.join(f'{k} {v:.2f}'
                              for k, v in out['learned_turn_decided']['per_class'].items()))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
