"""Calibration of the completion's occupancy probabilities (beo_ros.core.calibration)."""
import json
import re

import numpy as np
import pytest
from scipy.special import expit, logit

from beo_ros import evaluate, train
from beo_ros.core.bank import ModelBank, ModelError
from beo_ros.core.calibration import (OccupancyCalibration, calibration_metrics,
                                      calibration_sums, check_arrays, metrics_from_sums)
from beo_ros.core.grid import GridSpec
from beo_ros.core.synthetic import primitive_shapes, random_partial_view
from beo_ros.core.training import fit_bank, fit_occupancy_calibration

N = 16


def overconfident(m, rng):
    """Model probabilities and truths whose real frequency is expit(0.5 logit(p) + 0.5): the
    model is too sure, as the linear-Gaussian class models are."""
    p = expit(rng.uniform(-12, 12, m))
    t = rng.random(m) < expit(0.5 * logit(p) + 0.5)
    return p, t


def test_calibration_recovers_a_known_miscalibration():
    rng = np.random.default_rng(0)
    cal = OccupancyCalibration().fit(*overconfident(200_000, rng))
    p, t = overconfident(100_000, rng)
    q = cal.predict(p)
    assert q.dtype == np.float32 and q.shape == p.shape
    # the map follows the true frequency closely away from the sparse extremes
    grid = expit(np.linspace(-6, 6, 25))
    np.testing.assert_allclose(cal.predict(grid), expit(0.5 * logit(grid) + 0.5), atol=0.04)
    raw, fixed = calibration_metrics(p, t), calibration_metrics(q, t)
    assert raw['ece'] > 0.05 and fixed['ece'] < 0.01
    assert fixed['log_loss'] < raw['log_loss'] - 0.05 and fixed['brier'] < raw['brier']
    # monotone in the model's probability, and the knots keep to [0, 1]
    s = np.sort(p)
    assert np.all(np.diff(cal.predict(s)) >= 0)
    assert check_arrays(cal.arrays_) == ''


def test_partial_fit_view_by_view_equals_one_fit():
    p, t = overconfident(30_000, np.random.default_rng(1))
    whole = OccupancyCalibration().fit(p, t)
    parts = OccupancyCalibration()
    for a, b in zip(np.array_split(p, 7), np.array_split(t, 7)):
        parts.partial_fit(a, b)
    np.testing.assert_allclose(parts.counts_, whole.counts_)
    np.testing.assert_allclose(parts.predict(p), whole.predict(p))
    # fit starts the counts again
    again = parts.fit(p[:100], t[:100])
    assert again is parts and parts.counts_[:, 2].sum() == 100
    # other bins: partial_fit does not drop the counts so far (it did, without a word)
    parts.bins = 100
    with pytest.raises(ValueError, match='bins is 100, the voxels counted so far are in 800'):
        parts.partial_fit(p[:10], t[:10])
    assert parts.counts_[:, 2].sum() == 100
    assert parts.fit(p[:10], t[:10]).counts_.shape == (100, 3)


def test_fitted_state_shares_no_array_with_the_caller():
    # partial_fit added to counts_ in place: it changed the caller's array given to
    # from_arrays and an arrays_ taken before the call
    p, t = overconfident(2_000, np.random.default_rng(2))
    cal = OccupancyCalibration(bins=50).fit(p, t)
    taken = cal.arrays_
    given = {k: v.copy() for k, v in taken.items()}
    kept = {k: v.copy() for k, v in taken.items()}
    loaded = OccupancyCalibration.from_arrays(given)
    cal.partial_fit(p, t)
    loaded.partial_fit(p, t)
    for arrays in (taken, given):
        for k in kept:
            np.testing.assert_array_equal(arrays[k], kept[k])
    # and the caller's arrays changed later do not change the fitted state
    again = OccupancyCalibration.from_arrays(given)
    snapshot = again.arrays_
    for arrays in (given, snapshot):
        for v in arrays.values():
            v[...] = 0
    np.testing.assert_array_equal(again.counts_, kept['counts'])
    np.testing.assert_array_equal(again.probability_, kept['probability'])


@pytest.mark.parametrize('p, t, message', [
    ([0.2, np.nan], [0, 1], 'finite probabilities'),
    ([0.2, 1.5], [0, 1], 'finite probabilities'),
    ([-0.1, 0.5], [0, 1], 'finite probabilities'),
    ([0.2, 0.5], [0, 1, 1], 'same size'),
    ([0.2, 0.5], [0, 2], 'boolean or 0/1'),
])
def test_calibration_refuses_bad_input(p, t, message):
    with pytest.raises(ValueError, match=message):
        OccupancyCalibration().fit(np.array(p), np.array(t))
    with pytest.raises(ValueError, match=message):
        calibration_metrics(np.array(p), np.array(t))


@pytest.mark.parametrize('bins', [1, 0, 2.5, True, 'many'])
def test_calibration_refuses_bad_bins(bins):
    with pytest.raises(ValueError, match='bins must be an integer >= 2'):
        OccupancyCalibration(bins=bins).fit([0.1, 0.9], [0, 1])


def test_isotonic_map_by_hand():
    # three voxels at 0.1 (one occupied) and one at 0.9 (empty): decreasing frequencies are
    # pooled into one level, weighted by the voxels (1 / 4, not the bins' mean 1 / 6), and
    # the map stays non-decreasing (not turned into a decreasing one)
    cal = OccupancyCalibration().fit([0.1, 0.1, 0.1, 0.9], [0, 0, 1, 0])
    np.testing.assert_allclose(cal.predict([0.0, 0.1, 0.5, 0.9, 1.0]), 0.25, atol=1e-7)
    # a perfect separation maps to 0 and 1 exactly, also beyond the knots
    cal = OccupancyCalibration().fit([0.01, 0.01, 0.99, 0.99], [0, 0, 1, 1])
    np.testing.assert_array_equal(cal.predict([0.0, 0.01, 0.99, 1.0]), [0, 0, 1, 1])
    assert cal.predict(0.5) == pytest.approx(0.5, abs=1e-7)   # interpolated between knots


def test_probabilities_0_and_1_fall_in_the_end_bins():
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter('error')   # no log(0) on the way to the clipped logit
        cal = OccupancyCalibration(bins=10).fit([0.0, 0.0, 1.0, 1.0, 1.0], [0, 0, 1, 1, 0])
    np.testing.assert_array_equal(cal.counts_[0], [0, 0, 2])
    np.testing.assert_array_equal(cal.counts_[-1], [3, 2, 3])
    assert cal.counts_[1:-1].sum() == 0
    table = np.array(calibration_sums(np.array([0.0, 1.0, 1.0]), np.array([0, 1, 0]),
                                      bins=10)['bins'])
    assert table.shape == (10, 3)
    np.testing.assert_array_equal(table[0], [0, 0, 1])
    np.testing.assert_array_equal(table[-1], [2, 1, 2])


def test_predict_needs_two_distinct_probabilities():
    with pytest.raises(ValueError, match='not fitted'):
        OccupancyCalibration().predict([0.5])
    with pytest.raises(ValueError, match='not fitted'):
        OccupancyCalibration().fit([0.3, 0.3], [0, 1]).predict([0.5])
    # two distinct probabilities in one bin: the message said two distinct ones were needed
    with pytest.raises(ValueError, match=r'in at least two of its 800 bins, each 0\.05 wide'):
        OccupancyCalibration().fit([0.3, 0.3001], [0, 1]).predict([0.5])


def test_metrics_by_hand():
    m = calibration_metrics(np.array([0.2, 0.8]), np.array([False, True]))
    assert m['voxels'] == 2
    assert m['brier'] == pytest.approx(0.04)
    assert m['log_loss'] == pytest.approx(-np.log(0.8))
    assert m['ece'] == pytest.approx(0.2)       # |0.2 - 0| / 2 + |0.8 - 1| / 2
    # sums add up over views, through JSON
    a = calibration_sums(np.array([0.2]), np.array([False]))
    b = json.loads(json.dumps(calibration_sums(np.array([0.8]), np.array([True]))))
    assert metrics_from_sums([a, b]) == pytest.approx(m)
    assert np.isnan(metrics_from_sums([])['brier'])


@pytest.mark.parametrize('bins', [0, -2, 2.5, True, '10', None, np.timedelta64(10)])
def test_metrics_refuse_a_bin_count_that_is_no_positive_integer(bins):
    # numpy's errors before ('list' argument must have no negative elements, ...); the
    # classifiers' expected calibration error was 0 for bins 0 (no bin)
    from beo_ros.core.classifier_training import expected_calibration_error
    for metric in (calibration_metrics, calibration_sums, expected_calibration_error):
        with pytest.raises(ValueError, match='bins must be an integer >= 1'):
            metric(np.array([0.2, 0.8]), np.array([False, True]), bins=bins)
    assert calibration_metrics(np.array([0.2, 0.8]), np.array([False, True]), bins=1)['ece'] \
        == pytest.approx(0.0)   # |0.5 - 0.5|


def broken(key, value):
    cal = OccupancyCalibration().fit(*overconfident(5000, np.random.default_rng(2)))
    arrays = dict(cal.arrays_)
    if value is None:
        del arrays[key]
    else:
        arrays[key] = value(arrays[key])
    return arrays


@pytest.mark.parametrize('key, value, message', [
    ('frequency', None, 'missing array'),
    ('probability', lambda a: a[::-1].copy(), 'increasing'),
    ('frequency', lambda a: a[::-1].copy(), 'non-decreasing'),
    ('frequency', lambda a: a[:-1], 'same length'),
    ('probability', lambda a: np.where(np.arange(len(a)) == 1, np.nan, a), 'finite'),
    ('frequency', lambda a: a * 2, r'\[0, 1\]'),
    ('probability', lambda a: a.astype(np.int64), 'floating point'),
    ('counts', lambda a: -a, 'counts'),
    ('counts', lambda a: a[:, :2], 'counts'),
    # each bound on its own (only a frequency twice too large, reversed maps and negative
    # counts were refused here: dropping any other check passed)
    ('frequency', lambda a: a.astype(np.int64), 'floating point'),
    ('frequency', lambda a: np.where(np.arange(len(a)) == 1, np.inf, a), 'finite'),
    ('probability', lambda a: np.where(np.arange(len(a)) == 0, -0.01, a), r'\[0, 1\]'),
    ('probability', lambda a: np.where(np.arange(len(a)) == len(a) - 1, 1.01, a), r'\[0, 1\]'),
    ('frequency', lambda a: np.where(np.arange(len(a)) == 0, -0.01, a), r'\[0, 1\]'),
    ('frequency', lambda a: np.where(np.arange(len(a)) == len(a) - 1, 1.01, a), r'\[0, 1\]'),
    ('probability', lambda a: np.where(np.arange(len(a)) == 1, a[0], a), 'increasing'),
    ('counts', lambda a: a[:1], 'counts'),
    ('counts', lambda a: np.where(np.arange(len(a))[:, None] == 3, np.inf, a), 'counts'),
    # counts that contradict themselves (columns: sum of p, occupied, voxels; passed before)
    ('counts', lambda a: a + [0, 0, 0.5], 'whole numbers'),
    ('counts', lambda a: a + [0, 0.5, 1], 'whole numbers'),
    ('counts', lambda a: a[:, [0, 2, 1]], 'cannot exceed its voxels'),   # occupied > voxels
    ('counts', lambda a: a[:, [2, 1, 0]], 'whole numbers'),   # sums and voxels swapped
    ('counts', lambda a: a + [1, 0, 0], 'cannot exceed its voxels'),     # sum of p > voxels
])
def test_check_arrays_names_what_is_wrong(key, value, message):
    reason = check_arrays(broken(key, value), 'x.npz')
    assert reason.startswith('x.npz') and re.search(message, reason)


def test_check_arrays_wants_two_knots_and_takes_a_fitted_map():
    arrays = broken('counts', lambda a: a)
    assert check_arrays(arrays) == ''
    # a bin's sum of probabilities may equal its voxels (all at p = 1), empty bins are zeros
    full = arrays['counts'].copy()
    full[-1] = [7, 7, 7]
    full[0] = [0, 0, 5]
    assert check_arrays(dict(arrays, counts=full)) == ''
    assert check_arrays(dict(arrays, counts=full.astype(np.int64))) == ''
    one = dict(arrays, probability=arrays['probability'][:1], frequency=arrays['frequency'][:1])
    assert 'same length >= 2' in check_arrays(one)


# ---------------------------------------------------------------------- in the bank
@pytest.fixture(scope='module')
def calibrated(tmp_path_factory):
    X, y, names = primitive_shapes(N, 8, np.random.default_rng(0))
    bank = fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3, classifier_views=1,
                    folds=2, seed=0)
    path = bank.save(tmp_path_factory.mktemp('cal') / 'model')
    return bank, path, X, y


def test_fit_bank_calibrates_by_default(calibrated):
    bank, path, X, _ = calibrated
    cal = bank.occupancy_calibration
    assert cal is not None and 'calibrated yes' in repr(bank)
    rep = bank.training['occupancy_calibration']
    assert rep['views'] == len(X) and rep['folds'] == 2 and rep['knots'] == len(cal.probability_)
    assert rep['raw']['voxels'] == cal.counts_[:, 2].sum()
    assert rep['calibrated_in_sample']['log_loss'] <= rep['raw']['log_loss']
    loaded = ModelBank.load(path)
    np.testing.assert_array_equal(loaded.occupancy_calibration.probability_, cal.probability_)
    np.testing.assert_array_equal(loaded.occupancy_calibration.frequency_, cal.frequency_)


def test_the_calibration_travels_to_worker_processes(calibrated):
    import pickle
    bank = calibrated[0]
    copy = pickle.loads(pickle.dumps(bank))   # how the node's process pool gets the bank
    np.testing.assert_array_equal(copy.occupancy_calibration.frequency_,
                                  bank.occupancy_calibration.frequency_)


def test_completion_applies_the_calibration_to_unknown_voxels_only(calibrated):
    bank, _, X, _ = calibrated
    raw_bank = ModelBank(bank.models, bank.spec, bank.classifier, bank.training,
                         bank.pose_components)
    rng = np.random.default_rng(5)
    for i in (0, 9):
        grid = random_partial_view(X[i].reshape(N, N, N) > 0.5, rng)[0]
        est, raw = bank.estimate(grid), raw_bank.estimate(grid)
        assert est.label == raw.label and est.yaw == raw.yaw
        unknown = grid < 0
        assert unknown.any()
        np.testing.assert_allclose(est.completion[unknown],
                                   bank.occupancy_calibration.predict(raw.completion[unknown]),
                                   atol=1e-3)   # raw.completion is rounded to float32 first
        np.testing.assert_array_equal(est.completion[~unknown], grid[~unknown] == 1)
        np.testing.assert_array_equal(est.variance, raw.variance)


def test_a_broken_calibration_file_is_refused(calibrated, tmp_path):
    import shutil
    from beo_ros.core.bank import _sha256
    bank, path, _, _ = calibrated
    shutil.copytree(path, tmp_path / 'm')
    arrays = dict(bank.occupancy_calibration.arrays_)
    arrays['probability'] = arrays['probability'][::-1].copy()
    np.savez_compressed(tmp_path / 'm' / 'calibration.npz', **arrays)
    mf = json.loads((tmp_path / 'm' / 'manifest.json').read_text())
    mf['files']['calibration.npz'] = _sha256(tmp_path / 'm' / 'calibration.npz')
    (tmp_path / 'm' / 'manifest.json').write_text(json.dumps(mf))
    with pytest.raises(ModelError, match='calibration.npz: the map must be increasing'):
        ModelBank.load(tmp_path / 'm')
    # counts that contradict themselves: more occupied voxels than voxels in a bin
    arrays = dict(bank.occupancy_calibration.arrays_)
    arrays['counts'] = arrays['counts'] + [0, 1, 0]
    np.savez_compressed(tmp_path / 'm' / 'calibration.npz', **arrays)
    mf['files']['calibration.npz'] = _sha256(tmp_path / 'm' / 'calibration.npz')
    (tmp_path / 'm' / 'manifest.json').write_text(json.dumps(mf))
    with pytest.raises(ModelError, match='calibration.npz: counts: .* cannot exceed its voxels'):
        ModelBank.load(tmp_path / 'm')
    (tmp_path / 'm' / 'calibration.npz').write_bytes(b'not a zip')
    mf['files']['calibration.npz'] = _sha256(tmp_path / 'm' / 'calibration.npz')
    (tmp_path / 'm' / 'manifest.json').write_text(json.dumps(mf))
    with pytest.raises(ModelError, match='calibration.npz: unreadable'):
        ModelBank.load(tmp_path / 'm')
    with pytest.raises(ModelError, match='not fitted'):
        ModelBank(bank.models, bank.spec, occupancy_calibration=OccupancyCalibration())


def test_fit_bank_calibration_options():
    X, y, names = primitive_shapes(N, 4, np.random.default_rng(0))
    spec = GridSpec(size=N)
    # without a classifier 'auto' means none; asked for, it is fitted all the same
    assert fit_bank(X, y, names, spec, k=2, pose_components=2, classifier_views=0,
                    folds=2).occupancy_calibration is None
    assert fit_bank(X, y, names, spec, k=2, pose_components=2, classifier_views=0, folds=2,
                    calibration_views=1).occupancy_calibration is not None
    masks = np.ones_like(X, dtype=bool)
    with pytest.raises(ValueError, match='needs whole training objects'):
        fit_bank(X, y, names, spec, k=2, masks=masks, classifier_views=0, calibration_views=1)
    for bad in (-1, 1.5, True, 'yes'):
        with pytest.raises(ValueError, match='calibration_views must be'):
            fit_bank(X, y, names, spec, k=2, calibration_views=bad)
    with pytest.raises(ValueError, match='views must be an integer >= 1'):
        fit_occupancy_calibration(X, y, names, spec, k=2, folds=2, views=0)
    for fn, kw in ((fit_bank, dict(classifier_views=0, calibration_views=1)),
                   (fit_occupancy_calibration, {})):
        with pytest.raises(ValueError, match='needs folds >= 2'):
            fn(X, y, names, spec, k=2, folds=1, **kw)


def test_eval_reports_the_calibration_of_the_completion(calibrated, tmp_path, capsys):
    bank, path, X, y = calibrated
    np.savez(tmp_path / 'test.npz', voxels=np.packbits(X.astype(np.uint8), axis=1), labels=y,
             classes=np.array(bank.classes), shape=np.array([N, N, N]))
    assert evaluate.main(['--model', str(path), '--data', str(tmp_path / 'test.npz'),
                          '--max-objects', '4', '--out', str(tmp_path / 'e')]) == 0
    s = json.loads((tmp_path / 'e' / 'eval.json').read_text())['partial']
    recs = [json.loads(line) for line in (tmp_path / 'e' / 'records.jsonl').read_text()
            .splitlines()]
    sums = [r['voxels'] for r in recs if r['mode'] == 'partial']
    assert len(sums) == 4 and s['completion_calibration'] == pytest.approx(
        metrics_from_sums(sums))
    assert 0 < s['completion_calibration']['voxels'] == sum(v['voxels'] for v in sums)
    assert 'unknown voxels of the partial views: Brier' in capsys.readouterr().out


def test_train_calibrate_only_keeps_the_rest(calibrated, tmp_path, capsys):
    import shutil
    bank, path, X, y = calibrated
    data = tmp_path / 'train.npz'
    np.savez(data, voxels=np.packbits(X.astype(np.uint8), axis=1), labels=y,
             classes=np.array(bank.classes), shape=np.array([N, N, N]))
    shutil.copytree(path, tmp_path / 'm')
    (tmp_path / 'm' / 'calibration.npz').unlink()
    mf = json.loads((tmp_path / 'm' / 'manifest.json').read_text())
    del mf['files']['calibration.npz']
    (tmp_path / 'm' / 'manifest.json').write_text(json.dumps(mf))
    assert ModelBank.load(tmp_path / 'm').occupancy_calibration is None
    assert train.main([str(data), '-o', str(tmp_path / 'm'), '--calibrate-only']) == 0
    again = ModelBank.load(tmp_path / 'm')
    # the same folds, seed and views: the same calibration as fit_bank's
    np.testing.assert_array_equal(again.occupancy_calibration.frequency_,
                                  bank.occupancy_calibration.frequency_)
    for name in [f for f in mf['files'] if f != 'calibration.npz']:
        assert (tmp_path / 'm' / name).read_bytes() == (path / name).read_bytes()
    # another training set is refused, and nothing is written
    np.savez(data, voxels=np.packbits(X[:-2].astype(np.uint8), axis=1), labels=y[:-2],
             classes=np.array(bank.classes), shape=np.array([N, N, N]))
    before = (tmp_path / 'm' / 'manifest.json').read_bytes()
    assert train.main([str(data), '-o', str(tmp_path / 'm'), '--calibrate-only']) == 2
    assert 'was trained on 16 objects' in capsys.readouterr().err
    assert (tmp_path / 'm' / 'manifest.json').read_bytes() == before


@pytest.mark.parametrize('extra, message', [
    (['--calibrate-only', '--calibration-views', '0'], '--calibration-views must be >= 1'),
    (['--calibration-views', '-1'], '--calibration-views must be >= 0'),
    (['--scans', '--calibration-views', '1'], 'need whole objects, not --scans'),
    # silently ignored before: the model's own settings are kept
    (['--calibrate-only', '--k', '5'], 'not used with --calibrate-only'),
    (['--calibrate-only', '--congeal', '--oof-out', 'o.npz'],
     'not used with --calibrate-only (the model\'s own settings are kept): --oof-out, '
     '--congeal, --verifier-views'),
])
def test_train_calibration_arguments_refused(tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit) as ei:
        train.main([str(tmp_path / 'd.npz'), '-o', str(tmp_path / 'm'), '--verifier-views',
                    '0'] + extra)
    assert ei.value.code == 2
    assert message in capsys.readouterr().err


def test_refit_leaves_no_map_of_the_earlier_fit():
    rng = np.random.default_rng(0)
    p = rng.random(500)
    cal = OccupancyCalibration().fit(p, rng.random(500) < p)
    cal.predict([0.1, 0.9])
    cal.fit(np.full(50, 0.3), np.zeros(50, bool))   # one distinct probability: no map
    with pytest.raises(ValueError):
        cal.predict([0.1, 0.9])
