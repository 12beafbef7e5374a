#!/usr/bin/env python
"""Measurement: latency of ``bank.estimate`` (or ``bank.estimate_points``) per stage.

Not imported by the package (``test/test_scripts.py`` runs it on a tiny bank). Views are made
by the evaluation protocol from every ``--every``-th object of a voxel npz (the shared format):
``random_partial_view`` for grids, or ``render_view_points`` (a rendered cloud, voxelized and
ray cast by ``estimate_points``) with ``--points``. A few warm-up calls run first; then every view is estimated once and the p50 /
p95 of the total and the median of each stage in ``Estimate.timings`` are printed.
``--between render`` renders another view before each timed call (as ``beo-eval`` does, so
the caches are colder); ``--between none`` times the calls back to back.

Usage (from the repository root):

    .venv/bin/python scripts/latency.py $BEO_DATA_DIR/modelnet10/modelnet10_vox32_train.npz \
        [--model models/modelnet10_32] [--views 60] [--every 33] [--seed 0] \
        [--between none|render] [--points] [--repeats 1]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from beo_ros import load_models  # noqa: E402
from beo_ros.core.synthetic import random_partial_view, render_view_points  # noqa: E402
from beo_ros.core.training import load_voxel_npz  # noqa: E402


def make_views(objects, rng, points):
    """Protocol views: labelled grids, or (points, sensor origin) with ``points``."""
    if not points:
        return [random_partial_view(o, rng)[0] for o in objects]
    return [render_view_points(o, rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi),
                               np.deg2rad(rng.uniform(10, 50)), rng=rng) for o in objects]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('data', help='voxel npz (shared format)')
    ap.add_argument('--model', default=None, help='model directory (default: shipped model)')
    ap.add_argument('--views', type=int, default=60, help='timed views')
    ap.add_argument('--every', type=int, default=33, help='take every n-th object of the npz')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--between', choices=('none', 'render'), default='none',
                    help='what runs between timed calls')
    ap.add_argument('--points', action='store_true',
                    help='time estimate_points on rendered clouds instead of estimate on grids')
    ap.add_argument('--repeats', type=int, default=1, help='timed passes over the views')
    args = ap.parse_args(argv)
    if args.views < 1 or args.every < 1 or args.repeats < 1:
        ap.error('--views, --every and --repeats must be >= 1')

    bank = load_models(args.model)
    X, _, _, n = load_voxel_npz(args.data)
    objects = X[::args.every][:args.views].reshape(-1, n, n, n) > 0.5
    rng = np.random.default_rng(args.seed)
    views = make_views(objects, rng, args.points)

    def run(view):
        return bank.estimate_points(*view) if args.points else bank.estimate(view)

    for view in views[:5]:
        run(view)
    totals, stages, unknown = [], {}, []
    for _ in range(args.repeats):
        for obj, view in zip(objects, views):
            if args.between == 'render':
                make_views([obj], rng, args.points)
            t0 = time.perf_counter()
            est = run(view)
            totals.append(time.perf_counter() - t0)
            unknown.append(float((est.grid < 0).mean()))
            for name, t in est.timings.items():
                stages.setdefault(name, []).append(t)
    ms = 1e3 * np.asarray(totals)
    what = 'estimate_points' if args.points else 'estimate'
    print(f'{what}: {len(ms)} calls ({len(views)} views, between: {args.between}), '
          f'unknown voxels {np.mean(unknown):.2f}: p50 {np.median(ms):.1f} ms, '
          f'p95 {np.percentile(ms, 95):.1f} ms')
    for name, t in stages.items():
        print(f'  {name:20s} p50 {1e3 * np.median(t):6.1f} ms')
    return 0


if __name__ == '__main__':
    sys.exit(main())
