"""beo-bench: compare this project's estimator with the paper's plain method and an ICP database.

All peers answer the same query set: one random partial view (the evaluation protocol of
:func:`beo_ros.core.synthetic.random_partial_view`) of each held-out object, seeded. The peers
are trained on a seeded stratified split of the shared ModelNet10 voxel grids (or on generated
boxes/cylinders with ``--data none``, or when no ``--data`` is given and the default file is
missing; a given ``--data`` file that does not exist is an error).

Reported per peer: accuracy, yaw error (median; within 10 deg; within 10 deg counting 180 deg
flips), latency p50/p95 per object (median over ``--repeats`` runs of each query,
``time.perf_counter``), peak memory of the query phase (tracemalloc peak; allocations made
inside open3d's C++ are not seen by tracemalloc, see ``index_mb`` for the database size).
Then scaling curves, node-level throughput / latency through real rclpy, JSON + PNG output.

Example::

    beo-bench --quick --out /tmp/bench
    beo-bench --out /tmp/bench --queries-per-class 10 --train-per-class 40 \\
        --beo-classifier-views 0 --icp-db-per-class 10
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from .bench_node import log, node_bench
from .cli import ArgumentParser, count, given_options, interruptible, number
from .core.grid import yaw_error
from .cli import json_safe, out_dir_problem, output_dir

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = 'modelnet10/modelnet10_vox32_train.npz'
# highest --node-rates (Hz): the bench bag holds max rate x --node-duration clouds, so 1e6 Hz
# meant millions of clouds on disk; depth sensors run at 30-90 Hz
MAX_NODE_RATE_HZ = 1000.0
# highest max(--node-rates) x --node-duration: the clouds written into the bench bag (1000 Hz
# for 3600 s would still be 3.6 million)
MAX_NODE_MESSAGES = 20000
# the peers of bench.json; one switched off (--no-paper, --no-icp) is {'skipped': '--no-...'}
PEERS = ('beo', 'paper', 'icp')


# ---------------------------------------------------------------------- data
def data_path(arg):
    """The voxel npz to use: None for generated shapes ('none', or no ``arg`` and the default
    file missing), else the given path (checked by ``load_data``) or the default file."""
    if arg == 'none':
        return None
    if arg:
        return Path(arg)
    root = Path(os.environ.get('BEO_DATA_DIR', REPO.parent / 'shared' / 'data'))
    p = root / DEFAULT_DATA
    return p if p.is_file() else None


def load_data(args, rng):
    """(X, y, names, n, source) with optional class selection / subsampling."""
    from beo_ros.core.synthetic import primitive_shapes
    from beo_ros.core.datasets import drop_empty_objects, load_voxel_npz, select_classes
    path = data_path(args.data)
    if path is not None and not path.is_file():
        # only --data none or a missing default file fall back to generated shapes
        raise ValueError(f'--data {path}: no such file (--data none: generated boxes/cylinders)')
    if path is None:
        n = 16
        X, y, names = primitive_shapes(n, max(args.train_per_class or 15, 15) + 8, rng)
        source = 'generated boxes/cylinders (16^3)'
        if args.classes:   # as load_voxel_npz does for a file
            X, y, names = select_classes(X, y, names, args.classes, source)
        return X, y, names, n, source
    X, y, names, n = load_voxel_npz(path, args.classes or None)
    if not len(X):   # split() would fail with numpy's 'need at least one array to concatenate'
        raise ValueError(f'--data {path}: no objects' + (f' of the classes {args.classes}'
                                                         if args.classes else ''))
    # as beo-train: an object with no occupied voxel is nothing to train on or to query (the
    # peers refuse such a grid)
    X, y, dropped = drop_empty_objects(X, y, names)
    if dropped:
        log(f'dropped {sum(dropped.values())} objects with no occupied voxel ('
            + ', '.join(f'{c}: {m}' for c, m in dropped.items()) + ')')
    return X, y, names, n, str(path)


def split(y, test_frac, rng, train_per_class=None, queries_per_class=None):
    """Seeded stratified split -> (train idx, query idx)."""
    tr, te = [], []
    for c in np.unique(y):
        idx = rng.permutation(np.flatnonzero(y == c))
        n_te = max(1, int(round(test_frac * len(idx))))
        t, q = idx[n_te:], idx[:n_te]
        if train_per_class:
            t = t[:train_per_class]
        if queries_per_class:
            q = q[:queries_per_class]
        tr.append(t)
        te.append(q)
    return np.sort(np.concatenate(tr)), np.sort(np.concatenate(te))


def make_queries(X, y, idx, n, rng):
    from beo_ros.core.synthetic import random_partial_view
    out = []
    for i in idx:
        grid, yaw, az, el, _ = random_partial_view(X[i].reshape((n,) * 3) > 0.5, rng)
        out.append(dict(grid=grid, yaw=float(yaw), label=int(y[i]), az=float(az), el=float(el),
                        index=int(i)))
    return out


# ---------------------------------------------------------------------- metrics
def yaw_error_deg(a, b):
    return math.degrees(float(yaw_error(a, b)))


def has_object(grid):
    """True when the view ``grid`` has an occupied voxel (a view of a few-voxel object can
    lose it to the rotation)."""
    return bool((np.asarray(grid) == 1).any())


def answer_empty_views(predict):
    """``predict(grid) -> (label index, yaw)`` of a peer that refuses a grid with no occupied
    voxel (paper, icp: ValueError), answering such a view as beo does: no class (index -1,
    a miss) and yaw 0 (not scored, see :func:`run_peer`)."""
    def answer(grid):
        return predict(grid)[:2] if has_object(grid) else (-1, 0.0)
    return answer


def run_peer(name, predict, queries, repeats, mem_queries=3):
    """Run ``predict(grid) -> (label index, yaw)`` on all queries; metrics dict (with
    ``empty_views``: the queries with no occupied voxel, each a miss)."""
    empty = sum(not has_object(q['grid']) for q in queries)
    if empty:
        log(f'[{name}] {empty} of {len(queries)} views have no occupied voxel: each is a miss')
    lat, correct, yerr = [], [], []
    for qi, q in enumerate(queries):
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            c, yaw = predict(q['grid'])[:2]
            times.append(time.perf_counter() - t0)
        lat.append(float(np.median(times)))
        correct.append(int(c) == q['label'])
        # a view with no occupied voxel (the rotation lost an object of a few voxels) has no
        # pose: no yaw error (NaN, a miss), not the predictor's placeholder yaw scored
        yerr.append(yaw_error_deg(yaw, q['yaw']) if has_object(q['grid']) else float('nan'))
    # memory: a separate pass so tracemalloc's overhead stays out of the timings
    gc.collect()
    peaks = []
    for q in queries[:mem_queries]:
        tracemalloc.start()
        tracemalloc.reset_peak()
        predict(q['grid'])
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    return dict(summarize(lat, correct, yerr, peaks), empty_views=int(empty))


def summarize(lat, correct, yerr, peaks):
    lat = np.asarray(lat) * 1e3
    yerr = np.asarray(yerr)
    correct = np.asarray(correct, dtype=bool)
    flip = np.minimum(yerr, 180.0 - yerr)
    ym = np.where(np.isnan(yerr), 180.0, yerr)   # in the medians, no yaw: the largest error
    yc = ym[correct] if correct.any() else np.full(1, np.nan)   # no right class: no median
    return {
        'queries': int(len(lat)),
        'accuracy': float(correct.mean()),
        'yaw_median_deg': float(np.median(ym)),
        'yaw_median_deg_correct_class': float(np.median(yc)),
        'yaw_within_10deg': float((yerr <= 10).mean()),
        'yaw_within_10deg_flip': float((flip <= 10).mean()),
        'p50_ms': float(np.percentile(lat, 50)),
        'p95_ms': float(np.percentile(lat, 95)),
        'mean_ms': float(lat.mean()),
        'peak_mem_mb': float(max(peaks) / 2**20) if peaks else 0.0,
    }


def latency_point(predict, queries, repeats):
    """Median per-query latency (ms; median over repeats, then over queries) and peak MB."""
    predict(queries[0]['grid'])  # warm-up (rotation maps, caches)
    lat = []
    for q in queries:
        ts = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            predict(q['grid'])
            ts.append(time.perf_counter() - t0)
        lat.append(np.median(ts))
    gc.collect()
    tracemalloc.start()
    tracemalloc.reset_peak()
    predict(queries[0]['grid'])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return float(np.median(lat) * 1e3), float(peak / 2**20)


def bank_nbytes(bank):
    return int(sum(m.W.nbytes + m.mean.nbytes + m.mean_variance.nbytes for m in bank.models))


# ---------------------------------------------------------------------- peers
def beo_predict(bank, yaw_step_deg=1.0):
    names = list(bank.classes)

    def predict(grid):
        est = bank.estimate(grid, yaw_step_deg=yaw_step_deg)
        return (names.index(est.label) if est.label in names else -1), est.yaw
    return predict


def fit_beo(X, y, names, n, k, classifier_views, seed, folds=5, verifier_views=0, processes=1):
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_bank
    return fit_bank(X, y, names, GridSpec(size=n), k=k, classifier_views=classifier_views,
                    folds=folds, seed=seed, pose_components=min(8, k),
                    verifier_views=verifier_views, processes=processes)


def fit_class_bank(X, y, names, n, k):
    from beo_ros.core.bank import ModelBank
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_class_models
    spec = GridSpec(size=n)
    return ModelBank(fit_class_models(X, y, names, spec, k=k), spec, pose_components=min(8, k))


# ---------------------------------------------------------------------- scaling
def scaling(args, X, y, names, n, tr, queries, bank, rng):
    """The 'scaling' section of bench.json: latency and peak memory of beo (and icp) vs
    training objects, grid size, yaw step and classes, on the first ``--scaling-queries``
    queries; ``rng`` draws the training subsets."""
    sq = queries[:args.scaling_queries]
    Xtr, ytr = X[tr], y[tr]
    # the grid and class curves: class models on a small training set
    sub = np.sort(np.concatenate([np.flatnonzero(ytr == c)[:args.scaling_per_class]
                                  for c in range(len(names))]))
    return {
        'train_objects': _scaling_train_objects(args, Xtr, ytr, names, n, sq, bank, rng),
        'grid': _scaling_grid(args, X, Xtr[sub], ytr[sub], names, n, sq),
        'yaw_step': _scaling_yaw_step(args, sq, bank),
        'classes': _scaling_classes(args, Xtr[sub], ytr[sub], names, n, sq, bank),
        'note': _scaling_note(args, len(sq))}


def _scaling_note(args, n_queries):
    """The 'note' of the scaling section: what each curve measures (``n_queries`` queries)."""
    # it said "latency does not depend on the training set size for beo": a class gets
    # min(k, its objects - 1) components, so beo's model grows with the objects up to k + 1
    whole = (", at the whole split the beo peer's bank" if args.model is None else '')
    runs = f"{args.repeats} run{'s' if args.repeats != 1 else ''}"
    return (f"{n_queries} quer{'y' if n_queries == 1 else 'ies'} per point for beo ({runs} "
            'each), the first '
            f'{_icp_scaling_queries(n_queries)} for icp (1 run); vs training objects: beo class '
            f'models refitted on each class-stratified subset (min(k={args.k}, objects per '
            f'class - 1) components per class){whole}; icp a database of all the subset\'s '
            f'objects; grid and class curves: class models fitted on {args.scaling_per_class} '
            f"objects per class; yaw-step curve: the beo peer's bank")


def _icp_scaling_queries(n_queries):
    """How many of the scaling queries the icp database answers (it is slow)."""
    return max(1, n_queries // 2)


def _scaling_train_objects(args, Xtr, ytr, names, n, sq, bank, rng):
    """Latency / memory vs training objects (of the training split ``Xtr``, ``ytr``): beo
    refitted on class-stratified subsets (``bank`` for all of them unless --model), the icp
    database of all the subset's objects."""
    from beo_ros.core.baselines import ICPDatabase
    sizes = sorted({s for s in args.scaling_train if s < len(ytr)} | {len(ytr)})
    pts = []
    for s in sizes:
        sel = np.sort(np.concatenate([
            rng.permutation(np.flatnonzero(ytr == c))[:max(2, int(round(s * (ytr == c).mean())))]
            for c in range(len(names))]))
        log(f'[scaling] training objects {len(sel)}')
        b = bank if len(sel) >= len(ytr) and args.model is None else fit_class_bank(
            Xtr[sel], ytr[sel], names, n, args.k)
        bl, bm = latency_point(beo_predict(b), sq, args.repeats)
        db = ICPDatabase(per_class=None, n_init_yaws=args.icp_init_yaws, seed=args.seed).fit(
            Xtr[sel], ytr[sel], names, n)
        il, im = latency_point(answer_empty_views(db.predict), sq[:_icp_scaling_queries(len(sq))],
                               1)
        pts.append(dict(n_train=int(len(sel)), beo_ms=bl, beo_mb=bm, icp_ms=il, icp_mb=im,
                        icp_db_size=db.size))
    return pts


def _scaling_grid(args, X, Xs, ys, names, n, sq):
    """Latency / memory vs grid resolution: class models on the objects ``Xs``, ``ys``
    resampled to each ``--scaling-grids`` size, queried with new views of the queries'
    objects (rows of ``X``) at that size."""
    from beo_ros.core.synthetic import random_partial_view
    from scipy.ndimage import zoom
    qidx = [q['index'] for q in sq]
    pts = []
    for g in args.scaling_grids:
        log(f'[scaling] grid {g}^3')
        f = g / n

        def rs(v):
            return zoom(v.reshape((n,) * 3), f, order=0).ravel() if g != n else v
        Xg = np.array([rs(x) for x in Xs], dtype=np.float32)
        b = fit_class_bank(Xg, ys, names, g, args.k)
        qrng = np.random.default_rng(args.seed + 7)
        qs = [dict(grid=random_partial_view(rs(X[i]).reshape((g,) * 3) > 0.5, qrng)[0])
              for i in qidx]
        bl, bm = latency_point(beo_predict(b), qs, args.repeats)
        pts.append(dict(grid=int(g), beo_ms=bl, beo_mb=bm, model_mb=bank_nbytes(b) / 2**20))
        del b, Xg
        gc.collect()
    return pts


def _scaling_yaw_step(args, sq, bank):
    """Latency / memory vs yaw resolution (``bank``, exhaustive search)."""
    pts = []
    for step in args.scaling_yaw_steps:
        bl, bm = latency_point(beo_predict(bank, step), sq, args.repeats)
        pts.append(dict(yaw_step_deg=float(step), beo_ms=bl, beo_mb=bm))
    return pts


def _scaling_classes(args, Xs, ys, names, n, sq, bank):
    """Latency / memory vs number of classes: the first c of the class models fitted on the
    objects ``Xs``, ``ys``."""
    from beo_ros.core.bank import ModelBank
    models = fit_class_bank(Xs, ys, names, n, args.k).models
    pts = []
    for c in sorted({min(c, len(names)) for c in args.scaling_classes}):
        log(f'[scaling] classes {c}')
        b = ModelBank(models[:c], bank.spec, pose_components=min(8, args.k))
        bl, bm = latency_point(beo_predict(b), sq, args.repeats)
        pts.append(dict(classes=int(c), beo_ms=bl, beo_mb=bm))
    return pts


# ---------------------------------------------------------------------- output
def plots(res, out):
    """latency.png and accuracy.png of the peers measured, and scaling.png unless the scaling
    phase was skipped, into ``out``."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    peers = [p for p in PEERS if _measured(res, p)]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    x = np.arange(len(peers))
    ax.bar(x - 0.2, [res[p]['p50_ms'] for p in peers], 0.4, label='p50')
    ax.bar(x + 0.2, [res[p]['p95_ms'] for p in peers], 0.4, label='p95')
    ax.set_xticks(x, peers)
    ax.set_yscale('log')
    ax.set_ylabel('latency per object (ms)')
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / 'latency.png', dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 3.5))
    keys = [('accuracy', 'accuracy'), ('yaw_within_10deg', 'yaw<=10'),
            ('yaw_within_10deg_flip', 'yaw<=10 (flip)')]
    for j, (k, lab) in enumerate(keys):
        ax.bar(x + (j - 1) * 0.27, [res[p][k] for p in peers], 0.27, label=lab)
    ax.set_xticks(x, peers)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / 'accuracy.png', dpi=100)
    plt.close(fig)

    sc = res.get('scaling') or {}
    if 'skipped' in sc:
        # eight empty panels were written; and a scaling.png of an earlier run into the same
        # --out would pass for this run's
        stale = out / 'scaling.png'
        if stale.is_file():
            stale.unlink()
            log(f'[plots] removed {stale} of an earlier run (the scaling phase was skipped: '
                f"{sc['skipped']})")
        return
    fig, axes = plt.subplots(2, 4, figsize=(14, 6))
    panels = [('train_objects', 'n_train', 'training objects', [('beo', 'beo'), ('icp', 'icp')]),
              ('grid', 'grid', 'grid size N', [('beo', 'beo')]),
              ('yaw_step', 'yaw_step_deg', 'yaw step (deg)', [('beo', 'beo')]),
              ('classes', 'classes', 'classes', [('beo', 'beo')])]
    for col, (key, xk, xl, series) in enumerate(panels):
        pts = sc.get(key) or []
        for row, (suffix, yl) in enumerate((('ms', 'latency (ms)'), ('mb', 'peak memory (MB)'))):
            a = axes[row, col]
            for s, lab in series:
                if pts:
                    a.plot([p[xk] for p in pts], [p[f'{s}_{suffix}'] for p in pts], 'o-',
                           label=lab)
            a.set_xlabel(xl)
            a.set_ylabel(yl)
            if key == 'train_objects' and pts:
                a.set_yscale('log')
                a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / 'scaling.png', dpi=100)
    plt.close(fig)


def table(res):
    """The peers' table (markdown): a row per peer, 'not run' for one switched off."""
    rows = ['| peer | accuracy | yaw median (deg) | yaw <=10 | yaw <=10 (flip) | p50 ms | p95 ms '
            '| peak MB |', '|---|---|---|---|---|---|---|---|']
    for p in PEERS:
        if not _measured(res, p):
            rows.append(f'| {p} | {_not_run(res, p)} |' + ' |' * 6)
            continue
        r = res[p]
        rows.append(f"| {p} | {r['accuracy']:.3f} | {r['yaw_median_deg']:.1f} | "
                    f"{r['yaw_within_10deg']:.3f} | {r['yaw_within_10deg_flip']:.3f} | "
                    f"{r['p50_ms']:.1f} | {r['p95_ms']:.1f} | {r['peak_mem_mb']:.1f} |")
    return '\n'.join(rows)


def _measured(res, peer):
    """True when bench.json dict ``res`` holds ``peer``'s results (not its 'skipped')."""
    return isinstance(res.get(peer), dict) and 'skipped' not in res[peer]


def _not_run(res, peer):
    """'not run (--no-PEER)' for a peer switched off."""
    why = (res.get(peer) or {}).get('skipped')
    return f'not run ({why})' if why else 'not run'


def speedups(res, sep=''):
    """['vs icp (p50) 3.1x', 'vs paper 1.2x']: beo's speedups over the peers (``sep`` after
    the peer), 'n/a (not run ...)' for one switched off."""
    def one(p):
        if not _measured(res, p):
            return f'n/a ({_not_run(res, p)})'
        v = res.get(f'speedup_vs_{p}')
        return 'n/a' if v is None else f'{v:.1f}x'
    return [f"vs {p}{' (p50)' if p == 'icp' else ''}{sep} {one(p)}" for p in ('icp', 'paper')]


def markdown(res):
    """Markdown tables of a bench.json dict (peers, scaling, node)."""
    lines = _md_setup(res.get('setup', {}))
    if _measured(res, 'beo'):
        lines += _md_peers(res)
    sc = res.get('scaling') or {}
    if 'train_objects' in sc:
        lines += _md_scaling(sc)
    lines += _md_node(res.get('node') or {})
    return '\n'.join(lines) + '\n'


def _md_setup(st):
    """The data / sizes / machine line of bench.md (``st``: the 'setup' section)."""
    return [f"Data: {st.get('data')}; {len(st.get('classes', []))} classes, "
            f"{st.get('train_objects')} training objects, {st.get('queries')} queries "
            f"(seed {st.get('seed')}, k={st.get('k')}); beo: {st.get('beo_model')}; "
            f"{st.get('cpu_count')} CPUs"
            + (f", 1-min load average {st['load_average_1min']} at the start."
               if st.get('load_average_1min') is not None else '.'), '']


def _md_peers(res):
    """The peers' table and a list of speedups, index sizes and fit times (of the peers that
    ran)."""
    ran = [p for p in PEERS if _measured(res, p)]
    icp, paper = speedups(res)
    extra = [f'speedup {icp}', paper]
    if 'icp' in ran:
        extra.append(f"icp database {res['icp'].get('db_size')} objects "
                     f"({res['icp'].get('db_per_class')} per class, "
                     f"{res['icp'].get('init_yaws')} initial yaws)")
    extra += [f"{p} index {res[p]['index_mb']:.1f} MB, fit {res[p]['fit_s']:.0f} s"
              for p in ran]
    if res['beo'].get('empty_views'):   # the same queries for every peer
        extra.append(f"{res['beo']['empty_views']} of the {res['beo']['queries']} views have no "
                     'occupied voxel (the rotation lost the object): a miss for every peer')
    # n/a: a peer that classified no query right (null in bench.json)
    extra += [f"{p} yaw median on correctly classified "
              f"{_fmt(res[p]['yaw_median_deg_correct_class'])} deg"
              for p in ran]
    return [table(res), ''] + ['- ' + e for e in extra] + ['']


def _md_scaling(sc):
    """The scaling tables (``sc``: the 'scaling' section)."""
    lines = ['Latency / peak memory vs training objects:', '',
             '| training objects | beo ms | beo MB | icp ms | icp MB |',
             '|---|---|---|---|---|']
    lines += [f"| {p['n_train']} | {p['beo_ms']:.1f} | {p['beo_mb']:.1f} | {p['icp_ms']:.0f} "
              f"| {p['icp_mb']:.1f} |" for p in sc['train_objects']]
    lines += ['', 'vs grid size:', '', '| N | beo ms | beo MB | model MB |',
              '|---|---|---|---|']
    lines += [f"| {p['grid']} | {p['beo_ms']:.1f} | {p['beo_mb']:.1f} | {p['model_mb']:.1f} |"
              for p in sc['grid']]
    lines += ['', 'vs yaw step:', '', '| yaw step (deg) | beo ms | beo MB |', '|---|---|---|']
    lines += [f"| {p['yaw_step_deg']:g} | {p['beo_ms']:.1f} | {p['beo_mb']:.1f} |"
              for p in sc['yaw_step']]
    lines += ['', 'vs classes:', '', '| classes | beo ms | beo MB |', '|---|---|---|']
    lines += [f"| {p['classes']} | {p['beo_ms']:.1f} | {p['beo_mb']:.1f} |"
              for p in sc['classes']]
    return lines + ['', f"({sc.get('note')})", '']


def _md_node(node):
    """The node's headline, its per-rate table and the closed loop (``node``: the 'node'
    section), or why it was skipped."""
    if 'objects_per_s' not in node:
        return [f"Node: skipped ({node.get('skipped')})."]
    sus = node.get('sustained_rate_hz')
    lines = [f"Node (real rclpy, bag replay, workers={node.get('workers')}, "
             f"worker_processes={node.get('worker_processes', 0)}): "
             + (f"sustains {sus:g} Hz: {_fmt(node['objects_per_s'], '.2f')} objects/s out, "
                if sus else 'sustains none of the rates; at the lowest: '
                f"{_fmt(node['objects_per_s'], '.2f')} objects/s out, ")
             + f"{node['dropped_stale']} dropped, {node['lost']} lost, end-to-end publish -> "
             f"estimate p50 {_fmt(node['e2e_p50_ms'])} ms, p95 {_fmt(node['e2e_p95_ms'])} ms; "
             f"highest output rate {_fmt(node.get('max_objects_per_s'), '.2f')}/s; "
             f"{node['mode']}.", '']
    if node.get('rates'):
        lines += ['| replay Hz | sent | estimates | out/s | dropped stale | lost | '
                  'e2e p50 ms | e2e p95 ms |', '|---|---|---|---|---|---|---|---|']
        lines += [f"| {r['rate_hz']:g} | {r['sent']} | {r['estimates']} | "
                  f"{_fmt(r['objects_per_s'], '.2f')} | {r['dropped_stale']} | {r['lost']} | "
                  f"{_fmt(r['e2e_p50_ms'])} | {_fmt(r['e2e_p95_ms'])} |" for r in node['rates']]
    cl = node.get('closed_loop') or {}
    if cl:
        lines += ['', f"Closed loop ({cl['objects']} objects, {cl['lost']} lost): "
                  f"{_fmt(cl['objects_per_s'], '.2f')} objects/s, e2e p50 "
                  f"{_fmt(cl['e2e_p50_ms'])} ms, p95 {_fmt(cl['e2e_p95_ms'])} ms."]
    return lines


def _fmt(v, spec='.1f'):
    """``v`` formatted, or 'n/a' for None (a NaN in bench.json: e.g. no estimate at all)."""
    return 'n/a' if v is None else format(v, spec)


# ---------------------------------------------------------------------- main
# the options that a phase switched off (or --model, which replaces beo's fit) leaves unused
UNUSED_WITH = {
    'model': ('beo_classifier_views', 'beo_verifier_views'),
    'no_paper': ('paper_yaws',),
    'no_icp': ('icp_db_per_class',),   # --icp-init-yaws: the scaling phase's database too
    'no_scaling': ('scaling_train', 'scaling_grids', 'scaling_yaw_steps', 'scaling_classes',
                   'scaling_per_class', 'scaling_queries'),
    'no_node': ('node_objects', 'node_rounds', 'node_rates', 'node_duration', 'node_max_drop',
                'node_workers', 'node_worker_processes', 'node_blas_threads'),
}
# options of several phases: unused only when every one of them is switched off
UNUSED_WITH_ALL = {
    ('no_icp', 'no_scaling'): ('icp_init_yaws',),
    ('no_paper', 'no_icp'): ('slow_repeats',),
    ('model', 'no_paper', 'no_scaling'): ('k',),
    # the training split: beo's fit, the paper and icp peers and the scaling curves
    ('model', 'no_paper', 'no_icp', 'no_scaling'): ('train_per_class',),
}


def parse_args(argv):
    """beo-bench's options (``argv``; None: sys.argv) -> argparse Namespace, --quick
    applied."""
    ap = ArgumentParser(prog='beo-bench', description=__doc__.split('\n')[0])
    for add in (_add_data_options, _add_peer_options, _add_scaling_options, _add_node_options):
        add(ap)
    args = ap.parse_args(argv)
    given = given_options(ap, argv)   # also those given at their default value
    groups = [((switch,), names) for switch, names in UNUSED_WITH.items()] + \
        list(UNUSED_WITH_ALL.items())
    unused = [(switches, n) for switches, names in groups
              if all(getattr(args, s) for s in switches) for n in names if n in given]
    if unused:   # an option the run does not use is refused rather than silently ignored
        switches = [s for s in UNUSED_WITH if any(s in sw for sw, _ in unused)]
        ap.error('not used in this run (' + ', '.join(
            f"--{s.replace('_', '-')}" for s in switches) + '): '
            + ', '.join(f"--{n.replace('_', '-')}" for _, n in unused))
    if not args.no_node and max(args.node_rates) * args.node_duration > MAX_NODE_MESSAGES:
        ap.error(f'--node-rates x --node-duration: the highest rate for {args.node_duration:g} s '
                 f'is {max(args.node_rates) * args.node_duration:.0f} clouds in the bench bag, '
                 f'at most {MAX_NODE_MESSAGES} (a shorter --node-duration or a lower rate)')
    from beo_ros.core.training import check_grid_size
    for n in args.scaling_grids:   # the scaling phase fits class models at each size
        try:
            check_grid_size(n)
        except ValueError as e:
            ap.error(f'--scaling-grids: {e}')
    if args.quick:
        _quick_sizes(args)
    return args


def _add_data_options(ap):
    """--out, the data, the split and the seed."""
    ap.add_argument('--out', default='bench_out', help='output directory (bench.json, PNGs)')
    ap.add_argument('--data', default='', help="voxel npz (default: $BEO_DATA_DIR/"
                    f"{DEFAULT_DATA}, or generated boxes/cylinders when that file is "
                    "missing); 'none' = generated boxes/cylinders")
    ap.add_argument('--classes', nargs='+', default=None, help='class subset')
    ap.add_argument('--quick', action='store_true',
                    help='tiny run (< ~60 s): overrides the sizes (classes unless --classes or '
                         '--model, objects per class, repeats, k, scaling points, node rates and '
                         'objects) with small ones')
    ap.add_argument('--seed', type=count(0), default=0)
    ap.add_argument('--test-frac', type=number(0, 1, lo_open=True, hi_open=True), default=0.2,
                    help='held-out fraction per class, in (0, 1) (default 0.2)')
    # a class model needs 2 objects (1 failed in the first fit, or after the peers with --model)
    ap.add_argument('--train-per-class', type=count(2), default=None,
                    help='cap training objects per class, >= 2 (default: all of the split)')
    ap.add_argument('--queries-per-class', type=count(1), default=10,
                    help='cap held-out queries per class (default 10)')


def _add_peer_options(ap):
    """Timing repeats, the peers' sizes and the --no-<phase> switches."""
    ap.add_argument('--repeats', type=count(1), default=3,
                    help='timing repeats per query (beo)')
    ap.add_argument('--slow-repeats', type=count(1), default=1,
                    help='timing repeats per query for paper and icp')
    ap.add_argument('--k', type=count(1), default=20, help='components per class')
    ap.add_argument('--model', default=None,
                    help='use this bank for beo (must not have been trained on the queries)')
    ap.add_argument('--beo-classifier-views', type=count(0), default=1)
    ap.add_argument('--beo-verifier-views', type=count(0), default=6,
                    help="views per training object for beo's orientation verifier, as "
                         'beo-train makes it (0: none; --quick: 0)')
    ap.add_argument('--icp-db-per-class', type=count(1), default=10)
    ap.add_argument('--icp-init-yaws', type=count(1), default=4)
    ap.add_argument('--paper-yaws', type=count(1), default=36)
    ap.add_argument('--no-paper', action='store_true')
    ap.add_argument('--no-icp', action='store_true')
    ap.add_argument('--no-scaling', action='store_true')
    ap.add_argument('--no-node', action='store_true')
    ap.add_argument('--no-plots', action='store_true')


def _add_scaling_options(ap):
    """The points of the scaling curves."""
    from beo_ros.core.bank import YAW_STEP_RANGE_DEG
    ap.add_argument('--scaling-train', type=count(1), nargs='+', default=[100, 200])
    ap.add_argument('--scaling-grids', type=count(4, 256), nargs='+', default=[24, 32, 48, 64])
    ap.add_argument('--scaling-yaw-steps', type=number(*YAW_STEP_RANGE_DEG), nargs='+',
                    default=[10.0, 5.0, 1.0])
    ap.add_argument('--scaling-classes', type=count(1), nargs='+', default=[2, 5, 10])
    # >= 2: a class model needs 2 objects (1 failed in the grid curve, after the peers had run)
    ap.add_argument('--scaling-per-class', type=count(2), default=8)
    ap.add_argument('--scaling-queries', type=count(1), default=6)


def _node_rate(text):
    """argparse ``type`` of --node-rates: a rate in (0, MAX_NODE_RATE_HZ] Hz."""
    value = number(0, None, lo_open=True)(text)
    if value > MAX_NODE_RATE_HZ:
        raise argparse.ArgumentTypeError(
            f'must be at most {MAX_NODE_RATE_HZ:g} Hz, got {text} (the bench bag holds rate x '
            '--node-duration clouds)')
    return value


_node_rate.__name__ = 'number'   # argparse names the type in its messages


def _add_node_options(ap):
    """The node benchmark: the bag, the replay rates and the node's own parameters."""
    ap.add_argument('--node-objects', type=count(1), default=20,
                    help='rendered clouds in the node bench bag (cycled)')
    ap.add_argument('--node-rounds', type=count(1), default=1,
                    help='closed-loop passes over the clouds (latency without queueing)')
    ap.add_argument('--node-rates', type=_node_rate, nargs='+', default=[10, 15, 20, 25, 30],
                    help=f'open-loop bag replay rates (Hz), at most {MAX_NODE_RATE_HZ:g}')
    ap.add_argument('--node-duration', type=number(0, 3600, lo_open=True), default=8.0,
                    help='seconds of replay per rate')
    ap.add_argument('--node-max-drop', type=number(0, 1), default=0.05,
                    help='a replay rate counts as sustained with at most this fraction of its '
                         'clouds dropped as stale (and none lost, rejected or unanswered)')
    # the ranges of the node's own parameters (a value out of them fails at node start)
    ap.add_argument('--node-workers', type=count(0, 64), default=0,
                    help="the node's workers parameter, 1..64 (0: its default)")
    ap.add_argument('--node-worker-processes', type=count(-1, 64), default=2,
                    help="the node's worker_processes parameter, 0..64 (default 2, as in "
                         "config/beo.yaml; -1: the node's built-in default, 0)")
    ap.add_argument('--node-blas-threads', type=count(0, 64), default=None,
                    help="the node's blas_threads parameter, 0..64 (default: the node's "
                         "default; 0: the BLAS library's own default)")


def _quick_sizes(args):
    """--quick: small sizes in ``args`` (in place); two classes of the data file unless
    --classes names them or --model is given (chair and monitor when it has both)."""
    from beo_ros.core.datasets import npz_class_names
    p = data_path(args.data)
    # --model: the data's classes must be the bank's (two picked here never were)
    if p is not None and not args.classes and not args.model:
        try:
            with np.load(p) as z:
                have = npz_class_names(z['classes'], p)
        except (OSError, KeyError, ValueError):
            have = []   # the loader says what is wrong with the file
        args.classes = (['chair', 'monitor'] if {'chair', 'monitor'} <= set(have)
                        else have[:2] or None)
    args.train_per_class = args.train_per_class or 12
    args.queries_per_class = min(args.queries_per_class, 3)
    args.repeats = min(args.repeats, 2)
    args.beo_classifier_views = 0
    args.beo_verifier_views = 0
    args.icp_db_per_class = min(args.icp_db_per_class, 3)
    args.icp_init_yaws = min(args.icp_init_yaws, 4)
    args.k = min(args.k, 4 if p is None else 8)
    args.scaling_train = [8]
    args.scaling_grids = [12, 16] if p is None else [16, 24]
    args.scaling_yaw_steps = [10.0, 5.0]
    args.scaling_classes = [2]
    args.scaling_per_class = 4
    args.scaling_queries = 2
    args.node_objects = min(args.node_objects, 4)
    args.node_rates = [2.0, 4.0]
    args.node_duration = min(args.node_duration, 1.5)


@interruptible('beo-bench')
def main(argv=None):
    args = parse_args(argv)
    try:
        return run(args)
    except BrokenPipeError:   # stdout's reader is gone: see cli.interruptible
        raise
    except (ValueError, OSError) as e:
        print(f'beo-bench: error: {e}', file=sys.stderr)
        return 2


def run(args):
    """The bench of parsed ``args``: writes bench.json, bench.md and the PNGs; exit code (0,
    or 1 when the node benchmark failed: the other results are written all the same)."""
    out = Path(args.out)
    problem = out_dir_problem(out)
    if problem:
        raise ValueError(f'--out {out}: {problem}')
    rng = np.random.default_rng(args.seed)
    t_all = time.perf_counter()
    X, y, names, n, source = load_data(args, rng)
    tr, te = split(y, args.test_frac, np.random.default_rng(args.seed), args.train_per_class,
                   args.queries_per_class)
    bank = None
    if args.model:
        from beo_ros.core.bank import load_models
        bank = load_models(args.model)
        if list(bank.classes) != list(names):
            raise ValueError(f'--model classes {bank.classes} differ from the data {names}')
        if bank.spec.size != n:
            raise ValueError(f'--model {args.model} is for a {bank.spec.size}^3 grid, the data '
                             f'{source} is on {n}^3')
    # the inputs are valid: the work starts (a failure or Ctrl-C leaves no empty --out)
    with output_dir(out):
        return _bench(args, out, X, y, names, n, source, tr, te, bank, t_all)


def _bench(args, out, X, y, names, n, source, tr, te, bank, t_all):
    """The peers, scaling and node phases of :func:`run` and their output files; exit code."""
    queries = make_queries(X, y, te, n, np.random.default_rng(args.seed + 1))
    log(f'data: {source}; {len(names)} classes, {len(tr)} training objects, '
        f'{len(queries)} queries')
    res = {'setup': _setup(args, source, names, n, tr, queries)}
    bank = _bench_beo(args, res, X, y, tr, names, n, queries, bank)
    # a peer switched off is named so (the summary and bench.md say 'not run', not nothing)
    res['paper'] = ({'skipped': '--no-paper'} if args.no_paper else
                    _bench_paper(args, X, y, tr, names, n, queries))
    res['icp'] = ({'skipped': '--no-icp'} if args.no_icp else
                  _bench_icp(args, X, y, tr, names, n, queries))
    for p in ('icp', 'paper'):
        if _measured(res, p):
            res[f'speedup_vs_{p}'] = res[p]['p50_ms'] / res['beo']['p50_ms']

    res['scaling'] = ({'skipped': '--no-scaling'} if args.no_scaling else
                      scaling(args, X, y, names, n, tr, queries, bank,
                              np.random.default_rng(args.seed + 2)))
    res['node'], node_failed = _bench_node(args, bank, X, n, te)
    res['setup']['wall_s'] = time.perf_counter() - t_all

    res = json_safe(res)
    (out / 'bench.json').write_text(json.dumps(res, indent=2) + '\n')
    (out / 'bench.md').write_text(markdown(res))
    if not args.no_plots:
        plots(res, out)
    _print_summary(res)
    print(f'wrote {out / "bench.json"}')
    if node_failed:
        print(f'beo-bench: error: the node benchmark failed ({node_failed}); the other '
              'results are written', file=sys.stderr)
        return 1
    return 0


def _setup(args, source, names, n, tr, queries):
    """The 'setup' section of bench.json: data, sizes, protocol and the machine."""
    return {
        'data': source, 'classes': names, 'grid': n, 'train_objects': int(len(tr)),
        'queries': len(queries), 'seed': args.seed, 'k': args.k, 'repeats': args.repeats,
        'slow_repeats': args.slow_repeats, 'quick': bool(args.quick),
        'protocol': 'one random partial view per held-out object: yaw U[0,360), azimuth '
                    'U[0,360), elevation U[10,50] deg (beo_ros.core.synthetic)',
        'cpu_count': os.cpu_count(),
        # other work on the machine shows here (the bench does not know what else runs)
        'load_average_1min': round(os.getloadavg()[0], 2) if hasattr(os, 'getloadavg') else None}


def _bench_beo(args, res, X, y, tr, names, n, queries, bank):
    """beo's peer results into ``res['beo']`` (and how its bank came about into
    ``res['setup']``); the bank: ``bank`` (--model) or one fitted on the objects ``tr``."""
    t0 = time.perf_counter()
    if bank is not None:
        res['setup']['beo_model'] = (f'{args.model} (given: valid only if it was not trained '
                                     'on the query objects)')
    else:
        log('[beo] fitting the bank on the training split')
        bank = fit_beo(X[tr], y[tr], names, n, args.k, args.beo_classifier_views, args.seed,
                       verifier_views=args.beo_verifier_views, processes=2)
        res['setup']['beo_model'] = (f'trained here on the split, classifier_views='
                                     f'{args.beo_classifier_views}, verifier_views='
                                     f'{args.beo_verifier_views}')
    fit_s = time.perf_counter() - t0
    log('[beo] queries')
    bank.estimate(queries[0]['grid'])  # warm-up
    res['beo'] = run_peer('beo', beo_predict(bank), queries, args.repeats)
    res['beo'].update(fit_s=fit_s, index_mb=bank_nbytes(bank) / 2**20)
    return bank


def _bench_paper(args, X, y, tr, names, n, queries):
    """The paper's plain PCA method fitted on the objects ``tr`` and queried; its results."""
    from beo_ros.core.baselines import PaperPCA
    log('[paper] fitting PCA and querying')
    t0 = time.perf_counter()
    paper = PaperPCA(k=args.k, n_yaws=args.paper_yaws).fit(X[tr], y[tr], names, n)
    fit_s = time.perf_counter() - t0
    r = run_peer('paper', answer_empty_views(paper.predict), queries, args.slow_repeats)
    r.update(fit_s=fit_s, index_mb=paper.nbytes / 2**20, yaw_candidates=args.paper_yaws)
    return r


def _bench_icp(args, X, y, tr, names, n, queries):
    """The ICP database built from the objects ``tr`` and queried; its results."""
    from beo_ros.core.baselines import ICPDatabase
    log('[icp] building the database and querying')
    t0 = time.perf_counter()
    icp = ICPDatabase(per_class=args.icp_db_per_class, n_init_yaws=args.icp_init_yaws,
                      seed=args.seed).fit(X[tr], y[tr], names, n)
    fit_s = time.perf_counter() - t0
    r = run_peer('icp', answer_empty_views(icp.predict), queries, args.slow_repeats)
    r.update(fit_s=fit_s, index_mb=icp.nbytes / 2**20, db_size=icp.size,
             db_per_class=args.icp_db_per_class, init_yaws=args.icp_init_yaws)
    return r


def _bench_node(args, bank, X, n, te):
    """The node phase -> (its ``res['node']``, None or what made it fail)."""
    if args.no_node:
        return {'skipped': '--no-node'}, None
    log('[node] bag replay (open loop) and closed loop through BeoNode')
    try:
        return node_bench(bank, X, n, te, args, np.random.default_rng(args.seed + 3)), None
    except Exception as e:  # noqa: BLE001 - the peers' results are kept and written
        log(f'[node] failed: {type(e).__name__}: {e}')
        return {'skipped': f'failed: {type(e).__name__}: {e}'}, f'{type(e).__name__}: {e}'


def _print_summary(res):
    """The peers' table and speedups ('not run' for a peer switched off) and the node line,
    to stdout."""
    if _measured(res, 'beo'):
        print(table(res))
        print('speedup ' + ', '.join(speedups(res, ':')))
    node = res['node']
    if 'objects_per_s' in node:
        sus = node['sustained_rate_hz']
        # no rate sustained: the figures are those of the lowest rate (it read 'sustains 0 Hz')
        lowest = min((r['rate_hz'] for r in node.get('rates') or ()), default=None)
        print(f"node (workers={node['workers']}, "
              f"worker_processes={node.get('worker_processes', 0)}): "
              + (f"sustains {sus:g} Hz replay, " if sus is not None else
                 'sustains none of the replay rates; at the lowest'
                 + (f' ({lowest:g} Hz)' if lowest is not None else '') + ': ')
              + f"{_fmt(node['objects_per_s'], '.2f')} "
              f"objects/s out ({node['dropped_stale']} dropped, {node['lost']} lost), "
              f"end-to-end p50 {_fmt(node['e2e_p50_ms'])} ms, p95 {_fmt(node['e2e_p95_ms'])} ms; "
              f"highest output {_fmt(node.get('max_objects_per_s'), '.2f')}/s")
    else:
        print(f"node: skipped ({node.get('skipped')})")


if __name__ == '__main__':
    sys.exit(main())
