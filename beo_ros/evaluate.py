"""beo-eval: accuracy, yaw error, completion IoU and latency on labelled voxel objects.

Held-out mode:  beo-eval --model DIR --data test.npz --out DIR
Cross-validation on a training set (a bank is trained per fold, the held-out fold evaluated):
                beo-eval --cv 3 --data train.npz --out DIR
Tabletop scans (leave-one-scene-out):  beo-eval --scans learn*.pcd --out DIR [--k K]
                (their own options, e.g. --scan-classes, --no-congeal, --scene-folds,
                --from-points: python -m beo_ros.scan_eval --help)

Per object: the complete grid at yaw 0 (classification only) and one partial view made by the
evaluation protocol (random yaw; orthographic view from azimuth U[0, 360), elevation U[10, 50]).
Yaw within 10 deg is printed plain, with 180 deg flips counted right (+flip) and up to the
object's own symmetry (+sym: off by a quarter turn that maps the whole object onto itself).
--out gets eval.json (summary, per class, confusion), records.jsonl (one line per object and
view) and eval.png (examples, confusion matrix).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .cli import (ArgumentParser, complete_files, count, given_options, interruptible, json_safe,
                  out_dir_problem, output_dir)
from .core.bank import load_models, parse_class_prior
from .core.calibration import calibration_sums, metrics_from_sums
from .core.grid import GridSpec, symmetric_turns, yaw_error, yaw_error_up_to
from .core.synthetic import random_partial_view
from .core.datasets import (drop_empty_objects, load_voxel_npz, select_classes,
                            training_data_hash)
from .core.training import check_class_counts, fit_bank, progress_bar, stratified_folds

# folds of the out-of-fold classifier features of each --cv fold's bank (fit_bank's default)
CLASSIFIER_FOLDS = 5


def one_fold_parser(description, json_help):
    """ArgumentParser of the one-fold measurement scripts in scripts/: a voxel npz, --fold of
    --folds, every n-th held-out object, --k, --seed of the views, --json (``json_help``)."""
    ap = argparse.ArgumentParser(description=description,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('data', help='voxel npz (shared format)')
    ap.add_argument('--fold', type=int, default=0, help='held-out fold (default 0)')
    ap.add_argument('--folds', type=int, default=5, help='folds, as beo-eval --cv (default 5)')
    ap.add_argument('--every', type=int, default=1, help='every n-th held-out object')
    ap.add_argument('--k', type=int, default=20, help='components per class')
    ap.add_argument('--seed', type=int, default=7, help='seed of the views')
    ap.add_argument('--json', help=json_help)
    return ap


def held_out_fold(ap, argv=None):
    """Parse ``one_fold_parser`` arguments and split their npz into the folds of beo-eval --cv
    (with --seed 0) -> (args, X, y, class names, N, training indices, held-out indices)."""
    args = ap.parse_args(argv)
    if not 0 <= args.fold < args.folds or args.folds < 2 or args.every < 1:
        ap.error('need folds >= 2, 0 <= fold < folds and every >= 1')
    X, y, names, n = load_voxel_npz(args.data)
    fold = stratified_folds(y, args.folds, np.random.default_rng(0))
    tr, te = np.flatnonzero(fold != args.fold), np.flatnonzero(fold == args.fold)[::args.every]
    return args, X, y, names, n, tr, te


def stratified_subset(idx, y, m, rng):
    """At most ``m`` of the object indices ``idx`` (sorted), drawn per class of ``y[idx]`` in
    proportion to its count, at least one of every class when ``m`` allows (largest
    remainders get the rest)."""
    idx = np.asarray(idx)
    if m >= len(idx):
        return idx
    classes, counts = np.unique(y[idx], return_counts=True)
    base = np.ones(len(classes), dtype=int) if m >= len(classes) else np.zeros(len(classes),
                                                                              dtype=int)
    share = (m - base.sum()) * (counts - base) / (counts - base).sum()
    take = base + np.floor(share).astype(int)
    rest = m - int(take.sum())
    take[np.argsort(-(share - np.floor(share)), kind='stable')[:rest]] += 1
    pick = [rng.choice(idx[y[idx] == c], t, replace=False) for c, t in zip(classes, take)]
    return np.sort(np.concatenate(pick))


def warm_up_grid(n):
    """A fixed partial view (n, n, n) int8 for a warm-up estimate, drawn from no RNG: free
    voxels in front of a face of occupied voxels seen along +x, the rest unknown."""
    grid = np.full((n, n, n), -1, dtype=np.int8)
    grid[:n // 4] = 0
    grid[n // 4, n // 4:3 * n // 4, :n // 2] = 1
    return grid


def evaluate_bank(bank, X, y, names, rng, views=1, examples=6, progress=True, index=None):
    """Evaluate ``bank`` on objects X (m, N^3) with labels y indexing ``names``.

    ``index`` (m,): the objects' indices in their file, for the records (default 0..m-1).
    A view with no occupied voxel (an empty object, or one of a few voxels that the rotation
    lost) is answered 'unknown' without a pose: its yaw errors are NaN, counted as misses.
    Returns (summary dict, per-view records list, example list for the figure).
    """
    n = bank.spec.size
    index = np.arange(len(X)) if index is None else np.asarray(index)
    # one untimed estimate first: the bank's one-off costs (rotation maps of the yaw search,
    # lazy imports) made the first timed estimate several times slower than the others
    bank.estimate(warm_up_grid(n))
    recs, ex = [], []
    for i in progress_bar(range(len(X)), 'evaluating', disable=not progress):
        occ = X[i].reshape(n, n, n) > 0.5
        truth = names[y[i]]
        # quarter turns that map the whole object onto itself: a yaw off by one of them is
        # a right answer up to the object's own symmetry (reported beside the plain yaw error)
        turns = symmetric_turns(occ)
        empty = bool(not occ.any())
        t0 = time.perf_counter()
        e = bank.estimate(occ.astype(np.int8), yaw=0.0)
        rec_c = dict(i=int(index[i]), mode='complete', truth=truth, label=e.label,
                     latency=time.perf_counter() - t0, empty_object=empty)
        recs.append(rec_c)
        for _ in range(views):
            grid, yaw, az, el, rotated = random_partial_view(occ, rng)
            t0 = time.perf_counter()
            e = bank.estimate(grid)
            dt = time.perf_counter() - t0
            pred = e.completion >= 0.5
            inter = (pred & rotated).sum()
            union = (pred | rotated).sum()
            # a view with no occupied voxel has no pose (the estimate's yaw is a placeholder):
            # no yaw error (NaN), a miss, rather than the placeholder scored against the truth
            empty_view = bool(not (grid == 1).any())
            err = float('nan') if empty_view else float(yaw_error(e.yaw, yaw))
            err_sym = float('nan') if empty_view else float(yaw_error_up_to(e.yaw, yaw, turns))
            unknown = grid < 0
            recs.append(dict(i=int(index[i]), mode='partial', truth=truth, label=e.label,
                             latency=dt, yaw_deg=float(np.rad2deg(yaw)),
                             est_yaw_deg=float(np.rad2deg(e.yaw)),
                             symmetric_yaws_deg=[float(np.rad2deg(v)) for v in e.symmetric_yaws],
                             yaw_err_deg=float(np.rad2deg(err)),
                             self_turns_deg=[round(float(np.rad2deg(t))) for t in turns],
                             yaw_err_sym_deg=float(np.rad2deg(err_sym)),
                             # the rotation lost an object of a few voxels: nothing to see
                             empty_view=empty_view, empty_object=empty,
                             iou=float(inter / union) if union else 1.0,
                             # how well the unknown voxels' probabilities are calibrated
                             voxels=calibration_sums(e.completion[unknown], rotated[unknown]),
                             prob=float(e.probability)))
            if len(ex) < examples and (not ex or truth not in [x[0] for x in ex]):
                ex.append((truth, e.label, grid, e.completion, rotated, np.rad2deg(err)))
    return summarize(recs, bank.classes), recs, ex


def summarize(recs, classes):
    out = {}
    for mode in ('complete', 'partial'):
        r = [x for x in recs if x['mode'] == mode]
        if not r:
            continue
        lat = np.array([x['latency'] for x in r]) * 1000
        recall = [np.mean([x['label'] == c for x in r if x['truth'] == c]) for c in classes
                  if any(x['truth'] == c for x in r)]
        # mean per-class recall: what the accuracy would be with equal counts per class
        s = dict(n=len(r), accuracy=float(np.mean([x['label'] == x['truth'] for x in r])),
                 balanced_accuracy=float(np.mean(recall)),
                 latency_p50_ms=float(np.median(lat)), latency_p95_ms=float(np.percentile(lat, 95)))
        if mode == 'partial':
            e = np.array([x['yaw_err_deg'] for x in r])
            ok_cls = np.array([x['label'] == x['truth'] for x in r])
            es = np.array([x['yaw_err_sym_deg'] for x in r])
            s.update(yaw_within_10=float(np.mean(e <= 10)),
                     yaw_within_10_or_flip=float(np.mean((e <= 10) | (e >= 170))),
                     yaw_within_10_up_to_symmetry=float(np.mean(es <= 10)),
                     self_symmetric=float(np.mean([bool(x['self_turns_deg']) for x in r])),
                     empty_views=int(sum(x['empty_view'] for x in r)),
                     # a view without a yaw (NaN: no object seen) as the largest error
                     yaw_median_deg=float(np.median(np.where(np.isnan(e), 180.0, e))),
                     yaw_within_10_correct_class=float(np.mean(e[ok_cls] <= 10)) if ok_cls.any()
                     else float('nan'),
                     iou=float(np.mean([x['iou'] for x in r])),
                     completion_calibration=metrics_from_sums(
                         [x['voxels'] for x in r if 'voxels' in x]))
            per = {}
            for c in classes:
                rc = [x for x in r if x['truth'] == c]
                if rc:
                    per[c] = dict(
                        n=len(rc), accuracy=float(np.mean([x['label'] == c for x in rc])),
                        yaw_within_10=float(np.mean([x['yaw_err_deg'] <= 10 for x in rc])),
                        yaw_within_10_up_to_symmetry=float(np.mean(
                            [x['yaw_err_sym_deg'] <= 10 for x in rc])),
                        self_symmetric=float(np.mean([bool(x['self_turns_deg']) for x in rc])))
            s['per_class'] = per
        out[mode] = s
    # confusion matrices (rows truth, columns prediction; last column 'unknown')
    labels = list(classes) + ['unknown']
    for mode in out:
        cm = np.zeros((len(classes), len(labels)), dtype=int)
        for x in recs:
            if x['mode'] == mode and x['truth'] in classes:
                j = labels.index(x['label']) if x['label'] in labels else len(labels) - 1
                cm[classes.index(x['truth']), j] += 1
        out[mode]['confusion'] = cm.tolist()
    out['classes'] = list(classes)
    return out


def print_table(summary, file=None):
    file = file or sys.stdout   # looked up at call time (a default would pin the import's)
    print(f"{'mode':10s} {'n':>5s} {'acc':>6s} {'bal':>6s} {'yaw<=10':>8s} {'+flip':>6s} "
          f"{'+sym':>6s} {'IoU':>6s} {'p50 ms':>7s} {'p95 ms':>7s}", file=file)
    for mode in ('complete', 'partial'):
        if mode not in summary:
            continue
        s = summary[mode]
        f = (lambda k: f"{s[k]:.3f}" if k in s else '-')
        print(f"{mode:10s} {s['n']:5d} {s['accuracy']:6.3f} {f('balanced_accuracy'):>6s} "
              f"{f('yaw_within_10'):>8s} "
              f"{f('yaw_within_10_or_flip'):>6s} {f('yaw_within_10_up_to_symmetry'):>6s} "
              f"{f('iou'):>6s} {s['latency_p50_ms']:7.1f} "
              f"{s['latency_p95_ms']:7.1f}", file=file)
    cal = summary.get('partial', {}).get('completion_calibration')
    if cal and cal['voxels']:
        print(f"completion, {cal['voxels']} unknown voxels of the partial views: Brier "
              f"{cal['brier']:.4f}, log loss {cal['log_loss']:.4f}, ECE {cal['ece']:.4f}",
              file=file)


def write_figure(summary, examples, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    rows = max(len(examples), 1)
    fig = plt.figure(figsize=(13, 2.6 * rows + 4))
    for r, (truth, label, grid, comp, rotated, err) in enumerate(examples):
        for j, (title, vol, kind) in enumerate((('input view', grid, 'grid'),
                                                 ('completion p>=0.5', comp, 'prob'),
                                                 ('truth', rotated, 'bool'))):
            ax = fig.add_subplot(rows + 1, 4, r * 4 + j + 1, projection='3d')
            if kind == 'grid':
                pts = np.argwhere(vol == 1)
                unk = np.argwhere(vol == -1)
                if len(unk):
                    sub = unk[:: max(1, len(unk) // 400)]
                    ax.scatter(*sub.T, s=1, c='0.85')
                ax.scatter(*pts.T, s=2, c='tab:blue')
            elif kind == 'prob':
                pts = np.argwhere(vol >= 0.5)
                ax.scatter(*pts.T, s=2, c=vol[vol >= 0.5], cmap='viridis', vmin=0.5, vmax=1)
            else:
                pts = np.argwhere(vol)
                ax.scatter(*pts.T, s=2, c='tab:green')
            n = vol.shape[0]
            ax.set_xlim(0, n), ax.set_ylim(0, n), ax.set_zlim(0, n)
            ax.set_axis_off()
            # class names as written: a '$' in one is no mathtext (two failed the savefig)
            ax.set_title(f'{title}' + (f'\n{truth} -> {label}, yaw err {err:.0f} deg'
                                       if j == 0 else ''), fontsize=8, parse_math=False)
    if 'partial' in summary:
        ax = fig.add_subplot(rows + 1, 2, 2 * rows + 1)
        cm = np.array(summary['partial']['confusion'])
        ax.imshow(cm / np.maximum(cm.sum(axis=1, keepdims=True), 1), cmap='Blues', vmin=0, vmax=1)
        cl = summary['classes'] + ['unknown']
        ax.set_xticks(range(len(cl)), cl, rotation=90, fontsize=7, parse_math=False)
        ax.set_yticks(range(len(summary['classes'])), summary['classes'], fontsize=7,
                      parse_math=False)
        ax.set_title('partial views: confusion (rows truth)', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# options only one mode uses (--scans: see below)
CV_ONLY = ('folds', 'k', 'train_views', 'verifier_views', 'jobs')
HELD_OUT_ONLY = ('model',)


def _refuse_unused(ap, args, given, names, why):
    """``ap.error(why + flags)`` for the options of ``names`` on the command line (``given``:
    :func:`given_options`, one given at its default value too) that the run does not use;
    when every one of them is at its default value (it would have run the same without them)
    a warning on stderr instead: a script that spells the defaults out keeps working, and the
    user still hears that they do nothing."""
    unused = [f"--{n.replace('_', '-')}" for n in names if n in given]
    if not unused:
        return
    if any(getattr(args, n) != ap.get_default(n) for n in names if n in given):
        ap.error(why + ', '.join(unused))
    print(f'{ap.prog}: warning: {why}{", ".join(unused)} (given at the default value: '
          'ignored)', file=sys.stderr)


@interruptible('beo-eval')
def main(argv=None):
    ap = _parser()
    args, rest = ap.parse_known_args(argv)
    given = given_options(ap, argv)
    if args.scans:
        return _forward_to_scan_eval(ap, args, rest, given)
    class_prior, out = _checked_args(ap, args, rest, given)
    rng = np.random.default_rng(args.seed)
    try:
        X, y, names, n, bank = _load_inputs(args, class_prior)
        # nothing written yet: a failure or Ctrl-C leaves no empty --out behind
        with output_dir(out):
            if args.cv:
                summary, recs, examples, bank = _cross_validate(args, X, y, names, n,
                                                                class_prior, rng)
            else:
                summary, recs, examples = _evaluate_held_out(args, bank, X, y, names, rng)
            _report(summary, recs, examples, bank, out, argv)
    except BrokenPipeError:   # stdout's reader is gone: see cli.interruptible
        raise
    except (ValueError, OSError) as e:
        print(f'beo-eval: error: {e}', file=sys.stderr)
        return 2
    return 0


def _parser():
    """The ArgumentParser of beo-eval (--scans options of scan_eval pass through)."""
    ap = ArgumentParser(prog='beo-eval', description=__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--data', help='labelled voxel npz (shared format)')
    ap.add_argument('--model', help='model directory (held-out mode; default: shipped model)')
    ap.add_argument('--cv', type=int, default=0,
                    help='K-fold cross-validation on --data (K >= 2; 0: held-out mode)')
    ap.add_argument('--folds', type=int, default=0,
                    help='with --cv: evaluate only this many of the K folds (0: all)')
    ap.add_argument('--k', type=count(1), default=None,
                    help='components per class (--cv: default 20; --scans: default 8)')
    ap.add_argument('--train-views', type=count(0), default=1,
                    help='partial views per object for the OOF classifier (--cv)')
    ap.add_argument('--max-objects', type=count(0), default=0,
                    help='evaluate at most this many objects (per fold), stratified: per class '
                         'in proportion, at least one of each when there are enough (0: all)')
    ap.add_argument('--views', type=count(0), default=1,
                    help='partial views per evaluated object')
    ap.add_argument('--seed', type=count(0), default=0)
    ap.add_argument('--out', default='beo_eval_out',
                    help='directory for JSON and PNG (default: %(default)s)')
    ap.add_argument('--scans', nargs='+', help='tabletop PCD scans: leave-one-scene-out CV')
    ap.add_argument('--verifier-views', type=count(0), default=6, metavar='N',
                    help='--cv: random views per object for the orientation verifier of each '
                         "fold's bank, as beo-train makes it (0: none; default: %(default)s)")
    ap.add_argument('--jobs', type=count(1), default=1,
                    help="--cv: processes that make the verifier's views")
    ap.add_argument('--class-prior', default='', metavar='PRIOR',
                    help="prior over the classes: train, uniform or name=weight,... with every "
                         "class; default: the model's own (--cv: train)")
    return ap


def _forward_to_scan_eval(ap, args, rest, given):
    """--scans: refuse the voxel modes' options (``given``: those on the command line), hand
    the rest to scan_eval; its exit code."""
    if args.class_prior:
        ap.error('--class-prior is not used with --scans')
    _refuse_unused(ap, args, given, ('data', 'model', 'cv', 'folds', 'train_views',
                                     'max_objects', 'views', 'seed', 'verifier_views', 'jobs'),
                   'not used with --scans: ')
    from . import scan_eval
    k = [] if args.k is None else ['--k', str(args.k)]
    return scan_eval.main(['--scans', *args.scans, '--out', args.out, *k, *rest])


def _checked_args(ap, args, rest, given):
    """Refuse (``ap.error``) what the voxel modes cannot run (``given``: the options on the
    command line) -> (class prior, --out Path)."""
    if rest:
        ap.error(f'unrecognized arguments: {" ".join(rest)}')
    if not args.data:
        ap.error('--data is required (or --scans)')
    if args.cv < 0 or args.cv == 1:
        ap.error(f'--cv must be 0 (held-out mode) or a number of folds >= 2, got {args.cv}')
    if args.cv and not 0 <= args.folds <= args.cv:
        ap.error(f'--folds must be in [0, --cv] (0: all {args.cv} folds), got {args.folds}')
    # an option the mode does not use is refused rather than silently ignored
    _refuse_unused(ap, args, given, HELD_OUT_ONLY if args.cv else CV_ONLY,
                   'not used with --cv (each fold trains its own bank): ' if args.cv else
                   'used only with --cv, not in held-out mode: ')
    if args.cv and args.verifier_views == 0:
        _refuse_unused(ap, args, given, ('jobs',), "--jobs makes the orientation verifier's "
                       'views: not used with --verifier-views 0: ')
    if args.model and Path(args.model).exists() and not Path(args.model).is_dir():
        ap.error(f'--model {args.model}: is not a directory')
    try:
        class_prior = parse_class_prior(args.class_prior)
    except ValueError as e:
        ap.error(str(e))
    out = Path(args.out)
    problem = out_dir_problem(out)   # --out is made once the inputs have loaded
    if problem:
        ap.error(f'--out {out}: {problem}')
    return class_prior, out


def _load_inputs(args, class_prior):
    """--data (and, held out, the model) checked to fit together -> (X (m, N^3), y, class
    names, N, bank: None with --cv). Raises ValueError on a mismatch."""
    X, y, names, n = load_voxel_npz(args.data)
    if not len(X):
        raise ValueError(f'{args.data}: no objects to evaluate')
    if args.cv:
        # classes named by the file but without objects: nothing to train a model on
        present = [names[c] for c in np.unique(y)]
        if len(present) < 2:
            raise ValueError(f'--cv needs objects of at least 2 classes to train and test '
                             f'a classifier; {args.data} has objects of {present} only')
        if len(present) < len(names):
            print(f'beo-eval: classes without objects in {args.data} left out: '
                  f'{[c for c in names if c not in present]}', file=sys.stderr)
            X, y, names = select_classes(X, y, names, present, args.data)
        # stratified folds deal each class round-robin: a fold past the largest class's
        # number of objects holds none, and its bank would be trained for nothing
        most = int(np.bincount(y).max())
        if (args.folds or args.cv) > most:
            raise ValueError(f'--cv {args.cv}' + (f' --folds {args.folds}' if args.folds else '')
                             + f': {args.data} has at most {most} objects of a class, so the '
                             f'folds past {most} would hold no object to evaluate (give --cv '
                             f'or --folds <= {most})')
        return X, y, names, n, None
    bank = load_models(args.model, class_prior)
    # the classes of the objects, not the file's whole class list: a subset file may
    # still name every class
    present = {names[c] for c in np.unique(y)}
    missing = present - set(bank.classes)
    if missing:
        raise ValueError(f'data classes {sorted(missing)} (of objects in {args.data}) '
                         f'are not in the model (classes {bank.classes})')
    if n != bank.spec.size:
        raise ValueError(f'{args.data}: objects on a {n}^3 grid, the model '
                         f'{args.model or "(shipped)"} is for {bank.spec.size}^3')
    return X, y, names, n, bank


def _evaluate_held_out(args, bank, X, y, names, rng):
    """Held-out mode: ``bank`` on (at most --max-objects of) the objects -> (summary,
    records, examples)."""
    own = _is_training_data(bank, X, y, names)
    if own:   # e.g. the shipped model on the shared train split: its numbers look held-out
        print(f"beo-eval: warning: {args.data} holds the objects the model "
              f"{args.model or '(shipped)'} was trained on: these numbers are in-sample, not "
              "held-out (out-of-fold numbers: --cv K, or the model's manifest.json "
              "'cross_validation')", file=sys.stderr)
    te = np.arange(len(X))
    if args.max_objects:
        te = stratified_subset(te, y, args.max_objects, rng)
    summary, recs, examples = evaluate_bank(bank, X[te], y[te], names, rng, args.views,
                                             index=te)
    summary['protocol'] = (f'in-sample: model {args.model or "shipped"} on its own training '
                           f'data {args.data}' if own else
                           f'held-out: model {args.model or "shipped"} on {args.data}')
    return summary, recs, examples


def _is_training_data(bank, X, y, names) -> bool:
    """True when (X, y, names) are the objects ``bank`` was trained on: the manifest's
    ``data_sha256`` (beo-train's hash of its objects after dropping those with no occupied
    voxel) equals theirs. False when the model has no hash (older or --scans models)."""
    recorded = bank.training.get('data_sha256')
    if not recorded:
        return False
    try:   # the objects beo-train would have kept, by its own rule
        X, y, _ = drop_empty_objects(X, np.asarray(y), names)
    except ValueError:   # a class with no occupied object: no training set of beo-train's
        return False
    return training_data_hash(X, y, names) == recorded


def _cross_validate(args, X, y, names, n, class_prior, rng):
    """--cv: a bank trained per fold, the held-out fold evaluated -> (summary, records,
    examples, the last fold's bank)."""
    fold = stratified_folds(y, args.cv, rng)
    # as beo-train: objects with no occupied voxel have no shape to learn (fit_bank cannot
    # take them); they are still evaluated, answered 'unknown'
    empty = ~(X > 0.5).any(axis=1)
    if empty.any():
        print(f'beo-eval: warning: {int(empty.sum())} objects with no occupied voxel left out '
              'of the training folds', file=sys.stderr)
    # every fold's training part checked before the first bank is trained (minutes each);
    # with a classifier, --train-views 0 is the way out of a class with too few objects for
    # its out-of-fold features
    for f in range(args.folds or args.cv):
        try:
            check_class_counts(y[(fold != f) & ~empty], names,
                               CLASSIFIER_FOLDS if args.train_views else 0, '--train-views 0')
        except ValueError as e:
            raise ValueError(f'--cv {args.cv}: the bank of fold {f} cannot be trained: {e}') \
                from None
    recs, examples, info = [], [], []
    for f in range(args.folds or args.cv):
        tr, te = np.flatnonzero(fold != f), np.flatnonzero(fold == f)
        if args.max_objects:
            te = stratified_subset(te, y, args.max_objects, rng)
        Xtr, ytr, _ = drop_empty_objects(X[tr], y[tr], names)
        t0 = time.time()
        bank = fit_bank(Xtr, ytr, names, GridSpec(size=n),
                        k=20 if args.k is None else args.k,
                        classifier_views=args.train_views, folds=CLASSIFIER_FOLDS,
                        seed=args.seed + f,
                        verbose=True, class_prior=class_prior or 'train',
                        verifier_views=args.verifier_views, processes=args.jobs)
        info.append(dict(fold=f, train=int(len(Xtr)), test=int(len(te)),
                         train_seconds=round(time.time() - t0, 1)))
        s, r, ex = evaluate_bank(bank, X[te], y[te], names, rng, args.views, index=te)
        print(f'fold {f}:', file=sys.stderr)
        print_table(s, file=sys.stderr)
        recs += r
        examples = examples or ex
    summary = summarize(recs, names)
    summary['folds'] = info
    summary['protocol'] = f'{args.cv}-fold stratified CV on {args.data}'
    return summary, recs, examples, bank


def _report(summary, recs, examples, bank, out, argv):
    """Write eval.json, records.jsonl and eval.png into ``out`` and print the table."""
    summary['class_prior'] = bank.class_prior if isinstance(bank.class_prior, str) else \
        dict(zip(bank.classes, map(float, bank.class_prior)))
    summary['command'] = 'beo-eval ' + ' '.join(sys.argv[1:] if argv is None else argv)
    # a failure or Ctrl-C while the figure was drawn left eval.json and records.jsonl alone
    with complete_files(out, ('eval.json', 'records.jsonl', 'eval.png')) as tmp:
        # strict JSON: non-finite numbers (a mean over no rows) as null
        tmp['eval.json'].write_text(json.dumps(json_safe(summary), indent=2,
                                               allow_nan=False) + '\n')
        # one line per complete object and per view (i: the object's index in --data)
        tmp['records.jsonl'].write_text(''.join(json.dumps(json_safe(r), allow_nan=False)
                                                + '\n' for r in recs))
        write_figure(summary, examples, tmp['eval.png'])
    # the files first: a reader of stdout gone (beo-eval ... | head -1) stops the printing
    print_table(summary)
    empty = sum(r['empty_object'] for r in recs if r['mode'] == 'complete')
    if empty:
        print(f"{empty} object(s) have no occupied voxel at all, answered 'unknown', "
              "a wrong class")
    lost = sum(r['empty_view'] and not r['empty_object'] for r in recs if r['mode'] == 'partial')
    if lost:
        print(f"{lost} view(s) had no occupied voxel (objects of a few voxels lost to the "
              "rotation), answered 'unknown' without a yaw, a wrong class and yaw")
    print(f'wrote {out / "eval.json"}, {out / "records.jsonl"} and {out / "eval.png"}')


if __name__ == '__main__':
    sys.exit(main())
