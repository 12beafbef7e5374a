"""The orientation verifier: features, exported trees equal to scikit-learn's, the turn it
picks inside ModelBank.estimate, model-file checks, deterministic training rows."""
import pickle

import numpy as np
import pytest

from beo_ros.core.bank import ModelBank, ModelError
from beo_ros.core.grid import GridSpec, rotate_grid, yaw_error
from beo_ros.core.synthetic import random_partial_view
from beo_ros.core.training import check_grid_size, fit_bank, verifier_training_set
from beo_ros.core.verifier import (OrientationVerifier, check_arrays, quarter_turned_features,
                                   turned_features, verifier_features)
from _shapes import N, asymmetric_shapes

PARAMS = dict(max_iter=25, learning_rate=0.3)


def test_features_are_pooled_label_fractions():
    rng = np.random.default_rng(0)
    g = rng.integers(-1, 2, size=(16, 16, 16)).astype(np.int8)
    f = verifier_features(g)
    assert f.shape == (3 * 512,) and f.dtype == np.float32
    occ, free, unk = f.reshape(3, 8, 8, 8)
    np.testing.assert_allclose(occ + free + unk, 1.0, atol=1e-6)
    assert occ[0, 0, 0] == pytest.approx((g[:2, :2, :2] == 1).mean())
    assert unk[7, 3, 5] == pytest.approx((g[14:, 6:8, 10:12] == -1).mean())
    # turning by a hypothesis yaw looks at the view from the model's frame
    t = turned_features(g, [0.0, np.pi / 2])
    np.testing.assert_array_equal(t[0], f)
    np.testing.assert_array_equal(t[1], verifier_features(rotate_grid(g, -np.pi / 2, fill=-1)))
    # the four quarter turns of a hypothesis from one resampling
    for yaw in (0.0, 0.7, -2.3):
        np.testing.assert_array_equal(quarter_turned_features(g, yaw), turned_features(
            g, yaw + np.arange(4) * np.pi / 2))
    for bad in (np.zeros((12, 12, 12)), np.zeros((16, 16, 8)), np.zeros((16, 16))):
        with pytest.raises(ValueError, match='multiple of 8'):
            verifier_features(bad)
    # a grid size the verifier cannot pool: the error names the way out, training without one
    with pytest.raises(ValueError, match=r'without an orientation verifier \(--verifier-views 0'):
        verifier_features(np.zeros((12, 12, 12)))


@pytest.fixture(scope='module')
def trained():
    X, y = asymmetric_shapes(10, np.random.default_rng(0))
    F, turn, obj = verifier_training_set(X, N, views=3, seed=0)
    return X, y, F, turn, obj, OrientationVerifier(**PARAMS).fit(F, turn, y[obj], N)


def test_verifier_views_start_no_more_processes_than_chunks(trained, monkeypatch):
    # before: --jobs 40 on 7 objects (3 chunks here, 1 with the real 64-object chunks) forked
    # 40 worker processes at once (the pool starts all it is given), 37 of them idle
    import concurrent.futures
    X = trained[0]
    monkeypatch.setattr('beo_ros.core.training.VERIFIER_CHUNK', 3)  # 3 chunks of 7 objects
    pools = []
    real = concurrent.futures.ProcessPoolExecutor

    def pool(workers, **kwargs):
        pools.append(workers)
        return real(workers, **kwargs)
    monkeypatch.setattr(concurrent.futures, 'ProcessPoolExecutor', pool)
    rows = verifier_training_set(X[:7], N, views=1, seed=0, processes=40)
    assert pools == [3]
    verifier_training_set(X[:3], N, views=1, seed=0, processes=40)   # one chunk: no pool
    assert pools == [3]
    for a, b in zip(rows, verifier_training_set(X[:7], N, views=1, seed=0)):
        np.testing.assert_array_equal(a, b)


def test_training_rows_are_the_true_pose_and_its_turns(trained, monkeypatch):
    X, y, F, turn, obj, _ = trained
    assert F.shape == (len(X) * 3 * 4, 1536)
    assert (np.bincount(turn) == len(X) * 3).all()
    assert (np.bincount(obj) == 12).all()
    # the same rows whatever the number of processes (each chunk has its own stream)
    monkeypatch.setattr('beo_ros.core.training.VERIFIER_CHUNK', 3)  # 3 chunks of 7 objects
    one = verifier_training_set(X[:7], N, views=1, seed=0)
    two = verifier_training_set(X[:7], N, views=1, seed=0, processes=2)
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(one[2], np.repeat(np.arange(7), 4))
    F3, _, _ = verifier_training_set(X, N, views=3, seed=1)
    assert not np.array_equal(F3, F)
    # turn 0 is the view turned into the model's frame by its true yaw: its occupied cells
    # lie where the canonical object is (pooled to 8^3), more than those of the half turn
    from beo_ros.core.verifier import verifier_features
    canon = np.stack([verifier_features(np.where(x.reshape((N,) * 3) > 0.5, 1, 0)
                                        .astype(np.int8))[:512] for x in X])
    occ = F[:, :512]
    match = (occ * canon[obj]).sum(axis=1)
    assert np.mean(match[turn == 0] > match[turn == 2]) > 0.9


def test_each_chunk_of_verifier_views_has_its_own_random_stream(monkeypatch):
    # two copies of one object in chunks of one: the same seed must still give each chunk
    # other views (one stream for all chunks repeated them)
    monkeypatch.setattr('beo_ros.core.training.VERIFIER_CHUNK', 1)
    X, _ = asymmetric_shapes(1, np.random.default_rng(0))
    F, _, obj = verifier_training_set(X[[0, 0]], N, views=1, seed=0)
    np.testing.assert_array_equal(obj, np.repeat([0, 1], 4))
    assert not np.array_equal(F[obj == 0], F[obj == 1])


def test_training_views_are_turned_by_the_true_yaw_and_quarter_turns_with_a_small_jitter(
        monkeypatch):
    # turn t of a row: the view turned into the model's frame by its true yaw + t x 90 deg
    # (counter-clockwise, as ModelBank._verify_turns asks), within +-5 deg of jitter
    import beo_ros.core.training as training
    from beo_ros.core.training import verifier_training_set
    X, _ = asymmetric_shapes(2, np.random.default_rng(0))
    log = []
    real_view = training.random_partial_view

    def view(occ, rng):
        out = real_view(occ, rng)
        log.append(out[1])
        return out

    def turned(grid, yaws):
        log.append(np.asarray(yaws, dtype=np.float64))
        return np.zeros((len(yaws), 3 * (N // 2) ** 3), np.float32)

    monkeypatch.setattr(training, 'random_partial_view', view)
    monkeypatch.setattr(training, 'turned_features', turned)
    _, turn, _ = verifier_training_set(X, N, views=3, seed=0)
    assert len(log) == 2 * len(X) * 3
    off = np.array([np.rad2deg((yaws - yaw - np.arange(4) * np.pi / 2 + np.pi) % (2 * np.pi)
                               - np.pi) for yaw, yaws in zip(log[::2], log[1::2])])
    assert np.abs(off).max() <= 5.0
    assert np.abs(off).max() > 2.0   # jittered
    np.testing.assert_array_equal(turn, np.tile(np.arange(4), len(off)))


def test_exported_trees_give_scikit_learns_probabilities(trained):
    from sklearn.ensemble import HistGradientBoostingClassifier
    X, y, F, turn, obj, v = trained
    assert v.classes_ == [0, 1] and v.n_features_in_ == 1536
    for c in (0, 1):
        m = y[obj] == c
        ref = HistGradientBoostingClassifier(max_iter=25, learning_rate=0.3, max_leaf_nodes=15,
                                             l2_regularization=1.0, early_stopping=False,
                                             random_state=0).fit(F[m], turn[m])
        np.testing.assert_allclose(np.exp(v.predict_log_proba(c, F[m][:30])),
                                   ref.predict_proba(F[m][:30]), atol=1e-5)


@pytest.mark.parametrize('shape', [(2, 1535), (2, 1537), (3000,), (1, 10), (2, 2, 1536)])
def test_predict_refuses_rows_of_another_width(trained, shape):
    # a narrower row read the next row's features (or raised numpy's IndexError), a wider one
    # its first 1536 columns: probabilities without a word
    *_, F, turn, obj, v = trained
    with pytest.raises(ValueError, match=r'X must be \(m, 1536\) verifier features, got shape'):
        v.predict_log_proba(0, np.zeros(shape))
    np.testing.assert_array_equal(v.predict_log_proba(0, F[0]), v.predict_log_proba(0, F[:1]))


def test_it_tells_the_turn_of_new_views(trained):
    *_, v = trained
    Xt, yt = asymmetric_shapes(4, np.random.default_rng(7))
    rng = np.random.default_rng(3)
    right = []
    for i in range(len(Xt)):
        for _ in range(3):
            g, yaw, *_ = random_partial_view(Xt[i].reshape((N,) * 3) > 0.5, rng)
            lp = v.predict_log_proba(yt[i], turned_features(g, yaw + np.arange(4) * np.pi / 2))
            right.append(np.argmax(lp[:, 0]) == 0)
    assert np.mean(right) >= 0.75, np.mean(right)  # chance: 0.25


def test_training_set_without_views_or_objects_says_so():
    # numpy's 'need at least one array to concatenate' (a float count: a TypeError) before
    X, y = asymmetric_shapes(1, np.random.default_rng(0))
    for views in (0, -1, 1.5):
        with pytest.raises(ValueError, match='verifier views must be an integer >= 1'):
            verifier_training_set(X, N, views=views)
    with pytest.raises(ValueError, match='needs objects'):
        verifier_training_set(X[:0], N, views=2)


@pytest.mark.parametrize('n', [N // 2, float(N)])
def test_training_set_names_grids_of_another_size(n):
    # numpy's 'cannot reshape array of size 4096 into shape (8,8,8)' (a float n: a TypeError)
    X, y = asymmetric_shapes(1, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r'needs objects X of n\^3 = .*\^3 voxels, got shape'):
        verifier_training_set(X, n, views=1)


def test_fit_checks_its_input():
    v = OrientationVerifier()
    with pytest.raises(ValueError, match='same m'):
        v.fit(np.zeros((4, 1536)), np.zeros(3), np.zeros(4), 16)
    with pytest.raises(ValueError, match='quarter turns'):
        v.fit(np.zeros((4, 1536)), np.array([0, 1, 2, 4]), np.zeros(4), 16)
    with pytest.raises(ValueError, match='all four turns'):
        v.fit(np.zeros((4, 1536)), np.array([0, 1, 2, 2]), np.zeros(4), 16)
    for weight in (-1, np.nan, np.inf):
        with pytest.raises(ValueError, match='weight must be finite and >= 0'):
            OrientationVerifier(weight=weight).fit(np.zeros((4, 1536)), np.arange(4),
                                                   np.zeros(4), 16)


def test_export_refuses_trees_it_cannot_walk():
    # reachable only by a direct call (fit gives every class 4 turns and the same iterations)
    from sklearn.ensemble import HistGradientBoostingClassifier
    from beo_ros.core.verifier import export_trees
    rng = np.random.default_rng(0)
    X = rng.random((40, 5))

    def clf(turns, max_iter):
        return HistGradientBoostingClassifier(max_iter=max_iter, early_stopping=False).fit(
            X, np.arange(40) % turns)
    with pytest.raises(ValueError, match='predict the 4 turns'):
        export_trees([(0, clf(2, 2))], 1.0, 16)
    with pytest.raises(ValueError, match='same number of iterations'):
        export_trees([(0, clf(4, 2)), (1, clf(4, 3))], 1.0, 16)
    a = export_trees([(0, clf(4, 2)), (1, clf(4, 2))], 1.0, 16)
    assert a['roots'].shape == (2, 2, 4)


def test_probabilities_do_not_overflow_and_the_weight_is_loaded(trained):
    # the log-softmax subtracts the largest score: a common shift of the baseline (here 1000,
    # exp() overflows) changes nothing
    *_, F, turn, obj, v = trained
    arrays = dict(v.arrays_, baseline=v.arrays_['baseline'] + 1000.0,
                  weight=np.asarray(250.0))
    shifted = OrientationVerifier.from_arrays(arrays)
    np.testing.assert_allclose(shifted.predict_log_proba(0, F[:20]),
                               v.predict_log_proba(0, F[:20]), atol=1e-9)
    assert shifted.weight == 250.0   # not the default


@pytest.fixture(scope='module')
def bank(trained):
    X, y, *_, v = trained
    b = fit_bank(X, y, ['ell', 'step'], GridSpec(size=N), k=4, pose_components=4,
                 classifier_views=0, seed=0)
    return ModelBank(b.models, b.spec, verifier=v)


def test_estimate_takes_the_turn_with_the_best_combined_score(bank, monkeypatch):
    X, _ = asymmetric_shapes(1, np.random.default_rng(9))
    g, yaw, *_ = random_partial_view(X[0].reshape((N,) * 3) > 0.5, np.random.default_rng(2))
    plain = bank.estimate(g, verify=False)
    assert 'orientation_check' in plain.timings
    # a verifier sure of the 180° turn wins over any likelihood difference
    def sure_of_the_flip(c, F):  # rows: the refined yaw and its 90, 180, 270° turns
        lp = np.full((len(F), 4), np.log(1e-6))
        lp[2, 0] = np.log(1 - 3e-6)
        return lp

    monkeypatch.setattr(bank.verifier, 'predict_log_proba', sure_of_the_flip)
    monkeypatch.setattr(bank.verifier, 'weight', 1e9)
    turned = bank.estimate(g)
    assert np.rad2deg(yaw_error(turned.yaw, plain.yaw + np.pi)) < 1e-6
    # the hypotheses lead with the chosen (turned) yaw and still list the likelihood's own
    # choice with its pooled score; nothing else within 10 degrees of the turned yaw
    assert turned.hypotheses[0].yaw == pytest.approx(turned.yaw)
    assert turned.hypotheses[0].label == turned.label
    assert turned.hypotheses[1].yaw == pytest.approx(plain.yaw)
    assert turned.hypotheses[1].score == pytest.approx(plain.hypotheses[0].score)
    assert all(np.rad2deg(yaw_error(h.yaw, turned.yaw)) >= 10 for h in turned.hypotheses[1:])
    # the completion follows the chosen yaw (it is the model's, turned)
    assert not np.allclose(turned.completion, plain.completion)
    # a verifier without an opinion leaves the likelihood's choice
    monkeypatch.setattr(bank.verifier, 'predict_log_proba',
                        lambda c, F: np.full((len(F), 4), np.log(0.25)))
    assert bank.estimate(g).yaw == pytest.approx(plain.yaw)
    # a given yaw is never turned
    assert bank.estimate(g, yaw=0.3).yaw == pytest.approx(0.3)


def _view():
    X, _ = asymmetric_shapes(1, np.random.default_rng(9))
    return random_partial_view(X[0].reshape((N,) * 3) > 0.5, np.random.default_rng(2))[0]


def test_the_verifiers_rows_are_the_counter_clockwise_quarter_turns(bank, monkeypatch):
    # row t of the verifier's features is the refined yaw + t x 90 deg: a verifier sure of
    # row 1 turns the yaw by +90 deg, of row 3 by -90 deg
    g = _view()
    plain = bank.estimate(g, verify=False)
    monkeypatch.setattr(bank.verifier, 'weight', 1e9)
    for row, turn in ((1, 90.0), (3, -90.0)):
        def sure(c, F, row=row):
            lp = np.full((len(F), 4), np.log(1e-6))
            lp[row, 0] = np.log(1 - 3e-6)
            return lp
        monkeypatch.setattr(bank.verifier, 'predict_log_proba', sure)
        got = bank.estimate(g).yaw
        assert np.rad2deg(yaw_error(got, plain.yaw + np.deg2rad(turn))) < 1e-6


def test_a_turn_wins_by_likelihood_plus_weight_times_log_probability(bank, monkeypatch):
    # the score of turn t: exact log-likelihood + weight x log P(turn 0 | row t); a turn of a
    # lower likelihood wins just above the weight that makes up the difference, not below
    g = _view()
    _, per = bank.features(g)
    c = int(np.argmax([p['exact']['loglik'] for p in per]))
    per_c = bank._refine(g, c, per[c])
    y0, ll0 = per_c['yaw'], per_c['exact']['loglik']
    ll = [bank.engine.exact(g, c, y0 + t * np.pi / 2, with_prediction=False)['loglik']
          for t in range(4)]
    t = int(np.argmin(ll))   # a turn of a lower likelihood than the refined yaw's
    assert ll[t] < ll0
    logp = np.log(np.full(4, 0.01))
    logp[0], logp[t] = np.log(0.3), np.log(0.6)
    monkeypatch.setattr(bank.verifier, 'predict_log_proba',
                        lambda c, F: np.stack([logp, np.zeros(4), np.zeros(4), np.zeros(4)], 1))
    w = (ll0 - ll[t]) / (logp[t] - logp[0])
    monkeypatch.setattr(bank.verifier, 'weight', 1.01 * w)
    out = bank._verify_turns(g, c, dict(per_c))
    assert out['turned'] == t and out['yaw'] == pytest.approx(y0 + t * np.pi / 2)
    assert out['exact']['loglik'] == pytest.approx(ll[t])
    monkeypatch.setattr(bank.verifier, 'weight', 0.99 * w)
    out = bank._verify_turns(g, c, dict(per_c))
    assert 'turned' not in out and out['yaw'] == y0


def test_a_turn_the_verifier_rates_no_higher_than_the_refined_yaw_is_not_solved(bank,
                                                                                  monkeypatch):
    # only the turns the verifier prefers to the refined yaw are solved: on a tie none is,
    # however much more likely it would be
    g = _view()
    _, per = bank.features(g)
    per_c = bank._refine(g, 0, per[0])
    solved = []

    def exact(obs, c, yaw, per_c):
        solved.append(yaw)
        return {'loglik': per_c['exact']['loglik'] + 100.0}

    monkeypatch.setattr(bank, '_exact', exact)
    monkeypatch.setattr(bank.engine, 'add_prediction', lambda ex, obs, c: ex)
    monkeypatch.setattr(bank.verifier, 'predict_log_proba',
                        lambda c, F: np.full((len(F), 4), np.log(0.25)))
    out = bank._verify_turns(g, 0, dict(per_c))
    assert solved == [] and 'turned' not in out and out['yaw'] == per_c['yaw']


def test_the_real_verifier_does_not_hurt_on_asymmetric_shapes(bank):
    Xt, yt = asymmetric_shapes(4, np.random.default_rng(5))
    rng = np.random.default_rng(1)
    err = {False: [], True: []}
    for i in range(len(Xt)):
        g, yaw, *_ = random_partial_view(Xt[i].reshape((N,) * 3) > 0.5, rng)
        for verify in err:
            err[verify].append(np.rad2deg(yaw_error(bank.estimate(g, verify=verify).yaw, yaw)))
    assert np.mean(np.array(err[True]) <= 15) >= np.mean(np.array(err[False]) <= 15)


def test_verifier_survives_save_load_and_pickling(bank, tmp_path):
    path = bank.save(tmp_path / 'v')
    again = ModelBank.load(path)
    assert again.verifier.classes_ == [0, 1] and again.verifier.weight == bank.verifier.weight
    X, _ = asymmetric_shapes(1, np.random.default_rng(4))
    g, *_ = random_partial_view(X[1].reshape((N,) * 3) > 0.5, np.random.default_rng(0))
    e1, e2, e3 = bank.estimate(g), again.estimate(g), pickle.loads(pickle.dumps(again)).estimate(g)
    assert e1.yaw == e2.yaw == e3.yaw and e1.label == e2.label == e3.label
    # the trees themselves: the same probabilities for views at every turn
    F = turned_features(g, np.arange(4) * np.pi / 2 + 0.3)
    unpickled = pickle.loads(pickle.dumps(again)).verifier
    for c in (0, 1):
        ref = bank.verifier.predict_log_proba(c, F)
        assert np.ptp(ref) > 0.1   # not a constant: the comparison can tell trees apart
        np.testing.assert_allclose(again.verifier.predict_log_proba(c, F), ref, rtol=1e-6)
        np.testing.assert_allclose(unpickled.predict_log_proba(c, F), ref, rtol=1e-6)


@pytest.mark.parametrize('change, msg', [
    (lambda a: a.pop('roots'), 'missing'),
    (lambda a: a.__setitem__('left', a['left'] + 10 ** 6), 'left indices'),
    (lambda a: a.__setitem__('grid_size', np.asarray(32)), '32'),
    (lambda a: a.__setitem__('classes', np.array([0, 5])), 'distinct indices'),
    (lambda a: a.__setitem__('feature', np.full_like(a['feature'], 2000)), 'feature indices'),
    (lambda a: a.__setitem__('value', a['value'] * np.nan), 'finite'),
    (lambda a: a.__setitem__('value', a['value'][:-1]), 'differ in length'),
    # a bare TypeError (not naming verifier.npz) or, for float class indices, truncated
    (lambda a: a.__setitem__('weight', np.array([1.0, 2.0])), 'weight must be a scalar'),
    (lambda a: a.__setitem__('weight', np.asarray('1000')), 'weight has dtype'),
    (lambda a: a.__setitem__('grid_size', np.array([N, N])), 'grid_size must be a scalar'),
    (lambda a: a.__setitem__('classes', a['classes'] + 0.5), 'classes has dtype'),
    (lambda a: a.__setitem__('classes', a['classes'][None]), '1-D'),
    (lambda a: a.__setitem__('left', a['left'] + 0.5), 'left has dtype'),
    (lambda a: a.__setitem__('is_leaf', a['is_leaf'] + 0.5), 'is_leaf has dtype'),
    # every check on its own: shapes, index ranges, signs, depth
    (lambda a: a.__setitem__('roots', a['roots'][:, :, :3]), 'roots, baseline or depth'),
    (lambda a: a.__setitem__('baseline', a['baseline'][:, :3]), 'roots, baseline or depth'),
    (lambda a: a.__setitem__('depth', a['depth'][:1]), 'roots, baseline or depth'),
    (lambda a: a.__setitem__('classes', np.array([1, 1])), 'distinct indices'),
    (lambda a: a.__setitem__('classes', np.array([-1, 1])), 'distinct indices'),
    (lambda a: a.__setitem__('right', a['right'] - 10 ** 6), 'right indices'),
    (lambda a: a.__setitem__('roots', a['roots'] + 10 ** 6), 'roots indices'),
    (lambda a: a.__setitem__('feature', np.full_like(a['feature'], -1)), 'feature indices'),
    (lambda a: a.__setitem__('weight', np.asarray(-1.0)), 'weight >= 0'),
    (lambda a: a.__setitem__('weight', np.asarray(np.inf)), 'must be finite'),
    (lambda a: a.__setitem__('depth', a['depth'] * 0 + 65), 'depth out of range'),
    (lambda a: a.__setitem__('depth', a['depth'] * 0 - 1), 'depth out of range'),
])
def test_bad_verifier_files_are_refused(bank, tmp_path, change, msg):
    import hashlib
    import json
    path = bank.save(tmp_path / 'bad')
    arrays = dict(np.load(path / 'verifier.npz'))
    change(arrays)
    assert msg in (check_arrays(arrays, 2, N) or '')
    np.savez_compressed(path / 'verifier.npz', **arrays)
    m = json.loads((path / 'manifest.json').read_text())
    m['files']['verifier.npz'] = hashlib.sha256((path / 'verifier.npz').read_bytes()).hexdigest()
    (path / 'manifest.json').write_text(json.dumps(m))
    with pytest.raises(ModelError, match='verifier.npz'):
        ModelBank.load(path)


def test_bank_refuses_an_unfitted_or_mismatched_verifier(bank):
    with pytest.raises(ModelError, match='not fitted'):
        ModelBank(bank.models, bank.spec, verifier=OrientationVerifier())
    with pytest.raises(ModelError, match='distinct indices below 1'):
        ModelBank(bank.models[:1], bank.spec, verifier=bank.verifier)


def test_fit_bank_fits_a_verifier_when_asked():
    X, y = asymmetric_shapes(6, np.random.default_rng(0))
    b = fit_bank(X, y, ['ell', 'step'], GridSpec(size=N), k=3, pose_components=3,
                 classifier_views=0, verifier_views=1)
    assert b.verifier is not None and b.training['verifier_views'] == 1
    for bad, msg in ((-1, 'verifier_views'), (1.5, 'verifier_views')):
        with pytest.raises(ValueError, match=msg):
            fit_bank(X, y, ['ell', 'step'], GridSpec(size=N), k=3, verifier_views=bad)
    with pytest.raises(ValueError, match=r'multiple of 8 \(got 12\).*--verifier-views 0'):
        fit_bank(X[:, :12 ** 3], y, ['ell', 'step'], GridSpec(size=12), k=3, verifier_views=1)
    with pytest.raises(ValueError, match=r'multiple of 8, got 12.*--verifier-views 0'):
        check_grid_size(12, verifier=True)
