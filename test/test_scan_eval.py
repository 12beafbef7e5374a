"""Leave-one-scene-out evaluation of the tabletop models (beo_ros.scan_eval): out-of-fold
features and the scene-grouped second-level classifier comparison, on small generated scenes."""
import json
import re

import numpy as np
import pytest

from beo_ros.core.inference import FEATURE_NAMES
from beo_ros.core.pcd import write_pcd
from beo_ros.scan_eval import (
    classifier_comparison, classifier_design, main, scene_cv_logistic,
    scene_cv_point_predictions, scene_cv_predictions)


# a small, fast leave-one-scene-out run (grid 16, few iterations, no figures)
SMALL_LOSO = ['--no-congeal', '--k', '2', '--max-iter', '3', '--grid', '16', '--voxel-size',
              '0.03125', '--yaw-step', '10', '--figures', '0']


def _scene_points(kind, rng, n_obj=2):
    """Camera at the origin (y down, z forward) pitched down 40 deg, table 0.6 m below it, and
    ``n_obj`` boxes or cylinders on the table (their camera-facing surfaces). -> (points, labels)"""
    pitch = np.radians(40)
    up = np.array([0.0, -np.cos(pitch), -np.sin(pitch)])
    fwd = np.cross([1.0, 0, 0], up)
    fwd /= np.linalg.norm(fwd)
    side = np.cross(up, fwd)
    table_c = 0.9 * fwd - 0.6 * up

    def to_cam(a, b, h):
        return table_c + np.outer(a, side) + np.outer(b, fwd) + np.outer(h, up)

    m = 3000
    pts = [to_cam(rng.uniform(-0.45, 0.45, m), rng.uniform(-0.35, 0.35, m),
                  rng.normal(0, 0.002, m))]
    labels = [np.ones(m)]
    for j in range(n_obj):
        x0 = -0.15 + 0.3 * j
        r = rng.uniform(0.04, 0.06)
        h = rng.uniform(0.1, 0.2)
        k = 1200
        if kind == 'box':
            p = np.r_[to_cam(x0 + rng.uniform(-r, r, k), np.full(k, -r), rng.uniform(0, h, k)),
                      to_cam(x0 + rng.uniform(-r, r, k), rng.uniform(-r, r, k), np.full(k, h))]
        else:
            a = rng.uniform(np.pi, 2 * np.pi, k)          # the half facing the camera
            rr = r * np.sqrt(rng.uniform(0, 1, k))
            b = rng.uniform(0, 2 * np.pi, k)
            p = np.r_[to_cam(x0 + r * np.cos(a), r * np.sin(a), rng.uniform(0, h, k)),
                      to_cam(x0 + rr * np.cos(b), rr * np.sin(b), np.full(k, h))]
        pts.append(p)
        labels.append(np.full(len(p), 10 * (j + 2)))
    return np.concatenate(pts).astype(np.float32), np.concatenate(labels).astype(np.uint32)


@pytest.fixture(scope='module')
def scan_files(tmp_path_factory):
    """learn0, learn1 (boxes) and learn33, learn34 (cylinders): 2 objects per scene."""
    d = tmp_path_factory.mktemp('scans')
    files = []
    for i, (num, kind) in enumerate([(0, 'box'), (1, 'box'), (33, 'cyl'), (34, 'cyl')]):
        pts, lab = _scene_points(kind, np.random.default_rng(i))
        f = d / f'learn{num}.pcd'
        write_pcd(f, {'x': pts[:, 0], 'y': pts[:, 1], 'z': pts[:, 2], 'label': lab})
        files.append(f)
    return files


def test_classifier_design():
    F = np.arange(2 * 2 * 6, dtype=float).reshape(2, 2, 6)
    assert classifier_design(F, 'all').shape == (2, 12)
    np.testing.assert_array_equal(classifier_design(F, 'all')[1], F[1].ravel())
    np.testing.assert_array_equal(classifier_design(F, 'diff'), F[:, 0] - F[:, 1])
    with pytest.raises(ValueError):
        classifier_design(np.zeros((2, 3, 6)), 'diff')
    with pytest.raises(ValueError):
        classifier_design(F, 'ratio')
    with pytest.raises(ValueError):
        classifier_design(F[0], 'all')


def _features(rng, n_scenes=12, per_scene=4):
    """Features where the log-likelihood (feature 0) is biased toward class 0 and useless for
    class 1, while feature 2 (rmse) separates the classes: a learned rule must beat max-lik."""
    y = np.repeat(np.arange(n_scenes) % 2, per_scene)
    groups = np.repeat([f's{i}' for i in range(n_scenes)], per_scene)
    F = rng.normal(0, 1, (len(y), 2, len(FEATURE_NAMES)))
    F[:, 0, 0] += 3.0                                # class 0 always has the larger loglik
    F[:, 1, 2] += np.where(y == 1, -4.0, 4.0)        # rmse of class 1 tells the classes apart
    return F, y, groups


def test_scene_cv_is_grouped_and_learns():
    rng = np.random.default_rng(0)
    F, y, groups = _features(rng)
    comp = classifier_comparison(F, y, groups, ['a', 'b'])
    assert set(comp) == {'max_likelihood', 'lr_all_C0.1', 'lr_all_C1', 'lr_diff_C0.1',
                         'lr_diff_C1'}
    ml = comp['max_likelihood']
    assert ml['accuracy'] == pytest.approx(np.mean(np.argmax(F[:, :, 0], 1) == y), abs=1e-4)
    assert ml['accuracy'] < 0.7
    for name in ('lr_all_C1', 'lr_diff_C1'):
        assert comp[name]['accuracy'] > 0.9, comp[name]
        assert np.sum(comp[name]['confusion']) + comp[name]['n_unknown'] == len(y)
        assert comp[name]['n_correct'] == len(y) - len(comp[name]['wrong'])
    # grouped: a scene's predictions do not depend on its own labels. Scene s3 lies apart
    # from all others (feature 3 shifted), so a regression that saw its flipped labels would
    # flip its answers; one that never saw the scene keeps them.
    te = groups == 's3'
    F2 = F.copy()
    F2[te, :, 3] += 8.0
    y2 = y.copy()
    y2[te] = 1 - y2[te]
    for kind in ('all', 'diff'):
        pred, _ = scene_cv_predictions(F2, y, groups, kind, 1.0)
        pred2, _ = scene_cv_predictions(F2, y2, groups, kind, 1.0)
        np.testing.assert_array_equal(pred[te], pred2[te])
    # the 'unknown' check of ModelBank.classify_features: an object far worse explained than
    # the training objects of its predicted class is 'unknown' and counts as wrong
    F3 = F.copy()
    F3[0, :, 0] = -1e3
    pred, unknown = scene_cv_predictions(F3, y, groups, 'all', 1.0)
    assert unknown[0] and not unknown[1:].any()
    rep = classifier_comparison(F3, y, groups, variants=(('all', 1.0),))['lr_all_C1']
    assert rep['n_unknown'] == 1 and 0 in rep['wrong']
    # the unknown object is neither correct nor in the confusion of the known answers
    assert rep['n_correct'] == len(y) - len(rep['wrong'])
    assert rep['accuracy'] == pytest.approx(rep['n_correct'] / len(y), abs=1e-4)
    assert np.sum(rep['confusion']) == len(y) - 1


def test_scene_cv_logistic_when_the_other_scenes_hold_one_class():
    # scene 'c' holds the only class-1 objects: its regression was fitted on class 0 alone,
    # and scikit-learn refused ('needs samples of at least 2 classes')
    rng = np.random.default_rng(0)
    Z = rng.normal(size=(9, 3))
    Z[6:, 0] += 5.0
    y = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1])
    groups = np.array(['a', 'a', 'a', 'b', 'b', 'b', 'c', 'c', 'c'])
    pred = scene_cv_logistic(Z, y, groups)
    np.testing.assert_array_equal(pred[groups == 'c'], 0)   # the only class its fit saw
    assert set(pred[groups != 'c']) <= {0, 1}
    with pytest.raises(ValueError, match='at least 2 groups'):
        scene_cv_logistic(Z, y, np.zeros(9))
    # the only class the other scenes hold is that class, not class 0
    np.testing.assert_array_equal(scene_cv_logistic(Z, 1 - y, groups)[groups == 'c'], 1)
    F = np.random.default_rng(1).normal(size=(9, 2, len(FEATURE_NAMES)))
    pred, _ = scene_cv_predictions(F, 1 - y, groups, 'all')
    np.testing.assert_array_equal(pred[groups == 'c'], 1)
    pred, _ = scene_cv_point_predictions(F, Z[:, :2], 1 - y, groups)
    np.testing.assert_array_equal(pred[groups == 'c'], 1)
    # standardised: an affine change of the inputs changes no answer
    np.testing.assert_array_equal(scene_cv_logistic(Z * 1e3 + 500.0, y, groups),
                                  scene_cv_logistic(Z, y, groups))


def test_no_diff_rule_for_more_than_two_classes():
    rng = np.random.default_rng(0)
    F = rng.normal(size=(12, 3, len(FEATURE_NAMES)))
    y = np.arange(12) % 3
    comp = classifier_comparison(F, y, np.repeat(['a', 'b', 'c', 'd'], 3))
    assert set(comp) == {'max_likelihood', 'lr_all_C0.1', 'lr_all_C1'}


def test_footprint_angle_and_circular_spread():
    from beo_ros.scan_eval import circular_spread_deg, footprint_angle
    t = np.linspace(0, 1, 200, endpoint=False)
    outline = np.r_[np.c_[10 * t, 0 * t], np.c_[10 * t, 4 + 0 * t], np.c_[0 * t, 4 * t],
                    np.c_[10 + 0 * t, 4 * t]]
    for deg in (30.0, 70.0):
        a = np.deg2rad(deg)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        pts = np.c_[outline @ rot.T + [5.0, 7.0], np.ones(len(outline))]
        assert np.rad2deg(footprint_angle(pts)) == pytest.approx(deg, abs=0.5)
    # -10 and -20 deg modulo 90: mean 75, spread about 5 deg
    mean, std = circular_spread_deg(np.deg2rad([-10.0, -20.0]), 90.0)
    assert mean == pytest.approx(75.0, abs=1e-6) and std == pytest.approx(5.0, abs=0.2)


def test_a_fold_leaving_one_object_of_a_class_is_refused_only_without_mirror():
    from types import SimpleNamespace
    from beo_ros.scan_eval import _check_groups
    objs = SimpleNamespace(y=np.array([0, 0, 1, 1]), names=['box', 'cyl'],
                           scenes=np.array(['s0', 's1', 's2', 's3']))
    _check_groups(SimpleNamespace(mirror=True), objs, [['s2']])   # an object and its mirror
    with pytest.raises(ValueError, match=r"holding out s2 leaves class 'cyl' 1 training "
                                         r'object\(s\)'):
        _check_groups(SimpleNamespace(mirror=False), objs, [['s2']])


def test_loso_saves_out_of_fold_features(scan_files, tmp_path, monkeypatch):
    import beo_ros.scan_eval as scan_eval
    fitted_on = []
    real_fit = scan_eval.fit_models

    def spy(objs, *a, **k):
        fitted_on.append(set(objs.scenes))
        return real_fit(objs, *a, **k)
    monkeypatch.setattr(scan_eval, 'fit_models', spy)
    out = tmp_path / 'ev'
    rc = main(['--scans', *map(str, scan_files), '--out', str(out), *SMALL_LOSO])
    assert rc == 0
    z = np.load(out / 'oof_features.npz')
    m = len(z['y'])
    assert m == 8 and z['features'].shape == (m, 2, len(FEATURE_NAMES))
    assert list(z['classes']) == ['box', 'cylinder']
    assert list(z['feature_names']) == list(FEATURE_NAMES)
    assert sorted(set(z['scenes'])) == ['learn0', 'learn1', 'learn33', 'learn34']
    # one fit per held-out scene, each on the other three scenes only
    everything = {'learn0', 'learn1', 'learn33', 'learn34'}
    assert sorted(map(sorted, fitted_on)) == sorted(sorted(everything - {s}) for s in everything)
    assert np.isfinite(z['features']).all()
    res = json.loads((out / 'scan_eval.json').read_text())
    s, recs = res['summary'], res['objects']
    # the saved features are the ones of the records, under the models fitted without the scene
    for r, f, sc, oid in zip(recs, z['features'], z['scenes'], z['object_ids']):
        assert (r['scene'], r['object']) == (sc, oid)
        # the generated objects: 8-12 cm wide, 10-20 cm tall, standing on the table
        assert 7 < min(r['extent_cm'][:2]) and max(r['extent_cm'][:2]) < 15, r['extent_cm']
        assert 9 < r['extent_cm'][2] < 21 and abs(r['above_table_cm']) < 1.5, r
        assert 0 < r['n_occupied'] < 500 and 0 < r['unknown_fraction'] < 1
        np.testing.assert_allclose([r['features']['box'][n] for n in FEATURE_NAMES], f[0],
                                   atol=1e-4)
    # the maximum-likelihood rule on the saved features is the rule the loop used
    cv = s['classifier_cv']
    assert cv['max_likelihood']['accuracy'] == pytest.approx(s['accuracy'], abs=1e-4)
    assert cv['max_likelihood']['confusion'] == s['confusion']
    for name in ('lr_all_C0.1', 'lr_all_C1', 'lr_diff_C0.1', 'lr_diff_C1', 'points_C0.1',
                 'points_C1'):
        assert 0.0 <= cv[name]['accuracy'] <= 1.0
        assert np.sum(cv[name]['confusion']) + cv[name]['n_unknown'] == m
    # the side-normal descriptors of every object's raw points are saved and separate the
    # generated boxes (flat faces) from the cylinders (round fronts)
    D = z['point_descriptors']
    assert D.shape == (m, 2) and np.isfinite(D).all()
    box = z['y'] == 0
    assert D[box, 0].min() > D[~box, 0].max(), D


def test_a_class_that_a_fold_leaves_without_objects_is_refused_before_any_fit(
        scan_files, tmp_path, monkeypatch, capsys):
    # cylinder only in learn33: its fold used to fail last, after every other fold's fit,
    # with "class 'cylinder' has 0 training objects"
    import beo_ros.scan_eval as scan_eval
    fits, real_fit = [], scan_eval.fit_models
    monkeypatch.setattr(scan_eval, 'fit_models', lambda *a, **k: fits.append(1) or
                        real_fit(*a, **k))
    rc = main(['--scans', *map(str, scan_files[:3]), '--scan-classes', 'box:0-1,cylinder:33',
               '--out', str(tmp_path / 'ev'), '--no-congeal', '--k', '2', '--max-iter', '3',
               '--grid', '16', '--voxel-size', '0.03125', '--yaw-step', '10', '--figures', '0'])
    assert rc == 2 and fits == []
    assert "holding out learn33 leaves class 'cylinder' 0 training object(s)" in \
        capsys.readouterr().err
    assert not (tmp_path / 'ev').exists()


def test_loso_counts_an_object_without_occupied_voxels_as_unknown(scan_files, tmp_path,
                                                                    monkeypatch):
    # a grid with no occupied voxel gets 'unknown' and no features: counted wrong, not a crash
    import contextlib
    import io
    import time
    import beo_ros.scan_eval as scan_eval
    real_fit = scan_eval.fit_models
    calls = []

    def fit(*a, **k):
        bank = real_fit(*a, **k)
        real_estimate = bank.estimate

        def estimate(grid, **kw):
            calls.append(1)
            if len(calls) == 1:
                return bank._no_object(np.zeros_like(grid), None, time.perf_counter())
            return real_estimate(grid, **kw)
        bank.estimate = estimate
        return bank
    monkeypatch.setattr(scan_eval, 'fit_models', fit)
    out = tmp_path / 'ev'
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        rc = main(['--scans', *map(str, scan_files), '--out', str(out), *SMALL_LOSO])
    assert rc == 0
    assert 'accuracy' in stdout.getvalue()   # the table follows a redirected stdout
    # the second-level rules are over the 7 objects with features: their counts say so (the
    # table printed n_correct/8 beside an accuracy of n_correct/7)
    rules = re.findall(r'accuracy (\S+) \((\d+)/(\d+),', stdout.getvalue())
    assert len(rules) == 7   # max_likelihood, 4 lr_*, 2 points_*
    for acc, correct, n in rules:
        assert n == '7' and float(acc) == pytest.approx(int(correct) / 7, abs=5e-4)
    res = json.loads((out / 'scan_eval.json').read_text())
    s, recs = res['summary'], res['objects']
    assert len(recs) == 8 and s['n_unknown'] == 1
    first = recs[0]
    assert first['pred'] == 'unknown' and not first['correct'] and first['features'] is None
    assert np.sum(s['confusion']) == 7
    assert s['accuracy'] <= 7 / 8
    assert len(np.load(out / 'oof_features.npz')['y']) == 7


def test_scene_cv_point_predictions_learn_from_the_descriptors_and_are_grouped():
    from beo_ros.core.bank import apply_point_classifier
    from beo_ros.core.scan_training import train_point_classifier
    rng = np.random.default_rng(1)
    F, y, groups = _features(rng)
    # r4 high for class 0, low for class 1; the loglik is biased toward class 0
    D = np.c_[np.where(y == 0, 0.85, 0.1) + rng.normal(0, 0.05, len(y)),
              np.where(y == 0, 0.8, 0.3) + rng.normal(0, 0.05, len(y))]
    comp = classifier_comparison(F, y, groups, variants=(), point_descriptors=D)
    assert comp['max_likelihood']['accuracy'] < 0.7
    assert comp['points_C1']['accuracy'] > 0.95 and comp['points_C0.1']['accuracy'] > 0.95
    # grouped: flipping the labels of a held-out scene that lies apart changes nothing for it
    te = groups == 's3'
    D2 = D.copy()
    D2[te] += 5.0
    y2 = y.copy()
    y2[te] = 1 - y2[te]
    p1, _ = scene_cv_point_predictions(F, D2, y, groups)
    p2, _ = scene_cv_point_predictions(F, D2, y2, groups)
    np.testing.assert_array_equal(p1[te], p2[te])
    # undefined descriptors: that object keeps the maximum-likelihood class
    D3 = D.copy()
    i = int(np.flatnonzero(y == 1)[0])
    D3[i] = np.nan
    p3, u3 = scene_cv_point_predictions(F, D3, y, groups)
    assert p3[i] == np.argmax(F[i, :, 0]) and not u3[i]
    # the trained classifier: binary fit as a calibrated two-class softmax
    from sklearn.linear_model import LogisticRegression
    clf = train_point_classifier(F[:, :, 0], D, y, 2)
    assert clf['coef'].shape == (2, 4) and set(clf) == {
        'mean', 'scale', 'coef', 'intercept', 'unknown_threshold', 'class_counts'}
    np.testing.assert_array_equal(clf['class_counts'], np.bincount(y, minlength=2))
    Z = (np.hstack([F[:, :, 0], D]) - clf['mean']) / clf['scale']
    lr = LogisticRegression(C=1.0, max_iter=2000).fit(Z, y)
    p, unknown = apply_point_classifier(clf, F[:, :, 0], D)
    np.testing.assert_allclose(p[:, 1], lr.predict_proba(Z)[:, 1], atol=1e-6)
    with pytest.raises(ValueError, match='NaN'):
        train_point_classifier(F[:, :, 0], D3, y, 2)


def test_loso_from_points_uses_the_deployment_path(scan_files, tmp_path, monkeypatch):
    from beo_ros.core.bank import ModelBank
    calls = []
    real = ModelBank.estimate_points

    def spy(self, *a, **k):
        calls.append(1)
        return real(self, *a, **k)
    monkeypatch.setattr(ModelBank, 'estimate_points', spy)
    out = tmp_path / 'fp'
    rc = main(['--scans', *map(str, scan_files), '--out', str(out), *SMALL_LOSO,
               '--from-points', '--scenes', '2'])
    assert rc == 0
    z = np.load(out / 'oof_features.npz')
    assert str(z['grid_source']) == 'estimate_points'
    res = json.loads((out / 'scan_eval.json').read_text())
    assert 'estimate_points' in res['summary']['protocol']
    assert len(z['y']) == 4 and np.isfinite(z['features']).all()
    assert z['point_descriptors'].shape == (4, 2)
    assert len(calls) == 4   # every object's estimate went through estimate_points


def test_loso_from_points_counts_a_refused_object_as_unknown(scan_files, tmp_path, monkeypatch,
                                                             capsys):
    # estimate_points refusing one object's points (fewer than 10 left after the outlier
    # removal) ended the whole run after the folds' fits, naming no scene or object
    from beo_ros.core.bank import ModelBank
    real = ModelBank.estimate_points
    calls = []

    def refuse_first(self, *a, **k):
        calls.append(1)
        if len(calls) == 1:
            raise ValueError('need at least 10 points, got 9')
        return real(self, *a, **k)
    monkeypatch.setattr(ModelBank, 'estimate_points', refuse_first)
    out = tmp_path / 'fp'
    rc = main(['--scans', *map(str, scan_files), '--out', str(out), *SMALL_LOSO,
               '--from-points', '--scenes', '2'])
    assert rc == 0
    objects = json.loads((out / 'scan_eval.json').read_text())['objects']
    assert [r['pred'] for r in objects].count('unknown') == 1
    bad = next(r for r in objects if r['pred'] == 'unknown')
    assert not bad['correct'] and bad['n_occupied'] == 0
    assert f"{bad['scene']}/{bad['object']}: estimate_points refused its points: need at least " \
        '10 points' in capsys.readouterr().err
    assert len(np.load(out / 'oof_features.npz')['y']) == 3


@pytest.mark.parametrize('argv, message', [
    (['--scenes', '-1'], 'argument --scenes: must be in [0, inf)'),
    (['--scene-folds', '1'], '--scene-folds must be 0'),
    (['--scene-folds', '-1'], '--scene-folds must be 0'),
])
def test_scene_options_are_checked(argv, message, tmp_path, capsys):
    from beo_ros.scan_eval import main
    with pytest.raises(SystemExit):
        main(['--scans', str(tmp_path / 'none.pcd'), '--out', str(tmp_path / 'o'), *argv])
    assert message in capsys.readouterr().err


def test_scene_groups_spread_and_fold_the_scenes():
    from types import SimpleNamespace
    from beo_ros.scan_eval import _scene_groups
    scenes = np.array(['s0', 's0', 's1', 's2', 's2', 's3', 's4'])
    args = SimpleNamespace(scenes=0, scene_folds=0)
    assert _scene_groups(args, scenes) == (['s0', 's1', 's2', 's3', 's4'],
                                           [['s0'], ['s1'], ['s2'], ['s3'], ['s4']])
    args = SimpleNamespace(scenes=3, scene_folds=0)   # spread over the list, ends included
    assert _scene_groups(args, scenes) == (['s0', 's2', 's4'], [['s0'], ['s2'], ['s4']])
    args = SimpleNamespace(scenes=0, scene_folds=2)   # every scene held out once
    assert _scene_groups(args, scenes)[1] == [['s0', 's2', 's4'], ['s1', 's3']]
    args = SimpleNamespace(scenes=3, scene_folds=5)   # more folds than scenes: one per scene
    assert _scene_groups(args, scenes)[1] == [['s0'], ['s2'], ['s4']]


def test_loso_interrupted_in_the_comparison_leaves_no_partial_result(scan_files, tmp_path,
                                                                     monkeypatch):
    # Ctrl-C or SIGTERM in the second-level comparison (after the folds) left
    # oof_features.npz alone in --out, without scan_eval.json
    import beo_ros.scan_eval as scan_eval

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(scan_eval, '_classifier_cv', interrupted)
    out = tmp_path / 'ev'
    rc = main(['--scans', *map(str, scan_files), '--out', str(out), *SMALL_LOSO])
    assert rc == 130
    assert not out.exists()


def test_figures_are_shared_by_classes_whose_names_share_a_prefix(monkeypatch):
    # a figure counted for every class whose name starts its title: 'cup' took the 'cupboard'
    # figures as its own, and --figures 4 drew two cupboards and no cup
    import types
    from beo_ros import scan_eval
    est = types.SimpleNamespace(label='cup', completion=np.zeros((4, 4, 4)))
    monkeypatch.setattr(scan_eval, 'fit_models', lambda *a, **k: None)
    monkeypatch.setattr(scan_eval, '_evaluate_object',
                        lambda args, objs, bank, i: ({}, None, np.zeros((1, 3)), est))
    objs = types.SimpleNamespace(names=['cup', 'cupboard'], y=np.array([1, 1, 1, 0, 0]),
                                 scenes=np.array(['s0'] * 5), object_ids=np.arange(5),
                                 subset=lambda sel: None)
    args = types.SimpleNamespace(k=1, max_iter=1, congeal=False, mirror=False, figures=4)
    figs = []
    scan_eval._evaluate_fold(args, objs, ['s0'], [], figs, [])
    assert sorted(f[0].split()[0] for f in figs) == ['cup', 'cup', 'cupboard', 'cupboard']
