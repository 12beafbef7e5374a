#!/usr/bin/env python
"""Measurement: does a surface-normal cue from each object's raw segmented points separate box
from cylinder better, together with the BEO log-likelihood margin?

Not imported by the package or the tests; it imports the package's descriptor maths
(``beo_ros.core.normals``, which the shipped 'points' classifier of ``models/tabletop_32``
uses). Usage (from the repository root):

    .venv/bin/python scripts/tabletop_normals.py /tmp/beo_loso/oof_features.npz [--json out.json]

``oof_features.npz`` is the out-of-fold feature file that ``beo-eval --scans`` (``scan_eval``)
writes (features (76, 2, 6) in the order of ``FEATURE_NAMES[:6]``, y, scenes, object_ids,
classes). The scans are read from ``$BEO_DATA_DIR/osd/learn/learn*.pcd``; ``BEO_DATA_DIR``
defaults to ``../shared/data`` relative to the repository.

Per object (camera-frame points of its OSD label, the scene's fitted table normal ``up``):
normals by ``beo_ros.core.normals.point_normals`` (PCA of the at most 30 nearest neighbours
within 2 cm, as open3d's hybrid ``estimate_normals``, computed at at most 2000 evenly strided
points of the object; the first measurement used open3d at all points), oriented toward the
camera at the origin; "side" points are those whose normal is
within 45 deg of horizontal (|n . up| < cos 45 deg); theta is the horizontal direction of a side
normal about ``up``. The three descriptors (fixed before any per-object result was seen; all
invariant to a rotation about ``up``):

- ``r4``: |mean over side points of exp(4 i theta)|. The faces of a box are 90 deg apart, so
  4 theta maps them onto one direction (r4 near 1); the visible front of a cylinder spreads
  theta over about 180 deg (r4 near 0).
- ``frac10``: the largest fraction of side points whose theta mod 90 deg lies within 10 deg of
  one direction (mode fit over 1-deg candidates; covers 1-2 perpendicular dominant faces).
- ``surf_var``: median over side points of the surface variation l0 / (l0 + l1 + l2) of the
  covariance of the same 2-cm neighbourhood (curvature; a flat face is near 0).

Second level: leave-one-scene-out over the 29 scenes, every object's class from a standardised
(mean / std of the training rows) logistic regression fitted on the other 28 scenes' objects
only (``beo_ros.scan_eval.scene_cv_logistic``). Variants, all
reported: (a) the 3 normal descriptors, (b) the loglik margin (box minus cylinder, per known
voxel), (c) margin + the 3 descriptors, (d) ``r4, frac10`` only, (e) the shipped 'points'
classifier (``beo_ros.scan_eval.scene_cv_point_predictions``: the C per-class loglik values +
``r4, frac10``, with its 'unknown' check); each at C = 0.1 and 1. The maximum-likelihood rule on
the same out-of-fold features is the reference.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from beo_ros.core.normals import (  # noqa: E402  (the package's own maths: no drift)
    MIN_POINTS, MIN_SIDE, SIDE_COS, descriptors_from_normals, point_normals)

DESCRIPTORS = ('r4', 'frac10', 'surf_var')
CS = (0.1, 1.0)


def normal_descriptors(points, up):
    """(r4, frac10, surf_var, n_side) of one object's camera-frame points: r4 and frac10 are
    ``beo_ros.core.normals.side_normal_descriptors`` (what the shipped 'points' classifier
    sees); surf_var is the median surface variation over the side points of the same normals."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < MIN_POINTS:
        return np.nan, np.nan, np.nan, 0
    # the normals of side_normal_descriptors, computed once for all three descriptors
    _, n, sv = point_normals(pts, np.zeros(3))
    r4, frac10, ns = descriptors_from_normals(n, up)
    u = np.asarray(up, float) / np.linalg.norm(up)
    side = np.isfinite(n).all(axis=1) & (np.abs(n @ u) < SIDE_COS)
    surf_var = float(np.median(sv[side])) if ns >= MIN_SIDE else np.nan
    return r4, frac10, surf_var, ns


def report(name, y, pred, labels):
    conf = np.zeros((2, 2), dtype=int)
    known = pred >= 0                                # -1: 'unknown' (counted wrong)
    np.add.at(conf, (y[known], pred[known]), 1)
    wrong = [labels[i] for i in np.flatnonzero(pred != y)]
    return dict(variant=name, accuracy=round(float(np.mean(pred == y)), 4),
                n_correct=int((pred == y).sum()), confusion=conf.tolist(), wrong=wrong)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('npz', help='oof_features.npz of a leave-one-scene-out scan_eval run')
    ap.add_argument('--data-dir', default=os.environ.get('BEO_DATA_DIR',
                                                         str(REPO.parent / 'shared' / 'data')))
    ap.add_argument('--json', default=None, help='write per-object descriptors and results here')
    args = ap.parse_args(argv)

    from beo_ros.core.scans import fit_table_plane, load_scene, segment_objects
    from beo_ros.scan_eval import scene_cv_logistic, scene_cv_point_predictions

    d = np.load(args.npz, allow_pickle=False)
    F, y = d['features'], d['y'].astype(int)
    scenes, oids = d['scenes'].astype(str), d['object_ids'].astype(int)
    labels = [f'{s}/{o}' for s, o in zip(scenes, oids)]
    paths = {Path(p).stem: p for p in glob.glob(os.path.join(args.data_dir, 'osd', 'learn',
                                                             'learn*.pcd'))}
    desc = np.full((len(y), len(DESCRIPTORS)), np.nan)
    n_side = np.zeros(len(y), dtype=int)
    n_pts = np.zeros(len(y), dtype=int)
    for s in dict.fromkeys(scenes.tolist()):
        if s not in paths:
            raise SystemExit(f'{s}.pcd not found under {args.data_dir}/osd/learn')
        scene = load_scene(paths[s])
        up, _ = fit_table_plane(scene)               # as scan_training.load_scan_objects
        objs = segment_objects(scene)
        for i in np.flatnonzero(scenes == s):
            pts = objs[int(oids[i])]
            *desc[i], n_side[i] = normal_descriptors(pts, up)
            n_pts[i] = len(pts)
    if np.isnan(desc).any():
        raise SystemExit(f'descriptor undefined for {[labels[i] for i in np.flatnonzero(np.isnan(desc).any(1))]}')

    margin = F[:, 0, 0] - F[:, 1, 0]                 # box minus cylinder loglik per known voxel
    ml = np.argmax(F[:, :, 0], axis=1)
    results = [report('maximum likelihood (reference)', y, ml, labels)]
    sets = (('(a) normals: r4, frac10, surf_var', desc),
            ('(b) loglik margin', margin[:, None]),
            ('(c) margin + normals', np.column_stack([margin, desc])),
            ('(d) r4, frac10', desc[:, :2]))
    for name, Z in sets:
        for C in CS:
            results.append(report(f'{name}, C = {C:g}', y, scene_cv_logistic(Z, y, scenes, C),
                                  labels))
    for C in CS:
        pred, unknown = scene_cv_point_predictions(F, desc[:, :2], y, scenes, C)
        results.append(report(f"(e) 'points' classifier (loglik x C + r4, frac10), C = {C:g}"
                              f' ({int(unknown.sum())} unknown, counted wrong)', y,
                              np.where(unknown, -1, pred), labels))

    print('per class: median [IQR] of each descriptor')
    for c, cname in enumerate(d['classes'].astype(str)):
        row = '  '.join(f'{k} {np.median(desc[y == c, j]):.3f} '
                        f'[{np.percentile(desc[y == c, j], 25):.3f}, '
                        f'{np.percentile(desc[y == c, j], 75):.3f}]'
                        for j, k in enumerate(DESCRIPTORS))
        print(f'  {cname:9s} {row}')
    print('objects the maximum-likelihood rule gets wrong:')
    for i in np.flatnonzero(ml != y):
        print(f'  {labels[i]:10s} true {d["classes"][y[i]]:8s} margin {margin[i]:+.2f} '
              + ' '.join(f'{k} {v:.3f}' for k, v in zip(DESCRIPTORS, desc[i]))
              + f' side {n_side[i]}/{n_pts[i]}')
    print('| variant | accuracy | right of 76 | confusion (rows true box, cylinder) | wrong |')
    print('| --- | ---: | ---: | --- | --- |')
    for r in results:
        print(f"| {r['variant']} | {r['accuracy']:.3f} | {r['n_correct']} | {r['confusion']} | "
              f"{', '.join(r['wrong'])} |")
    if args.json:
        per = [dict(object=labels[i], y=int(y[i]), margin=float(margin[i]), n_points=int(n_pts[i]),
                    n_side=int(n_side[i]), **{k: float(desc[i, j]) for j, k in enumerate(DESCRIPTORS)})
               for i in range(len(y))]
        Path(args.json).write_text(json.dumps(dict(results=results, objects=per), indent=1))
    return results


if __name__ == '__main__':
    main()
