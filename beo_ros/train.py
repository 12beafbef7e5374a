"""beo-train: learn a model directory (per-class VBPCA + out-of-fold classifier).

Inputs: voxel npz files in the shared format (keys voxels (bit-packed or (n, N, N, N)), labels,
classes), meshes (OFF/OBJ/STL/PLY, class from the name before '_<digits>' or the folder), or
labelled tabletop scans (``--scans``, PCD files; see beo_ros.core.scans).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from .cli import ArgumentParser, count, existing_parent, interruptible, number, writable_dir
from .core.classifier import parse_class_prior
from .core.grid import GridSpec
from .core.model_files import UNREADABLE, check_class_names, check_save_target, is_model_dir
from .core.datasets import (drop_empty_objects, load_meshes, load_voxel_npz, select_classes,
                            training_data_hash)
from .core.training import check_class_counts, check_grid_size, fit_bank


# the values of the auto|on|off options, as fit_bank takes them
AUTO_ON_OFF = {'auto': 'auto', 'on': True, 'off': False}
# defaults of the options that apply to --scans (or --scans --mirror) only; the options
# default to None so that giving one without --scans is refused
SCAN_CLASSES, VOXEL_SIZE, MAX_ITER = 'box:0-16,cylinder:33-44', 0.5 / 32, 200


@interruptible('beo-train')
def main(argv=None):
    ap = _parser()
    args = ap.parse_args(argv)
    class_prior = _check_args(ap, args)
    try:
        replace = _check_out(args)
        if args.mirror:
            return _train_mirror(args, class_prior, replace)
        X, y, names, masks, spec = _load_inputs(args)
        training = _training_info(args, X, y, names, masks)
        grids = None
        if masks is not None:  # real partial scans: OOF classifier features from these grids
            grids = np.where(masks, X > 0.5, -1).astype(np.int8).reshape((-1,) + spec.shape)
        if args.calibrate_only:
            return _calibrate_only(args, X, y, names, spec, training.get('data_sha256'))
        if args.congeal:
            X, masks = _congeal(args, X, y, names, masks, spec, grids)
        t0 = time.time()
        bank = _fit(args, X, y, names, masks, spec, grids, training, class_prior)
        _save(bank, args.out, replace)
    except BrokenPipeError:   # stdout's reader is gone: see cli.interruptible
        raise
    except (ValueError, OSError) as e:
        print(f'beo-train: error: {e}', file=sys.stderr)
        return 2
    print(f'wrote {args.out}: {len(names)} classes {names}, {len(X)} objects, '
          f'{time.time() - t0:.1f} s')
    return 0


def _parser():
    """The beo-train argument parser."""
    ap = ArgumentParser(prog='beo-train', description=__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('inputs', nargs='+', help='voxel .npz files, mesh files, or PCD scans')
    ap.add_argument('-o', '--out', required=True,
                    help='model directory to write: new, empty, or holding a model, which is '
                         'replaced as a whole once the new one is complete')
    ap.add_argument('--k', type=count(1), default=20,
                    help='upper bound on components per class (default: %(default)s)')
    ap.add_argument('--grid', type=count(4, 256), default=None,
                    help='grid size N for meshes/scans: even, a multiple of 8 with the '
                         'orientation verifier (default 32; npz files carry their own, which '
                         'must then equal it)')
    ap.add_argument('--classes', nargs='+', help='train only these classes (npz and mesh input)')
    _add_scan_options(ap)
    ap.add_argument('--congeal', action='store_true',
                    help='align the yaw of unaligned training objects within each class')
    ap.add_argument('--views', type=int, default=1,
                    help='random partial views per object for the OOF classifier (0: none, '
                         'the maximum-likelihood rule; default: %(default)s)')
    ap.add_argument('--folds', type=int, default=5,
                    help='folds for out-of-fold features and the calibration views (>= 2; '
                    'not used with --views 0 unless --calibration-views is >= 1; default: '
                    '%(default)s)')
    ap.add_argument('--pose-components', type=int, default=8,
                    help='leading components per class used by the coarse pose search (>= 1; '
                         "at most the class model's components are used; --mirror banks always "
                         'use 8; default: %(default)s)')
    ap.add_argument('--seed', type=count(0), default=0, help='default: %(default)s')
    ap.add_argument('--oof-out', help='also save the out-of-fold features and records (npz)')
    _add_fit_options(ap)
    return ap


def _add_scan_options(ap):
    """The options of --scans input (and of --scans --mirror banks)."""
    ap.add_argument('--scans', action='store_true',
                    help='inputs are labelled tabletop PCD scans (see --scan-classes)')
    ap.add_argument('--scan-classes', default=None,
                    help='class:scene ranges for --scans, by the number in learnN.pcd '
                         f'(default: {SCAN_CLASSES})')
    ap.add_argument('--voxel-size', type=number(0, None, lo_open=True), default=None,
                    help=f'metres per voxel for --scans (metric grid; default {VOXEL_SIZE:g})')
    ap.add_argument('--mirror', action='store_true',
                    help='--scans: also train on the mirror image of every scan grid (needs '
                         '--views 0: out-of-fold folds over objects would split mirror pairs)')
    ap.add_argument('--max-iter', type=count(1), default=None,
                    help=f'VBPCA iterations per class (--scans --mirror only; default {MAX_ITER})')
    ap.add_argument('--point-classifier', metavar='OOF_NPZ', default=None,
                    help="--scans --mirror: also store a 'points' classifier (used by "
                         'estimate_points: per-class loglik + side-normal descriptors of the raw '
                         'points), fitted on every object with its out-of-fold features from '
                         'this oof_features.npz of a leave-one-scene-out beo-eval --scans run')


def _add_fit_options(ap):
    """The options of the classifier, orientation verifier and occupancy calibration fits."""
    ap.add_argument('--row-standardize', choices=tuple(AUTO_ON_OFF), default='auto',
                    help='standardise every feature across the classes of its row before the '
                         'classifier; auto: per mode, whichever cross-validates better (needs '
                         '3+ classes)')
    ap.add_argument('--descriptors', choices=tuple(AUTO_ON_OFF), default='auto',
                    help="also give the classifier the 43 yaw-invariant shape descriptors of the "
                         "grid's occupied voxels; auto: per mode, whichever cross-validates "
                         'better')
    ap.add_argument('--classifier', choices=('auto', 'logistic', 'mlp'), default='auto',
                    help='the classifier on the out-of-fold features: a logistic regression, a '
                         'one-layer ReLU network (128 units), or auto: per mode, whichever '
                         'cross-validates better with the inputs above')
    ap.add_argument('--verifier-views', type=int, default=None, metavar='N',
                    help='random views per object for the orientation verifier, which picks '
                         'among a yaw and its quarter turns (default 6; 0: none; not with '
                         '--scans, whose objects have no known yaw)')
    ap.add_argument('--calibration-views', type=int, default=None, metavar='N',
                    help="random views per object for the calibration of the completion's "
                         'occupancy probabilities, made under the out-of-fold folds (default 1 '
                         'with a classifier on whole objects; 0: none; not with --scans, whose '
                         'unknown voxels have no truth)')
    ap.add_argument('--calibrate-only', action='store_true',
                    help='refit only the occupancy calibration of the existing model directory '
                         '-o on the inputs it was trained on (its k, folds and seed; its class '
                         'models, classifier and verifier are kept) and rewrite it')
    ap.add_argument('--jobs', type=int, default=1,
                    help="processes that make the verifier's views (default: %(default)s)")
    ap.add_argument('--class-prior', default='train', metavar='PRIOR',
                    help="prior over the classes the model assumes (recorded in its manifest; "
                         "the node's class_prior parameter overrides it): train (the training "
                         "set's class frequencies), uniform, or name=weight,... with every "
                         'class; the classifier input is chosen by the accuracy expected under '
                         'it (default: %(default)s)')


def _check_args(ap, args):
    """Refuse (ap.error) option values out of range or that do not apply, fill in the defaults
    that depend on the mode; the class prior ('train', 'uniform' or {name: weight})."""
    try:
        class_prior = parse_class_prior(args.class_prior) or 'train'
    except ValueError as e:
        ap.error(str(e))
    verifier_given = args.verifier_views is not None
    if args.verifier_views is None:
        args.verifier_views = 0 if args.scans else 6
    _check_counts(ap, args)
    if args.calibrate_only:
        _check_calibrate_only(ap, args, verifier_given)
    _check_mode_options(ap, args)
    _check_repeated_inputs(ap, args.inputs)
    args.scan_classes = args.scan_classes or SCAN_CLASSES
    args.voxel_size = args.voxel_size or VOXEL_SIZE
    args.max_iter = args.max_iter or MAX_ITER
    if args.grid is not None:
        try:
            check_grid_size(args.grid, verifier=args.verifier_views > 0)
        except ValueError as e:
            ap.error(f'--grid: {e}')
    return class_prior


# options --calibrate-only does not use (nor --verifier-views, whose default depends on the
# mode): the calibration is refitted with the model's own k, folds, seed, classifier, class
# prior and pose components, and nothing else is fitted
NOT_CALIBRATE_ONLY = ('k', 'views', 'folds', 'seed', 'pose_components', 'oof_out', 'congeal',
                      'row_standardize', 'descriptors', 'classifier', 'jobs', 'class_prior')


def _check_calibrate_only(ap, args, verifier_given):
    """Refuse (ap.error) the options --calibrate-only would silently ignore
    (``verifier_given``: whether --verifier-views was given, its default being filled in)."""
    unused = [f"--{n.replace('_', '-')}" for n in NOT_CALIBRATE_ONLY
              if getattr(args, n) != ap.get_default(n)]
    unused += ['--verifier-views'] if verifier_given else []
    if unused:
        ap.error("not used with --calibrate-only (the model's own settings are kept): "
                 + ', '.join(unused))


def _check_repeated_inputs(ap, inputs):
    """Refuse (ap.error) an input given twice (as written or through another path to the same
    file): its objects would be trained on twice, and weigh twice in the class model."""
    seen = {}
    for p in inputs:
        key = os.path.realpath(p)
        if key in seen:
            ap.error(f'input {p} given twice' + ('' if seen[key] == p else f' (as {seen[key]})'))
        seen[key] = p


def _check_counts(ap, args):
    """Refuse (ap.error) counts of views, folds, jobs and components out of range."""
    if args.verifier_views < 0 or args.jobs < 1:
        ap.error('--verifier-views must be >= 0 and --jobs >= 1')
    if args.pose_components < 1:
        ap.error(f'--pose-components must be >= 1, got {args.pose_components}')
    if args.views < 0:
        ap.error(f'--views must be >= 0 (0: no classifier), got {args.views}')
    if args.views > 0 and args.folds < 2:
        ap.error(f'--folds must be >= 2 for the out-of-fold classifier features, got '
                 f'{args.folds} (--views 0 trains no classifier)')
    if args.calibration_views is not None and args.calibration_views < 0:
        ap.error(f'--calibration-views must be >= 0, got {args.calibration_views}')
    if args.calibrate_only and args.calibration_views == 0:
        ap.error('--calibrate-only fits a calibration: --calibration-views must be >= 1')


def _check_mode_options(ap, args):
    """Refuse (ap.error) options that the mode (--scans, --mirror, --views 0) does not use."""
    if args.scans and (args.calibration_views or args.calibrate_only):
        ap.error('--calibration-views and --calibrate-only need whole objects, not --scans')
    if args.scans and args.verifier_views:
        ap.error('--verifier-views needs objects in their canonical pose, not --scans')
    if args.mirror and not (args.scans and args.views == 0):
        ap.error('--mirror is for --scans with --views 0 (maximum-likelihood rule)')
    if args.point_classifier and not args.mirror:
        ap.error('--point-classifier is for --scans --mirror --views 0')
    if args.oof_out and args.views == 0:
        ap.error('--oof-out needs --views >= 1 (--views 0 makes no out-of-fold features)')
    if args.mirror:   # train_scan_bank: maximum-likelihood rule, no out-of-fold classifier
        unused = [name for name in ('seed', 'folds', 'row_standardize', 'descriptors',
                                    'classifier', 'calibration_views', 'calibrate_only')
                  if getattr(args, name) != ap.get_default(name)]
        if unused:
            ap.error('not used with --mirror: ' + ', '.join(f"--{n.replace('_', '-')}"
                                                         for n in unused))
    if not args.scans:
        given = [f"--{n.replace('_', '-')}" for n in ('scan_classes', 'voxel_size')
                 if getattr(args, n) is not None]
        if given:
            ap.error(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for --scans only")
    elif args.classes:
        ap.error('--classes is for npz and mesh input; with --scans use --scan-classes')
    if args.max_iter is not None and not args.mirror:
        ap.error('--max-iter is for --scans --mirror only (the other fits use their own)')
    if args.verifier_views == 0 and args.jobs != ap.get_default('jobs'):
        ap.error("--jobs makes the orientation verifier's views: not used with "
                 + ('--scans (no verifier)' if args.scans else '--verifier-views 0'))


def _train_mirror(args, class_prior, replace):
    """--scans --mirror: fit and save a maximum-likelihood bank on the scans and their mirror
    images (train_scan_bank); 0."""
    from .core.classifier import resolve_class_prior
    from .core.scan_training import parse_scan_classes, train_scan_bank
    # a prior naming a class the scans lack fails before the fit, not after it
    scan_names = parse_scan_classes(args.scan_classes)[0]
    check_class_names(scan_names, '--scan-classes')
    resolve_class_prior(class_prior, scan_names)
    if args.point_classifier:
        _check_oof_npz(args.point_classifier, scan_names)
    t0 = time.time()
    bank = train_scan_bank(args.inputs, args.scan_classes, args.grid or 32,
                           args.voxel_size, args.k, args.max_iter, mirror=True,
                           congeal=args.congeal, verbose=True,
                           point_classifier=args.point_classifier)
    bank.class_prior = class_prior
    _save(bank, args.out, replace)
    print(f'wrote {args.out}: {len(bank.classes)} classes {bank.classes}, '
          f'{bank.training["n_training_grids"]} training grids, '
          f'{time.time() - t0:.1f} s')
    return 0


def _load_inputs(args):
    """(X, y, names, masks, spec) of the inputs: labelled scans (masks (n, N^3) bool: the
    observed voxels) or npz and mesh objects (masks None). ValueError when a classifier is to
    be trained on fewer than 2 classes."""
    if args.scans:
        from .core.scan_training import load_scan_training_set, parse_scan_classes
        check_class_names(parse_scan_classes(args.scan_classes)[0], '--scan-classes')
        X, y, names, masks, spec = load_scan_training_set(
            args.inputs, args.scan_classes, args.grid or 32, args.voxel_size,
            verbose=True)
    else:
        masks = None
        X, y, names, spec = _load_objects(args)
    if args.views > 0 and len(names) < 2 and not args.calibrate_only:
        raise ValueError(f'the classifier needs 2 or more classes, the inputs have '
                         f'{len(names)} ({names}): add a class, or train no classifier '
                         'with --views 0 (the maximum-likelihood rule)')
    return X, y, names, masks, spec


def _training_info(args, X, y, names, masks):
    """The manifest's record of the training inputs (before any congealing)."""
    training = dict(inputs=[str(p) for p in args.inputs], congeal=args.congeal)
    if args.scans:   # which scenes made which class, as the --mirror manifest says
        training.update(scan_classes=str(args.scan_classes),
                        voxel_size=float(args.voxel_size))
    if masks is None:   # whole objects: --calibrate-only can tell other data apart
        training['data_sha256'] = training_data_hash(X, y, names)
    return training


def _congeal(args, X, y, names, masks, spec, grids=None):
    """(X, masks) with the yaw of the objects aligned within each class (--congeal)."""
    from .core.congeal import congeal_classes
    from .core.training import _check_fit_options
    # fit_bank's checks, before minutes of congealing (a verifier on a grid not a multiple
    # of 8, --row-standardize on with 2 classes, ... were refused after it); the folds count
    # when a classifier or a calibration is fitted
    _, calibration_views = _check_fit_options(
        names, spec, args.k, masks, args.views, args.folds, None,
        AUTO_ON_OFF[args.row_standardize], AUTO_ON_OFF[args.descriptors], args.verifier_views,
        args.classifier, 'auto' if args.calibration_views is None else args.calibration_views,
        grids, args.oof_out)
    check_class_counts(y, names, args.folds if args.views > 0 or calibration_views else 0)
    if masks is not None:
        X, masks = congeal_classes(X, y, spec.size, masks=masks, verbose=True)
    else:
        X = congeal_classes(X, y, spec.size, verbose=True)
    return X, masks


def _fit(args, X, y, names, masks, spec, grids, training, class_prior):
    """The ModelBank fitted on the objects with the options of args (fit_bank)."""
    bank = fit_bank(X, y, names, spec, k=args.k, masks=masks,
                    pose_components=args.pose_components, classifier_views=args.views,
                    folds=args.folds, seed=args.seed, verbose=True, training=training,
                    grids=grids, oof_path=args.oof_out,
                    row_standardize=AUTO_ON_OFF[args.row_standardize],
                    descriptors=AUTO_ON_OFF[args.descriptors], class_prior=class_prior,
                    verifier_views=args.verifier_views, processes=args.jobs,
                    classifier_kind=args.classifier,
                    calibration_views=('auto' if args.calibration_views is None
                                       else args.calibration_views))
    if args.scans and args.views == 0:
        # no out-of-fold classifier, calibration or verifier (none with --scans): the
        # folds and the seed drew nothing, so the manifest does not claim them
        for unused in ('folds', 'seed'):
            bank.training.pop(unused, None)
    return bank


def _check_out(args):
    """Refuse an output directory that cannot be written before any training: -o may be new,
    empty or hold a model (replaced as a whole). ValueError otherwise; True when it holds a
    model."""
    if args.oof_out:   # written after all the training: checked first
        oof = Path(args.oof_out)
        if oof.is_dir():
            raise ValueError(f'--oof-out {oof} is a directory (give a file name)')
        if Path(args.out).resolve() in oof.resolve().parents:
            # written before the model: it would make a new -o a directory that is not a
            # model (refused by the save) or be deleted with the model it replaces
            raise ValueError(f'--oof-out {oof} lies in the model directory {args.out}, which '
                             'is written as a whole: give a file outside it')
        parent = existing_parent(oof)
        if not writable_dir(parent):
            raise ValueError(f'cannot write --oof-out {oof}: {parent} is not a writable '
                             'directory')
    if args.calibrate_only:   # rewrites the model it loads (ModelBank.load checks it)
        return False
    check_save_target(args.out)
    parent = existing_parent(args.out)
    if not writable_dir(parent):
        raise ValueError(f'cannot write {args.out}: {parent} is not a writable directory')
    return is_model_dir(args.out)


def _save(bank, out, replace):
    """bank.save(out), saying so when it replaces the model there."""
    if replace:
        print(f'beo-train: replacing the model in {out} as a whole', file=sys.stderr)
    bank.save(out)


def _load_objects(args):
    """(X, y, names, spec) of the npz and mesh inputs: one class list in the order the classes
    first appear, the npz files (in their order) before the meshes (or the --classes order),
    without objects that have no occupied voxel."""
    # the extension in any case, as the meshes' ('.OFF' is a mesh, '.NPZ' an npz)
    is_npz = [p.lower().endswith('.npz') for p in args.inputs]
    parts = [(p, *load_voxel_npz(p)) for p, z in zip(args.inputs, is_npz) if z]
    mesh_paths = [p for p, z in zip(args.inputs, is_npz) if not z]
    n = args.grid or (parts[0][4] if parts else 32)
    if not args.grid and parts:   # else "GridSpec.size must be ...", naming no file
        try:
            check_grid_size(n)
        except ValueError as e:
            raise ValueError(f'{parts[0][0]}: grids of {n}^3: {e}') from None
    if mesh_paths:   # all at once: one class list for every mesh; --classes: only theirs read
        parts.append(('the meshes', *load_meshes(mesh_paths, n, args.classes), n))
    Xs, ys, names = [], [], []
    for src, X1, y1, names1, n1 in parts:
        if n1 != n:
            why = '--grid' if args.grid else 'the first input'
            raise ValueError(f'{src}: grid {n1} differs from {n} ({why})')
        names += [c for c in names1 if c not in names]
        Xs.append(X1)
        ys.append(np.array([names.index(names1[v]) for v in y1], dtype=int))
    X, y = np.vstack(Xs), np.concatenate(ys)
    where = args.inputs[0] if len(args.inputs) == 1 else 'the inputs'
    if args.classes:
        X, y, names = select_classes(X, y, names, args.classes, where)
    check_class_names(names, where)
    X, y, dropped = drop_empty_objects(X, y, names)
    if dropped:
        print(f'beo-train: warning: dropped {sum(dropped.values())} objects with no occupied '
              'voxel (' + ', '.join(f'{c}: {m}' for c, m in dropped.items()) + ')',
              file=sys.stderr)
    # fit_bank checks this too, but cannot name the option that leaves a class out
    check_class_counts(y, names, leave_out='--classes with the others')
    return X, y, names, GridSpec(size=n)


def _check_oof_npz(path, names):
    """ValueError unless ``path`` is an oof_features.npz of ``beo-eval --scans`` over the
    classes ``names`` (what --point-classifier reads), before the scans are loaded."""
    keys = ('features', 'scenes', 'object_ids', 'classes')
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(f'{path}: a single array, not an oof_features.npz')
        with z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise ValueError(f'{path}: not an oof_features.npz of beo-eval --scans '
                                 f'(missing {missing}; has {z.files})')
            shape = z['features'].shape
            classes = [str(c) for c in np.atleast_1d(z['classes'])]
    except UNREADABLE as e:
        if str(path) in str(e):
            raise
        raise ValueError(f'{path}: not a readable npz ({type(e).__name__}: {e})') from None
    if len(shape) != 3 or shape[1] != len(classes):
        raise ValueError(f'{path}: features must be (objects, classes, features), got {shape}')
    if classes != list(names):
        raise ValueError(f'{path}: classes {classes} differ from the scan classes {names}')


def _calibrate_only(args, X, y, names, spec, data_sha256=None):
    """``--calibrate-only``: refit the occupancy calibration of the model directory args.out
    on X, y (its training objects) with its own k, folds and seed, and rewrite it (atomically:
    on failure the model stays as it was)."""
    from .core.bank import ModelBank
    from .core.training import fit_occupancy_calibration
    bank = ModelBank.load(args.out)
    if list(bank.classes) != list(names) or bank.spec.size != spec.size:
        raise ValueError(f'{args.out}: classes {bank.classes} on a {bank.spec.size}^3 grid, but '
                         f'the inputs have {names} on {spec.size}^3: not its training set')
    info = bank.training
    if info.get('n_objects') not in (None, len(X)):
        raise ValueError(f"{args.out} was trained on {info['n_objects']} objects, the inputs "
                         f'have {len(X)}')
    if info.get('data_sha256') not in (None, data_sha256):   # recorded since 2026-11-23
        raise ValueError(f'{args.out} was trained on other data: the inputs have the same '
                         'classes and object count but not the same objects')
    if info.get('congeal'):
        raise ValueError(f'{args.out} was trained on congealed objects: retrain it with '
                         '--calibration-views instead')
    t0 = time.time()
    cal, report = fit_occupancy_calibration(
        X, y, names, spec, int(info.get('k', args.k)), int(info.get('folds', args.folds)),
        int(info.get('seed', args.seed)), args.calibration_views or 1, bank.classifier,
        bank.class_prior, bank.pose_components, verbose=True,
        # manifests before the floor (2026-11) have none: their models were fitted without it
        min_noise_variance=info.get('min_noise_variance', 0.0))
    report.update(seconds=round(time.time() - t0, 1))
    print(f'occupancy calibration: {report}', file=sys.stderr)
    ModelBank(bank.models, bank.spec, bank.classifier, dict(info, occupancy_calibration=report),
              bank.pose_components, stage2_noise_map=bank.stage2_noise_map,
              class_prior=bank.class_prior, verifier=bank.verifier,
              occupancy_calibration=cal).save(args.out)
    print(f'wrote {args.out}: occupancy calibration from {report["views"]} views, '
          f'{time.time() - t0:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
