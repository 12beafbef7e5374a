"""Class model bank: per-class VBPCA models plus the classifier, saved as a checked directory.

The model directory's layout, its checks and readers are in :mod:`beo_ros.core.model_files`, the
classifier plumbing (inputs, probabilities, class priors) in :mod:`beo_ros.core.classifier`,
``ClassModel`` and ``ModelError`` in :mod:`beo_ros.core.class_model`; their public names are
importable from here too.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from .calibration import OccupancyCalibration, check_arrays as check_calibration_arrays
from .class_model import ClassModel, ModelError, coarse_noise
from .classifier import (CLASS_PRIORS, HIDDEN_CLASSIFIER_KEYS, MODES, OPTIONAL_CLASSIFIER_KEYS,
                         POINT_CLASSIFIER_KEYS, POINTS_MODE, _softmax, apply_point_classifier,
                         check_classifier_arrays, check_grid_classifier, check_point_classifier,
                         classifier_input, classifier_probabilities, descriptor_count,
                         format_class_prior, parse_class_prior, prior_offset,
                         resolve_class_prior, uses_descriptors)
from .estimate import UNKNOWN_LABEL, Estimate, Hypothesis
from .grid import (GridSpec, check_count, real_number, symmetric_turns, unit_vector,
                   wrap_yaw as _wrap, yaw_error, yaw_grid, yaw_matrix)
from .inference import (FEATURE_NAMES, InferenceEngine, observed_edt, top_modes, top_yaw_modes,
                        yaw_key)
from .model_files import (CLASS_KEYS, FORMAT, OPTIONAL_CLASS_KEYS, OPTIONAL_FILES, UNREADABLE,
                          VERSION, _check_manifest_settings, _load_class_models,
                          _load_classifier, _manifest_layout, _optional_arrays, _read_checked,
                          _read_manifest, _settings_reason, _sha256, check_class_arrays,
                          check_class_names, check_noise_map, check_save_target,
                          class_name_problem, is_model_dir)
from .outliers import OUTLIER_MADS, OUTLIER_NEIGHBORS, clean_points
from .shape import shape_descriptors
from .verifier import TURNS, OrientationVerifier, check_arrays, quarter_turned_features

# the bank's names, and those of the modules split from it (importable from here as before)
__all__ = [
    'ModelBank', 'TooFewPoints', 'load_models', 'default_model_dir', 'resolve_model_dir', 'shipped_models',
    'object_centre', 'object_extent', 'heading_offset', 'check_yaw', 'check_step', 'check_count',
    'SEARCH_STEP_DEG', 'PROBE_DEG', 'STAGE2_MIN_STEP_DEG', 'YAW_STEP_RANGE_DEG',
    # class_model
    'ClassModel', 'ModelError', 'coarse_noise',
    # classifier
    'CLASS_PRIORS', 'HIDDEN_CLASSIFIER_KEYS', 'MODES', 'OPTIONAL_CLASSIFIER_KEYS',
    'POINT_CLASSIFIER_KEYS', 'POINTS_MODE', 'apply_point_classifier', 'check_classifier_arrays',
    'check_grid_classifier', 'check_point_classifier', 'classifier_input',
    'classifier_probabilities', 'descriptor_count', 'format_class_prior',
    'parse_class_prior', 'prior_offset', 'resolve_class_prior', 'uses_descriptors',
    # model_files
    'CLASS_KEYS', 'FORMAT', 'OPTIONAL_CLASS_KEYS', 'OPTIONAL_FILES', 'UNREADABLE', 'VERSION',
    'check_class_arrays', 'check_class_names', 'check_save_target', 'class_name_problem',
    'is_model_dir',
]

# stage 1 (all classes, leading components) searches at this step; the chosen class is then
# refined at the requested resolution, so a finer stage 1 costs time and gains nothing (measured)
SEARCH_STEP_DEG = 2.0
# the refinement's exact probes either side of the pooled optimum (see ModelBank._refine)
PROBE_DEG = (10.0, 20.0)
# the finest step of the pooled re-scoring and of the first climb: the pooled grid does not
# resolve finer yaws, and its rotation maps of every multiple of a finer step cost seconds and
# gigabytes (0.1 deg: 5 s, 1.4 GB); finer returned yaws come from a second, exact climb
STAGE2_MIN_STEP_DEG = 1.0
# ModelBank.load reads a directory that a save replaced meanwhile again, at most this often
LOAD_ATTEMPTS = 3
# ModelBank.load waits for a save into the directory in progress (which leaves none between
# its two renames) in steps of this many seconds, at most this many steps
SAVE_WAIT_STEP_S = 0.01
SAVE_WAIT_STEPS = 100
# the yaw steps (degrees) that estimate takes (check_step); commands check theirs against it
YAW_STEP_RANGE_DEG = (0.05, 90.0)


class TooFewPoints(ValueError):
    """``estimate_points``: fewer points than an estimate needs are left after the outlier
    and cluster removal (a ValueError, so callers that catch those see no change)."""


class ModelBank:
    """A set of class models over one grid, with pose search, completion and classification.

    Args:
        models: list of ClassModel (same d = spec.size ** 3).
        spec: GridSpec of the training grids.
        classifier: dict mode -> dict(mean, scale, coef, intercept, unknown_threshold), or None
            (then the class with the largest likelihood wins, as in the paper). Mode 'points'
            (optional, see :func:`check_point_classifier`) is used by ``estimate_points``: on
            the per-class log-likelihoods + the raw points' side-normal descriptors.
        training: free-form dict recorded in the manifest.
        pose_components: leading components used by the coarse pose search.
        class_prior: the prior over classes the probabilities assume (see
            :func:`resolve_class_prior`): 'train' (default: the classifier as trained, its
            training rows' class frequencies), 'uniform', or weights per class. Settable; the
            manifest records the one a model directory was built for.
        verifier: optional fitted ``OrientationVerifier``: picks among the refined yaw and its
            90, 180 and 270° turns (``estimate(..., verify=True)``).
        occupancy_calibration: optional fitted ``OccupancyCalibration``: maps the completion's
            model probabilities of the unknown voxels to calibrated ones.
        stage2_noise_map: score the stage-2 refinement with the per-voxel noise variance of
            the pooled model (``coarse_noise_map``) instead of the class scalar. Off: since
            the observed-frame scoring it lowers the yaw accuracy (397 views of fold 0, yaw of
            the true class within 10 deg: 0.728 with the map, 0.768 with the scalar), because
            the log-determinant of a nearest-neighbour-rotated noise map changes with the yaw.
    """

    def __init__(self, models, spec: GridSpec, classifier=None, training=None,
                 pose_components=8, stage2_noise_map=False, class_prior='train',
                 verifier=None, occupancy_calibration=None):
        if not models:
            raise ModelError('a model bank needs at least one class')
        names = [m.name for m in models]
        if len(set(names)) != len(names):
            raise ModelError(f'class names must be unique, got {names}')
        d = spec.size ** 3
        for m in models:
            if m.W.ndim != 2 or m.W.shape[0] != d or m.mean.shape != (d,):
                raise ModelError(f'class {m.name!r}: W {m.W.shape} / mean {m.mean.shape} do not '
                                 f'match the {spec.size}^3 grid')
            # as load checks them: a zero or NaN noise variance gave NaN class probabilities
            # (and a label) without a word, a NaN mean an IndexError, a loading covariance of
            # another k numpy's shape error in the completion
            check_class_arrays({k: np.asarray(getattr(m, k)) for k in CLASS_KEYS}, d,
                               f'class {m.name!r}', spec.size)
            check_noise_map(m.coarse_noise_map, m.W, m.mean, d, f'class {m.name!r}')
        # a mode of another name was never used (the max-likelihood rule decided) and save
        # wrote a classifier.npz that load refuses
        unknown = sorted(set(classifier or {}) - set(MODES) - {POINTS_MODE})
        if unknown:
            raise ModelError(f'unknown classifier mode(s) {unknown} (known: '
                             f'{", ".join(MODES + (POINTS_MODE,))})')
        for mode, clf in (classifier or {}).items():
            # as load checks them: save wrote what load refused, estimate raised numpy's
            # errors or used a row standardisation of two classes
            if mode == POINTS_MODE:
                check_point_classifier(clf, len(models))
            else:
                check_grid_classifier(clf, mode, len(models), 'model bank')
        self.models = list(models)
        self.spec = spec
        self.classifier = classifier
        self.class_prior = class_prior
        if verifier is not None:
            if not hasattr(verifier, 'arrays_'):
                raise ModelError('the orientation verifier is not fitted')
            reason = check_arrays(verifier.arrays_, len(models), spec.size)
            if reason:
                raise ModelError(reason)
        self.verifier = verifier
        if occupancy_calibration is not None:
            if not hasattr(occupancy_calibration, 'probability_'):
                raise ModelError('the occupancy calibration is not fitted')
            reason = check_calibration_arrays(occupancy_calibration.arrays_)
            if reason:
                raise ModelError(reason)
        self.occupancy_calibration = occupancy_calibration
        reason = _settings_reason(pose_components, training)
        if reason:
            raise ModelError(reason)
        self.training = dict(training or {})
        self.pose_components = int(pose_components)
        self.stage2_noise_map = bool(stage2_noise_map)
        k = max(m.W.shape[1] for m in models)
        W = np.zeros((len(models), d, k), dtype=np.float32)
        for i, m in enumerate(models):
            W[i, :, :m.W.shape[1]] = m.W
        self.engine = InferenceEngine(
            W, np.stack([m.mean for m in models]), [m.noise_variance for m in models],
            [m.coarse_noise_variance for m in models], spec.size, pose_components,
            coarse_noise_maps=[m.coarse_noise_map for m in models] if stage2_noise_map else None)

    def __reduce__(self):
        # pickled as its constructor arguments: the inference engine (thread-local scratch,
        # caches) is rebuilt on the other side, e.g. in a worker process
        return (type(self), (self.models, self.spec, self.classifier, self.training,
                             self.pose_components, self.stage2_noise_map, self.class_prior,
                             self.verifier, self.occupancy_calibration))

    def __repr__(self):
        lo, hi = min(m.W.shape[1] for m in self.models), max(m.W.shape[1] for m in self.models)
        modes = [f"{m}: {'mlp' if 'hidden_coef' in self.classifier[m] else 'logistic'}"
                 for m in sorted(self.classifier)] if self.classifier else ['max-likelihood']
        return (f'ModelBank({len(self.models)} classes {self.classes}, grid {self.spec.size}^3 '
                f'{self.spec.units}, k {lo if lo == hi else f"{lo}-{hi}"}, classifier {modes}, '
                f'verifier {"yes" if self.verifier is not None else "no"}, '
                f'calibrated {"yes" if self.occupancy_calibration is not None else "no"}, '
                f'prior {self.class_prior!r})')

    @property
    def classes(self):
        return [m.name for m in self.models]

    @property
    def class_prior(self):
        """'train', 'uniform' or the (C,) normalised weights set (see the class docstring)."""
        return self._class_prior

    @class_prior.setter
    def class_prior(self, prior):
        weights = resolve_class_prior(prior, self.classes)
        self._prior_weights = weights
        self._class_prior = prior if isinstance(prior, str) else weights

    def with_class_prior(self, prior):
        """A copy of the bank with another class prior, sharing models, classifier and inference
        engine (no rebuild); raises ValueError for a bad prior."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.class_prior = prior
        return new

    def _prior_offset(self, clf):
        """Logit offsets (C,) of ``clf`` for the bank's class prior, or None (see
        :func:`prior_offset`)."""
        return prior_offset(clf.get('class_counts'), self._prior_weights)

    def prior_note(self, mode):
        """Why the class prior is not applied to classifier ``mode`` ('' when it is, or when
        the prior is 'train')."""
        clf = (self.classifier or {}).get(mode)
        if self._prior_weights is None or clf is None or 'class_counts' in clf:
            return ''
        return (f'class_prior not applied: the {mode!r} classifier has no class_counts '
                '(trained before they were recorded); its training prior is used')

    @property
    def has_point_classifier(self) -> bool:
        """True when ``estimate_points`` classifies with the raw points' normal descriptors."""
        return bool(self.classifier) and POINTS_MODE in self.classifier

    # ------------------------------------------------------------------ persistence
    def save(self, path):
        """Write the bank to directory ``path`` and return it. ``path`` may be new, empty, or
        hold a model, which is replaced as a whole (see :func:`check_save_target`). The files
        go to a temporary directory beside ``path`` that is renamed into place when complete:
        on any failure (or Ctrl-C) it is removed and a model already at ``path`` is kept."""
        check_class_names(self.classes, 'cannot save the model')
        path = Path(path)
        # replace the directory, keep the link; '.' and '..' cannot be renamed (an OSError
        # 'Device or resource busy' after training): the directory they name is
        if path.is_symlink() and path.is_dir() or path.name in ('', '..'):
            path = path.resolve()
        check_save_target(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = _new_directory(path.parent, _sibling_prefix(path, 'tmp'))
        try:
            self._write(tmp)
            if path.is_dir():
                # two renames: a reader sees the old model or the new one, never a mix (for
                # the instant between them, no directory)
                old = Path(tempfile.mkdtemp(prefix=_sibling_prefix(path, 'old'),
                                            dir=path.parent))
                try:
                    os.replace(path, old)   # onto the empty directory mkdtemp made
                    try:
                        os.replace(tmp, path)
                    except BaseException:
                        os.replace(old, path)
                        raise
                finally:
                    shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    def _write(self, path):
        """Write the model files and the manifest (last) into the existing directory ``path``."""
        files = {}
        for i, m in enumerate(self.models):
            fn = f'class_{i:02d}_{m.name}.npz'
            np.savez_compressed(path / fn, **{k: np.asarray(getattr(m, k)) for k in
                                              CLASS_KEYS + OPTIONAL_CLASS_KEYS
                                              if getattr(m, k) is not None})
            files[fn] = _sha256(path / fn)
        if self.verifier is not None:
            np.savez_compressed(path / 'verifier.npz', **self.verifier.arrays_)
            files['verifier.npz'] = _sha256(path / 'verifier.npz')
        if self.occupancy_calibration is not None:
            np.savez_compressed(path / 'calibration.npz', **self.occupancy_calibration.arrays_)
            files['calibration.npz'] = _sha256(path / 'calibration.npz')
        if self.classifier:
            arrays = {f'{mode}__{k}': np.asarray(v) for mode, clf in self.classifier.items()
                      for k, v in clf.items()}
            np.savez_compressed(path / 'classifier.npz', **arrays)
            files['classifier.npz'] = _sha256(path / 'classifier.npz')
        manifest = {
            'format': FORMAT, 'version': VERSION, 'classes': self.classes,
            'grid': dict(self.spec.to_dict(), axes='xyz', up='+z'),
            'pose_components': self.pose_components,
            'stage2_noise_map': self.stage2_noise_map,
            'class_prior': (self.class_prior if isinstance(self.class_prior, str)
                            else [float(w) for w in self.class_prior]),  # in class order
            'features': list(FEATURE_NAMES),
            'training': self.training, 'files': files,
        }
        (path / 'manifest.json').write_text(json.dumps(manifest, indent=2, default=_json_value)
                                            + '\n')

    @classmethod
    def load(cls, path, class_prior=None):
        """Load and check a model directory; raises ModelError naming the bad file.

        ``class_prior``: overrides the manifest's (None: the manifest's; 'train' when it has
        none); a bad value raises ValueError (a bad one in the manifest: ModelError).

        A save of the same directory (see :meth:`save`) while it is read is not a mix: every
        file is parsed from the bytes checked against the manifest read; when the check
        fails and the directory (or its manifest) has changed since, it is read again (up to
        ``LOAD_ATTEMPTS`` times). When it fails while a save into the directory is in
        progress (its temporary directories are there: e.g. none between its two renames), it
        is read again every ``SAVE_WAIT_STEP_S`` seconds, at most ``SAVE_WAIT_STEPS`` times."""
        path = Path(path)
        attempt, waits = 1, 0
        while True:
            before, text = _dir_identity(path), None
            try:
                mf, manifest, text = _read_manifest(path)
                return cls._load(path, mf, manifest, class_prior)
            except ModelError as e:
                # another directory now (a save renamed its own into place; the same
                # manifest text does not tell: a model saved again writes the same one), or
                # none (between the two renames of a save), or another manifest
                replaced = _dir_identity(path) != before
                if not replaced and text is not None:
                    try:
                        replaced = _read_manifest(path)[2] != text
                    except ModelError:
                        replaced = True
                if not replaced:
                    # unchanged meanwhile, but a save may be about to change it: a load that
                    # began between its two renames failed with 'does not exist'
                    if waits < SAVE_WAIT_STEPS and _save_in_progress(path):
                        waits += 1
                        time.sleep(SAVE_WAIT_STEP_S)
                        continue
                    if waits:
                        raise ModelError(f'{e} (a save into {path} was in progress for '
                                         f'{waits * SAVE_WAIT_STEP_S:g} s)') from None
                    raise
                if attempt == LOAD_ATTEMPTS:
                    raise ModelError(f'{e} ({path} was replaced while it was read, '
                                     f'{attempt} times: is it being saved over and over?)') \
                        from None
                attempt += 1

    @classmethod
    def _load(cls, path, mf, manifest, class_prior):
        """:meth:`load` of the directory ``path`` whose manifest ``mf`` holds ``manifest``."""
        spec, classes, files = _manifest_layout(path, mf, manifest)
        data = _read_checked(path, files)
        models = _load_class_models(path, data, classes, spec)
        classifier = _load_classifier(path, data, len(classes))
        arrays = _optional_arrays(path, data, 'verifier.npz',
                                  lambda a, where: check_arrays(a, len(classes), spec.size, where))
        verifier = None if arrays is None else OrientationVerifier.from_arrays(arrays)
        arrays = _optional_arrays(path, data, 'calibration.npz', check_calibration_arrays)
        calibration = None if arrays is None else OccupancyCalibration.from_arrays(arrays)
        if class_prior is None:
            class_prior = manifest.get('class_prior', 'train')
            try:
                resolve_class_prior(class_prior, classes)
            except ValueError as e:
                raise ModelError(f'{mf}: {e}') from None
        _check_manifest_settings(mf, manifest)
        return cls(models, spec, classifier, manifest.get('training'),
                   manifest.get('pose_components', 8),
                   stage2_noise_map=manifest.get('stage2_noise_map', False),
                   class_prior=class_prior,
                   verifier=verifier, occupancy_calibration=calibration)

    # ------------------------------------------------------------------ queries
    def check_grid(self, grid):
        grid = np.asarray(grid)
        if grid.shape != self.spec.shape:
            raise ValueError(f'grid must have shape {self.spec.shape}, got {grid.shape}')
        if np.issubdtype(grid.dtype, np.floating):
            # whole values only: a cast would truncate 0.7 to free and NaN to anything
            if not np.isfinite(grid).all() or (grid != np.round(grid)).any():
                raise ValueError('a float grid must hold the whole values 1 (occupied), 0 (free) '
                                 'or -1 (unknown)')
        elif grid.dtype.kind not in 'iub':   # not timedelta64, which numpy counts as integer
            raise ValueError(f'grid must be an integer array (1 occupied, 0 free, -1 unknown), '
                             f'got dtype {grid.dtype}')
        # checked before the cast to int8, which would wrap 255 to -1 and 257 to 1
        if grid.min() < -1 or grid.max() > 1:
            raise ValueError('grid values must be 1 (occupied), 0 (free) or -1 (unknown)')
        return grid.astype(np.int8)

    def features(self, grid, yaw=None, yaw_step_deg=SEARCH_STEP_DEG, exhaustive=True):
        """Per-class best yaw (stage-1 search every ``yaw_step_deg``), exact posterior and
        features for a labelled grid.

        Returns (features (C, F), list of per-class dicts: yaw, exact, hypotheses, searched,
        search_step_deg, pooled and observed (the grid's pooled weights and its
        ``InferenceEngine.observe`` arrays, shared), solved (the class's exact posteriors
        solved so far, see :meth:`_exact`)).
        """
        grid = self.check_grid(grid)
        yaw_step_deg = check_step('yaw_step_deg', yaw_step_deg)
        yaw = check_yaw(yaw)
        if not (grid == 1).any():   # all free or all unknown: every class would "fit"
            raise ValueError('grid has no occupied voxel: there is no object to estimate')
        eng = self.engine
        pooled = eng.pooled(grid)
        obs = eng.observe(grid)
        if yaw is None:
            best_yaw, best_ll, searched = eng.search(grid, yaw_step_deg, exhaustive=exhaustive,
                                                     pooled=pooled)
        else:
            best_ll = eng.scores(pooled, [float(yaw)])[0]
            best_yaw = np.full(eng.C, float(yaw))
            searched = [(np.array([float(yaw)]), best_ll[c:c + 1]) for c in range(eng.C)]
        edt_pad = np.append(observed_edt(grid).ravel(), 0.0)
        n_pooled = grid.size / 8.0
        feats, per = [], []
        for c in range(eng.C):
            ex = eng.exact(obs, c, float(best_yaw[c]))
            feats.append(eng.features(ex, c, best_ll[c] / n_pooled, edt_pad[ex['idx']]))
            yaws_c, ll_c = searched[c]
            modes = top_yaw_modes(yaws_c, ll_c, 3)   # exhaustive or coarse-to-fine yaws
            per.append(dict(yaw=float(best_yaw[c]), exact=ex, searched=searched[c],
                            search_step_deg=float(yaw_step_deg), pooled=pooled, observed=obs,
                            solved={_solved_key(float(best_yaw[c])): ex},
                            hypotheses=[(float(yaws_c[i]), float(ll_c[i])) for i in modes]))
        return np.array(feats), per

    def classify_features(self, feats, mode, grid=None):
        """Class probabilities (C,) and the unknown flag from a (C, F) feature array (and the
        labelled grid, for a classifier that also takes its shape descriptors)."""
        if self.classifier and mode in self.classifier:
            clf = self.classifier[mode]
            desc = None
            if uses_descriptors(clf):
                if grid is None:
                    raise ValueError(f'the {mode!r} classifier takes shape descriptors: pass the '
                                     'grid')
                desc = shape_descriptors(grid)[:descriptor_count(clf)]
            x = classifier_input(feats, len(self.models), bool(clf.get('row_standardize', False)),
                                 desc)
            p, unknown = classifier_probabilities(clf, x, feats[:, 0], self._prior_offset(clf))
            return p[0], bool(unknown[0])
        # the paper's rule: the class whose model explains the observation best (times the
        # class prior, when one is set: 'uniform' changes nothing)
        logits = feats[:, 0] * 50.0
        if self._prior_weights is not None:
            with np.errstate(divide='ignore'):
                logits = logits + np.log(self._prior_weights)
        return _softmax(logits), False

    def classify_points(self, feats, point_features):
        """Class probabilities (C,) and the unknown flag of the 'points' classifier from the
        (C, F) grid features and the (2,) finite side-normal descriptors of the raw points."""
        clf = self.classifier[POINTS_MODE]
        p, unknown = apply_point_classifier(clf, np.asarray(feats)[:, 0][None], point_features,
                                            self._prior_offset(clf))
        return p[0], bool(unknown[0])

    def _completion(self, grid, per, probs, best, min_prob=0.1, max_classes=3):
        """Occupancy probability and variance (N, N, N) in the observed frame, averaged over the
        likely classes (Bayesian model averaging: weights = class probabilities >= min_prob);
        the probability of the unknown voxels is then calibrated when the bank has an
        ``occupancy_calibration``. The variance is that of the linear-Gaussian occupancy."""
        order = [int(c) for c in np.argsort(-probs)[:max_classes] if probs[c] >= min_prob]
        order = order or [best]
        w = probs[order] / probs[order].sum()
        prob = np.zeros(grid.shape, np.float64)
        m1 = np.zeros(grid.shape, np.float64)
        m2 = np.zeros(grid.shape, np.float64)
        for wc, c in zip(w, order):
            mc = self.models[c]
            p_c, mean_c, var_c = self.engine.predictive(
                per[c]['exact'], c, mc.loading_covariance.astype(np.float64), mc.mean_variance)
            yaw_c = per[c]['yaw']
            # back to the observed frame; outside the rotated model is empty space
            to_obs = self.engine.to_observed
            prob += wc * to_obs(p_c, yaw_c).reshape(grid.shape)
            mean_c = to_obs(mean_c, yaw_c).reshape(grid.shape)
            var_c = to_obs(var_c, yaw_c).reshape(grid.shape)
            m1 += wc * mean_c
            m2 += wc * (var_c + mean_c.astype(np.float64) ** 2)
        variance = np.maximum(m2 - m1 ** 2, 0)
        if self.occupancy_calibration is not None:
            unknown = grid < 0
            prob[unknown] = self.occupancy_calibration.predict(prob[unknown])
        # what was observed is kept: seen surface occupied, seen space free
        prob = np.where(grid == 1, 1.0, np.where(grid == 0, 0.0, prob))
        variance = np.where(grid >= 0, 0.0, variance)
        return prob.astype(np.float32), variance.astype(np.float32)

    def _refine(self, grid, c, per_c, step_deg=1.0, window_deg=3.0, stage2_step_deg=1.0,
                stage2_modes=6, stage2_window_deg=15.0, probe_deg=PROBE_DEG):
        """Refine the yaw of class ``c``: re-score it on the pooled grid with all its components
        (every ``stage2_step_deg``; None skips this), then re-solve it exactly at full resolution
        at the pooled optimum and at +-``probe_deg`` from it, and climb from the best of those
        to the best yaw within +-window_deg (the pooled grid cannot tell apart yaws a few
        degrees apart, and its optimum is sometimes 10-20 degrees off the full-resolution one).
        ``window_deg`` 0 skips the probes and the climb."""
        best = per_c
        eng = self.engine
        obs = eng.observe(per_c.get('observed', grid))
        if stage2_step_deg:
            step = np.deg2rad(stage2_step_deg)
            yaws = yaw_grid(stage2_step_deg)
            rows = None
            if stage2_modes and stage2_window_deg:
                sy, sl = per_c['searched']
                m0 = top_yaw_modes(sy, sl, stage2_modes)
                r = np.rint(sy[m0] / step).astype(int)
                w = int(round(stage2_window_deg / stage2_step_deg))
                rows = np.unique((r[:, None] + np.arange(-w, w + 1)).ravel() % len(yaws))
            ll = self.engine.scores(self._pooled(grid, per_c), yaws, c, full=True,
                                    rows=rows)[:, 0]
            if rows is not None:
                full_ll = np.full(len(yaws), -np.inf)
                full_ll[rows] = ll
                ll = full_ll
            modes = top_modes(ll, 3, max(1, int(round(20.0 / stage2_step_deg))))
            modes = [i for i in modes if np.isfinite(ll[i])]
            y0 = float(yaws[modes[0]])
            best = dict(per_c, yaw=y0, exact=self._exact(obs, c, y0, per_c),
                        hypotheses=[(float(yaws[i]), float(ll[i])) for i in modes])
        if window_deg > 0 and probe_deg:
            # exact solves a little further out: on 794 partial views of fold 0 (true class)
            # the probes at +-10, +-20 deg raised yaw <= 10 deg from 0.783 to 0.795 and with
            # flips from 0.902 to 0.918 for about 5 ms (2 ms since the exact posterior is
            # faster); probes at the other pooled modes, at the 90 and 180 deg turns or also at
            # +-30, +-45 deg did not help (the pooled ranking of distant modes is better)
            y0, top = best['yaw'], best['exact']['loglik']
            for off in probe_deg:
                for sign in (1, -1):
                    y = float(y0 + sign * np.deg2rad(off))
                    ex = self._exact(obs, c, y, best)
                    if ex['loglik'] > top:
                        top, best = ex['loglik'], dict(best, yaw=y, exact=ex)
        # hill climbing up to +-window_deg in steps of max(step_deg, 1 deg), then below 1 deg
        # in step_deg steps within +-1 deg: 2-4 exact solves per level instead of a scan
        coarse = max(step_deg, STAGE2_MIN_STEP_DEG)
        best = self._climb(obs, c, best, coarse, window_deg)
        if step_deg < coarse and window_deg > 0:
            best = self._climb(obs, c, best, step_deg, min(window_deg, coarse))
        eng.add_prediction(best['exact'], obs, c)
        return best

    def _exact(self, obs, c, yaw, per_c):
        """``engine.exact(obs, c, yaw, with_prediction=False)`` of the search result ``per_c``
        of class c, or the posterior of the same rotation map solved earlier for it
        (``per_c['solved']``, shared by the dicts made from it): the refinement often solves
        the stage-1 yaw again. The result depends on the yaw only through its map keys."""
        solved = per_c.get('solved')
        key = _solved_key(yaw)
        ex = None if solved is None else solved.get(key)
        if ex is None:
            ex = self.engine.exact(obs, c, yaw, with_prediction=False)
            if solved is not None:
                solved[key] = ex
        return ex

    def _climb(self, obs, c, best, step_deg, window_deg):
        """Hill climbing of the exact log-likelihood from best['yaw'] in step_deg steps, up
        to +-window_deg, first upward, then downward if that found nothing better (the
        full-resolution likelihood is smooth at this scale, up to the plateaus of the
        nearest-neighbour rotation, which the climb walks across)."""
        step, y0 = np.deg2rad(step_deg), best['yaw']
        for direction in (1, -1):
            top = best['exact']['loglik']
            for i in range(1, int(round(window_deg / step_deg)) + 1):
                y = float(y0 + direction * i * step)
                ex = self._exact(obs, c, y, best)
                if ex['loglik'] < top:
                    break
                top = ex['loglik']
                if top > best['exact']['loglik']:
                    best = dict(best, yaw=y, exact=ex)
            if best['yaw'] != y0:
                break
        return best

    def _pooled_score(self, grid, c, per_c, yaw, step_deg=STAGE2_MIN_STEP_DEG):
        """Pooled log-likelihood of class ``c`` with all its components at ``yaw`` rounded to
        the stage-2 grid of ``step_deg`` (whose rotation maps are cached), as the hypotheses'
        scores."""
        yaws = yaw_grid(step_deg)
        # the nearest on the circle: a grid of a step that does not divide 360 deg (7, 50) has
        # no period of 2 pi (a turned yaw beyond it was scored at another yaw) and a wider gap
        # between its last yaw and 360 deg (358 deg is nearer 0 than 350 deg)
        row = int(np.argmin(yaw_error(yaws, yaw)))
        return float(self.engine.scores(self._pooled(grid, per_c), yaws, c, full=True,
                                        rows=[row])[0, 0])

    def _pooled(self, grid, per_c):
        """The 2x-pooled observation: the search's (``per_c['pooled']``), else made now."""
        pooled = per_c.get('pooled')
        return self.engine.pooled(grid) if pooled is None else pooled

    def _verify_turns(self, grid, c, per_c):
        """The refined yaw of class ``c`` or one of its 90, 180, 270° turns: the one with the
        largest exact log-likelihood + weight x log P(turn 0) of the orientation verifier
        (fold 0 of ModelNet10 through ``estimate``, models, classifier and verifier fitted
        without it: yaw within 10° 0.797 -> 0.827 and 0.777 -> 0.811 on two sets of 794
        views, with flips +1.1 / +1.2 points; see ``beo_ros.core.verifier``)."""
        y0 = per_c['yaw']
        yaws = y0 + np.arange(TURNS) * (np.pi / 2)
        logp = self.verifier.predict_log_proba(c, quarter_turned_features(grid, y0))[:, 0]
        # only the turns the verifier prefers to y0 are solved: y0 is the likelihood's own
        # choice, so another turn could win only by a higher likelihood (5 % of the turns on
        # fold 0); skipping them changed 0.5 % of the choices and none of the accuracy, and
        # saves 3 exact solves on most views (0.26 per view instead of 3)
        w = float(self.verifier.weight)
        eng = self.engine
        obs = eng.observe(per_c.get('observed', grid))
        best_k, best_score, best_ex = 0, per_c['exact']['loglik'] + w * logp[0], None
        for k in range(1, TURNS):
            if logp[k] <= logp[0]:
                continue
            ex = self._exact(obs, c, float(yaws[k]), per_c)
            if ex['loglik'] + w * logp[k] > best_score:
                best_k, best_score, best_ex = k, ex['loglik'] + w * logp[k], ex
        if best_k == 0:
            return per_c
        return dict(per_c, yaw=float(yaws[best_k]), exact=eng.add_prediction(best_ex, obs, c),
                    turned=best_k)

    def estimate(self, grid, yaw=None, yaw_step_deg=1.0, n_hypotheses=5, exhaustive=True,
                 refine_deg=3.0, stage2_modes=6, stage2_window_deg=15.0, search_step_deg=None,
                 point_features=None, probe_deg=PROBE_DEG, verify=True):
        """Classify, orient and complete one labelled grid (see :class:`Estimate`).

        Args:
            grid: int8 (N, N, N), 1 occupied, 0 free, -1 unknown, axes x, y, z, z up.
            yaw: if given (radians), no pose search is done.
            yaw_step_deg: resolution of the returned yaw, in [0.05, 90]. Below 1° the pooled
                re-scoring stays at 1° and a last exact climb within +-1° gives the finer
                yaw (at 32^3 the nearest-neighbour rotation hardly resolves it).
            search_step_deg: step of the stage-1 search over all classes (default
                max(SEARCH_STEP_DEG, yaw_step_deg)); its features feed the classifier.
            exhaustive: stage 1 scores all 360 / search_step_deg yaws at once (default); False
                searches coarse-to-fine (5 degree steps, then the best modes).
            stage2_modes, stage2_window_deg: the chosen class is re-scored on the pooled grid
                with all its components (not only the leading ``pose_components``) every
                yaw_step_deg within +-stage2_window_deg of its ``stage2_modes`` best stage-1
                modes (either None or 0: all yaws);
            probe_deg: then it is solved exactly at full resolution at the pooled optimum
                and at +- each of these offsets (degrees; () or None: no probes), and
            refine_deg: climbs from the best of those within +-refine_deg
                (0: no refinement at all, the stage-1 yaw is returned).
            verify: with an orientation verifier for the chosen class, the refined yaw may
                then be replaced by one of its quarter turns (``_verify_turns``; False: not).
            point_features: optional (2,) side-normal descriptors of the object's raw points
                (:func:`beo_ros.core.normals.side_normal_descriptors`; ``estimate_points``
                passes them). When the bank has a 'points' classifier and they are finite, that
                classifier decides the class (and so the refined pose and the completion);
                NaN descriptors fall back to the grid rule (``classifier_note`` says so).
                None: the grid rule, exactly as without this argument.
        """
        t0 = time.perf_counter()
        grid = self.check_grid(grid)
        yaw_step_deg, search_step_deg, probe_deg, refine_deg, stage2_window_deg = \
            _check_estimate_options(
            yaw_step_deg, search_step_deg, probe_deg, refine_deg, stage2_window_deg, n_hypotheses,
            stage2_modes)
        yaw = check_yaw(yaw)
        if not (grid == 1).any():
            return self._no_object(grid, yaw, t0)
        feats, per = self.features(grid, yaw, search_step_deg, exhaustive)
        t1 = time.perf_counter()
        probs, unknown, rule, note, point_features = self._classify(feats, grid, point_features)
        best = int(np.argmax(probs))
        t_cls = time.perf_counter()
        if yaw is None and refine_deg > 0:
            per[best] = self._refine(grid, best, per[best], yaw_step_deg, refine_deg,
                                     max(yaw_step_deg, STAGE2_MIN_STEP_DEG), stage2_modes,
                                     stage2_window_deg, probe_deg)
        t_ref = time.perf_counter()
        refined_yaw = per[best]['yaw']
        if yaw is None and refine_deg > 0 and verify and self.verifier is not None \
                and self.verifier.has_class(best):
            per[best] = self._verify_turns(grid, best, per[best])
        t2 = time.perf_counter()
        completion, variance = self._completion(grid, per, probs, best)
        est_yaw = per[best]['yaw']
        turns = symmetric_turns(completion >= 0.5)
        t3 = time.perf_counter()
        hyps = self._hypotheses(grid, per, best, refined_yaw, yaw_step_deg)
        label = UNKNOWN_LABEL if unknown else self.classes[best]
        return Estimate(
            label=label, scores={c: float(p) for c, p in zip(self.classes, probs)},
            yaw=_wrap(est_yaw),
            symmetric_yaws=[_wrap(est_yaw + t) for t in turns],
            completion=completion, variance=variance,
            hypotheses=[Hypothesis(lab, _wrap(y), float(s))
                        for lab, y, s in hyps[:n_hypotheses]],
            timings={'pose_and_features': t1 - t0, 'classify': t_cls - t1,
                     'pose_refinement': t_ref - t_cls, 'orientation_check': t2 - t_ref,
                     'completion': t3 - t2,
                     'total': t3 - t0},
            features=feats, grid=grid, classifier_mode=rule, point_features=point_features,
            classifier_note=note)

    def _classify(self, feats, grid, point_features):
        """Class probabilities (C,) and 'unknown' flag of one grid (N, N, N) from its features
        ``feats`` (C, F): by the 'points' classifier when the bank has one and the optional
        ``point_features`` (2,) are finite, else by the grid rule of the grid's mode.

        Returns (probs, unknown, rule: 'points', 'complete', 'partial' or 'max_likelihood',
        note: why the 'points' classifier was not used and / or the class prior not applied,
        point_features as float64 (2,) or None); ValueError for point_features of another
        shape."""
        mode = 'complete' if (grid < 0).mean() < 0.01 else 'partial'
        rule, note = None, ''
        if point_features is not None:
            try:
                point_features = np.asarray(point_features, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f'point_features must be 2 numbers (r4, frac10), got '
                                 f'{point_features!r}') from None
            if point_features.shape != (2,):
                raise ValueError(f'point_features must be 2 values (r4, frac10), got shape '
                                 f'{point_features.shape}')
            if self.has_point_classifier:
                if np.isfinite(point_features).all():
                    probs, unknown = self.classify_points(feats, point_features)
                    rule = POINTS_MODE
                else:
                    note = ("'points' classifier not used: side-normal descriptors undefined "
                            '(too few points or side normals); grid rule')
        if rule is None:
            probs, unknown = self.classify_features(feats, mode, grid)
            rule = mode if self.classifier and mode in self.classifier else 'max_likelihood'
        note = '; '.join(n for n in (note, self.prior_note(rule)) if n)
        return probs, unknown, rule, note, point_features

    def _hypotheses(self, grid, per, best, refined_yaw, yaw_step_deg):
        """The pose hypotheses (class name, yaw, score), best first, of a grid whose chosen
        class ``best`` has the refined (and maybe verifier-turned) search result ``per[best]``
        (``refined_yaw``: its yaw before the verifier): that class's yaw modes (the first at
        ``refined_yaw``; a verifier's quarter turn before them, with its own pooled score), then
        every other class's best mode, by score."""
        est_yaw = per[best]['yaw']
        # the chosen class's yaw modes first (symmetric objects have several), then the others
        hyps = [(self.classes[best], y, ll) for y, ll in per[best]['hypotheses']]
        if hyps:  # the best mode, as refined at full resolution
            hyps[0] = (hyps[0][0], refined_yaw, hyps[0][2])
        if per[best].get('turned'):
            # the verifier's quarter turn goes first, with its own pooled score (it may be
            # lower than the likelihood's choice, which stays listed); modes within 10 degrees
            # of it are the same hypothesis
            score = self._pooled_score(grid, best, per[best], est_yaw,
                                       max(yaw_step_deg, STAGE2_MIN_STEP_DEG))
            hyps = [(self.classes[best], est_yaw, score)] + \
                [h for h in hyps if abs(_wrap(h[1] - est_yaw)) >= np.deg2rad(10.0)]
        hyps += sorted(((self.classes[c], y, ll) for c in range(len(per)) if c != best
                        for y, ll in per[c]['hypotheses'][:1]), key=lambda h: -h[2])
        return hyps

    def _no_object(self, grid, yaw, t0):
        """The estimate of a grid with no occupied voxel (all free or unknown, e.g. the view of
        a one-voxel object that the rotation lost): no object, so label 'unknown', the class
        prior as scores, nothing completed, no pose hypotheses."""
        weights = self._prior_weights
        if weights is None:   # the 'train' prior: the classifier's training rows per class
            # (the 'partial' one's, else those of the bank's other classifier: a bank with a
            # 'points' or 'complete' classifier only answered uniform)
            clfs = self.classifier or {}
            counts = next((clfs[m]['class_counts'] for m in ('partial', 'complete', POINTS_MODE)
                           if 'class_counts' in clfs.get(m, {})), None)
            weights = np.ones(len(self.classes)) if counts is None else \
                np.asarray(counts, dtype=np.float64)
        weights = np.asarray(weights, dtype=np.float64) / np.sum(weights)
        yaw = 0.0 if yaw is None else _wrap(float(yaw))
        zeros = np.zeros(grid.shape, dtype=np.float32)
        return Estimate(label=UNKNOWN_LABEL, scores=dict(zip(self.classes, map(float, weights))),
                        yaw=yaw, completion=zeros, variance=zeros.copy(), grid=grid,
                        timings={'total': time.perf_counter() - t0}, classifier_mode='none',
                        classifier_note='grid has no occupied voxel: no object to estimate')

    def estimate_points(self, points, sensor_origin=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0),
                        yaw_step_deg=1.0, threshold=0.5, center=None,
                        outlier_mads=OUTLIER_MADS, outlier_neighbors=OUTLIER_NEIGHBORS,
                        cluster_tolerance=None):
        """Estimate from an (n, 3) cloud in metres (any frame; the sensor at ``sensor_origin``).

        The pose and completed points come back in the input frame (see :class:`Estimate`).
        Non-finite points are dropped, then statistical outliers
        (:func:`beo_ros.core.outliers.statistical_outliers` with ``outlier_neighbors`` and
        ``outlier_mads``; None: none removed; ``Estimate.n_outliers`` counts them), as the
        extent of the points places and scales the grid. With a ``cluster_tolerance`` (same
        unit as the points; None: off) only the largest cluster of the remaining points is
        kept (:func:`beo_ros.core.outliers.outside_largest_cluster`; counted in
        ``Estimate.n_off_cluster``): for segments that caught part of another surface or
        object. Points that fall outside the grid (a metric one, or one placed by ``center``)
        are not voxelized (counted in ``Estimate.n_outside_grid``). With a 'points' classifier
        the side-normal descriptors of the remaining points are computed too
        (``timings['point_descriptors']``) and passed to :meth:`estimate`. The outlier removal
        grows faster than the points (5 s for a million): downsample big clouds first, as the
        node does (``max_points``).
        """
        from .voxelize import (MIN_POINTS, finite_points, grid_to_points, unit_direction,
                               voxelize_view)
        prob_threshold = real_number(threshold)
        if prob_threshold is None or not 0 < prob_threshold <= 1:   # also refuses NaN
            raise ValueError(f'threshold must be an occupancy probability in (0, 1], got '
                             f'{threshold!r}')
        t0 = time.perf_counter()
        finite = finite_points(points)
        pts_in, n_outliers, n_off_cluster = clean_points(
            finite, outlier_mads, outlier_neighbors, cluster_tolerance)
        if len(pts_in) < MIN_POINTS:   # voxelize_view would say "finite points": name why
            raise TooFewPoints(f'need at least {MIN_POINTS} points, got {len(pts_in)} of the '
                             f'{len(finite)} finite ones after removing {n_outliers} outliers '
                             f'(outlier_mads {outlier_mads}) and {n_off_cluster} outside the '
                             f'largest cluster (cluster_tolerance {cluster_tolerance})')
        t_out = time.perf_counter()
        try:
            view = voxelize_view(pts_in, sensor_origin, up, self.spec, center=center)
        except ValueError as e:
            if not n_outliers + n_off_cluster:
                raise
            # e.g. "the points span 0": the cleaning left only copies of one point
            raise ValueError(f'{e} (the {len(pts_in)} points left of {len(finite)} finite '
                             f'ones after removing {n_outliers} outliers (outlier_mads '
                             f'{outlier_mads}) and {n_off_cluster} outside the largest cluster '
                             f'(cluster_tolerance {cluster_tolerance}))') from None
        t1 = time.perf_counter()
        up = unit_direction(up, 'up')   # valid: voxelize_view has checked it
        point_features = None
        if self.has_point_classifier:
            from .normals import side_normal_descriptors
            point_features = side_normal_descriptors(pts_in, up, sensor_origin)
        t2 = time.perf_counter()
        est = self.estimate(view.grid, yaw_step_deg=yaw_step_deg, point_features=point_features)
        T = np.asarray(view.grid_to_input, dtype=np.float64)
        R_grid = T[:3, :3] / np.linalg.norm(T[:3, :3], axis=0)
        pose = np.eye(4)
        pose[:3, :3] = R_grid @ yaw_matrix(est.yaw)
        # float64 points for the pose: float32 ones are centimetres off at 1e6 m
        pts, prob = grid_to_points(est.completion, T, prob_threshold, dtype=np.float64)
        c = (self.spec.size - 1) / 2.0
        pose[:3, 3] = object_centre(
            pts if len(pts) else grid_to_points(view.grid, T, 1, dtype=np.float64)[0],
            pose[:3, :3], T @ np.array([c, c, c, 1.0]))
        est.pose = pose
        est.dimensions = object_extent(pts, pose, np.linalg.norm(T[:3, 0]))
        est.heading_offset = heading_offset(R_grid, up)
        est.grid_to_input = T
        est.completed_points = np.asarray(pts, dtype=np.float32)
        est.completed_probability = np.asarray(prob, dtype=np.float32)
        est.n_outliers = n_outliers
        est.n_off_cluster = n_off_cluster
        est.n_outside_grid = len(pts_in) - view.n_points
        est.timings['outliers'] = t_out - t0
        est.timings['voxelize'] = t1 - t_out
        if point_features is not None:
            est.timings['point_descriptors'] = t2 - t1
        est.timings['total'] = time.perf_counter() - t0
        return est


def _solved_key(yaw):
    """What ``InferenceEngine.exact`` takes of a yaw (radians): the keys of its two maps."""
    return yaw_key(-yaw), yaw_key(yaw)


def _dir_identity(path):
    """(device, inode, ctime) of directory ``path`` (followed if a link), None when there is
    none: a save that replaces it changes it."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino, st.st_ctime_ns


def _json_value(value):
    """A numpy scalar or array in the manifest (e.g. ``training=dict(k=np.int64(20))``) as the
    JSON value of its Python equivalent; TypeError for anything else JSON cannot hold."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f'the manifest cannot hold {type(value).__name__} {value!r} (JSON)')


# random characters that _new_directory (12) and mkdtemp (8) append to a prefix
_RANDOM_CHARS = 12


def _sibling_prefix(path: Path, kind: str) -> str:
    """The name prefix ``.<name>.<kind>-`` of the temporary directories ``ModelBank.save``
    makes beside directory ``path``, with ``<name>`` (the name of ``path``) cut short so that
    the prefix and its random characters fit the file system's limit on a name (255 bytes
    usually): a target name near the limit failed with 'File name too long'."""
    try:
        limit = os.pathconf(path.parent, 'PC_NAME_MAX')
    except (OSError, ValueError):   # no such parent yet, or no limit known
        limit = 255
    name = os.fsencode(path.name)[:max(limit - len(f'..{kind}-') - _RANDOM_CHARS, 1)]
    return f'.{os.fsdecode(name)}.{kind}-'   # a cut UTF-8 character: surrogate escapes


def _save_in_progress(path) -> bool:
    """True when the temporary directories of a ``ModelBank.save`` into directory ``path``
    (see :func:`_sibling_prefix`) are beside it: the save is writing or renaming (or was
    killed and left them)."""
    try:
        path = Path(path).resolve()   # save replaces the directory a link or '..' names
        prefixes = tuple(_sibling_prefix(path, kind) for kind in ('tmp', 'old'))
        with os.scandir(path.parent) as entries:
            return any(e.name.startswith(prefixes) and e.is_dir(follow_symlinks=False)
                       for e in entries)
    except (OSError, RuntimeError, ValueError):   # no parent; a link loop; NUL in the name
        return False


def _new_directory(parent: Path, prefix: str) -> Path:
    """A new directory ``parent/prefix<random>`` with the permissions of the process's umask
    (mkdtemp's 0o700 would outlive the rename into place, and reading the umask by setting it
    to 0 and back left it 0 for the other threads meanwhile)."""
    for _ in range(100):
        p = parent / f'{prefix}{os.urandom(6).hex()}'
        try:
            os.mkdir(p, 0o777)   # less the umask
            return p
        except FileExistsError:
            continue
    raise FileExistsError(f'no free name {prefix}* in {parent}')


def object_centre(points, rotation, fallback) -> np.ndarray:
    """(3,) middle of the extent of ``points`` (m, 3, input frame) along the object axes
    ``rotation`` (3, 3: axes as columns, input frame); ``fallback`` (3,) when there are none.
    (The grid centre alone is where the voxelization put the view, not the object: on a
    'bottom' grid it lies (N-1)/2 voxels above the support, above a short object.)"""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.asarray(fallback, dtype=np.float64)[:3]
    local = pts @ rotation
    return rotation @ ((local.min(axis=0) + local.max(axis=0)) / 2.0)


def object_extent(points, pose, voxel) -> np.ndarray:
    """float64 (3,) extent in metres of the voxels of edge ``voxel`` centred at ``points``
    (m, 3, input frame) along the axes of ``pose`` (4, 4), outer face to outer face; zeros when
    there are none. (From float64 points: the float32 completed points of a map frame are
    centimetres off at 1e6 m.)"""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(3)
    pose = np.asarray(pose, dtype=np.float64)
    local = (pts - pose[:3, 3]) @ pose[:3, :3]
    return local.max(axis=0) - local.min(axis=0) + float(voxel)


def heading_offset(grid_rotation, up) -> float:
    """Radians to add to a grid-frame yaw to get the heading about ``up`` in the input frame:
    the angle from the input frame's x axis projected on the plane normal to ``up`` (its y axis
    when x is within 25 degrees of ``up`` or of down) to the grid's x axis.
    ``grid_rotation`` (3, 3): the grid axes in the input frame, z = up."""
    u = unit_vector(up)
    ref = np.eye(3)[0] - u * u[0]
    if np.linalg.norm(ref) < np.sin(np.deg2rad(25.0)):
        ref = np.eye(3)[1] - u * u[1]
    ref /= np.linalg.norm(ref)
    g = np.asarray(grid_rotation, dtype=np.float64)[:, 0]
    return float(np.arctan2(np.cross(u, ref) @ g, ref @ g))


def check_yaw(yaw):
    """``yaw`` as a float (radians), or None (search it); ValueError unless it is a finite
    real number (see :func:`~beo_ros.core.grid.real_number`) or None."""
    if yaw is None:
        return None
    value = real_number(yaw)
    if value is None:
        raise ValueError(f'yaw must be None or a number of radians, got {yaw!r}')
    if not np.isfinite(value):
        raise ValueError('yaw must be finite, got ' + (
            f'an integer of {yaw.bit_length()} bits' if isinstance(yaw, int) else f'{yaw}'))
    return value


def check_step(name, value):
    """``value`` as a float; ValueError unless it is a real number (see :func:`~beo_ros.core.grid.real_number`)
    of degrees in YAW_STEP_RANGE_DEG ([0.05, 90])."""
    lo, hi = YAW_STEP_RANGE_DEG
    step = real_number(value)
    if step is None or not lo <= step <= hi:   # also refuses NaN
        raise ValueError(f'{name} must be a number of degrees in [{lo:g}, {hi:g}], got {value!r}')
    return step


def _probe_offsets(probe_deg):
    """``probe_deg`` of :meth:`ModelBank.estimate` (None, one number or several, a list or an
    array) as a tuple of float offsets (degrees); ValueError unless each is a real number (see
    :func:`~beo_ros.core.grid.real_number`) in (0, 180]."""
    if probe_deg is None:
        probe_deg = ()
    elif np.ndim(probe_deg) == 0:
        probe_deg = (probe_deg.item() if isinstance(probe_deg, np.ndarray) else probe_deg,)
    elif isinstance(probe_deg, np.ndarray):
        probe_deg = probe_deg.ravel().tolist()
    try:
        probe_deg = tuple(probe_deg)
    except TypeError:
        raise ValueError(f'probe_deg must be offsets in (0, 180] degrees, got '
                         f'{probe_deg!r}') from None
    offsets = tuple(real_number(p) for p in probe_deg)
    if not all(p is not None and 0 < p <= 180 for p in offsets):
        raise ValueError(f'probe_deg must be offsets in (0, 180] degrees, got {probe_deg}')
    return offsets


def _check_estimate_options(yaw_step_deg, search_step_deg, probe_deg, refine_deg,
                            stage2_window_deg, n_hypotheses, stage2_modes):
    """Check the search options of :meth:`ModelBank.estimate` (ValueError naming the first bad
    one) and return them as floats (yaw_step_deg; search_step_deg: max(SEARCH_STEP_DEG,
    yaw_step_deg) when None; probe_deg: a tuple (see :func:`_probe_offsets`); refine_deg;
    stage2_window_deg: 0.0 when None)."""
    yaw_step_deg = check_step('yaw_step_deg', yaw_step_deg)
    if search_step_deg is not None:
        search_step_deg = check_step('search_step_deg', search_step_deg)
    probe_deg = _probe_offsets(probe_deg)
    if stage2_window_deg is None:
        stage2_window_deg = 0.0
    degrees = []
    for name, value in (('refine_deg', refine_deg), ('stage2_window_deg', stage2_window_deg)):
        degrees.append(real_number(value))
        if degrees[-1] is None or not 0 <= degrees[-1] <= 180:   # also refuses NaN
            raise ValueError(f'{name} must be in [0, 180] degrees, got {value!r}')
    check_count('n_hypotheses', n_hypotheses)
    if stage2_modes is not None:
        check_count('stage2_modes', stage2_modes)
    if search_step_deg is None:
        search_step_deg = max(SEARCH_STEP_DEG, yaw_step_deg)
    return yaw_step_deg, search_step_deg, probe_deg, *degrees


def load_models(path=None, class_prior=None):
    """Load a model directory (default: the shipped ``models/modelnet10_32``; a shipped model's
    bare name such as 'tabletop_32' also works, see :func:`resolve_model_dir`); ``class_prior``
    overrides the manifest's (see :class:`ModelBank`)."""
    return ModelBank.load(resolve_model_dir(path), class_prior)


def default_model_dir(name='modelnet10_32'):
    """The shipped model directory: the installed share dir, else the source tree's models/.

    The share dir is looked up in the ament index (AMENT_PREFIX_PATH), else next to the package
    as a plain ``pip install .`` (or ``--user``, ``--target DIR``) puts it:
    ``<prefix>/share/beo_ros`` for ``<prefix>/lib/pythonX.Y/site-packages/beo_ros``."""
    try:
        from ament_index_python.packages import get_package_share_directory
        p = Path(get_package_share_directory('beo_ros')) / 'models' / name
        if p.is_dir():
            return p
    except Exception:  # not installed through ament, or ament_index missing
        pass
    top = Path(__file__).resolve().parents[2]   # the source tree, or site-packages
    source = top / 'models' / name
    for p in (source, top.parent.parent.parent / 'share' / 'beo_ros' / 'models' / name,
              top / 'share' / 'beo_ros' / 'models' / name):
        if p.is_dir():
            return p
    return source


def resolve_model_dir(text) -> Path:
    """A model directory as a user names it: '' or None is the shipped default; a path that
    exists is itself; a bare name that is not a path here (e.g. 'tabletop_32') is that shipped
    model, so an installed package needs no share path. Anything else comes back as given
    (loading it then names it as missing)."""
    if not text:
        return default_model_dir()
    try:
        path = Path(text).expanduser()
    except RuntimeError:   # '~user' of no such user: as given (the node crashed on it)
        return Path(text)
    if path.exists() or len(path.parts) != 1 or str(text).startswith(('.', '~')):
        return path
    shipped = default_model_dir(str(text))
    return shipped if shipped.is_dir() else path


def shipped_models() -> list:
    """Names of the shipped model directories (those with a manifest)."""
    root = default_model_dir().parent
    return sorted(p.parent.name for p in root.glob('*/manifest.json'))
