#!/usr/bin/env python
"""Measurement: which per-voxel uncertainty tells where the completion is wrong?

Not imported by the package or the tests' assertions on numbers. For one cross-validation fold
of a voxel npz (the shared format), the class models, classifier and occupancy calibration are
fitted on the other folds (``fit_bank``, no orientation verifier), and each held-out object is
seen once by the evaluation protocol (``beo_ros.core.synthetic.random_partial_view``). Over the
unknown voxels of those views, two uncertainties are compared:

- ``variance``: ``Estimate.variance``, the predictive variance of the linear-Gaussian
  occupancy (from the posterior of the coefficients, the loadings and the mean, plus the
  class's noise variance, mixed over the likely classes);
- ``occupancy_variance``: ``Estimate.occupancy_variance``, p (1 - p) of the calibrated
  probability: the variance of the 0/1 voxel under it.

Scores (AUROC: the chance that a random wrong voxel gets a higher uncertainty than a random
right one; 0.5 is no better than chance):

- ``error``: a voxel is wrong when (p >= 0.5) differs from the truth;
- ``false in cloud``: among the voxels with p >= 0.5 (those the node publishes at its default
  threshold), the ones that are not occupied;
- ``change``: a second view of the same object from an azimuth 90-270 deg away is merged into
  the grid and estimated again at the first yaw; Spearman correlation of the uncertainty with
  |p2 - p| (what a next-best-view planner wants the uncertainty to predict).

Usage (from the repository root):

    .venv/bin/python scripts/uncertainty.py $BEO_DATA_DIR/modelnet10/modelnet10_vox32_train.npz \\
        [--fold 0] [--folds 5] [--every 1] [--seed 7] [--json out.json]
"""
import json
import sys
import time

import numpy as np
from scipy.stats import spearmanr
from sklearn.metrics import roc_auc_score

from beo_ros.core.calibration import calibration_metrics
from beo_ros.core.grid import GridSpec
from beo_ros.core.synthetic import partial_view, random_partial_view
from beo_ros.core.training import fit_bank
from beo_ros.evaluate import held_out_fold, one_fold_parser

KINDS = ('variance', 'occupancy_variance')


def scores(p, truth, unc, p2):
    """AUROC of each uncertainty in ``unc`` (dict name -> (v,)) for the wrong voxels and for the
    false voxels among p >= 0.5, and its Spearman correlation with |p2 - p|."""
    wrong = (p >= 0.5) != truth
    shown = p >= 0.5
    change = np.abs(p2 - p)
    out = {}
    for name, u in unc.items():
        out[name] = dict(
            error=float(roc_auc_score(wrong, u)) if 0 < wrong.mean() < 1 else float('nan'),
            false_in_cloud=(float(roc_auc_score(~truth[shown], u[shown]))
                            if 0 < truth[shown].mean() < 1 else float('nan')),
            change=(float(spearmanr(u, change)[0]) if np.ptp(change) > 0 and np.ptp(u) > 0
                    else float('nan')))
    return out


def main(argv=None):
    ap = one_fold_parser(__doc__, 'write the scores here')
    args, X, y, names, n, tr, te = held_out_fold(ap, argv)
    t0 = time.time()
    bank = fit_bank(X[tr], y[tr], names, GridSpec(size=n), k=args.k, classifier_views=1,
                    seed=args.fold, class_prior='train', verifier_views=0,
                    calibration_views=1)
    print(f'fitted on {len(tr)} objects in {time.time() - t0:.0f} s '
          f'(calibrated: {bank.occupancy_calibration is not None})', file=sys.stderr)
    rng = np.random.default_rng(args.seed)
    cols = {k: [] for k in ('p', 'truth', 'p2') + KINDS}
    views = 0
    for i in te:
        occ = X[i].reshape((n,) * 3) > 0.5
        grid, _, az, el, rotated = random_partial_view(occ, rng)
        unknown = grid < 0
        if not (grid == 1).any() or not unknown.any():
            continue
        e = bank.estimate(grid)
        second = partial_view(rotated, az + np.deg2rad(rng.uniform(90, 270)), el)
        e2 = bank.estimate(np.where(grid >= 0, grid, second), yaw=e.yaw)
        for k, v in (('p', e.completion), ('truth', rotated), ('p2', e2.completion),
                     ('variance', e.variance), ('occupancy_variance', e.occupancy_variance)):
            cols[k].append(v[unknown])
        views += 1
    c = {k: np.concatenate(v) for k, v in cols.items()}
    truth = c['truth'].astype(bool)
    result = dict(views=views, voxels=int(truth.size),
                  calibration=calibration_metrics(c['p'], truth),
                  wrong=float(((c['p'] >= 0.5) != truth).mean()),
                  scores=scores(c['p'], truth, {k: c[k] for k in KINDS}, c['p2']))
    print(f"{views} views, {truth.size} unknown voxels, {result['wrong']:.3f} wrong at p >= 0.5; "
          f"Brier {result['calibration']['brier']:.4f}, ECE {result['calibration']['ece']:.4f}")
    print(f"{'uncertainty':20s} {'AUROC error':>11s} {'AUROC false in cloud':>20s} "
          f"{'Spearman change':>15s}")
    for k in KINDS:
        s = result['scores'][k]
        print(f"{k:20s} {s['error']:11.3f} {s['false_in_cloud']:20.3f} {s['change']:15.3f}")
    if args.json:
        with open(args.json, 'w') as fh:
            json.dump(result, fh, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
