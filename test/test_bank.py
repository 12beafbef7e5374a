"""ModelBank and InferenceEngine: persistence, the estimate contract, the batched pose search, the
exact posterior formula, load errors, classifier and the point-cloud entry point."""
import dataclasses
import json
import os
import shutil
import warnings
from decimal import Decimal
from fractions import Fraction
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from beo_ros.core.bank import ClassModel, ModelBank, ModelError, load_models
from beo_ros.core.grid import GridSpec, rotate_grid, yaw_error, yaw_source_index
from beo_ros.core.inference import InferenceEngine
from beo_ros.core.shape import DESCRIPTOR_NAMES
from beo_ros.core.synthetic import (make_tiny_bank, partial_view, primitive_shapes,
                                    render_view_points)
from _shapes import asymmetric_shapes

N = 16


@pytest.fixture(scope='module')
def tiny_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp('tiny') / 'm'
    make_tiny_bank(path)
    return path


@pytest.fixture(scope='module')
def tiny(tiny_dir):
    return ModelBank.load(tiny_dir)


def views(seed=0):
    """A complete box at yaw 0 and a partial view of a rotated cylinder."""
    X, _, _ = primitive_shapes(N, 1, np.random.default_rng(100 + seed))
    box = X[0].reshape((N,) * 3).astype(np.int8)
    cyl = X[1].reshape((N,) * 3) > 0.5
    part = partial_view(rotate_grid(cyl.astype(np.uint8), 0.7).astype(bool), 0.4,
                        np.deg2rad(30))
    return box, part


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ---------------------------------------------------------------------- persistence / contract
def test_save_load_round_trip_gives_identical_estimates(tiny_dir, tiny, tmp_path):
    fresh = make_tiny_bank()
    assert tiny.classes == fresh.classes == ['box', 'cylinder']
    assert tiny.spec == fresh.spec
    for a, b in zip(tiny.models, fresh.models):
        np.testing.assert_array_equal(a.W, b.W)
        np.testing.assert_array_equal(a.mean, b.mean)
        assert a.noise_variance == b.noise_variance
        np.testing.assert_array_equal(a.coarse_noise_map, b.coarse_noise_map)
    for g in views():
        e1, e2 = tiny.estimate(g), fresh.estimate(g)
        assert e1.label == e2.label and e1.yaw == e2.yaw
        np.testing.assert_array_equal(e1.completion, e2.completion)
        assert e1.scores == e2.scores
    # saving the loaded bank again gives the same files
    again = tiny.save(tmp_path / 'again')
    m1 = json.loads((tiny_dir / 'manifest.json').read_text())
    m2 = json.loads((again / 'manifest.json').read_text())
    assert m1['files'] == m2['files']


@pytest.mark.parametrize('name', ['.', 'sub/..'])
def test_save_to_dot_replaces_the_directory_it_names(tmp_path, monkeypatch, name):
    # was OSError 'Device or resource busy' (os.replace of '.'), e.g. beo-train -o . after
    # training in an empty directory
    bank = make_tiny_bank(n=8, k=2)
    (tmp_path / 'm').mkdir()
    if name == 'sub/..':
        bank.save(tmp_path / 'm')   # a model: replaced as a whole
        (tmp_path / 'm' / 'sub').mkdir()
    monkeypatch.chdir(tmp_path / 'm')
    assert bank.save(name) == tmp_path / 'm'
    assert ModelBank.load(tmp_path / 'm').classes == bank.classes
    assert sorted(p.name for p in tmp_path.iterdir()) == ['m']


def test_save_writes_numpy_scalars_of_the_training_settings(tiny, tmp_path):
    # fit_bank(k=np.int64(20)) records k in ``training``: json.dumps refused the manifest
    bank = ModelBank(tiny.models, tiny.spec, tiny.classifier,
                     dict(tiny.training, k=np.int64(4), fill=np.float32(0.5),
                          sizes=np.arange(2)), tiny.pose_components)
    loaded = ModelBank.load(bank.save(tmp_path / 'm'))
    assert loaded.training['k'] == 4 and loaded.training['fill'] == 0.5
    assert loaded.training['sizes'] == [0, 1]
    with pytest.raises(TypeError, match='manifest cannot hold'):
        ModelBank(tiny.models, tiny.spec, training={'x': object()}).save(tmp_path / 'n')
    assert not (tmp_path / 'n').exists()


@pytest.mark.parametrize('name', ['a' * 255, 'a' + '\u00fc' * 127])
def test_save_under_a_name_of_the_longest_length_the_file_system_takes(tmp_path, name):
    # was OSError 'File name too long': the temporary directories beside the target were
    # named '.<name>.tmp-<random>' and '.<name>.old-<random>' (255 bytes, 'ü' 2 of them: the
    # cut is inside one)
    bank = make_tiny_bank(n=8, k=2)
    assert len(name.encode()) <= 255
    path = bank.save(tmp_path / name)
    assert bank.save(path) == tmp_path / name   # replacing a model: the second rename too
    assert ModelBank.load(path).classes == bank.classes
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


@pytest.mark.parametrize('which', [0, 1])
def test_estimate_contract(tiny, which):
    grid = views()[which]
    e = tiny.estimate(grid)
    assert e.label in tiny.classes + ['unknown']
    assert set(e.scores) == set(tiny.classes)
    assert abs(sum(e.scores.values()) - 1) < 1e-6
    assert all(0 <= p <= 1 for p in e.scores.values())
    assert -np.pi <= e.yaw <= np.pi
    assert e.completion.dtype == np.float32 and e.completion.shape == (N,) * 3
    assert e.completion.min() >= 0 and e.completion.max() <= 1
    assert e.variance.dtype == np.float32 and e.variance.shape == (N,) * 3
    assert e.variance.min() >= 0 and np.isfinite(e.variance).all()
    assert (e.variance[grid >= 0] == 0).all()
    ov = e.occupancy_variance
    assert ov.dtype == np.float32 and ov.shape == (N,) * 3
    np.testing.assert_allclose(ov, e.completion * (1 - e.completion), rtol=1e-6)
    assert (ov[grid >= 0] == 0).all() and ov.max() <= 0.25
    # observed voxels are kept
    assert (e.completion[grid == 1] == 1).all()
    assert (e.completion[grid == 0] == 0).all()
    # hypotheses: the chosen class first, at the estimate's yaw, its modes best first
    h = e.hypotheses
    assert 1 <= len(h) <= 5
    assert all(np.isfinite(x.score) and -np.pi <= x.yaw <= np.pi for x in h)
    best = e.label if e.label != 'unknown' else max(e.scores, key=e.scores.get)
    assert h[0].label == best and abs(wrap(h[0].yaw - e.yaw)) < 1e-9
    own = [x.score for x in h if x.label == best]
    assert own == sorted(own, reverse=True)
    others = [x.score for x in h if x.label != best]
    assert others == sorted(others, reverse=True)
    assert {'pose_and_features', 'classify', 'pose_refinement', 'completion',
            'total'} <= set(e.timings)
    assert all(t >= 0 for t in e.timings.values())
    assert e.timings['total'] >= e.timings['pose_and_features']
    assert e.features.shape == (2, 6) and np.isfinite(e.features).all()
    # the unknown part of a partial view is completed with something
    if (grid < 0).any():
        assert e.completion[grid < 0].max() > 0.5


@pytest.mark.parametrize('which', [0, 1])
def test_symmetric_yaws_are_the_turns_that_map_the_completion_onto_itself(tiny, which):
    from beo_ros.core.grid import symmetric_turns
    e = tiny.estimate(views()[which])
    turns = symmetric_turns(e.completion >= 0.5)
    np.testing.assert_allclose(wrap(np.array(e.symmetric_yaws) - e.yaw), wrap(np.array(turns)),
                               atol=1e-9)
    assert len(turns) == (3 if which == 1 else 1)   # the cylinder, the box


def test_symmetric_yaws_of_complete_shapes(tiny):
    # a complete grid is its own completion (observed voxels are kept): a slab looks the same
    # turned round, a square block at every quarter turn, a slab with a post at one corner at none
    slab = np.zeros((N,) * 3, np.int8)
    slab[3:13, 5:11, 0:6] = 1
    square = np.zeros((N,) * 3, np.int8)
    square[4:12, 4:12, 0:8] = 1
    post = slab.copy()
    post[3:6, 5:8, 6:14] = 1
    for grid, turns in ((slab, [np.pi]), (square, [np.pi / 2, np.pi, 3 * np.pi / 2]),
                        (post, [])):
        for yaw in (None, 0.4):
            e = tiny.estimate(grid, yaw=yaw)
            # compared on the circle: a turn of pi may come out as -pi
            assert len(e.symmetric_yaws) == len(turns)
            assert (yaw_error(np.array(e.symmetric_yaws) - e.yaw, turns) < 1e-9).all()
            assert all(-np.pi <= y <= np.pi for y in e.symmetric_yaws)


@pytest.mark.parametrize('yaw', [0.3, -2.0, 4.0, 7.5])
def test_given_yaw_skips_the_search(tiny, yaw, monkeypatch):
    def no_search(*a, **k):
        raise AssertionError('search must not run when yaw is given')
    monkeypatch.setattr(tiny.engine, 'search', no_search)
    e = tiny.estimate(views()[1], yaw=yaw)
    assert abs(wrap(e.yaw - yaw)) < 1e-9
    assert all(abs(wrap(h.yaw - yaw)) < 1e-9 for h in e.hypotheses)


def test_check_grid(tiny):
    g = np.zeros((N,) * 3, dtype=np.int8)
    assert tiny.check_grid(g).dtype == np.int8
    assert tiny.check_grid(g.astype(bool)).dtype == np.int8
    assert tiny.check_grid(g.astype(np.int64)).dtype == np.int8
    with pytest.raises(ValueError, match='shape'):
        tiny.check_grid(np.zeros((N, N, N + 1), dtype=np.int8))
    with pytest.raises(ValueError, match='shape'):
        tiny.estimate(np.zeros((8, 8, 8), dtype=np.int8))
    with pytest.raises(ValueError, match='integer'):
        tiny.check_grid(g.astype(np.complex64))
    for bad in (2, -2):
        b = g.copy()
        b[3, 3, 3] = bad
        with pytest.raises(ValueError, match='values'):
            tiny.check_grid(b)
    # whole-valued floats are the same grid; anything a cast to int8 would change is refused
    part = views()[1]
    np.testing.assert_array_equal(tiny.check_grid(part.astype(np.float32)), part)
    assert tiny.check_grid(part.astype(np.float64)).dtype == np.int8
    for bad in (0.7, np.nan, np.inf):
        b = part.astype(np.float32)
        b[3, 3, 3] = bad
        with pytest.raises(ValueError, match='whole values'):
            tiny.check_grid(b)
    for dtype, bad in ((np.int64, 257), (np.uint8, 255), (np.int16, -255)):
        b = part.astype(dtype)
        b[3, 3, 3] = bad
        with pytest.raises(ValueError, match='values'):
            tiny.check_grid(b)
    for kw in (dict(yaw_step_deg=0.0), dict(yaw_step_deg='1'), dict(yaw_step_deg=np.nan),
               dict(search_step_deg=0), dict(search_step_deg=True)):
        with pytest.raises(ValueError, match=next(iter(kw))):
            tiny.estimate(views()[1], **kw)
    for bad in ((float('nan'),), (-10.0,), (0.0,), ('10',)):
        with pytest.raises(ValueError, match='probe_deg'):
            tiny.estimate(g, probe_deg=bad)
    assert np.isfinite(tiny.estimate(views()[1], probe_deg=None).yaw)
    # nothing occupied (all free, all unknown): no object, not a class; the yaw is still checked
    for empty in (g, np.full_like(g, -1)):
        with pytest.raises(ValueError, match='no occupied voxel'):
            tiny.features(empty)
        with pytest.raises(ValueError, match='yaw'):
            tiny.estimate(empty, yaw=np.nan)


def test_every_estimate_field_is_documented(tiny):
    # 'features' was not: documented as an attribute line or named in another one
    import re
    from beo_ros.core.estimate import Estimate
    from beo_ros.core.inference import FEATURE_NAMES
    doc = Estimate.__doc__
    for f in dataclasses.fields(Estimate):
        assert re.search(rf'^ {{8}}{f.name}:|``{f.name}``', doc, re.M), f.name
    e = tiny.estimate(views()[1])
    assert e.features.dtype == np.float64 and e.features.shape == (2, len(FEATURE_NAMES))
    assert tiny.estimate(np.zeros((N,) * 3, np.int8)).features is None


@pytest.mark.parametrize('fill', [0, -1])
def test_grid_without_occupied_voxel_is_no_object(tiny, fill):
    # the protocol's view of a one-voxel object can lose it to the rotation: an answer (no
    # object), not an exception that would stop a whole evaluation
    empty = np.full((N,) * 3, fill, np.int8)
    for yaw, want in ((None, 0.0), (7.0, 7.0 - 2 * np.pi)):
        e = tiny.estimate(empty, yaw=yaw)
        assert e.label == 'unknown' and e.probability == 0.0
        assert e.classifier_mode == 'none' and 'no occupied voxel' in e.classifier_note
        assert e.yaw == pytest.approx(want)
        assert set(e.scores) == set(tiny.classes)
        assert sum(e.scores.values()) == pytest.approx(1.0)
        assert e.completion.shape == (N,) * 3 and e.completion.dtype == np.float32
        assert not e.completion.any() and not e.variance.any()
        assert not e.occupancy_variance.any()
        assert e.hypotheses == [] and e.symmetric_yaws == []
    # the scores are the class prior when one is set
    w = tiny.with_class_prior({'box': 3, 'cylinder': 1}).estimate(empty).scores
    assert w == pytest.approx({'box': 0.75, 'cylinder': 0.25})


@pytest.mark.parametrize('mode, n_in', [('points', 2 + 2), ('complete', 2 * 6)])
def test_grid_without_occupied_voxel_scores_the_training_prior_of_any_classifier(tiny, mode,
                                                                                 n_in):
    # under the 'train' prior the scores are the classifier's training rows per class: only a
    # 'partial' classifier's were looked at, so a 'points'-only bank (as tabletop_32) or a
    # 'complete'-only one said uniform
    clf = dict(mean=np.zeros(n_in), scale=np.ones(n_in), coef=np.zeros((2, n_in)),
               intercept=np.zeros(2), unknown_threshold=np.full(2, -np.inf),
               class_counts=np.array([30.0, 10.0]))
    bank = ModelBank(tiny.models, tiny.spec, {mode: clf})
    e = bank.estimate(np.zeros((N,) * 3, np.int8))
    assert e.scores == pytest.approx({'box': 0.75, 'cylinder': 0.25})


def test_fine_yaw_steps_refine_exactly_without_fine_pooled_maps(tiny):
    # below 1 deg only the last exact climb runs at the finer step: the pooled maps of every
    # 0.1 deg (3600 yaws: 5 s and 1.4 GB at 32^3) must not be built, and the finer yaw is the
    # 1 deg one or a better one by the exact likelihood, within 1 deg of it
    g = views()[1]
    eng = tiny.engine
    coarse = tiny.estimate(g, verify=False)
    fine = tiny.estimate(g, yaw_step_deg=0.1, verify=False)
    assert fine.label == coarse.label
    assert max(first.shape[0] for first, _ in eng._maps.values()) <= 360
    c = tiny.classes.index(fine.label)
    obs = eng.observe(g)
    ll = [eng.exact(obs, c, e.yaw, with_prediction=False)['loglik'] for e in (coarse, fine)]
    assert ll[1] >= ll[0]
    assert abs(np.rad2deg(wrap(fine.yaw - coarse.yaw))) <= 1.0 + 1e-9


# ---------------------------------------------------------------------- the batched search
def test_batched_scores_equal_per_yaw_and_per_class_loop(tiny):
    eng = tiny.engine
    rng = np.random.default_rng(0)
    yaws = np.sort(rng.uniform(0, 2 * np.pi, 12))
    for g in views():
        P = eng.pooled(g)
        all_ = eng.scores(P, yaws)
        assert all_.shape == (12, eng.C) and np.isfinite(all_).all()
        one = np.array([[eng.scores(P, [y], c=c)[0, 0] for c in range(eng.C)] for y in yaws])
        # the float32 products sum in a different order for other batch shapes, and
        # G = I + gram / v is ill-conditioned (v small), so the paths agree to ~1e-5 relative
        # (a few hundredths of a nat), not to the last digit
        np.testing.assert_allclose(all_, one, rtol=1e-4, atol=1e-6)
        per_class = np.stack([eng.scores(P, yaws, c=c)[:, 0] for c in range(eng.C)], axis=1)
        np.testing.assert_allclose(all_, per_class, rtol=1e-4, atol=1e-6)
        per_yaw = np.vstack([eng.scores(P, [y]) for y in yaws])
        np.testing.assert_allclose(all_, per_yaw, rtol=1e-4, atol=1e-6)


def test_stage2_noise_map_is_off_by_default():
    # measured: with the observed-frame scoring the per-voxel noise lowers the yaw accuracy
    tiny = make_tiny_bank()
    assert all(m.coarse_noise_map is not None for m in tiny.models)
    assert all(t[3] is None for t in tiny.engine._full_terms)
    from beo_ros.core.bank import ModelBank
    on = ModelBank(tiny.models, tiny.spec, stage2_noise_map=True).engine
    assert all(t[3] is not None for t in on._full_terms)


def test_stage2_noise_map_survives_save_and_load(tmp_path):
    tiny = make_tiny_bank()
    for flag in (True, False):
        path = ModelBank(tiny.models, tiny.spec, stage2_noise_map=flag).save(tmp_path / str(flag))
        back = ModelBank.load(path)
        assert back.stage2_noise_map is flag
        assert all((t[3] is not None) is flag for t in back.engine._full_terms)
    mf = tmp_path / 'True' / 'manifest.json'
    manifest = json.loads(mf.read_text())
    manifest['stage2_noise_map'] = 'yes'
    mf.write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match='stage2_noise_map must be true or false'):
        ModelBank.load(tmp_path / 'True')


def test_full_component_scores_equal_the_leading_components_when_all_are_used():
    # stage 2 (full=True) scores class c with all k components; with pose_components = k the
    # stage-1 arrays hold the same components, so both paths must agree: without a noise map,
    # and with a constant noise map equal to the scalar (the per-voxel-noise formula)
    import dataclasses
    from beo_ros.core.bank import ModelBank
    tiny = make_tiny_bank()
    assert all(m.coarse_noise_map is not None for m in tiny.models)
    yaws = np.deg2rad(np.arange(0, 360, 7.0))
    for noise in ('none', 'constant'):
        models = [dataclasses.replace(m, coarse_noise_map=None if noise == 'none' else np.full_like(
            m.coarse_noise_map, m.coarse_noise_variance)) for m in tiny.models]
        eng = ModelBank(models, tiny.spec, pose_components=tiny.engine.k,
                        stage2_noise_map=True).engine
        for g in views():
            P = eng.pooled(g)
            for c in range(eng.C):
                np.testing.assert_allclose(eng.scores(P, yaws, c, full=True),
                                           eng.scores(P, yaws, c), rtol=1e-4, atol=1e-6)


def test_per_voxel_noise_scores_equal_a_dense_weighted_gaussian():
    # the per-voxel-noise path against the Gaussian marginal of the pooled observation written
    # out densely in the observed frame: observed cell q is explained by canonical cell
    # R(-yaw) q of the model (beyond the model's grid: empty, with the noise of its outer
    # shell); y ~ N(mu_q, W_q W_q^T + diag(noise_q)), each cell weighted by its known fraction
    # D (a cell with D known of 8 voxels counts D times, with mean T / D)
    from beo_ros.core.bank import ModelBank
    from beo_ros.core.inference import pool2
    tiny = make_tiny_bank()
    eng = ModelBank(tiny.models, tiny.spec, stage2_noise_map=True).engine
    n, nc = eng.n, eng.nc
    c = 1
    g = views()[0]
    D, T, TT = (a[:-1].astype(float) for a in eng.pooled(g))
    W = (pool2(eng.W[c].reshape(n, n, n, -1).astype(float)) / 8).reshape(nc ** 3, -1)
    mu = (pool2(eng.mu[c].reshape(n, n, n).astype(float)) / 8).ravel()
    psi = tiny.models[c].coarse_noise_map.astype(float)
    shell = np.ones((nc,) * 3, dtype=bool)
    shell[1:-1, 1:-1, 1:-1] = False
    W = np.vstack([W, np.zeros((1, W.shape[1]))])
    mu = np.append(mu, 0.0)
    psi = np.append(psi, np.median(psi[shell.ravel()]))
    for yaw in (0.0, 0.7, 2.0):
        got = eng.scores(eng.pooled(g), [yaw], c, full=True)[0, 0]
        q = yaw_source_index(nc, [yaw])[0]
        Wq, muq, pq = W[q], mu[q], psi[q]
        # weighted least squares form of the marginal: precision D / psi per cell
        w = D / pq
        G = np.eye(W.shape[1]) + (Wq * w[:, None]).T @ Wq
        b = Wq.T @ (T / pq - w * muq)
        rr = (TT / pq - 2 * T * muq / pq + w * muq ** 2).sum()
        want = -0.5 * ((D * np.log(2 * np.pi * pq)).sum() + rr - b @ np.linalg.solve(G, b)
                       + np.linalg.slogdet(G)[1])
        np.testing.assert_allclose(got, want, rtol=1e-5)


def test_pooled_scores_are_of_the_observation_in_its_own_frame():
    # every yaw scores the same data: the pooled observation as it is, against the model
    # rotated into the observed frame (scalar noise, leading components), densely
    from beo_ros.core.inference import pool2
    tiny = make_tiny_bank()
    eng = tiny.engine
    n, nc, kp = eng.n, eng.nc, eng.kp
    g = views()[1]
    D, T, TT = (a[:-1].astype(float) for a in eng.pooled(g))
    for c in range(eng.C):
        W = (pool2(eng.W[c, :, :kp].reshape(n, n, n, -1).astype(float)) / 8).reshape(-1, kp)
        mu = (pool2(eng.mu[c].reshape(n, n, n).astype(float)) / 8).ravel()
        W, mu, v = np.vstack([W, np.zeros((1, kp))]), np.append(mu, 0.0), eng.v_coarse[c]
        for yaw in (0.3, 1.1, 4.0):
            q = yaw_source_index(nc, [yaw])[0]
            Wq, muq = W[q], mu[q]
            G = np.eye(kp) + (Wq * D[:, None]).T @ Wq / v
            b = Wq.T @ (T - D * muq) / v
            rr = (TT - 2 * T * muq + D * muq ** 2).sum() / v
            want = -0.5 * (D.sum() * np.log(2 * np.pi * v) + rr - b @ np.linalg.solve(G, b)
                           + np.linalg.slogdet(G)[1])
            # float32 products of a tiny ill-conditioned model: ~1e-5 relative, as above
            np.testing.assert_allclose(eng.scores(eng.pooled(g), [yaw], c)[0, 0], want,
                                       rtol=1e-4)


def test_every_yaw_scores_the_same_observation():
    # against an empty model (W = 0, mu = 0) the likelihood of an observation is the same at
    # every yaw, at full resolution and pooled: the observation is never resampled (resampling
    # it into the model's frame dropped or doubled thin parts at some yaws, and those yaws won)
    n, k = 16, 2
    rng = np.random.default_rng(4)
    grid = rng.choice(np.array([-1, 0, 1], dtype=np.int8), size=(n,) * 3, p=[0.3, 0.6, 0.1])
    eng = InferenceEngine(np.zeros((1, n ** 3, k), np.float32), np.zeros((1, n ** 3), np.float32),
                          [0.05], [0.05], n, pose_components=k)
    yaws = np.deg2rad(np.arange(0, 360, 7.0))
    full = np.array([eng.exact(grid, 0, float(y))['loglik'] for y in yaws])
    known, occ = (grid >= 0).sum(), (grid == 1).sum()
    np.testing.assert_allclose(full, -0.5 * (known * np.log(2 * np.pi * 0.05) + occ / 0.05))
    pooled = eng.scores(eng.pooled(grid), yaws)[:, 0]
    np.testing.assert_allclose(pooled, pooled[0], rtol=1e-6)


def test_scoring_a_subset_of_rows_equals_the_same_rows_of_all(tiny):
    eng = tiny.engine
    yaws = np.deg2rad(np.arange(360.0))
    rows = np.array([3, 4, 5, 90, 91, 200, 359])
    for g in views():
        P = eng.pooled(g)
        for full in (False, True):
            all_ = eng.scores(P, yaws, 1, full=full)
            np.testing.assert_allclose(eng.scores(P, yaws, 1, full=full, rows=rows), all_[rows],
                                       rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize('step', [1.0, 7.0, 50.0])
def test_hypothesis_score_of_a_yaw_beyond_a_turn_is_that_of_the_same_yaw(tiny, step):
    # a verifier-turned yaw (refined yaw + 90 k degrees) can exceed 2 pi; its pooled score was
    # read at row rint(yaw / step) % len(grid), but a step that does not divide 360 deg gives
    # a grid of another period (8 x 50 deg = 400 deg): 460 deg was scored at 50 deg, not 100
    _, part = views()
    feats, per = tiny.features(part)
    for deg in (10.0, 100.0, 200.0):
        y = np.deg2rad(deg)
        want = tiny._pooled_score(part, 0, per[0], y, step)
        for turns in (1, 2):
            assert tiny._pooled_score(part, 0, per[0], y + turns * 2 * np.pi, step) == want


def test_hypothesis_score_of_a_yaw_in_the_last_gap_of_the_grid_is_that_of_the_nearest(tiny):
    # a step that does not divide 360 deg leaves a wider gap before 360: yaw_grid(80) ends at
    # 320 deg, and 350 deg was scored at 320 (rint(350 / 80) = 4), not at the nearer 0 deg
    _, part = views()
    feats, per = tiny.features(part)
    at = {deg: tiny._pooled_score(part, 0, per[0], np.deg2rad(deg), 80.0) for deg in (0, 320)}
    assert at[0] != at[320]
    for deg in (350.0, -10.0, 710.0):
        assert tiny._pooled_score(part, 0, per[0], np.deg2rad(deg), 80.0) == at[0]


def test_scoring_a_row_twice_gives_its_score_twice(tiny):
    # the rotation's extra cells (observed cells that show the same canonical cell) went to the
    # last copy of a repeated row only: the first copy was scored without them
    eng = tiny.engine
    yaws = np.deg2rad(np.arange(360.0))
    first, extra = eng._rotation_maps(yaws)
    dc = first.shape[1]
    row = int(np.bincount(np.concatenate([pos // dc for pos, _ in extra]),
                          minlength=len(yaws)).argmax())   # a yaw with extra cells
    rows = np.array([row, 5, row, row - len(yaws)])
    for g in views():
        P = eng.pooled(g)
        for full in (False, True):
            want = eng.scores(P, yaws, 1, full=full)[rows % len(yaws)]
            np.testing.assert_allclose(eng.scores(P, yaws, 1, full=full, rows=rows), want,
                                       rtol=1e-4, atol=1e-6)


def test_pooled_column_maps_sum_the_observed_cells_of_every_canonical_cell(tiny):
    # the pooled maps are of (x, y) columns (16x smaller, and scores gathers whole columns):
    # expanded to cells they must give each canonical cell exactly the observed cells that
    # show it, as the cell-level map yaw_source_index says
    eng = tiny.engine
    nc, m, dc = eng.nc, eng.nc ** 2, eng.nc ** 3
    yaws = np.deg2rad(np.arange(0, 360, 7.0))
    first, extra = eng._rotation_maps(yaws)
    assert first.shape == (len(yaws), m)
    w = np.random.default_rng(0).integers(1, 1000, dc).astype(np.float64)   # exact sums
    wcol = np.vstack([w.reshape(m, nc), np.zeros((1, nc))])
    got = wcol[first]                                        # (Y, m, nc)
    for pos, src in extra:
        got.reshape(-1, nc)[pos] += wcol[src]
    inv = yaw_source_index(nc, yaws)                         # observed cell -> canonical cell
    for y in range(len(yaws)):
        want = np.bincount(inv[y], weights=w, minlength=dc + 1)[:dc]
        np.testing.assert_array_equal(got[y].ravel(), want)


def test_stage2_windows_find_the_exhaustive_full_component_optimum(pose_case):
    # estimate() re-scores the chosen class with all components only within +-15 deg of its 6
    # best stage-1 modes; the exhaustive stage-2 search (stage2_modes=None) is the reference
    bank, cases = pose_case
    same = []
    for g, yaw, c, _ in cases:
        _, per = bank.features(g)
        win = bank._refine(g, c, per[c], 1.0, 0.0, 1.0, stage2_modes=6, stage2_window_deg=15.0)
        ex = bank._refine(g, c, per[c], 1.0, 0.0, 1.0, stage2_modes=None)
        same.append(abs(win['hypotheses'][0][1] - ex['hypotheses'][0][1])
                    <= 1e-6 * abs(ex['hypotheses'][0][1]))
    assert np.mean(same) >= 0.9, same


def test_rotation_map_cache_keeps_within_its_budget(monkeypatch):
    from beo_ros.core import inference
    eng = make_tiny_bank().engine
    P = eng.pooled(views()[0])
    eng.scores(P, np.deg2rad(np.arange(0, 360, 5.0)))
    size = eng._maps_bytes
    assert len(eng._maps) == 1 and size > 0
    monkeypatch.setattr(inference, 'MAP_CACHE_BYTES', int(2.5 * size))
    eng.scores(P, np.deg2rad(np.arange(1, 361, 5.0)))
    eng.scores(P, np.deg2rad(np.arange(2, 362, 5.0)))   # would pass the budget: not kept
    assert len(eng._maps) == 2 and eng._maps_bytes <= 2.5 * size
    ref = make_tiny_bank().engine.scores(P, np.deg2rad(np.arange(2, 362, 5.0)))
    np.testing.assert_allclose(eng.scores(P, np.deg2rad(np.arange(2, 362, 5.0))), ref,
                               rtol=1e-6)


def test_full_resolution_map_cache_keeps_within_its_budget(monkeypatch):
    # it kept 720 maps whatever the grid: 94 MB at 32^3, 720 MB at 64^3, 5.6 GB at 128^3
    from beo_ros.core import inference
    eng = make_tiny_bank().engine
    one = eng.d * 4   # an int32 map
    monkeypatch.setattr(inference, 'FULL_MAP_CACHE_BYTES', 10 * one, raising=False)
    g = views()[1]
    yaws = np.deg2rad(np.arange(0.5, 40.0))
    got = [eng.exact(g, 1, float(y))['loglik'] for y in yaws]
    assert 0 < len(eng._full_maps) <= 10
    fresh = make_tiny_bank().engine
    np.testing.assert_allclose(got, [fresh.exact(g, 1, float(y))['loglik'] for y in yaws],
                               rtol=1e-12)


def test_rotation_map_cache_does_not_confuse_yaw_sets():
    fresh = make_tiny_bank().engine
    eng = make_tiny_bank().engine
    P = eng.pooled(views()[0])
    A = np.deg2rad(np.linspace(0, 70, 40))
    B = A.copy()
    B[1:-1] = np.deg2rad(np.linspace(20, 50, 38))
    eng.scores(P, A)
    np.testing.assert_allclose(eng.scores(P, B), fresh.scores(P, B), rtol=1e-6)


# ---------------------------------------------------------------------- the exact posterior
def dense_marginal(grid, W, mu, v, src):
    """Log marginal likelihood of the known voxels of ``grid`` under N(mu, W W^T + v I) with
    observed voxel q explained by model voxel src[q] (n^3: beyond the grid, empty), by dense
    linear algebra; also the known rows of W (K, k) and residuals y - mu (K,) in float64."""
    K = np.flatnonzero(grid.ravel() >= 0)
    y = (grid.ravel()[K] == 1).astype(np.float64)
    WK = np.vstack([W, np.zeros((1, W.shape[1]))])[src[K]].astype(np.float64)
    r = y - np.append(mu, 0)[src[K]].astype(np.float64)
    Cov = WK @ WK.T + v * np.eye(len(K))
    ll = -0.5 * (len(K) * np.log(2 * np.pi) + np.linalg.slogdet(Cov)[1]
                 + r @ np.linalg.solve(Cov, r))
    return ll, WK, r


def test_exact_loglik_equals_dense_gaussian_marginal():
    n, k, C = 8, 3, 2
    d = n ** 3
    rng = np.random.default_rng(0)
    W = (rng.standard_normal((C, d, k)) * 0.2).astype(np.float32)
    mu = rng.uniform(0, 1, (C, d)).astype(np.float32)
    v = np.array([0.05, 0.2])
    eng = InferenceEngine(W, mu, v, v * 2, n, pose_components=2)
    grid = rng.choice(np.array([-1, 0, 1], dtype=np.int8), size=(n,) * 3, p=[0.4, 0.3, 0.3])
    for c in range(C):
        for yaw in (0.0, np.pi / 2, 0.6):
            ex = eng.exact(grid, c, yaw)
            # the canonical labels (for the features): the observation rotated by -yaw, free
            # outside the grid
            canon = rotate_grid(grid, -yaw, fill=0).ravel()
            np.testing.assert_array_equal(ex['canon'], canon)
            # the likelihood: of the known observed voxels as they are, each explained by the
            # canonical voxel the model rotated by yaw puts there (empty beyond its grid)
            src = yaw_source_index(n, [yaw])[0]
            dense, WK, r = dense_marginal(grid, W[c], mu[c], v[c], src)
            assert ex['n_known'] == np.count_nonzero(grid >= 0)
            np.testing.assert_allclose(ex['loglik'], dense, rtol=1e-6)
            # posterior mean of the coefficients: S W_K^T r / v
            G = np.eye(k) + WK.T @ WK / v[c]
            np.testing.assert_allclose(ex['m'], np.linalg.solve(G, WK.T @ r / v[c]), rtol=1e-5,
                                       atol=1e-8)


def test_exact_posterior_with_few_known_voxels_and_small_noise():
    # the known-voxel gram is the full gram minus the unknown rows' gram; with fewer known
    # voxels than components and a small noise variance, float32 rounding of that difference
    # made G = I + gram / v indefinite (LinAlgError inside fit_bank on ModelNet classes of 20)
    n, k = 16, 6
    rng = np.random.default_rng(3)
    W = (rng.standard_normal((1, n ** 3, k)) * 3).astype(np.float32)
    mu = rng.uniform(0, 1, (1, n ** 3)).astype(np.float32)
    v = np.array([1e-4])
    eng = InferenceEngine(W, mu, v, v, n, pose_components=2)
    grid = np.full((n,) * 3, -1, dtype=np.int8)
    grid[7:9, 7, 7] = 1
    grid[8, 8, 8] = 0
    ex = eng.exact(grid, 0, 0.0)
    K = np.flatnonzero(ex['canon'] >= 0)
    assert len(K) == 3 < k
    y = (ex['canon'][K] == 1).astype(np.float64)
    WK = W[0][K].astype(np.float64)
    Cov = WK @ WK.T + v[0] * np.eye(len(K))
    r = y - mu[0][K].astype(np.float64)
    _, ld = np.linalg.slogdet(Cov)
    dense = -0.5 * (len(K) * np.log(2 * np.pi) + ld + r @ np.linalg.solve(Cov, r))
    np.testing.assert_allclose(ex['loglik'], dense, rtol=1e-6)



def test_models_of_no_components_are_searched_and_solved():
    # the model files accept a class of k = 0 (its mean alone, e.g. one object); a bank of
    # such classes only crashed in the pose search (numpy cannot reshape the empty batch of
    # (0, 0) grams by -1) and then in LAPACK, which refuses the empty exact solve
    n = N
    d = n ** 3
    X, _, _ = primitive_shapes(n, 1, np.random.default_rng(0))
    models = [ClassModel(name, np.zeros((d, 0), np.float32), X[i], 0.05, 0.02,
                         np.zeros((0, 0), np.float32), np.zeros(d, np.float32),
                         np.zeros(0, np.float32)) for i, name in enumerate(('box', 'cylinder'))]
    bank = ModelBank(models, GridSpec(size=n))
    grid = partial_view(X[0].reshape((n,) * 3) > 0.5, 0.3, 0.4)
    e = bank.estimate(grid)
    assert e.label == 'box' and np.isfinite(e.features).all() and e.hypotheses
    assert bank.estimate(grid, yaw=0.5).yaw == 0.5
    # the exact log-likelihood is that of independent voxels N(mu, v)
    ex = bank.engine.exact(grid, 0, 0.0)
    K = np.flatnonzero(grid.ravel() >= 0)
    r = (grid.ravel()[K] == 1) - X[0][K].astype(np.float64)
    assert ex['loglik'] == pytest.approx(-0.5 * (len(K) * np.log(2 * np.pi * 0.05)
                                                 + r @ r / 0.05), rel=1e-9)


def test_exact_gram_of_components_only_unknown_voxels_carry_is_not_rounded_away():
    # with more known than unknown rows the known gram is the total gram minus the unknown
    # rows' one; summed in float32 over thousands of rows, that difference divided by a small
    # v made G many times too sure of a component that only unknown voxels carry (G 74 for
    # 1 at v = 1e-6, LinAlgError at 1e-8)
    n, k, v = 32, 3, 1e-6
    d = n ** 3
    rng = np.random.default_rng(0)
    W = (rng.standard_normal((1, d, k)) * 0.1).astype(np.float32)
    mu = rng.uniform(0, 1, (1, d)).astype(np.float32)
    grid = rng.choice(np.array([0, 1], np.int8), (n,) * 3)
    grid[:, :12] = -1
    W[0, :, 0] = 0
    W[0].reshape(n, n, n, k)[:, :10, :, 0] = rng.standard_normal((n, 10, n)) * 0.3
    eng = InferenceEngine(W, mu, [v], [v], n, pose_components=2)
    for yaw in (0.0, 0.1):
        ex = eng.exact(grid, 0, yaw)
        src = yaw_source_index(n, [yaw])[0]
        K = np.flatnonzero(grid.ravel() >= 0)
        WK = np.vstack([W[0], np.zeros((1, k))])[src[K]].astype(np.float64)
        np.testing.assert_allclose(ex['G'], np.eye(k) + WK.T @ WK / v, rtol=1e-9, atol=1e-6)
        assert ex['G'][0, 0] == pytest.approx(1.0, abs=1e-6)

def test_pooled_scores_equal_dense_gaussian_of_pooled_grid():
    # the coarse score of yaw 0 is the Gaussian marginal of the pooled occupancy fractions when
    # every voxel is known (D = 1): a dense check of the batched formula
    n, k = 8, 3
    rng = np.random.default_rng(1)
    W = (rng.standard_normal((1, n ** 3, k)) * 0.2).astype(np.float32)
    mu = rng.uniform(0, 1, (1, n ** 3)).astype(np.float32)
    eng = InferenceEngine(W, mu, [0.1], [0.03], n, pose_components=k)
    grid = rng.integers(0, 2, (n,) * 3).astype(np.int8)
    s = eng.scores(eng.pooled(grid), [0.0])[0, 0]
    from beo_ros.core.inference import pool2
    h = n // 2
    Wc = (pool2(W[0].reshape(n, n, n, k)) / 8).reshape(-1, k).astype(np.float64)
    muc = (pool2(mu[0].reshape(n, n, n)) / 8).ravel().astype(np.float64)
    y = (pool2((grid == 1).astype(np.float64)) / 8).ravel()
    Cov = Wc @ Wc.T + 0.03 * np.eye(h ** 3)
    r = y - muc
    _, ld = np.linalg.slogdet(Cov)
    dense = -0.5 * (h ** 3 * np.log(2 * np.pi) + ld + r @ np.linalg.solve(Cov, r))
    np.testing.assert_allclose(s, dense, rtol=1e-5)


# ---------------------------------------------------------------------- load errors
def _copy(tiny_dir, tmp_path):
    dst = tmp_path / 'copy'
    shutil.copytree(tiny_dir, dst)
    return dst


def _manifest(p):
    return json.loads((p / 'manifest.json').read_text())


def _write_manifest(p, m):
    (p / 'manifest.json').write_text(json.dumps(m))


def test_repr_names_classes_grid_and_parts(tiny):
    r = repr(tiny)
    k = tiny.models[0].W.shape[1]
    assert r.startswith("ModelBank(2 classes ['box', 'cylinder'], grid 16^3 normalized")
    assert f'k {k},' in r and "prior 'train'" in r and 'verifier no' in r
    assert "classifier ['max-likelihood']" in r   # the tiny bank has no classifier
    assert repr(tiny.with_class_prior('uniform')).endswith("prior 'uniform')")


def test_load_missing_dir_and_manifest(tmp_path, tiny_dir):
    with pytest.raises(ModelError, match='nope'):
        ModelBank.load(tmp_path / 'nope')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(ModelError, match='manifest.json'):
        ModelBank.load(tmp_path / 'empty')
    p = _copy(tiny_dir, tmp_path)
    (p / 'manifest.json').write_text('{"format": ')
    with pytest.raises(ModelError, match='manifest.json.*JSON'):
        ModelBank.load(p)


@pytest.mark.parametrize('change,msg', [
    (dict(format='other'), 'format'),
    (dict(version=99), 'version'),
    (dict(grid=None), 'manifest.json'),
    (dict(grid=[['size', 16]]), 'grid must be an object'),
    (dict(grid='16'), 'grid must be an object'),
    # were 'class_00_b.npz for class 'b' is not listed', 'a model bank needs at least one class'
    # (no file named) and a dict's keys taken as the classes
    (dict(classes='box'), "classes must be a non-empty list of class names, got 'box'"),
    (dict(classes=[]), 'classes must be a non-empty list'),
    (dict(classes={'box': 0, 'cylinder': 1}), 'classes must be a non-empty list'),
])
def test_load_bad_manifest(tmp_path, tiny_dir, change, msg):
    p = _copy(tiny_dir, tmp_path)
    _write_manifest(p, dict(_manifest(p), **change))
    with pytest.raises(ModelError, match=msg) as ei:
        ModelBank.load(p)
    assert 'manifest.json' in str(ei.value)


def test_load_checksum_mismatch(tmp_path, tiny_dir):
    p = _copy(tiny_dir, tmp_path)
    fn = sorted(p.glob('class_01_*.npz'))[0]
    data = bytearray(fn.read_bytes())
    data[len(data) // 2] ^= 0xFF
    fn.write_bytes(bytes(data))
    with pytest.raises(ModelError, match=fn.name + '.*checksum'):
        ModelBank.load(p)


def test_load_missing_class_file(tmp_path, tiny_dir):
    p = _copy(tiny_dir, tmp_path)
    fn = sorted(p.glob('class_00_*.npz'))[0]
    fn.unlink()
    with pytest.raises(ModelError, match=fn.name + '.*missing'):
        ModelBank.load(p)
    # not listed in the manifest either
    m = _manifest(p)
    del m['files'][fn.name]
    _write_manifest(p, m)
    with pytest.raises(ModelError, match=fn.name):
        ModelBank.load(p)


def test_load_wrong_shapes(tmp_path, tiny_dir):
    from beo_ros.core.bank import _sha256
    p = _copy(tiny_dir, tmp_path)
    fn = sorted(p.glob('class_00_*.npz'))[0]
    with np.load(fn) as z:
        arr = {k: z[k] for k in z.files}
    arr['W'] = arr['W'][: N ** 3 // 2]
    np.savez(fn, **arr)
    m = _manifest(p)
    m['files'][fn.name] = _sha256(fn)        # consistent checksum: the shape check must catch it
    _write_manifest(p, m)
    with pytest.raises(ModelError, match=fn.name + '.*grid'):
        ModelBank.load(p)
    # a manifest grid that does not fit the class files
    m['grid']['size'] = 8
    np.savez(fn, **dict(arr, W=np.zeros((N ** 3, 4), np.float32)))
    m['files'][fn.name] = _sha256(fn)
    _write_manifest(p, m)
    with pytest.raises(ModelError, match='class_00'):
        ModelBank.load(p)


@pytest.mark.parametrize('cut', [0.5, 0.95])
def test_truncated_npz_with_a_matching_checksum_is_named(tmp_path, tiny_dir, cut):
    # a write cut short before the manifest was signed: zipfile / zlib errors, not only OSError
    from beo_ros.core.bank import _sha256
    p = _copy(tiny_dir, tmp_path)
    names = sorted(f.name for f in p.glob('class_*.npz'))
    assert len(names) == 2, names
    # the optional files: any arrays do, they are cut before being read
    names += ['classifier.npz', 'verifier.npz', 'calibration.npz']
    for name in names:
        q = _copy(p, tmp_path / f'{name}_{cut}')
        if not (q / name).exists():
            np.savez_compressed(q / name, complete__coef=np.random.default_rng(0).random((50, 50)))
        data = (q / name).read_bytes()
        (q / name).write_bytes(data[:int(len(data) * cut)])
        m = _manifest(q)
        m['files'][name] = _sha256(q / name)
        _write_manifest(q, m)
        with pytest.raises(ModelError, match=f'{name}: unreadable: '):
            ModelBank.load(q)


@pytest.mark.parametrize('name', ['class_00_box.npz', 'classifier.npz'])
def test_an_array_header_claiming_a_huge_shape_is_named(tmp_path, tiny_dir, name):
    # a corrupt header (checksum signed after it): load raised MemoryError naming no file
    import io
    import zipfile
    from beo_ros.core.bank import _sha256
    p = _copy(tiny_dir, tmp_path)
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head, {'descr': '<f4', 'fortran_order': False, 'shape': (10 ** 14, 4)})
    with zipfile.ZipFile(p / name, 'w') as zf:
        zf.writestr('W.npy' if name.startswith('class') else 'complete__coef.npy',
                    head.getvalue() + bytes(64))
    m = _manifest(p)
    m['files'][name] = _sha256(p / name)
    _write_manifest(p, m)
    with pytest.raises(ModelError, match=f'{name}: unreadable: .*MemoryError'):
        ModelBank.load(p)


def test_a_single_array_under_an_npz_name_is_named(tmp_path, tiny_dir):
    # np.load returns a bare array for an np.save file (it has no context manager): TypeError
    from beo_ros.core.bank import _sha256
    p = _copy(tiny_dir, tmp_path)
    names = sorted(f.name for f in p.glob('class_*.npz')) + ['classifier.npz', 'verifier.npz']
    for name in names:
        q = _copy(p, tmp_path / name)
        with open(q / name, 'wb') as f:
            np.save(f, np.zeros(3))
        m = _manifest(q)
        m['files'][name] = _sha256(q / name)
        _write_manifest(q, m)
        with pytest.raises(ModelError, match=f'{name}: unreadable: .*single array'):
            ModelBank.load(q)


def test_a_classifier_array_without_a_mode_is_named(tmp_path, tiny_dir):
    # it was called 'unreadable: ValueError: not enough values to unpack'
    from beo_ros.core.bank import _sha256
    p = _copy(tiny_dir, tmp_path)
    np.savez(p / 'classifier.npz', stray=np.zeros(2))
    m = _manifest(p)
    m['files']['classifier.npz'] = _sha256(p / 'classifier.npz')
    _write_manifest(p, m)
    with pytest.raises(ModelError, match="array 'stray' is not named '<mode>__<array>'"):
        ModelBank.load(p)


@pytest.mark.parametrize('text', ['{"format": ' + '9' * 5000 + '}', '[' * 100000 + ']' * 100000])
def test_a_manifest_json_cannot_parse_is_named(tmp_path, tiny_dir, text):
    # an integer of over 4300 digits (ValueError) and deep nesting (RecursionError)
    from beo_ros.core.bank import is_model_dir
    p = _copy(tiny_dir, tmp_path)
    (p / 'manifest.json').write_text(text)
    with pytest.raises(ModelError, match='manifest.json is not valid JSON'):
        ModelBank.load(p)
    assert not is_model_dir(p)


@pytest.mark.parametrize('size', ['1e400', 'NaN', '-Infinity', '"16"'])
def test_a_grid_size_that_is_no_finite_number_is_named(tmp_path, tiny_dir, size):
    p = _copy(tiny_dir, tmp_path)
    m = _manifest(p)
    m['grid']['size'] = '@SIZE@'
    (p / 'manifest.json').write_text(json.dumps(m).replace('"@SIZE@"', size))
    with pytest.raises(ModelError, match='manifest.json.*GridSpec.size'):
        ModelBank.load(p)


def test_an_odd_grid_size_is_refused_naming_the_manifest(tmp_path, tiny_dir):
    # class files that fit a 5^3 grid: the inference engine raised a ValueError naming no file
    p = _copy(tiny_dir, tmp_path)
    for fn in sorted(p.glob('class_*.npz')):
        with np.load(fn) as z:
            cut = {k: z[k][:125] for k in ('W', 'mean', 'mean_variance')}
            cut['coarse_noise_map'] = z['coarse_noise_map'][:125 // 8]
        _rewrite_signed(p, fn, **cut)
    m = _manifest(p)
    m['grid']['size'] = 5
    _write_manifest(p, m)
    with pytest.raises(ModelError, match='manifest.json: grid size must be even.*got 5'):
        ModelBank.load(p)


def _rewrite_signed(p, fn, **changes):
    """Rewrite class file ``fn`` of model dir ``p`` with ``changes`` and a matching checksum."""
    from beo_ros.core.bank import _sha256
    with np.load(fn) as z:
        arr = {k: z[k] for k in z.files}
    np.savez(fn, **dict(arr, **changes))
    m = _manifest(p)
    m['files'][fn.name] = _sha256(fn)
    _write_manifest(p, m)


def test_a_subnormal_noise_variance_is_refused(tmp_path, tiny_dir):
    # it passed "> 0" and became 0 in float32: NaN scores and completions
    p = _copy(tiny_dir, tmp_path)
    fn = sorted(p.glob('class_00_*.npz'))[0]
    _rewrite_signed(p, fn, noise_variance=np.array(1e-320))
    with pytest.raises(ModelError, match=fn.name + '.*noise variances must be positive'):
        ModelBank.load(p)


@pytest.mark.parametrize('key,value,msg', [
    ('W', 1e20, "'W' has values up to 1e\\+20"),   # passed: NaN scores, IndexError in estimate
    ('mean', 1e30, "'mean' has values up to 1e\\+30"),
    ('loading_covariance', 1e300, "'loading_covariance' has values beyond the float32"),
    ('mean_variance', 1e300, "'mean_variance' has values beyond the float32"),   # Inf variance
    ('coarse_noise_map', 1e-37, 'coarse_noise_map must be 512 values in'),
    ('coarse_noise_map', 1e300, 'coarse_noise_map must be 512 values in'),
    ('noise_variance', 1e39, 'noise variances must be positive .* at most 3.4e\\+38'),
])
def test_values_that_overflow_the_float32_inference_are_refused(tmp_path, tiny_dir, key,
                                                                 value, msg):
    p = _copy(tiny_dir, tmp_path)
    fn = sorted(p.glob('class_00_*.npz'))[0]
    with np.load(fn) as z:
        a = z[key].astype(np.float64)
    if key in ('W', 'mean'):
        a = a / np.abs(a).max() * value
    else:
        a = np.eye(len(a)) * value if key == 'loading_covariance' else np.full(a.shape, value)
    _rewrite_signed(p, fn, **{key: a})
    m = _manifest(p)
    _write_manifest(p, dict(m, stage2_noise_map=True))
    with pytest.raises(ModelError, match=fn.name + '.*' + msg):
        ModelBank.load(p)
    # values short of the limits still load and estimate
    ok = {'W': 1e6, 'mean': 1e6, 'coarse_noise_map': 1e-30}.get(key, 1e30)
    _rewrite_signed(p, fn, **{key: a / value * ok})
    bank = ModelBank.load(p)
    est = bank.estimate(views()[1])
    assert est.label in bank.classes and np.isfinite(est.variance).all()


@pytest.mark.parametrize('noise_map,ok', [(None, True), ('short', False), ('zero', False)])
def test_optional_noise_map_is_checked(tmp_path, tiny_dir, noise_map, ok):
    # model directories without the per-voxel pose noise (older ones) still load; a bad map is
    # a ModelError naming the file
    from beo_ros.core.bank import _sha256
    p = _copy(tiny_dir, tmp_path)
    fn = sorted(p.glob('class_00_*.npz'))[0]
    with np.load(fn) as z:
        arr = {k: z[k] for k in z.files}
    if noise_map is None:
        del arr['coarse_noise_map']
    else:
        arr['coarse_noise_map'] = (arr['coarse_noise_map'][:10] if noise_map == 'short'
                                   else np.zeros_like(arr['coarse_noise_map']))
    np.savez(fn, **arr)
    m = _manifest(p)
    m['files'][fn.name] = _sha256(fn)
    _write_manifest(p, m)
    if ok:
        bank = ModelBank.load(p)
        assert bank.models[0].coarse_noise_map is None
        assert bank.models[1].coarse_noise_map is not None
        assert bank.estimate(views()[0]).label in bank.classes
    else:
        with pytest.raises(ModelError, match=fn.name + '.*coarse_noise_map'):
            ModelBank.load(p)


def test_load_models_and_public_api(tiny_dir):
    import beo_ros
    bank = beo_ros.load_models(tiny_dir)
    assert isinstance(bank, beo_ros.ModelBank) and bank.classes == ['box', 'cylinder']
    assert issubclass(beo_ros.ModelError, ValueError)


def test_load_refuses_a_file_path_and_names_it(tmp_path):
    f = tmp_path / 'model.npz'
    f.write_bytes(b'x')
    with pytest.raises(ModelError, match='model.npz is a file'):
        ModelBank.load(f)


@pytest.mark.parametrize('name', ['../outside.npz', 'sub/x.npz', '..'])
def test_load_refuses_files_outside_the_model_directory(tmp_path, tiny_dir, name):
    p = _copy(tiny_dir, tmp_path)
    m = _manifest(p)
    m['files'][name] = '0' * 64
    _write_manifest(p, m)
    with pytest.raises(ModelError, match='files must name files in the model directory'):
        ModelBank.load(p)


@pytest.mark.parametrize('name', ['classifier.npz', 'verifier.npz', 'calibration.npz'])
def test_load_refuses_an_optional_part_present_but_not_listed(tmp_path, tiny_dir, name):
    # the bank would otherwise run without it (a classifier: max likelihood) and not say so
    p = _copy(tiny_dir, tmp_path)
    (p / name).write_bytes(b'whatever')
    with pytest.raises(ModelError, match=f'{name} is present but not listed'):
        ModelBank.load(p)


def _racing_save(monkeypatch, hook, banks, path, times=1):
    """Make ModelBank.load save the next bank of ``banks`` (in turn) to ``path`` as it enters
    its ``hook`` (the first ``times`` times): a save of the directory it reads, in the middle
    of the read."""
    import beo_ros.core.bank as bank_mod
    orig, saves = getattr(bank_mod, hook), []

    def racing(*args):
        if len(saves) < times:
            saves.append(banks[len(saves) % len(banks)].save(path))
        return orig(*args)
    monkeypatch.setattr(bank_mod, hook, racing)
    return saves


def _pair(tmp_path):
    old = make_tiny_bank(tmp_path / 'm', n=8, k=2, seed=0)
    new = make_tiny_bank(n=8, k=2, seed=1)
    new.training = {'which': 'new'}
    return old, new, tmp_path / 'm'


def test_load_during_a_save_of_the_directory_loads_no_mix(tmp_path, monkeypatch):
    # the old manifest with the new class files loaded without a word (the checksums were
    # checked on the old files, the arrays read from the new ones)
    old, new, path = _pair(tmp_path)
    _racing_save(monkeypatch, '_load_class_models', [new], path)
    bank = ModelBank.load(path)
    W_new = np.array_equal(bank.models[0].W, new.models[0].W)
    assert W_new == (bank.training == {'which': 'new'}), (W_new, bank.training)
    np.testing.assert_array_equal(bank.models[1].W, (new if W_new else old).models[1].W)


def test_load_during_a_save_of_the_directory_reads_it_again(tmp_path, monkeypatch):
    # was '.../class_00_box.npz is corrupt: checksum does not match the manifest'
    old, new, path = _pair(tmp_path)
    saves = _racing_save(monkeypatch, '_manifest_layout', [new], path)
    bank = ModelBank.load(path)
    assert saves and bank.training == {'which': 'new'}
    np.testing.assert_array_equal(bank.models[0].W, new.models[0].W)


def test_load_during_two_saves_that_restore_the_manifest_reads_it_again(tmp_path, monkeypatch):
    # the new model is saved as the load checks the files (the old manifest's checksums fail),
    # then the old one again: the manifest text is the one read, the directory is not
    import beo_ros.core.bank as bank_mod
    old, new, path = _pair(tmp_path)
    _racing_save(monkeypatch, '_manifest_layout', [new], path)
    orig, calls = bank_mod._read_manifest, []

    def read_manifest(p):
        calls.append(p)
        if len(calls) == 2:   # after the failure
            old.save(path)
        return orig(p)
    monkeypatch.setattr(bank_mod, '_read_manifest', read_manifest)
    bank = ModelBank.load(path)   # was: 'class_00_box.npz is corrupt'
    np.testing.assert_array_equal(bank.models[0].W, old.models[0].W)


def test_load_that_finds_no_directory_between_the_renames_of_a_save_reads_it_again(
        tmp_path, monkeypatch):
    # was 'model directory ... does not exist' for a directory that a save was replacing
    import beo_ros.core.bank as bank_mod
    old, new, path = _pair(tmp_path)
    orig, calls = bank_mod._read_manifest, []

    def read_manifest(p):
        calls.append(p)
        if len(calls) == 1:   # the first rename of a save has just moved the old model away
            path.rename(tmp_path / 'old')
            try:
                return orig(p)
            finally:
                new.save(path)   # the second one
        return orig(p)
    monkeypatch.setattr(bank_mod, '_read_manifest', read_manifest)
    assert ModelBank.load(path).training == {'which': 'new'} and len(calls) == 2
    with pytest.raises(ModelError, match='does not exist'):   # no directory: no retry
        ModelBank.load(tmp_path / 'none')
    assert len(calls) == 3


def test_load_that_begins_between_the_renames_of_a_save_waits_for_it(tmp_path, monkeypatch):
    # was 'model directory ... does not exist': the directory was already gone when the load
    # began, and gone still when it looked again; now it waits in steps while the save's
    # temporary directories are beside it (here: each step lets the save end)
    import threading
    import beo_ros.core.bank as bank_mod
    old, new, path = _pair(tmp_path)
    gap, go, sleeps = threading.Event(), threading.Event(), []
    replace = os.replace

    def paused_replace(src, dst):
        replace(src, dst)
        if Path(src) == path:   # the first rename: the old model is moved away
            gap.set()
            go.wait(60)
    monkeypatch.setattr(bank_mod.os, 'replace', paused_replace)
    saving = threading.Thread(target=new.save, args=(path,))
    saving.start()
    try:
        assert gap.wait(60)

        def sleep(seconds):
            sleeps.append(seconds)
            go.set()
            saving.join(60)
        monkeypatch.setattr(bank_mod.time, 'sleep', sleep)
        assert ModelBank.load(path).training == {'which': 'new'}
    finally:
        go.set()
        saving.join(60)
    assert sleeps == [bank_mod.SAVE_WAIT_STEP_S]


def test_load_waits_a_bounded_time_for_a_save_in_progress(tmp_path, monkeypatch):
    import beo_ros.core.bank as bank_mod
    sleeps = []
    monkeypatch.setattr(bank_mod.time, 'sleep', sleeps.append)
    (tmp_path / '.m.tmp-0123456789ab').mkdir()   # a save writing (or one that was killed)
    with pytest.raises(ModelError, match=r'm does not exist \(a save into .*m was in progress '
                                         r'for 1 s\)'):
        ModelBank.load(tmp_path / 'm')
    assert sleeps == [bank_mod.SAVE_WAIT_STEP_S] * bank_mod.SAVE_WAIT_STEPS
    with pytest.raises(ModelError, match='n does not exist$'):   # no save of it: no wait
        ModelBank.load(tmp_path / 'n')
    assert len(sleeps) == bank_mod.SAVE_WAIT_STEPS


def test_load_of_a_directory_saved_over_and_over_says_so(tmp_path, monkeypatch):
    from beo_ros.core.bank import LOAD_ATTEMPTS
    old, new, path = _pair(tmp_path)
    saves = _racing_save(monkeypatch, '_manifest_layout', [new, old], path, times=10)
    with pytest.raises(ModelError, match=f'corrupt.*was replaced while it was read, '
                                         f'{LOAD_ATTEMPTS} times'):
        ModelBank.load(path)
    assert len(saves) == LOAD_ATTEMPTS


# ---------------------------------------------------------------------- the point-cloud path
def test_estimate_points_pose_and_points(tiny):
    occ = tiny.models[0].mean.reshape((N,) * 3) > 0.5
    pts, origin = render_view_points(occ, 0.5, 0.3, np.deg2rad(30), distance=2.0, size=0.4)
    e = tiny.estimate_points(pts, sensor_origin=origin)
    assert e.pose.shape == (4, 4)
    R = e.pose[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(R) > 0
    np.testing.assert_allclose(R[:, 2], [0, 0, 1], atol=1e-6)   # z axis = up
    np.testing.assert_allclose(e.pose[3], [0, 0, 0, 1])
    assert np.linalg.norm(e.pose[:3, 3]) < 0.3                 # the object is at the origin
    assert e.completed_points.dtype == np.float32 and e.completed_points.shape[1] == 3
    assert len(e.completed_points) > 0 and np.isfinite(e.completed_points).all()
    assert len(e.completed_probability) == len(e.completed_points)
    assert e.completed_probability.min() >= 0.5
    assert 'voxelize' in e.timings and e.label in tiny.classes + ['unknown']


def test_estimate_points_pose_keeps_its_precision_far_from_the_origin(tiny):
    # the pose is float64: its centre came from the float32 completed points, 1-13 mm off at
    # 1e4-1e6 m (a map frame), while the grid placement (float64) stayed exact
    occ = tiny.models[0].mean.reshape((N,) * 3) > 0.5
    pts, origin = render_view_points(occ, 0.5, 0.3, np.deg2rad(30), distance=2.0, size=0.4)
    e0 = tiny.estimate_points(pts, sensor_origin=origin, outlier_mads=None)
    shift = np.array([9e5, -7e5, 10.0])
    e = tiny.estimate_points(pts + shift, sensor_origin=origin + shift, outlier_mads=None)
    np.testing.assert_allclose(e.grid_to_input[:3, 3] - shift, e0.grid_to_input[:3, 3],
                               atol=1e-6)
    np.testing.assert_allclose(e.pose[:3, 3] - shift, e0.pose[:3, 3], atol=1e-6)
    assert e.completed_points.dtype == np.float32


def test_estimate_points_heading_is_the_same_from_every_side(tiny):
    # yaw is in the grid frame, whose x axis follows the bearing from the sensor; yaw +
    # heading_offset is the heading in the input frame (here up = +z: from the x axis)
    occ = tiny.models[0].mean.reshape((N,) * 3) > 0.5        # a box, 180 deg symmetric
    yaws, headings = [], []
    for az in (0.3, 1.5, 2.8, 4.0):
        pts, origin = render_view_points(occ, 0.5, az, np.deg2rad(30), distance=2.0, size=0.4)
        e = tiny.estimate_points(pts, sensor_origin=origin)
        h = e.yaw + e.heading_offset
        pose_heading = np.arctan2(e.pose[1, 0], e.pose[0, 0])
        assert np.rad2deg(yaw_error(h, pose_heading)) < 1e-6
        yaws.append(e.yaw)
        headings.append(h)
    # up to the box's half turn, three of the four views agree with the true 0.5 rad
    off = [min(yaw_error(h, 0.5), yaw_error(h, 0.5 + np.pi)) for h in headings]
    assert np.sum(np.rad2deg(off) < 15) >= 3, np.rad2deg(headings).round()
    # while the grid-frame yaws follow the sensor around
    assert np.ptp(np.rad2deg(np.mod(yaws, np.pi))) > 60


def test_estimate_points_takes_up_at_any_positive_scale(points_bank):
    # up is a direction: 1e300 x up (accepted by the voxelization) gives the same heading and
    # point descriptors as the unit vector, not an overflowed norm
    bank, pts, origin, *_ = points_bank
    a = bank.estimate_points(pts, sensor_origin=origin, up=(0.0, 0.0, 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter('error', RuntimeWarning)
        b = bank.estimate_points(pts, sensor_origin=origin, up=(0.0, 0.0, 1e300))
    assert b.classifier_mode == a.classifier_mode == 'points'
    np.testing.assert_allclose(b.point_features, a.point_features, rtol=1e-9)
    assert b.heading_offset == pytest.approx(a.heading_offset)
    assert b.yaw == pytest.approx(a.yaw)
    np.testing.assert_allclose(b.pose, a.pose, atol=1e-9)


def test_heading_offset_for_a_camera_frame():
    from beo_ros.core.bank import heading_offset
    # optical frame, level: up = -y; reference axis = x (horizontal); the grid x axis along
    # the optical z axis (straight ahead) is a quarter turn from x about up (-y x x = +z)
    R = np.column_stack([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert np.rad2deg(heading_offset(R, (0.0, -1.0, 0.0))) == pytest.approx(90.0)
    # x along up: the y axis is the reference
    R = np.column_stack([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    assert heading_offset(R, (2.0, 0.0, 0.0)) == pytest.approx(0.0)


def test_pose_centre_is_the_middle_of_a_short_object_on_a_bottom_grid():
    # the tabletop model's grids sit on the support ('bottom'): the grid centre is 0.24 m up,
    # above this 0.12 m box; the pose is at the middle of the completed box
    import beo_ros
    bank = beo_ros.load_models(Path(__file__).resolve().parents[1] / 'models' / 'tabletop_32')
    assert bank.spec.anchor == 'bottom'
    rng = np.random.default_rng(0)
    L, W, H = 0.16, 0.10, 0.12
    top = np.c_[rng.uniform(-L / 2, L / 2, 800), rng.uniform(-W / 2, W / 2, 800),
                np.full(800, H)]
    front = np.c_[np.full(800, -L / 2), rng.uniform(-W / 2, W / 2, 800), rng.uniform(0, H, 800)]
    e = bank.estimate_points(np.r_[top, front], sensor_origin=(-0.8, 0.0, 0.5))
    assert abs(e.pose[2, 3] - H / 2) < 0.03, e.pose[:3, 3]
    assert np.linalg.norm(e.pose[:2, 3]) < 0.03, e.pose[:3, 3]


def test_too_few_points_left_by_the_cleaning_says_so(tiny):
    # 100 finite points, 98 off the largest cluster: the error said "need at least 10 finite
    # points, got 2", as if the cloud had 2 finite points
    rng = np.random.default_rng(0)
    pts = np.c_[np.full(100, 1.0), rng.uniform(-0.05, 0.05, 100), rng.uniform(0, 0.1, 100)]
    with pytest.raises(ValueError, match=r'got 2 of the 100 finite ones after removing 0 '
                                         r'outliers .* and 98 outside the largest cluster '
                                         r'\(cluster_tolerance 0.001\)'):
        tiny.estimate_points(pts, cluster_tolerance=0.001)
    with pytest.raises(ValueError, match='need at least 10 finite points, got 5'):
        tiny.estimate_points(pts[:5])


@pytest.mark.parametrize('threshold', [float('nan'), 0.0, -1.0, 1.5, True, '0.5', None])
def test_estimate_points_refuses_a_threshold_that_is_no_probability(tiny, threshold):
    occ = tiny.models[0].mean.reshape((N,) * 3) > 0.5
    pts, origin = render_view_points(occ, 0.5, 0.3, np.deg2rad(30), distance=2.0, size=0.4)
    with pytest.raises(ValueError, match='threshold must be'):
        tiny.estimate_points(pts, sensor_origin=origin, threshold=threshold)


# ---------------------------------------------------------------------- pose on asymmetric shapes
@pytest.fixture(scope='module')
def pose_case():
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_bank
    X, y = asymmetric_shapes(12, np.random.default_rng(0))
    bank = fit_bank(X, y, ['ell', 'step'], GridSpec(size=N), k=4, pose_components=4,
                    classifier_views=0, seed=0)
    Xt, yt = asymmetric_shapes(4, np.random.default_rng(5))
    rng = np.random.default_rng(1)
    cases = []     # (grid, true yaw, true class, 'complete' | 'partial')
    for i in range(len(Xt)):
        occ = Xt[i].reshape((N,) * 3) > 0.5
        for _ in range(2):
            yaw = rng.uniform(-np.pi, np.pi)
            rot = rotate_grid(occ.astype(np.uint8), yaw).astype(bool)
            pv = partial_view(rot, rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(10, 50)))
            cases += [(rot.astype(np.int8), yaw, yt[i], 'complete'), (pv, yaw, yt[i], 'partial')]
    return bank, cases


def test_asymmetric_means_are_not_yaw_symmetric(pose_case):
    bank, _ = pose_case
    for m in bank.models:
        mean = m.mean.reshape((N,) * 3)
        for deg in (90, 180, 270):
            assert np.abs(rotate_grid(mean, np.deg2rad(deg)) - mean).mean() > 0.05


def test_pose_of_rotated_objects(pose_case):
    # The pose search scores yaws on the 2x-pooled grid with nearest-neighbour rotation: at 16^3
    # (pooled 8^3) all yaws within about +-7 deg of a multiple of 90 give the same pooled grid,
    # so the yaw resolution is several degrees, not yaw_step_deg. Measured (true class, 1 deg
    # step, the model rotated into the observed frame): complete views median 5.8 deg, max
    # 20.9, 12 of 16 within 15; partial views median 6.9 deg, max 24.9, 12 of 16 (16 views
    # each). Rotating the observation into the model's frame instead scored 4.2 / 3.8 deg here,
    # because these views were made by the same nearest-neighbour rotation it then undid; on
    # ModelNet10 at 32^3 it lost (see README: yaw within 10 deg 0.70 -> 0.73 of 397 views).
    bank, cases = pose_case
    for mode in ('complete', 'partial'):
        err = []
        for g, yaw, c, m in cases:
            if m == mode:
                ye, _, _ = bank.engine.search(g, 1.0, exhaustive=True)
                err.append(np.rad2deg(abs(wrap(ye[c] - yaw))))
        err = np.array(err)
        assert np.median(err) <= 8.0, (mode, err.round(1))
        assert np.mean(err <= 15) >= 0.7, (mode, err.round(1))
        assert err.max() <= 30, (mode, err.round(1))


@pytest.mark.xfail(strict=True, reason='yaw resolution of the pooled 8^3 search at 16^3 is '
                   '~+-7 deg (see test_pose_of_rotated_objects): errors up to ~20 deg')
def test_pose_within_a_few_degrees(pose_case):
    bank, cases = pose_case
    err = [np.rad2deg(abs(wrap(bank.engine.search(g, 1.0, exhaustive=True)[0][c] - yaw)))
           for g, yaw, c, _ in cases]
    assert max(err) <= 5, np.round(err, 1)


def test_coarse_to_fine_agrees_with_exhaustive(pose_case):
    # Measured on these 32 views (true class): the best yaw agrees within 1 deg in 15 of 32 and
    # the log-likelihoods are equal in 15; in the others coarse-to-fine misses the exhaustive
    # optimum (the peaks on the pooled 8^3 grid are narrower than the 5 deg coarse step). At
    # 16^3 coarse-to-fine is not good enough, which is why estimate() searches exhaustively.
    bank, cases = pose_case
    eng = bank.engine
    same, gaps = [], []
    for g, yaw, c, _ in cases:
        ye, lle, _ = eng.search(g, 1.0, exhaustive=True)
        yc, llc, _ = eng.search(g, 1.0, exhaustive=False)
        # the coarse-to-fine candidates are a subset of the exhaustive yaws: never better
        assert np.all(llc <= lle + 1e-4 * np.abs(lle))
        same.append(np.rad2deg(abs(wrap(ye[c] - yc[c]))) <= 1.0 + 1e-9)
        gaps.append(lle[c] - llc[c])
    assert np.mean(same) >= 0.4, (np.mean(same), np.round(gaps, 1))
    # the same optimum: equal log-likelihood (a tie or the same yaw) for a large part
    assert np.mean(np.array(gaps) <= 1e-4 * np.abs(lle).max()) >= 0.4, np.round(gaps, 1)


def test_coarse_to_fine_keeps_both_modes_and_scores_them_exactly(pose_case):
    # the coarse-to-fine candidates are two windows, not a circular grid: both modes survive
    # into the hypotheses, and each window holds its coarse mode itself (at a 2 degree step too)
    bank, cases = pose_case
    g, *_ = cases[0]
    for step in (1.0, 2.0):
        _, _, per = bank.engine.search(g, step, exhaustive=False)
        yaws, _ = per[0]
        deg = np.rad2deg(yaws)
        assert len(yaws) == 2 * (2 * int(round(5 / step)) + 1)
        centres = deg.reshape(2, -1)[:, len(yaws) // 4]
        assert np.allclose((centres + 2.5) % 5 - 2.5, 0, atol=1e-6), deg
    # a coarse step no larger than the step: every yaw is scored
    _, _, per = bank.engine.search(g, 5.0, coarse_step_deg=5.0, exhaustive=False)
    assert len(per[0][0]) == 72
    est = bank.estimate(g, exhaustive=False)
    ys = [h.yaw for h in est.hypotheses if h.label == est.label]
    assert len(ys) >= 2


def test_estimate_takes_array_probes_and_no_stage2_window(pose_case):
    bank, cases = pose_case
    g, *_ = cases[0]
    ref = bank.estimate(g, probe_deg=(10, 20))
    assert bank.estimate(g, probe_deg=np.array([10, 20])).yaw == pytest.approx(ref.yaw)
    # one offset may be given as a number
    assert bank.estimate(g, probe_deg=10).yaw == pytest.approx(
        bank.estimate(g, probe_deg=(10,)).yaw)
    for bad in (object(), 'x', -5, np.nan, True):
        with pytest.raises(ValueError, match='probe_deg'):
            bank.estimate(g, probe_deg=bad)
    for name in ('refine_deg', 'stage2_window_deg'):
        with pytest.raises(ValueError, match=name):
            bank.estimate(g, **{name: True})
    # no window: stage 2 scores every yaw, as with stage2_modes=None
    assert bank.estimate(g, stage2_window_deg=None).yaw == pytest.approx(
        bank.estimate(g, stage2_modes=None).yaw)


def test_top_yaw_modes_separates_by_angle():
    from beo_ros.core.inference import top_yaw_modes
    yaws = np.deg2rad([40, 41, 42, 10, 11, 12, 359, 1])
    scores = np.array([9, 10, 8, 7, 6, 5, 4, 3], dtype=float)
    assert top_yaw_modes(yaws, scores, 3) == [1, 3]        # 359 and 1 are 12-13 deg from 11
    assert top_yaw_modes(yaws, scores, 3, min_sep_deg=5) == [1, 3, 6]
    # modes exactly min_sep_deg apart are separated, whatever the rounding of their radians
    deg = np.deg2rad(np.arange(360.0))
    for a in (0, 58, 100, 300):
        s = np.zeros(360)
        s[a], s[(a + 20) % 360] = 2.0, 1.0
        assert top_yaw_modes(deg, s, 2, min_sep_deg=20) == [a, (a + 20) % 360]
    # on a regular circular grid the index-based top_modes picks what it picks among the
    # grid's local maxima
    from beo_ros.core.inference import top_modes
    rng = np.random.default_rng(0)
    ll = rng.normal(size=360)
    peaks = [i for i in range(360) if ll[i] >= ll[i - 1] and ll[i] >= ll[(i + 1) % 360]]
    assert [peaks[i] for i in top_yaw_modes(np.deg2rad(peaks), ll[peaks], 3)] == \
        top_modes(ll, 3, 20)


def test_top_yaw_modes_refuses_no_modes():
    # n_modes=0 never met the "enough modes" check and returned every separated mode
    from beo_ros.core.inference import top_modes, top_yaw_modes
    yaws = np.deg2rad([0, 90, 180])
    scores = np.array([3.0, 2.0, 1.0])
    for bad in (0, -1, True, 1.5):
        with pytest.raises(ValueError, match='n_modes'):
            top_yaw_modes(yaws, scores, bad)
    with pytest.raises(ValueError, match='n_modes'):
        top_modes(np.arange(36.0) % 7, 0, 2)
    assert top_yaw_modes(yaws, scores, np.int64(1)) == [0]


def test_top_modes_are_local_maxima():
    # a second mode 20 steps down the slope of the best one is no mode: the hypotheses listed
    # such yaws (a neighbour scoring higher) for 17 of 60 secondary modes on ModelNet views
    from beo_ros.core.inference import top_modes
    deg = np.arange(360)
    ll = np.maximum(-((deg - 100) / 30.0) ** 2, -3 - ((deg - 250) / 10.0) ** 2)
    assert top_modes(ll, 3, 20) == [100, 250]
    assert top_modes(np.roll(ll, 300), 2, 20) == [40, 190]   # across 0 too
    assert len(top_modes(np.zeros(36), 2, 10)) == 2   # a plateau's yaws are all maxima


@pytest.mark.parametrize('size', [32.0, np.int64(16)])
def test_grid_spec_size_becomes_an_int(size):
    from beo_ros.core.grid import GridSpec
    spec = GridSpec(size=size)
    assert type(spec.size) is int and spec.shape == (int(size),) * 3


@pytest.mark.parametrize('size', [32.5, True, '32', 3, 300])
def test_grid_spec_refuses_a_bad_size(size):
    from beo_ros.core.grid import GridSpec
    with pytest.raises(ValueError, match='GridSpec.size'):
        GridSpec(size=size)


def test_engine_refuses_an_odd_grid():
    from beo_ros.core.inference import InferenceEngine
    d = 15 ** 3
    with pytest.raises(ValueError, match='even'):
        InferenceEngine(np.zeros((1, d, 2), np.float32), np.zeros((1, d), np.float32),
                        np.ones(1), np.ones(1), 15, pose_components=2)


# ---------------------------------------------------------------------- classifier path
@pytest.fixture(scope='module')
def clf_bank():
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_bank
    X, y, names = primitive_shapes(N, 8, np.random.default_rng(0))
    return fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3,
                    classifier_views=1, folds=2, seed=0), X, y


def test_classifier_modes_and_cross_validation(clf_bank, tmp_path):
    from beo_ros.core.training import MLP_HIDDEN
    bank, X, y = clf_bank
    assert set(bank.classifier) == {'complete', 'partial'}
    cv = bank.training['cross_validation']
    for mode, clf in bank.classifier.items():
        # 'auto': the 12 per-class features, plus the shape descriptors if they won
        assert bool(clf['descriptors']) == cv[mode]['descriptors']
        n_in = 12 + len(DESCRIPTOR_NAMES) * cv[mode]['descriptors']
        if cv[mode]['kind'] == 'mlp':   # 'auto' also tries the one-layer network
            assert clf['hidden_coef'].shape == (MLP_HIDDEN, n_in)
            assert clf['coef'].shape == (2, MLP_HIDDEN)
        else:
            assert clf['coef'].shape == (2, n_in) and 'hidden_coef' not in clf
        assert clf['unknown_threshold'].shape == (2,)
    assert set(cv) == {'complete', 'partial'}
    for mode, rep in cv.items():
        assert rep['n'] == 16
        assert 0 <= rep['accuracy'] <= 1 and 0 <= rep['accuracy_max_likelihood'] <= 1
    assert 0 <= cv['partial']['iou'] <= 1 and 0 <= cv['partial']['yaw_within_10'] <= 1
    # the classifier survives save/load and gives the same answer
    again = ModelBank.load(bank.save(tmp_path / 'clf'))
    g = X[0].reshape((N,) * 3).astype(np.int8)
    e1, e2 = bank.estimate(g), again.estimate(g)
    assert e1.label == e2.label and e1.scores == pytest.approx(e2.scores)
    # training objects (complete, yaw 0) are mostly classified right
    labels = [bank.estimate(X[i].reshape((N,) * 3).astype(np.int8), yaw=0.0).label
              for i in range(len(X))]
    assert np.mean(np.array(labels) == np.array(bank.classes)[y]) >= 0.75


@pytest.mark.xfail(strict=True, reason="'unknown' is never returned here: the box class's "
                   'unknown_threshold is far below any real value (per-voxel loglik): median '
                   '- 8 MAD of the '
                   'out-of-fold log-likelihoods of only 8 boxes in 2 folds, which spread over '
                   'orders of magnitude because each fold fits its boxes with a tiny noise '
                   'variance; random scatter scores about -4 to -10 and is called box with '
                   'p ~ 0.8-0.99')
def test_unknown_for_random_scatter(clf_bank):
    bank, _, _ = clf_bank
    rng = np.random.default_rng(0)
    for dens in (0.05, 0.15, 0.3):
        g = (rng.random((N,) * 3) < dens).astype(np.int8)
        assert bank.estimate(g).label == 'unknown'


def test_classifier_input_row_standardize_removes_per_object_affine_changes():
    from beo_ros.core.bank import classifier_input
    from beo_ros.core.inference import FEATURE_NAMES
    nf = len(FEATURE_NAMES)
    rng = np.random.default_rng(0)
    F = rng.normal(size=(5, 3 * nf))
    assert np.array_equal(classifier_input(F, 3), F)
    Z = classifier_input(F, 3, row_standardize=True).reshape(5, 3, nf)
    assert np.allclose(Z.mean(axis=1), 0) and np.allclose(Z.std(axis=1), 1)
    # what an object does to every class alike (per-feature scale and offset) drops out
    a, b = rng.uniform(0.1, 10, (5, 1, nf)), rng.normal(size=(5, 1, nf))
    G = (F.reshape(5, 3, nf) * a + b).reshape(5, -1)
    assert np.allclose(classifier_input(G, 3, True), Z.reshape(5, -1))
    # one (C, F) array is one row
    assert np.allclose(classifier_input(F[0].reshape(3, nf), 3, True), Z[:1].reshape(1, -1))


def _three_shapes(n, count, rng):
    X, y, _ = primitive_shapes(n, count, rng)
    c = (n - 1) / 2.0
    ii, jj, kk = np.meshgrid(*(np.arange(n) - c,) * 3, indexing='ij')
    extra = []
    for _ in range(count):  # a third class: ellipsoids
        a, b, h = rng.uniform(0.25, 0.45, 3) * n
        extra.append(((ii / a) ** 2 + (jj / (0.6 * b)) ** 2 + (kk / h) ** 2 <= 1).ravel())
    return (np.vstack([X, np.array(extra, dtype=np.float32)]),
            np.concatenate([y, np.full(count, 2)]), ['box', 'cylinder', 'ellipsoid'])


def test_row_standardized_classifier_is_chosen_saved_and_checked(tmp_path):
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_bank
    X, y, names = _three_shapes(N, 6, np.random.default_rng(3))
    bank = fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3, classifier_views=1,
                    folds=2, seed=0, row_standardize=True)
    for mode, clf in bank.classifier.items():
        assert bool(clf['row_standardize'])
        assert bank.training['cross_validation'][mode]['row_standardize'] is True
    again = ModelBank.load(bank.save(tmp_path / 'rs'))
    assert all(bool(c['row_standardize']) for c in again.classifier.values())
    g = X[-1].reshape((N,) * 3).astype(np.int8)
    e1, e2 = bank.estimate(g, yaw=0.0), again.estimate(g, yaw=0.0)
    assert e1.label == e2.label and e1.scores == pytest.approx(e2.scores)
    # the input rule changes the answer: the same weights on raw features differ
    raw = dict(again.classifier['complete'], row_standardize=np.asarray(False))
    f, _ = again.features(g, yaw=0.0)
    assert not np.allclose(again.classify_features(f, 'complete', g)[0],
                           ModelBank(again.models, again.spec, {'complete': raw}
                                     ).classify_features(f, 'complete', g)[0])
    # 'auto' tries both and records the other one's accuracy
    auto = fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3, classifier_views=1,
                    folds=2, seed=0)
    rep = auto.training['cross_validation']['complete']
    assert isinstance(rep['row_standardize'], bool) and 0 <= rep['accuracy_other_input'] <= 1
    assert rep['accuracy'] >= rep['accuracy_other_input']
    # two classes: only raw features
    with pytest.raises(ValueError, match='at least 3 classes'):
        fit_bank(X[y < 2], y[y < 2], names[:2], GridSpec(size=N), k=3, classifier_views=1,
                 folds=2, row_standardize=True)
    with pytest.raises(ValueError, match='row_standardize'):
        fit_bank(X, y, names, GridSpec(size=N), k=3, row_standardize='yes')


def test_unknown_when_the_classes_that_explain_the_object_hold_little_probability():
    # three classes; the classifier's weights put the winner by the second feature, the
    # bound is on the first (per-voxel log-likelihood)
    from beo_ros.core.inference import FEATURE_NAMES
    nf = len(FEATURE_NAMES)
    bank = make_tiny_bank(n=8, k=2)
    models = bank.models + [dataclasses.replace(bank.models[0], name='box2')]
    coef = np.zeros((3, 3 * nf))
    for c in range(3):
        coef[c, c * nf + 1] = 1.0
    clf = dict(mean=np.zeros(3 * nf), scale=np.ones(3 * nf), coef=coef, intercept=np.zeros(3),
               unknown_threshold=np.array([-1.0, -1.0, -1.0]))
    b3 = ModelBank(models, bank.spec, {'complete': clf})
    feats = np.zeros((3, nf))
    feats[:, 1] = [np.log(0.4), np.log(0.35), np.log(0.25)]  # probabilities 0.4, 0.35, 0.25
    feats[:, 0] = [0.0, -5.0, -5.0]  # only the winner explains it: 0.4 < 0.5
    p, unknown = b3.classify_features(feats, 'complete')
    assert np.argmax(p) == 0 and p[0] == pytest.approx(0.4) and unknown
    feats[:, 0] = [0.0, 0.0, -5.0]  # the explaining classes hold 0.75
    assert not b3.classify_features(feats, 'complete')[1]
    feats[:, 0] = [-5.0, 0.0, 0.0]  # the winner itself does not explain it
    assert b3.classify_features(feats, 'complete')[1]


def test_non_finite_logits_are_an_error_not_the_first_class():
    """A subnormal scale (or weights) that overflow the logits gave NaN probabilities, and
    argmax named the first class without a word; it is an error naming the logits."""
    from beo_ros.core.inference import FEATURE_NAMES
    nf = len(FEATURE_NAMES)
    bank = make_tiny_bank(n=8, k=2)
    coef = np.zeros((2, 2 * nf))
    coef[:, 1] = [1.0, -1.0]
    scale = np.ones(2 * nf)
    clf = dict(mean=np.zeros(2 * nf), scale=scale, coef=coef, intercept=np.zeros(2),
               unknown_threshold=np.full(2, -np.inf))
    b2 = ModelBank(bank.models, bank.spec, {'complete': clf})
    feats = np.zeros((2, nf))
    feats[:, 1] = [0.3, 0.3]
    assert np.isfinite(b2.classify_features(feats, 'complete')[0]).all()
    scale[1] = 1e-320   # the second feature of class 0: its logit +inf, class 1's -inf
    with pytest.raises(ValueError, match='non-finite logits'):
        b2.classify_features(feats, 'complete')


def test_cross_validated_report_keeps_the_views_of_an_object_in_one_fold():
    # 3 identical rows (views) per object, random labels: a classifier that saw one view of
    # an object answers its other views from memory; grouped by object it is at chance
    from beo_ros.core.inference import FEATURE_NAMES
    from beo_ros.core.training import cross_validated_report
    rng = np.random.default_rng(0)
    n_obj = 40
    F0 = rng.normal(size=(n_obj, 20 * len(FEATURE_NAMES)))
    y0 = np.arange(n_obj) % 2
    F, y, groups = np.repeat(F0, 3, axis=0), np.repeat(y0, 3), np.repeat(np.arange(n_obj), 3)
    leaky = cross_validated_report(F, y, [], folds=5)['accuracy']
    grouped = cross_validated_report(F, y, [], folds=5, groups=groups)['accuracy']
    assert leaky > 0.9 and grouped < 0.75, (leaky, grouped)
    # one row per object: the same as without groups
    assert (cross_validated_report(F0, y0, [], groups=np.arange(n_obj))
            == cross_validated_report(F0, y0, []))


def test_binary_classifier_probabilities_are_the_regressions():
    from sklearn.linear_model import LogisticRegression
    from beo_ros.core.bank import classifier_probabilities
    from beo_ros.core.inference import FEATURE_NAMES
    from beo_ros.core.training import train_classifier
    rng = np.random.default_rng(1)
    y = np.arange(60) % 2
    F = rng.normal(size=(60, 2 * len(FEATURE_NAMES))) + y[:, None]
    clf = train_classifier(F, y, 2)
    p, _ = classifier_probabilities(clf, F, F[:, 0::len(FEATURE_NAMES)])
    Z = (F - F.mean(axis=0)) / (F.std(axis=0) + 1e-9)
    want = LogisticRegression(max_iter=2000).fit(Z, y).predict_proba(Z)
    assert np.allclose(p, want, atol=1e-6)


def test_two_class_model_with_row_standardized_classifier_is_refused(clf_bank, tmp_path):
    bank, _, _ = clf_bank
    clf = {mode: dict(c, row_standardize=np.asarray(True)) for mode, c in bank.classifier.items()}
    with pytest.raises(ModelError, match="model bank: classifier 'complete' .*at least 3 classes"):
        ModelBank(bank.models, bank.spec, clf, bank.training)
    path = bank.save(tmp_path / 'two')
    _rewrite_npz(path, 'classifier.npz', partial__row_standardize=np.asarray(True))
    with pytest.raises(ModelError, match="classifier 'partial' .*at least 3 classes"):
        ModelBank.load(path)


@pytest.mark.parametrize('change, msg', [
    (dict(coef=lambda c: c[:, :3]), "'coef' has shape"),   # estimate: numpy's matmul error
    (dict(descriptors=lambda c: np.asarray('no')), "'descriptors' must be true or false"),
    (dict(mean=None), "no 'mean'"),
    (dict(scale=lambda c: np.zeros_like(c)), "'scale' must be positive"),
])
def test_constructor_refuses_the_grid_classifiers_that_load_refuses(clf_bank, tmp_path, change,
                                                                    msg):
    # the bank was built, then save wrote a directory that load refused
    bank, _, _ = clf_bank
    clf = {mode: dict(c) for mode, c in bank.classifier.items()}
    for k, f in change.items():
        if f is None:
            del clf['partial'][k]
        else:
            clf['partial'][k] = f(clf['partial'][k])
    with pytest.raises(ModelError, match=f"model bank: classifier 'partial'.*{msg}"):
        ModelBank(bank.models, bank.spec, clf, bank.training)
    with pytest.raises(ModelError, match="classifier 'partial' must be a dict"):
        ModelBank(bank.models, bank.spec, dict(clf, partial=[1.0]), bank.training)


def test_constructor_refuses_unexpected_grid_classifier_arrays(clf_bank):
    bank, _, _ = clf_bank
    clf = dict(bank.classifier, partial=dict(bank.classifier['partial'], descriptor=True))
    with pytest.raises(ModelError, match=r"'partial' has unexpected arrays \['descriptor'\]"):
        ModelBank(bank.models, bank.spec, clf, bank.training)


@pytest.mark.parametrize('change, msg', [
    (dict(noise_variance=0.0), 'noise variances must be positive'),
    (dict(noise_variance=np.nan), 'NaN or Inf'),
    (dict(coarse_noise_variance=-1.0), 'noise variances must be positive'),
    (dict(mean='nan'), 'NaN or Inf'),
    (dict(loading_covariance=np.eye(7, dtype=np.float32)), "'loading_covariance' has shape"),
    (dict(mean_variance=np.zeros(5, np.float32)), "'mean_variance' has shape"),
])
def test_constructor_refuses_the_class_models_that_load_refuses(tiny, change, msg):
    # a zero or NaN noise variance gave NaN class probabilities and a label without a word, a
    # NaN mean an IndexError, a loading covariance of another k numpy's errors in the
    # completion: load refuses them (check_class_arrays), the constructor took them
    if change.get('mean') == 'nan':
        change = dict(mean=np.where(np.arange(N ** 3) == 0, np.nan, tiny.models[0].mean))
    bad = dataclasses.replace(tiny.models[0], **change)
    with pytest.raises(ModelError, match=f"class 'box': .*{msg}"):
        ModelBank([bad, tiny.models[1]], tiny.spec)


@pytest.mark.parametrize('noise_map', [np.full(N ** 3 // 8, np.nan), np.zeros(N ** 3 // 8),
                                       np.ones(5)])
def test_constructor_refuses_the_coarse_noise_maps_that_load_refuses(tiny, noise_map):
    # stage 2 with the map (stage2_noise_map=True) divides by it: NaN or 0 made every score
    # NaN and estimate raised IndexError, a map of another size numpy's broadcast error
    bad = [dataclasses.replace(m, coarse_noise_map=noise_map.astype(np.float32))
           for m in tiny.models]
    with pytest.raises(ModelError, match="class 'box': coarse_noise_map must be 512 values"):
        ModelBank(bad, tiny.spec, stage2_noise_map=True)


def test_full_resolution_refinement_sharpens_the_yaw(pose_case):
    # estimate() re-solves the chosen class exactly at full resolution within +-3 deg of the
    # pooled optimum; on these asymmetric shapes that must beat the pooled search (measured:
    # median 7.2 deg pooled, 5.5 refined, of 32 views at 16^3)
    bank, cases = pose_case
    pooled, refined = [], []
    for g, yaw, c, _ in cases:
        _, per = bank.features(g)
        pooled.append(np.rad2deg(abs(wrap(per[c]['yaw'] - yaw))))
        ref = bank._refine(g, c, per[c], 1.0, 3.0, stage2_step_deg=None)
        assert ref['exact']['loglik'] >= per[c]['exact']['loglik']
        refined.append(np.rad2deg(abs(wrap(ref['yaw'] - yaw))))
    assert np.median(refined) < np.median(pooled), (np.round(pooled, 1), np.round(refined, 1))
    assert np.median(refined) <= 6.0, np.round(refined, 1)


def test_exact_probes_recover_yaws_the_pooled_optimum_misses(pose_case):
    # _refine solves exactly at +-10 and +-20 deg of the pooled optimum before climbing; on
    # these views the pooled optimum is often several degrees off (measured, 32 views at 16^3:
    # median error 4.9 deg without probes, 1.2 with; within 5 deg 0.50 -> 0.94; 17 views
    # better by > 1 deg, 2 worse)
    bank, cases = pose_case
    without, with_ = [], []
    for g, yaw, c, _ in cases:
        _, per = bank.features(g)
        without.append(np.rad2deg(abs(wrap(bank._refine(g, c, dict(per[c]), probe_deg=())['yaw']
                                           - yaw))))
        with_.append(np.rad2deg(abs(wrap(bank._refine(g, c, dict(per[c]))['yaw'] - yaw))))
    without, with_ = np.array(without), np.array(with_)
    assert np.median(with_) < np.median(without) - 1.0, (np.round(without, 1), np.round(with_, 1))
    assert np.mean(with_ <= 5) >= np.mean(without <= 5) + 0.25
    assert (with_ < without - 1).sum() > 3 * (with_ > without + 1).sum()


@pytest.mark.parametrize('landscape, window, want', [
    ({d: -(d - 4) ** 2 for d in range(-20, 21)}, 10.0, 4),      # up to the peak
    ({d: -(d + 3) ** 2 for d in range(-20, 21)}, 10.0, -3),     # nothing up: down
    ({d: -(d - 8) ** 2 for d in range(-20, 21)}, 5.0, 5),       # at most +-window
    # equal values (the plateaus of the nearest-neighbour rotation) are walked across
    ({**{d: -10.0 for d in range(-20, 21)}, 0: 0, 1: 0, 2: 0, 3: 1, 4: 0.5}, 10.0, 3),
    # downward only when upward found nothing better
    ({**{d: -10.0 for d in range(-20, 21)}, 0: 0, 1: 1, 2: 0.5, -1: 2, -2: 3}, 10.0, 1),
])
def test_climb_of_the_exact_likelihood(tiny, monkeypatch, landscape, window, want):
    # the climb of ModelBank._climb on a made-up likelihood of whole degrees
    def exact(obs, c, yaw, per_c):
        return {'loglik': float(landscape[int(round(np.rad2deg(yaw)))])}

    monkeypatch.setattr(tiny, '_exact', exact)
    best = tiny._climb(None, 0, {'yaw': 0.0, 'exact': exact(None, 0, 0.0, None)}, 1.0, window)
    assert np.rad2deg(best['yaw']) == pytest.approx(want)
    assert best['exact']['loglik'] == landscape[want]


def test_stage2_rescores_the_windows_around_the_best_stage1_modes(tiny, monkeypatch):
    # _refine re-scores the class with all its components every stage2_step_deg within
    # +-stage2_window_deg of its stage2_modes best stage-1 modes, and nowhere else
    from beo_ros.core.inference import top_yaw_modes
    _, part = views()
    _, per = tiny.features(part)
    eng = tiny.engine
    calls = []
    real = eng.scores

    def scores(pooled, yaws, c=None, full=False, rows=None):
        if full:
            calls.append((np.rad2deg(np.asarray(yaws)), rows))
        return real(pooled, yaws, c, full, rows)

    monkeypatch.setattr(eng, 'scores', scores)
    sy, sl = per[1]['searched']
    modes = np.rad2deg(sy[top_yaw_modes(sy, sl, 2)])
    assert yaw_error(np.deg2rad(modes[0]), np.deg2rad(modes[1])) > np.deg2rad(25)
    tiny._refine(part, 1, per[1], 2.0, 0.0, 2.0, stage2_modes=2, stage2_window_deg=10.0)
    (yaws, rows), = calls
    assert len(yaws) == 180
    got = np.sort(yaws[rows])
    want = np.unique(np.round((modes[:, None] + np.arange(-10, 11, 2)) % 360, 6))
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_stage2_keeps_only_the_modes_it_scored(tiny):
    # outside the stage-2 windows the re-scored likelihood is -inf: a window too narrow for a
    # second mode (min separation 20 deg) gives one hypothesis, never a yaw scored -inf
    _, part = views()
    _, per = tiny.features(part)
    ref = tiny._refine(part, 1, per[1], 2.0, 0.0, 2.0, stage2_modes=1, stage2_window_deg=4.0)
    assert len(ref['hypotheses']) == 1
    assert np.isfinite(ref['hypotheses'][0][1])
    assert ref['yaw'] == ref['hypotheses'][0][0]


def _refine_on(tiny, monkeypatch, loglik, step_deg, window_deg, probe_deg):
    """The yaw (deg, from the stage-1 yaw) that ``_refine`` of class 1 of a view picks on the
    made-up exact log-likelihood ``loglik(deg from the stage-1 yaw)``, without stage 2."""
    _, part = views()
    _, per = tiny.features(part)
    y0 = per[1]['yaw']
    monkeypatch.setattr(tiny, '_exact', lambda obs, c, yaw, per_c: {
        'loglik': float(loglik(np.rad2deg(yaw - y0)))})
    monkeypatch.setattr(tiny.engine, 'add_prediction', lambda ex, obs, c: ex)
    start = dict(per[1], exact=tiny._exact(None, 1, y0, per[1]))
    best = tiny._refine(part, 1, start, step_deg, window_deg, stage2_step_deg=None,
                        probe_deg=probe_deg)
    return float(np.rad2deg(best['yaw'] - y0))


def test_exact_probes_look_on_both_sides_and_keep_the_best(tiny, monkeypatch):
    # probes at +-10, +-20 deg of the stage-1 yaw, then a climb of +-3 deg (which finds
    # nothing better here): the best probe, on the negative side, wins
    scores = {0: -9.0, 10: -6.0, -10: -4.0, 20: -2.0, -20: 0.0}
    got = _refine_on(tiny, monkeypatch, lambda d: scores.get(int(round(d)), -10.0), 1.0, 3.0,
                     (10, 20))
    assert got == pytest.approx(-20.0)


def test_refinement_climbs_in_whole_degrees_then_in_the_finer_step(tiny, monkeypatch):
    # the peak is 2.5 deg off: the 1 deg climb stops at 2 deg (3 deg is no better), the 0.5 deg
    # climb within +-1 deg of that reaches 2.5 (either climb alone would stop at 2 or 1 deg)
    got = _refine_on(tiny, monkeypatch, lambda d: -(d - 2.5) ** 2, 0.5, 3.0, ())
    assert got == pytest.approx(2.5)


def test_hypotheses_lead_with_the_refined_yaw_then_the_other_classes_by_score():
    # the chosen class's modes first, the best one at the refined yaw with its pooled score,
    # then each other class's best mode, best score first (not class order)
    # (tiny has two classes: four names are enough for the bank's own _hypotheses)
    four = SimpleNamespace(classes=['a', 'b', 'c', 'd'])
    per = [{'yaw': 0.0, 'hypotheses': [(0.125 * c, -100.0 + c), (1.0 + 0.125 * c, -200.0)]}
           for c in range(4)]
    hyps = ModelBank._hypotheses(four, None, per, 0, 0.0625, 1.0)
    assert hyps == [('a', 0.0625, -100.0), ('a', 1.0, -200.0), ('d', 0.375, -97.0),
                    ('c', 0.25, -98.0), ('b', 0.125, -99.0)]


def test_shipped_model_answers_unknown_for_dense_clutter():
    # The shipped ModelNet10 bank's robust bound (median - 8 MAD of the out-of-fold
    # log-likelihood) rejects dense random clutter (20 % of the voxels and more; measured:
    # 6 of 6 grids at 20 and 30 %, 5 of 6 at 10 %). At 15 % it reads as a night stand (the
    # class whose bound tolerates it) and sparse scatter (2-5 %) as a chair: README limitations.
    from beo_ros import default_model_dir, load_models
    bank = load_models(default_model_dir())
    rng = np.random.default_rng(0)
    for density in (0.2, 0.3, 0.5):
        grid = (rng.random(bank.spec.shape) < density).astype(np.int8)
        est = bank.estimate(grid)
        assert est.label == 'unknown', (density, est.scores)
    # and a real-looking object is not rejected: the first class's mean shape, seen partially
    mean = bank.models[0].mean.reshape(bank.spec.shape)
    est = bank.estimate(partial_view(mean >= np.quantile(mean, 1 - mean.clip(0, 1).mean()),
                                     0.5, 0.4))
    assert est.label != 'unknown'


def test_bank_pickles_as_its_constructor_arguments():
    # worker processes receive the bank pickled; the engine is rebuilt, settings kept
    import pickle
    tiny = make_tiny_bank()
    on = ModelBank(tiny.models, tiny.spec, pose_components=2, stage2_noise_map=True)
    back = pickle.loads(pickle.dumps(on))
    assert back.engine is not on.engine
    assert back.pose_components == 2 and back.stage2_noise_map
    g = views()[0]
    assert back.estimate(g).scores == pytest.approx(on.estimate(g).scores)


# ---------------------------------------------------------------------- 'points' classifier
def _points_classifier(n_classes, favour, r4_weight=0.0):
    """A hand-made 'points' classifier: intercepts favour class ``favour`` (plus an optional
    weight on r4 for class 0), never 'unknown'."""
    nin = n_classes + 2
    coef = np.zeros((n_classes, nin))
    coef[0, n_classes] = r4_weight
    intercept = np.zeros(n_classes)
    intercept[favour] = 5.0
    return dict(mean=np.zeros(nin), scale=np.ones(nin), coef=coef, intercept=intercept,
                unknown_threshold=np.full(n_classes, -np.inf))


def _box_cloud(tiny):
    occ = tiny.models[0].mean.reshape((N,) * 3) > 0.5
    return render_view_points(occ, 0.5, 0.3, np.deg2rad(30), distance=2.0, size=0.4,
                              ray_spacing=0.25)


@pytest.fixture(scope='module')
def points_bank(tiny):
    # the class the grid rule picks for the rendered cloud; the classifier favours another one
    pts, origin = _box_cloud(tiny)
    ml = tiny.estimate_points(pts, sensor_origin=origin)
    other = (tiny.classes.index(ml.label) + 1) % len(tiny.classes)
    bank = ModelBank(tiny.models, tiny.spec, {'points': _points_classifier(len(tiny.classes),
                                                                           other)},
                     tiny.training, tiny.pose_components)
    return bank, pts, origin, ml, other


def test_points_classifier_decides_estimate_points_but_not_estimate(points_bank):
    bank, pts, origin, ml, other = points_bank
    assert ml.classifier_mode == 'max_likelihood' and ml.point_features is None
    e = bank.estimate_points(pts, sensor_origin=origin)
    assert e.classifier_mode == 'points' and e.classifier_note == ''
    assert e.point_features.shape == (2,) and np.isfinite(e.point_features).all()
    assert 'point_descriptors' in e.timings
    assert e.label == bank.classes[other] != ml.label
    assert e.scores[bank.classes[other]] > 0.9
    assert e.hypotheses[0].label == bank.classes[other]   # refined pose of the winner
    # estimate(grid) without points: the grid rule, exactly as a bank without the classifier
    g = e.grid
    plain = ModelBank(bank.models, bank.spec, None, bank.training, bank.pose_components)
    a, b = bank.estimate(g), plain.estimate(g)
    assert a.classifier_mode == b.classifier_mode == 'max_likelihood'
    assert a.label == b.label and a.scores == pytest.approx(b.scores) and a.yaw == b.yaw
    # the descriptors passed by hand do the same as estimate_points
    c = bank.estimate(g, point_features=e.point_features)
    assert c.classifier_mode == 'points' and c.label == e.label
    with pytest.raises(ValueError, match='point_features'):
        bank.estimate(g, point_features=[0.5])


def test_points_classifier_uses_the_descriptors(tiny):
    # a weight on r4 only: the class follows the descriptor value passed in
    clf = _points_classifier(len(tiny.classes), 1, r4_weight=40.0)
    clf['intercept'][:] = 0.0
    clf['intercept'][0] = -20.0                          # class 0 iff r4 > 0.5
    bank = ModelBank(tiny.models, tiny.spec, {'points': clf})
    g = views()[0]
    assert bank.estimate(g, point_features=[0.9, 0.8]).label == bank.classes[0]
    assert bank.estimate(g, point_features=[0.1, 0.3]).label == bank.classes[1]


def test_undefined_descriptors_fall_back_to_the_grid_rule_and_say_so(points_bank):
    bank, _, _, ml, _ = points_bank
    # a flat horizontal patch: no side normals, so the descriptors are undefined
    u, v = np.meshgrid(np.linspace(-0.1, 0.1, 40), np.linspace(-0.1, 0.1, 40))
    flat = np.c_[u.ravel(), v.ravel(), np.zeros(u.size)]
    e = bank.estimate_points(flat, sensor_origin=(0.0, -1.0, 1.0))
    assert np.isnan(e.point_features).all()
    assert e.classifier_mode == 'max_likelihood' and 'undefined' in e.classifier_note
    plain = ModelBank(bank.models, bank.spec).estimate_points(flat, sensor_origin=(0.0, -1.0, 1.0))
    assert e.scores == pytest.approx(plain.scores)


def test_points_classifier_round_trips_and_pickles(points_bank, tmp_path):
    import pickle
    bank, pts, origin, _, _ = points_bank
    bank.save(tmp_path / 'p')
    assert 'classifier.npz' in _manifest(tmp_path / 'p')['files']
    back = ModelBank.load(tmp_path / 'p')
    assert back.has_point_classifier
    for k, v in bank.classifier['points'].items():
        np.testing.assert_array_equal(back.classifier['points'][k], v)
    e0 = bank.estimate_points(pts, sensor_origin=origin)
    for other in (back, pickle.loads(pickle.dumps(back))):
        e = other.estimate_points(pts, sensor_origin=origin)
        assert e.classifier_mode == 'points' and e.label == e0.label
        assert e.scores == pytest.approx(e0.scores)
        np.testing.assert_allclose(e.point_features, e0.point_features)


def _rewrite_points_classifier(p, **change):
    from beo_ros.core.bank import _sha256
    with np.load(p / 'classifier.npz') as z:
        arrays = {k: z[k] for k in z.files}
    for k, v in change.items():
        if v is None:
            arrays.pop(f'points__{k}')
        else:
            arrays[f'points__{k}'] = v
    np.savez_compressed(p / 'classifier.npz', **arrays)
    m = _manifest(p)
    m['files']['classifier.npz'] = _sha256(p / 'classifier.npz')
    _write_manifest(p, m)


@pytest.mark.parametrize('change, msg', [
    (dict(coef=np.zeros((2, 3))), "'coef' has shape"),
    (dict(mean=np.zeros(5)), "'mean' has shape"),
    (dict(intercept=None), "no 'intercept'"),
    (dict(scale=np.array([1.0, np.nan, 1.0, 1.0])), 'NaN'),
    (dict(scale=np.array([1.0, 0.0, 1.0, 1.0])), 'positive'),
    (dict(unknown_threshold=np.array([np.nan, 0.0])), 'NaN'),
    (dict(extra=np.zeros(2)), 'unexpected'),
])
def test_malformed_points_classifier_is_refused(points_bank, tmp_path, change, msg):
    bank = points_bank[0]
    assert len(bank.classes) == 2
    bank.save(tmp_path / 'p')
    _rewrite_points_classifier(tmp_path / 'p', **change)
    with pytest.raises(ModelError, match=msg):
        ModelBank.load(tmp_path / 'p')


def test_malformed_points_classifier_is_refused_by_the_constructor(tiny):
    clf = _points_classifier(len(tiny.classes), 0)
    clf['coef'] = clf['coef'][:, :-1]
    with pytest.raises(ModelError, match='coef'):
        ModelBank(tiny.models, tiny.spec, {'points': clf})


def test_classifier_of_an_unknown_mode_is_refused_by_the_constructor(tiny):
    # 'partail' was taken and never used (the max-likelihood rule decided), and save wrote a
    # classifier.npz that load refuses
    clf = _points_classifier(len(tiny.classes), 0)
    with pytest.raises(ModelError, match=r"unknown classifier mode\(s\) \['partail'\]"):
        ModelBank(tiny.models, tiny.spec, {'partail': clf})


# ---------------------------------------------------------------------- class prior
def test_resolve_class_prior_accepts_names_dicts_and_weights_and_names_what_is_wrong():
    from beo_ros.core.bank import resolve_class_prior
    names = ['box', 'cylinder', 'ellipsoid']
    assert resolve_class_prior('train', names) is None
    assert resolve_class_prior('uniform', names) == pytest.approx([1 / 3] * 3)
    assert resolve_class_prior({'box': 2, 'cylinder': 1, 'ellipsoid': 1}, names) == \
        pytest.approx([0.5, 0.25, 0.25])
    assert resolve_class_prior([0, 1, 3], names) == pytest.approx([0, 0.25, 0.75])
    # weights near the float64 limit: their sum would overflow to inf
    assert resolve_class_prior([1e308, 1e308, 5e307], names) == pytest.approx([0.4, 0.4, 0.2])
    assert resolve_class_prior([0, 5e-324, 0], names) == pytest.approx([0, 1, 0])
    for bad, msg in [('Uniform', 'one of'), ({'box': 1}, 'missing'),
                     ({'box': 1, 'cylinder': 1, 'ellipsoid': 1, 'cup': 1}, 'unknown'),
                     ([1, 2], '3 weights'), ([1, -1, 1], '>= 0'), ([0, 0, 0], 'not all 0'),
                     ([1, np.nan, 1], 'finite'), ({'box': 'a', 'cylinder': 1, 'ellipsoid': 1},
                                                  'numbers'), (None, '3 weights')]:
        with pytest.raises(ValueError, match=msg):
            resolve_class_prior(bad, names)


def _prior_bank():
    """Three classes with a classifier that knows its training counts (4, 2, 2)."""
    from beo_ros.core.inference import FEATURE_NAMES
    nf = len(FEATURE_NAMES)
    bank = make_tiny_bank(n=8, k=2)
    coef = np.zeros((3, 3 * nf))
    for c in range(3):
        coef[c, c * nf + 1] = 1.0
    clf = dict(mean=np.zeros(3 * nf), scale=np.ones(3 * nf), coef=coef, intercept=np.zeros(3),
               unknown_threshold=np.full(3, -np.inf), class_counts=np.array([4.0, 2.0, 2.0]))
    feats = np.zeros((3, nf))
    feats[:, 1] = np.log([0.5, 0.3, 0.2])  # the classifier's own probabilities
    third = dataclasses.replace(bank.models[0], name='box2')
    return ModelBank(bank.models + [third], bank.spec, {'complete': clf}), feats


def test_class_prior_moves_the_probabilities_by_bayes_rule():
    bank, feats = _prior_bank()
    assert bank.class_prior == 'train'
    p_train = np.array([0.5, 0.3, 0.2])
    assert bank.classify_features(feats, 'complete')[0] == pytest.approx(p_train)
    # uniform: divide by the training frequencies (0.5, 0.25, 0.25) and renormalise
    bank.class_prior = 'uniform'
    want = p_train / np.array([0.5, 0.25, 0.25])
    p = bank.classify_features(feats, 'complete')[0]
    assert p == pytest.approx(want / want.sum()) and np.argmax(p) == 1
    # explicit weights: a class of weight 0 is never chosen
    bank.class_prior = [0, 1, 1]
    p = bank.classify_features(feats, 'complete')[0]
    assert p[0] == 0 and p[1:] / p[1:].sum() == pytest.approx([0.6, 0.4])
    with pytest.raises(ValueError, match='3 weights'):
        bank.class_prior = [1, 1]
    assert bank.class_prior == pytest.approx([0, 0.5, 0.5])  # a refused value changes nothing


def test_a_class_of_prior_0_without_training_rows_is_never_chosen():
    # class 0 had no training rows (fit_logistic's intercept -30): its offset was 0, so it kept
    # its probability, all of it when the other classes' logits fell far below
    bank, feats = _prior_bank()
    clf = dict(bank.classifier['complete'], class_counts=np.array([0.0, 2.0, 2.0]),
               intercept=np.array([-30.0, 0.0, 0.0]))
    bank = ModelBank(bank.models, bank.spec, {'complete': clf}, class_prior=[0, 1, 1])
    feats[1:, 1] = -100.0
    p = bank.classify_features(feats, 'complete')[0]
    assert p[0] == 0 and p[1:] == pytest.approx([0.5, 0.5])


def test_classes_without_training_rows_follow_their_prior_weights():
    # classes 0 and 1 had no training rows (intercept -30, no weights): their offset was 0,
    # so their prior weights were ignored (0.7 / 0.3 gave 0.5 / 0.5 once the prior ruled out
    # class 2, while the no-object estimate of the same bank answered the prior 0.7 / 0.3)
    bank, feats = _prior_bank()
    clf = dict(bank.classifier['complete'], class_counts=np.array([0.0, 0.0, 4.0]),
               intercept=np.array([-30.0, -30.0, 0.0]),
               coef=bank.classifier['complete']['coef'] * [[0], [0], [1]])
    bank = ModelBank(bank.models, bank.spec, {'complete': clf}, class_prior=[0.7, 0.3, 0])
    p = bank.classify_features(feats, 'complete')[0]
    assert p == pytest.approx([0.7, 0.3, 0.0]) and p[2] == 0
    scores = bank.estimate(np.zeros((8, 8, 8), np.int8), yaw=0.0).scores
    assert list(scores.values()) == pytest.approx(list(p))
    # with the class that had rows allowed, they stay at ~0, in proportion to their weights
    bank.class_prior = [0.7, 0.3, 0.5]
    p = bank.classify_features(feats, 'complete')[0]
    assert p[2] == pytest.approx(1.0) and p[:2].max() < 1e-11
    assert p[0] / p[1] == pytest.approx(0.7 / 0.3)


def test_class_prior_without_class_counts_is_not_applied_and_the_estimate_says_so():
    bank, feats = _prior_bank()
    clf = {k: v for k, v in bank.classifier['complete'].items() if k != 'class_counts'}
    old = ModelBank(bank.models, bank.spec, {'complete': clf}, class_prior='uniform')
    assert old.classify_features(feats, 'complete')[0] == pytest.approx([0.5, 0.3, 0.2])
    g = np.ones((8, 8, 8), np.int8)
    e = old.estimate(g, yaw=0.0)
    assert e.classifier_mode == 'complete' and 'no class_counts' in e.classifier_note
    assert bank.estimate(g, yaw=0.0).classifier_note == ''


def test_class_prior_is_saved_overridden_on_load_and_checked(tmp_path):
    bank, feats = _prior_bank()
    bank.class_prior = 'uniform'
    path = bank.save(tmp_path / 'prior')
    assert _manifest(path)['class_prior'] == 'uniform'
    assert ModelBank.load(path).class_prior == 'uniform'
    assert ModelBank.load(path, class_prior='train').class_prior == 'train'
    weights = load_models(path, class_prior=[1, 2, 1])
    assert weights.class_prior == pytest.approx([0.25, 0.5, 0.25])
    assert _manifest(weights.save(tmp_path / 'w'))['class_prior'] == pytest.approx(
        [0.25, 0.5, 0.25])
    assert ModelBank.load(tmp_path / 'w').class_prior == pytest.approx([0.25, 0.5, 0.25])
    with pytest.raises(ValueError, match='class_prior'):
        ModelBank.load(path, class_prior='flat')
    m = _manifest(path)
    m['class_prior'] = 'flat'
    _write_manifest(path, m)
    with pytest.raises(ModelError, match=r'manifest.json: class_prior'):
        ModelBank.load(path)
    # without the key (older directories): the classifier as trained
    del m['class_prior']
    _write_manifest(path, m)
    assert ModelBank.load(path).class_prior == 'train'


def test_a_class_name_too_long_for_a_file_name_is_refused(tmp_path, tiny_dir):
    # load raised OSError 'File name too long' (and save, after training)
    p = _copy(tiny_dir, tmp_path)
    m = _manifest(p)
    long = 'x' * 250
    m['classes'][0] = long
    m['files'][f'class_00_{long}.npz'] = m['files'].pop(sorted(m['files'])[0])
    _write_manifest(p, m)
    with pytest.raises(ModelError, match='manifest.json: class names can be at most 200 bytes'):
        ModelBank.load(p)
    bank = ModelBank.load(tiny_dir)
    bank.models[0].name = '\u00e9' * 101   # 202 bytes in UTF-8
    with pytest.raises(ModelError, match='at most 200 bytes'):
        bank.save(tmp_path / 'new')
    bank.models[0].name = '\u00e9' * 100
    assert ModelBank.load(bank.save(tmp_path / 'new')).classes[0] == '\u00e9' * 100


def test_a_class_name_the_file_system_cannot_encode_is_refused(tmp_path, tiny_dir):
    # a lone surrogate: save raised UnicodeEncodeError, a manifest naming it made load raise it
    bank = ModelBank.load(tiny_dir)
    bank.models[0].name = 'box\ud800'
    with pytest.raises(ModelError, match='file system can encode'):
        bank.save(tmp_path / 'new')
    p = _copy(tiny_dir, tmp_path)
    m = _manifest(p)
    m['classes'][0] = 'box\ud800'
    m['files']['class_00_box\ud800.npz'] = m['files'].pop('class_00_box.npz')
    _write_manifest(p, m)
    with pytest.raises(ModelError, match='manifest.json: class names must be text the file'):
        ModelBank.load(p)
    bank.models[0].name = 'box\udc80'   # undecodable bytes of a file name: fine
    assert ModelBank.load(bank.save(tmp_path / 'ok')).classes[0] == 'box\udc80'


def test_class_names_must_be_distinct(tmp_path, tiny_dir):
    tiny = make_tiny_bank(n=8, k=2)
    with pytest.raises(ModelError, match='unique'):
        ModelBank(tiny.models + [tiny.models[0]], tiny.spec)
    path = _copy(tiny_dir, tmp_path)
    m = _manifest(path)
    m['classes'] = [m['classes'][0]] * len(m['classes'])
    _write_manifest(path, m)
    with pytest.raises(ModelError, match='distinct'):
        ModelBank.load(path)


def test_bad_class_counts_are_refused_on_load(tmp_path):
    bank, _ = _prior_bank()
    bank.classifier['complete']['class_counts'] = np.array([1.0, -1.0, 2.0])
    path = bank.save(tmp_path / 'bad')
    with pytest.raises(ModelError, match=r"classifier.npz: classifier 'complete': class_counts"):
        ModelBank.load(path)


def _rewrite_npz(path, fn, **change):
    """Change (value) or drop (None) arrays of ``path / fn`` and keep the manifest consistent."""
    from beo_ros.core.bank import _sha256
    with np.load(path / fn) as z:
        arrays = {k: z[k] for k in z.files}
    for k, v in change.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez(path / fn, **arrays)
    m = _manifest(path)
    m['files'][fn] = _sha256(path / fn)
    _write_manifest(path, m)


@pytest.mark.parametrize('change, msg', [
    (dict(complete__intercept=np.array([0.0, np.nan, 0.0])), "'intercept' contains NaN"),
    (dict(complete__scale=np.ones(5)), "'scale' has shape"),                # wrong length
    ('zero_scale', "'scale' must be positive"),
    (dict(complete__mean=None), "no 'mean'"),
    (dict(complete__unknown_threshold=None), "no 'unknown_threshold'"),
    (dict(complete__coef=np.zeros((3, 2))), "'coef' has shape"),
    (dict(other__coef=np.zeros((3, 2))), "unknown classifier 'other'"),
    # bool() of these: a bare ValueError ('truth value ... ambiguous'), or 'no' read as true
    (dict(complete__row_standardize=np.array([True, False])), "'row_standardize' must be true"),
    (dict(complete__descriptors=np.asarray('no')), "'descriptors' must be true or false"),
    # timedelta64, a number to numpy: loaded, then estimate raised UFuncTypeError
    (dict(complete__intercept=np.zeros(3, 'm8[s]')), "'intercept' has shape .*expected numbers"),
    (dict(complete__class_counts=np.ones(3, 'm8[s]')), 'class_counts must be 3 finite counts'),
    # no rows at all, an infinite count, an unknown bound of +inf (-inf is 'never unknown')
    (dict(complete__class_counts=np.zeros(3)), 'class_counts must be 3 finite counts'),
    (dict(complete__class_counts=np.array([1.0, np.inf, 1.0])), 'class_counts must be 3 finite'),
    (dict(complete__unknown_threshold=np.array([0.0, np.inf, 0.0])),
     "'unknown_threshold' contains NaN or Inf"),
    # a misspelt array was ignored without a word (the 'points' classifier refused it)
    (dict(complete__row_standardise=np.asarray(True)),
     r"classifier 'complete' has unexpected arrays \['row_standardise'\]"),
])
def test_bad_grid_classifier_arrays_are_refused_on_load(tmp_path, change, msg):
    bank, _ = _prior_bank()
    path = bank.save(tmp_path / 'm')
    if change == 'zero_scale':
        with np.load(path / 'classifier.npz') as z:
            change = dict(complete__scale=np.where(np.arange(z['complete__scale'].size) == 1,
                                                   0.0, z['complete__scale']))
    _rewrite_npz(path, 'classifier.npz', **change)
    with pytest.raises(ModelError, match=msg):
        ModelBank.load(path)


@pytest.mark.parametrize('key, value, msg', [
    ('mean_variance', lambda a: -np.ones_like(a), 'must be >= 0'),
    ('component_variance', lambda a: -np.ones_like(a), 'must be >= 0'),
    ('loading_covariance', lambda a: -100 * np.eye(len(a), dtype=a.dtype), 'semi-definite'),
    ('loading_covariance', lambda a: a + np.triu(np.ones_like(a), 1), 'semi-definite'),
    ('loading_covariance', lambda a: a[:1, :1], 'has shape'),
    ('mean_variance', lambda a: a[:5], 'has shape'),
    ('component_variance', lambda a: np.append(a, 1.0), 'has shape'),
    ('noise_variance', lambda a: np.array([0.1, 0.2]), 'has shape'),
    ('noise_variance', lambda a: np.array('abc'), 'real numbers'),
    ('W', lambda a: a.astype(bool), 'real numbers'),
    # numpy counts timedelta64 as a number: this raised UFuncNoLoopError, a W loaded
    ('noise_variance', lambda a: np.array(5, dtype='m8[s]'), 'real numbers'),
    ('W', lambda a: (a * 1000).astype(np.int64).astype('m8[s]'), 'real numbers'),
])
def test_bad_class_arrays_are_refused_on_load(tmp_path, tiny_dir, key, value, msg):
    p = _copy(tiny_dir, tmp_path)
    fn = sorted(p.glob('class_00_*.npz'))[0]
    with np.load(fn) as z:
        bad = value(z[key])
    _rewrite_npz(p, fn.name, **{key: bad})
    with pytest.raises(ModelError, match=fn.name + '.*' + msg):
        ModelBank.load(p)


@pytest.mark.parametrize('change, msg', [
    (dict(pose_components=0), 'pose_components'), (dict(pose_components='x'), 'pose_components'),
    (dict(pose_components=2.5), 'pose_components'), (dict(training=[1, 2]), 'training'),
])
def test_bad_bank_settings_are_refused(tmp_path, tiny_dir, change, msg):
    p = _copy(tiny_dir, tmp_path)
    _write_manifest(p, dict(_manifest(p), **change))
    with pytest.raises(ModelError, match='manifest.json: ' + msg):
        ModelBank.load(p)
    tiny = make_tiny_bank(n=8, k=2)
    with pytest.raises(ModelError, match=msg):
        ModelBank(tiny.models, tiny.spec, **change)


def test_cross_validated_report_under_both_priors():
    from beo_ros.core.inference import FEATURE_NAMES
    from beo_ros.core.training import cross_validated_report
    rng = np.random.default_rng(0)
    y = np.repeat([0, 1, 2], [60, 20, 20])
    F = rng.normal(size=(100, 3 * len(FEATURE_NAMES))) + 0.8 * np.eye(3)[y].repeat(
        len(FEATURE_NAMES), axis=1)
    tr = cross_validated_report(F, y, [])
    un = cross_validated_report(F, y, [], class_prior='uniform')
    assert tr['prior_accuracy'] == tr['accuracy'] == tr['accuracy_train_prior']
    assert un['prior_accuracy'] == un['balanced_accuracy'] == un['balanced_accuracy_uniform_prior']
    for key in ('accuracy_train_prior', 'accuracy_uniform_prior',
                'balanced_accuracy_uniform_prior'):
        assert tr[key] == un[key]
    # the rare classes gain recall under the uniform prior, the common one loses accuracy
    assert un['balanced_accuracy'] > tr['balanced_accuracy']
    assert tr['accuracy'] >= un['accuracy']


def test_cross_validated_report_with_a_class_that_has_no_rows():
    # every view of class 1 skipped: the cross-validation is over the classes present
    from beo_ros.core.inference import FEATURE_NAMES
    from beo_ros.core.training import cross_validated_report
    rng = np.random.default_rng(0)
    y = np.repeat([0, 2], 15)
    F = rng.normal(size=(30, 3 * len(FEATURE_NAMES))) + 2.0 * np.eye(3)[y].repeat(
        len(FEATURE_NAMES), axis=1)
    rep = cross_validated_report(F, y, [], folds=5)
    assert rep['n'] == 30 and rep['accuracy'] > 0.8


@pytest.mark.parametrize('grouped', [False, True])
def test_cross_validated_report_with_a_class_of_one_row_or_object(grouped):
    # the other views of class 2's objects skipped (small objects lost to the rotation):
    # fit_bank stopped with scikit-learn's 'requires at least one train/test split ...
    # n_splits=1'; the lone class is now classified by folds that never saw it
    from beo_ros.core.inference import FEATURE_NAMES
    from beo_ros.core.training import cross_validated_report, select_classifier
    rng = np.random.default_rng(0)
    y = np.repeat([0, 1, 2], [20, 20, 3 if grouped else 1])
    objects = np.r_[np.arange(40) // 2, [100] * 3] if grouped else np.arange(len(y))
    F = rng.normal(size=(len(y), 3 * len(FEATURE_NAMES))) + 2.0 * np.eye(3)[y].repeat(
        len(FEATURE_NAMES), axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', UserWarning)   # scikit-learn: 1 member, a missing class
        rep = cross_validated_report(F, y, [], groups=objects)
        clf, _ = select_classifier(F, y, [], objects, None, 3, C=1.0, descriptors=False,
                                   row_standardize=False, kind='logistic')
    assert rep['n'] == len(y) and rep['accuracy'] > 0.8
    assert clf['class_counts'][2] == len(y) - 40


def test_unknown_bound_counts_objects_not_views():
    # loglik_bounds: -inf for a class with fewer than 5 objects; with 4 views per object
    # (beo-train --views 4) a class of 3 objects had 12 rows and a bound from them
    from beo_ros.core.inference import FEATURE_NAMES
    from beo_ros.core.training import loglik_bounds, select_classifier
    nf = len(FEATURE_NAMES)
    rng = np.random.default_rng(0)
    objects = np.repeat(np.arange(23), 4)
    y = np.repeat([0] * 10 + [1] * 10 + [2] * 3, 4)
    F = rng.normal(size=(len(y), 3 * nf)) + 2.0 * np.eye(3)[y].repeat(nf, axis=1)
    clf, _ = select_classifier(F, y, [], objects, None, 3, C=1.0, descriptors=False,
                               row_standardize=False, kind='logistic')
    want = loglik_bounds(F[:, 0::nf], y, 3)
    assert np.isfinite(want).all()                     # rows counted: every class bounded
    np.testing.assert_array_equal(clf['unknown_threshold'], [want[0], want[1], -np.inf])


def test_unknown_bounds_are_inclusive():
    # a log-likelihood at the class's bound explains the object, and explaining classes that
    # hold exactly half the probability are enough (the '>=' and '< 0.5' of the docstring)
    from beo_ros.core.bank import classifier_probabilities
    clf = dict(mean=np.zeros(3), scale=np.ones(3), coef=np.eye(3), intercept=np.zeros(3),
               unknown_threshold=np.full(3, -1.0))
    Z = np.log([[0.5, 0.25, 0.25]])
    p, unknown = classifier_probabilities(clf, Z, [[-1.0, -5.0, -5.0]])
    np.testing.assert_array_equal(p, [[0.5, 0.25, 0.25]])
    assert not unknown[0]
    assert classifier_probabilities(clf, Z, [[-1.0 - 1e-9, -5.0, -5.0]])[1][0]
    # the winner explains it, but with the others less than half: unknown
    Z = np.log([[0.45, 0.3, 0.25]])
    assert classifier_probabilities(clf, Z, [[0.0, -5.0, -5.0]])[1][0]


def test_prior_offset_by_hand():
    # Bayes' rule: log prior - log training frequency; a class without training rows gets log
    # prior (no frequency to divide by), -inf when its prior is 0
    from beo_ros.core.bank import prior_offset
    third = np.full(3, 1 / 3)
    np.testing.assert_allclose(prior_offset([4, 2, 2], third),
                               np.log(third) - np.log([0.5, 0.25, 0.25]))
    np.testing.assert_allclose(prior_offset([0, 2, 2], third),
                               [np.log(1 / 3), np.log(2 / 3), np.log(2 / 3)])
    np.testing.assert_allclose(prior_offset([0, 0, 4], [0.7, 0.3, 0]),
                               [np.log(0.7), np.log(0.3), -np.inf])
    np.testing.assert_array_equal(prior_offset([0, 2, 2], [0, 0.5, 0.5]), [-np.inf, 0.0, 0.0])
    np.testing.assert_array_equal(prior_offset([1, 2, 1], [0.5, 0, 0.5])[1], -np.inf)
    assert prior_offset(None, third) is None and prior_offset([4, 2, 2], None) is None


def test_expected_calibration_error_bins_by_hand():
    from beo_ros.core.training import expected_calibration_error
    # bins are [0, 0.1], then (a, b]: a confidence of exactly 1 is in the last bin, 0.5 in
    # (0.4, 0.5] only
    assert expected_calibration_error(np.array([1.0]), np.array([False])) == pytest.approx(1.0)
    assert expected_calibration_error(np.array([0.5]), np.array([False])) == pytest.approx(0.5)
    # weighted by the share of rows in the bin: 2/3 * 0.05 + 1/3 * 0.65
    assert expected_calibration_error(np.array([0.95, 0.95, 0.35]), np.ones(3, bool)) == \
        pytest.approx(0.25)
    # 4 bins: 0.3 and 0.45 share (0.25, 0.5]
    assert expected_calibration_error(np.array([0.3, 0.45]), np.array([True, False]), bins=4) \
        == pytest.approx(abs(0.375 - 0.5))


def test_expected_calibration_error_counts_a_confidence_of_zero():
    from beo_ros.core.training import expected_calibration_error
    # the first bin is [0, 0.1]: a row at 0 was in no bin, dropped (0 for a sure miss of 0)
    assert expected_calibration_error(np.array([0.0]), np.array([True])) == pytest.approx(1.0)
    # 0 and 0.05 share the first bin: |mean confidence 0.025 - accuracy 0.5|
    assert expected_calibration_error(np.array([0.0, 0.05]), np.array([True, False])) == \
        pytest.approx(0.475)
    assert expected_calibration_error(np.array([0.0, 0.9]), np.array([False, True])) == \
        pytest.approx(0.05)   # 1/2 * 0 + 1/2 * 0.1
    assert expected_calibration_error(np.array([]), np.array([], bool)) == 0.0


@pytest.mark.parametrize('confidence, correct, message', [
    ([1.5], [True], r'confidence must be finite probabilities in \[0, 1\]'),
    ([-0.5], [False], 'confidence must be finite probabilities'),
    ([np.nan], [True], 'confidence must be finite probabilities'),
    ([np.inf], [True], 'confidence must be finite probabilities'),
    ([0.5], [True, False], 'confidence and correct must have the same shape'),
    ([0.5, 0.5], [True], 'confidence and correct must have the same shape'),
    ([0.5], [0.5], 'correct must be boolean or 0/1'),
    ([0.5], [np.nan], 'correct must be boolean or 0/1'),
])
def test_expected_calibration_error_refuses_bad_rows(confidence, correct, message):
    # before: 0 for a confidence out of [0, 1] or NaN (in no bin), numpy's IndexError for
    # different lengths
    from beo_ros.core.training import expected_calibration_error
    with pytest.raises(ValueError, match=message):
        expected_calibration_error(np.array(confidence), np.array(correct))


def test_loglik_bounds_by_hand():
    # median - UNKNOWN_MADS (8) scaled MADs of a class's own out-of-fold log-likelihoods, at
    # least 1e-3 of MAD; -inf below 5 objects; an outlier moves neither median nor MAD
    from beo_ros.core.training import UNKNOWN_MADS, loglik_bounds
    assert UNKNOWN_MADS == 8.0
    y = np.repeat([0, 1, 2], [5, 4, 5])
    ll = np.zeros((len(y), 3))
    ll[y == 0, 0] = [0.0, 1.0, 2.0, 3.0, 100.0]
    ll[y == 1, 1] = [0.0, 1.0, 2.0, 3.0]
    ll[y == 2, 2] = -3.0
    np.testing.assert_allclose(loglik_bounds(ll, y, 3),
                               [2.0 - 8 * 1.4826, -np.inf, -3.0 - 8e-3])
    np.testing.assert_allclose(loglik_bounds(ll, y, 3, mads=2.0)[0], 2.0 - 2 * 1.4826)


def test_fit_bank_refuses_labels_that_are_not_class_indices():
    # a label past the names: its objects were left out of every model without a word;
    # a negative one: numpy's "'list' argument must have no negative elements"
    from beo_ros.core.training import fit_bank
    X, y, names = primitive_shapes(8, 4, np.random.default_rng(0))
    for bad, shown in ((np.r_[y[:-3], [2, 2, 2]], r'\[2\]'), (np.r_[y[:-1], [-1]], r'\[-1\]'),
                       (np.r_[y[:-1], [0.5]], r'\[0\.5\]')):
        with pytest.raises(ValueError, match=r'labels must be class indices 0\.\.1 .*' + shown):
            fit_bank(X, bad, names, GridSpec(size=8), k=2, classifier_views=0)


def test_fit_bank_refuses_objects_and_labels_that_do_not_fit_together():
    # one label short: an IndexError of the first class's rows; grids of another size: a
    # ModelError about the first class's W once every class model was fitted
    from beo_ros.core.training import fit_bank
    X, y, names = primitive_shapes(8, 4, np.random.default_rng(0))
    for Xb, yb, shown in ((X, y[:-1], r'X \(8, 512\) and y \(7,\)'),
                          (np.zeros((8, 16 ** 3), np.float32), y, r'X \(8, 4096\)')):
        with pytest.raises(ValueError, match=r'X must be \(objects, 512\).*' + shown):
            fit_bank(Xb, yb, names, GridSpec(size=8), k=2, classifier_views=0)


def test_stratified_folds_deal_every_class_evenly_and_repeat_with_the_seed():
    from beo_ros.core.training import stratified_folds
    y = np.repeat([0, 1, 2], [10, 7, 3])
    fold = stratified_folds(y, 3, np.random.default_rng(4))
    assert fold.shape == y.shape and set(fold) == {0, 1, 2}
    for c, n in ((0, 10), (1, 7), (2, 3)):
        counts = np.bincount(fold[y == c], minlength=3)
        assert counts.max() - counts.min() <= 1 and counts.sum() == n
    assert np.array_equal(fold, stratified_folds(y, 3, np.random.default_rng(4)))
    assert not all(np.array_equal(fold, stratified_folds(y, 3, np.random.default_rng(s)))
                   for s in range(5, 10))


def test_hypothesis_quality_is_the_yaw_error_and_the_completion_iou_in_the_observed_frame(tiny):
    # the out-of-fold records: per class hypothesis, the yaw error and the IoU of its
    # completion (the prediction turned into the observed frame by the hypothesis' yaw, the
    # observed voxels kept) with the rotated truth
    from beo_ros.core.synthetic import random_partial_view
    from beo_ros.core.training import _hypothesis_quality
    from _shapes import asymmetric_shapes
    X, _ = asymmetric_shapes(1, np.random.default_rng(3))
    occ = X[0].reshape((N,) * 3) > 0.5
    grid, yaw, _, _, rotated = random_partial_view(occ, np.random.default_rng(2))
    assert 0.3 < yaw_error(yaw, 0.0) < np.pi - 0.3
    per = [dict(yaw=yaw, exact=dict(pred=occ.ravel().astype(np.float32))),   # the truth
           dict(yaw=yaw - 0.5, exact=dict(pred=np.zeros(N ** 3, np.float32)))]   # nothing
    q = _hypothesis_quality(tiny.engine, grid, per, yaw, rotated)
    np.testing.assert_allclose(q['yaw_err'], [0.0, 0.5], atol=1e-12)
    assert q['iou'][0] == 1.0
    assert q['iou'][1] == pytest.approx((grid == 1).sum() / rotated.sum())
    assert 0 < q['iou'][1] < 1


def test_view_features_refine_the_three_classes_of_the_largest_likelihood(monkeypatch):
    # of five classes, the pose refinement goes to the three whose likelihood feature
    # (column 0) is largest, as estimate() would refine the chosen one
    import beo_ros.core.training as training
    refined = []
    f = np.zeros((5, 3))
    f[:, 0] = [3.0, 1.0, 5.0, 0.0, 4.0]
    fake = SimpleNamespace(spec=SimpleNamespace(size=N),
                           features=lambda grid: (f, [{} for _ in range(5)]),
                           _refine=lambda grid, c, per_c: refined.append(c) or per_c,
                           engine=None)
    monkeypatch.setattr(training, '_hypothesis_quality', lambda *a: {})
    X, _ = asymmetric_shapes(1, np.random.default_rng(0))
    out, skipped = training.view_features(fake, X[:1], np.random.default_rng(0), complete=False)
    assert skipped == 0 and len(out['partial'][0]) == 1
    assert refined == [2, 4, 0]


def test_out_of_fold_class_models_never_see_the_objects_they_score(monkeypatch):
    # each fold's class models are fitted on the other folds' objects only, and every object
    # is scored once, by the models of its own fold
    import beo_ros.core.training as training
    from beo_ros.core.grid import GridSpec
    X, y, names = primitive_shapes(N, 3, np.random.default_rng(0))
    index = {x.tobytes(): i for i, x in enumerate(X)}
    assert len(index) == len(X)
    log = []
    real_fit, real_views = training.fit_class_models, training.view_features

    def fit(Xf, *a, **k):
        log.append(('fit', {index[x.tobytes()] for x in Xf}))
        return real_fit(Xf, *a, **k)

    def views_of(bank, Xv, *a, **k):
        log.append(('view', index[Xv[0].tobytes()]))
        return real_views(bank, Xv, *a, **k)

    monkeypatch.setattr(training, 'fit_class_models', fit)
    monkeypatch.setattr(training, 'view_features', views_of)
    training._out_of_fold_rows(X, y, names, GridSpec(size=N), 2, None, None, 2, 1, 3, 0, False)
    scored, trained = [], None
    for kind, what in log:
        if kind == 'fit':
            trained = what
            assert len(what) == len(X) - 2   # 3 folds of 2 objects per class
        else:
            assert what not in trained
            scored.append(what)
    assert sorted(scored) == list(range(len(X)))


def test_cholesky_terms_match_numpy_and_refuse_an_indefinite_matrix():
    from beo_ros.core.inference import cholesky_terms
    rng = np.random.default_rng(4)
    A = rng.standard_normal((6, 9))
    G = np.eye(6) + A @ A.T
    b = rng.standard_normal(6)
    quad, logdet, x = cholesky_terms(G, b)
    np.testing.assert_allclose(x, np.linalg.solve(G, b), rtol=1e-10)
    np.testing.assert_allclose(quad, b @ np.linalg.solve(G, b), rtol=1e-10)
    np.testing.assert_allclose(logdet, np.linalg.slogdet(G)[1], rtol=1e-10)
    with pytest.raises(np.linalg.LinAlgError):
        cholesky_terms(-G, b)


def test_exact_is_consistent_at_yaws_whose_rotation_has_ties():
    # at 45 deg (+ k 90) some voxel centres rotate onto a rounding tie, so yaw and yaw + 2 pi
    # give different nearest-neighbour maps; every map, count and cached term of a yaw must
    # come from the same one, or known-voxel counts go negative (NaN or LinAlgError)
    from beo_ros.core.inference import yaw_key
    n, k = 8, 3
    d = n ** 3
    rng = np.random.default_rng(5)
    W = (rng.standard_normal((1, d, k)) * 0.2).astype(np.float32)
    mu = rng.uniform(0, 1, (1, d)).astype(np.float32)
    eng = InferenceEngine(W, mu, [0.05], [0.1], n, pose_components=2)
    grid = rng.choice(np.array([-1, 0, 1], dtype=np.int8), size=(n,) * 3, p=[0.3, 0.4, 0.3])
    base = np.pi / 4
    assert (yaw_source_index(n, [base])[0] != yaw_source_index(n, [base + 2 * np.pi])[0]).any()
    for q in range(4):
        lls = []
        for turns in (0, 1, -1, 2):
            yaw = base + q * np.pi / 2 + turns * 2 * np.pi
            lls.append(eng.exact(grid, 0, yaw)['loglik'])
            # the dense marginal under the map of the yaw's cache key
            src = yaw_source_index(n, [-yaw_key(-yaw)])[0]
            dense = dense_marginal(grid, W[0], mu[0], 0.05, src)[0]
            np.testing.assert_allclose(lls[-1], dense, rtol=1e-6)
        assert len(set(lls)) == 1


@pytest.mark.parametrize('yaw', [float('nan'), float('inf'), -np.inf, '0.5', True, [0.1],
                                 1j, 10 ** 400])
def test_estimate_refuses_a_yaw_that_is_not_a_finite_number(tiny, yaw):
    bank = tiny
    n = bank.spec.size
    grid = np.zeros((n,) * 3, dtype=np.int8)
    grid[5:10, 5:10, 3:8] = 1
    with pytest.raises(ValueError, match='yaw must be'):
        bank.estimate(grid, yaw=yaw)
    with pytest.raises(ValueError, match='yaw must be'):
        bank.features(grid, yaw=yaw)
    for ok in (np.float32(0.5), np.array(0.5), 0):
        assert bank.estimate(grid, yaw=ok).yaw == pytest.approx(float(ok), abs=1e-6)
    # an integer beyond int64 is a number too (numpy would hold it as an object), as 1e300 is
    from beo_ros.core.grid import wrap_yaw
    for big in (2 ** 70, 1e300):
        assert bank.estimate(grid, yaw=big).yaw == pytest.approx(wrap_yaw(float(big)))


@pytest.mark.parametrize('kw', [dict(grid=None), dict(yaw=np.timedelta64(1, 's')),
                                dict(yaw_step_deg=np.timedelta64(5)),
                                dict(search_step_deg=np.timedelta64(5)),
                                dict(n_hypotheses=np.timedelta64(2)),
                                dict(stage2_modes=np.timedelta64(2)),
                                dict(probe_deg=np.timedelta64(10)),
                                dict(probe_deg=[10, np.timedelta64(20)]),
                                # these raised numpy's TypeError (np.rint) instead
                                dict(refine_deg=np.timedelta64(3)),
                                dict(stage2_window_deg=np.timedelta64(15))])
def test_estimate_refuses_durations_which_numpy_counts_as_integers(tiny, kw):
    # np.timedelta64 is an np.integer: a grid of them was estimated, a duration as yaw or step
    # raised numpy's TypeError, one as count or probe offset was taken
    n = tiny.spec.size
    grid = np.zeros((n,) * 3, dtype=np.int8)
    grid[5:10, 5:10, 3:8] = 1
    if 'grid' in kw:
        kw = dict(grid=grid.astype('m8[s]'))
        match = 'grid must be an integer array'
    else:
        kw = dict(kw, grid=grid)
        match = next(iter(kw))
    with pytest.raises(ValueError, match=match):
        tiny.estimate(**kw)


@pytest.mark.parametrize('kw', [dict(refine_deg=float('nan')), dict(refine_deg=-1),
                                dict(refine_deg=1e9), dict(stage2_window_deg=float('nan')),
                                dict(stage2_window_deg=-5), dict(n_hypotheses=-1),
                                dict(n_hypotheses=2.5), dict(stage2_modes=-2),
                                dict(stage2_modes=True),
                                # no numbers: TypeErrors of '<=' before
                                dict(refine_deg='3'), dict(refine_deg=None),
                                dict(stage2_window_deg=[15]), dict(refine_deg=1j),
                                dict(point_features='ab'), dict(point_features=[0.5, 'x'])])
def test_estimate_refuses_bad_search_settings(tiny, kw):
    n = tiny.spec.size
    grid = np.zeros((n,) * 3, dtype=np.int8)
    grid[5:10, 5:10, 3:8] = 1
    with pytest.raises(ValueError, match=next(iter(kw))):
        tiny.estimate(grid, **kw)


@pytest.mark.parametrize('kind', [Fraction, Decimal])
def test_estimate_takes_fractions_and_decimals_as_real_numbers(tiny, kind):
    # the yaw, steps and probe offsets refused them ('must be a number'), refine_deg and
    # stage2_window_deg took a Fraction but a Decimal raised TypeError (Decimal / float); counts
    # stay integers: an integral Fraction or Decimal is refused as a float would be
    n = tiny.spec.size
    grid = np.zeros((n,) * 3, dtype=np.int8)
    grid[5:10, 5:10, 3:8] = 1
    for name, value in (('yaw', 0.5), ('yaw_step_deg', 2.0), ('search_step_deg', 5.0),
                        ('refine_deg', 2.5), ('stage2_window_deg', 10.0), ('probe_deg', 7.5)):
        want = tiny.estimate(grid, **{name: value})
        got = tiny.estimate(grid, **{name: kind(str(value))})
        assert (got.label, got.yaw) == (want.label, want.yaw), name
    assert tiny.features(grid, yaw=kind('0.5'))[0].tolist() == tiny.features(grid, yaw=0.5)[
        0].tolist()
    for name in ('n_hypotheses', 'stage2_modes'):
        with pytest.raises(ValueError, match=f'{name} must be an integer >= 0'):
            tiny.estimate(grid, **{name: kind(2)})
    with pytest.raises(ValueError, match='yaw must be finite'):
        tiny.estimate(grid, yaw=kind(10) ** 400)


def test_estimate_points_threshold_is_a_real_number(tiny):
    # a duration (an integer to numpy) was taken and failed in numpy's comparison
    pts = np.argwhere(views()[0] > 0) * 0.01
    for bad in (np.timedelta64(1), True, 0.5j, '0.5'):
        with pytest.raises(ValueError, match='threshold must be an occupancy probability'):
            tiny.estimate_points(pts, threshold=bad)
    want = tiny.estimate_points(pts, threshold=0.5)
    for ok in (Fraction(1, 2), Decimal('0.5'), np.array(0.5)):
        assert tiny.estimate_points(pts, threshold=ok).label == want.label


def test_training_skips_views_that_lost_the_object(monkeypatch, capsys):
    # a one-voxel object's view can lose the voxel to the nearest-neighbour rotation (3.5 % of
    # random views): the out-of-fold features skip it, count it and say so, not stop training
    import beo_ros.core.training as training
    from beo_ros.core.grid import GridSpec
    X, y, names = primitive_shapes(N, 8, np.random.default_rng(0))
    dot = np.zeros((1, N ** 3), X.dtype)
    dot[0, 7 * N * N + 9 * N + 2] = 1
    X, y = np.vstack([X, dot]), np.append(y, 0)
    real = training.random_partial_view

    def lossy(occ, rng):
        grid, *rest = real(occ, rng)
        return (np.zeros_like(grid) if occ.sum() == 1 else grid, *rest)

    monkeypatch.setattr(training, 'random_partial_view', lossy)
    bank = training.fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3,
                             classifier_views=2, folds=2, seed=0)
    assert bank.training['skipped_views'] == 2
    assert '2 partial view(s) skipped' in capsys.readouterr().err
    cv = bank.training['cross_validation']
    assert cv['complete']['n'] == 17 and cv['partial']['n'] == 16 * 2


def test_occupancy_variance_is_none_without_a_completion(tiny):
    # what the node's worker processes send back: the grids are dropped
    e = dataclasses.replace(tiny.estimate(views()[0]), completion=None, variance=None)
    assert e.occupancy_variance is None


def test_model_dir_of_an_unknown_user_is_named_as_missing():
    # Path.expanduser raised RuntimeError 'Could not determine home directory.': the node
    # died at start (not a StartupError) and on a set of model_dir
    import pwd
    from beo_ros.core.bank import resolve_model_dir
    with pytest.raises(KeyError):
        pwd.getpwnam('no_such_beo_user')
    assert resolve_model_dir('~no_such_beo_user/m') == Path('~no_such_beo_user/m')
    with pytest.raises(ModelError, match='~no_such_beo_user/m does not exist'):
        load_models('~no_such_beo_user/m')


def test_load_models_takes_a_shipped_models_name(tmp_path, monkeypatch):
    from beo_ros.core.bank import default_model_dir, resolve_model_dir, shipped_models
    assert {'modelnet10_32', 'tabletop_32'} <= set(shipped_models())
    monkeypatch.chdir(tmp_path)
    assert load_models('tabletop_32').classes == ['box', 'cylinder']
    assert resolve_model_dir('') == resolve_model_dir(None) == default_model_dir()
    # a path that exists here wins over the shipped name, and paths are never renamed
    (tmp_path / 'tabletop_32').mkdir()
    with pytest.raises(ModelError, match='manifest.json is missing'):
        load_models('tabletop_32')
    for text in ('./modelnet10_32', 'sub/tabletop_32', 'no_such_model'):
        assert resolve_model_dir(text) == Path(text)
        with pytest.raises(ModelError, match='does not exist'):
            load_models(text)


@pytest.mark.parametrize('site', ['lib/python3.11/site-packages', 'target'])
def test_shipped_models_found_next_to_a_pip_installed_package(tmp_path, monkeypatch, site):
    # `pip install .` (not editable) puts the package in <prefix>/lib/pythonX.Y/site-packages
    # and setup.py's data_files in <prefix>/share/beo_ros (`--target DIR`: both in DIR); with
    # no AMENT_PREFIX_PATH, load_models() looked for <site-packages>/models and failed
    from beo_ros.core import bank
    prefix = tmp_path / 'prefix'
    top = prefix / site
    (top / 'beo_ros' / 'core').mkdir(parents=True)
    share = (top if site == 'target' else prefix) / 'share' / 'beo_ros' / 'models'
    share.mkdir(parents=True)
    for name in ('modelnet10_32', 'tabletop_32'):
        (share / name).symlink_to(bank.default_model_dir(name), target_is_directory=True)
    monkeypatch.setattr(bank, '__file__', str(top / 'beo_ros' / 'core' / 'bank.py'))
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    monkeypatch.chdir(tmp_path)
    assert bank.default_model_dir() == share / 'modelnet10_32'
    assert bank.shipped_models() == ['modelnet10_32', 'tabletop_32']
    assert load_models('tabletop_32').classes == ['box', 'cylinder']


# ---------------------------------------------------------------------- formulas, directly
def test_features_equal_a_direct_computation_at_yaw_zero(tiny):
    # at yaw 0 the canonical frame is the observed one: every feature can be computed by hand
    from beo_ros.core.inference import FEATURE_NAMES, observed_edt
    _, part = views()
    eng = tiny.engine
    edt = observed_edt(part).ravel()
    canon = part.ravel()
    known = canon >= 0
    for c in range(len(tiny.classes)):
        ex = eng.exact(part, c, 0.0)
        np.testing.assert_array_equal(ex['canon'], canon)
        f = dict(zip(FEATURE_NAMES, eng.features(ex, c, 0.0, edt)))
        pred = ex['pred'].astype(np.float64)
        p = pred >= 0.5
        occ, free = canon == 1, canon == 0
        assert f['rmse'] == pytest.approx(np.sqrt(np.mean((canon[known] - pred[known]) ** 2)),
                                          rel=1e-4)
        assert f['recall'] == pytest.approx((p & occ).sum() / occ.sum())
        assert f['false_occupied'] == pytest.approx((p & free).sum() / free.sum())
        assert f['dt_error'] == pytest.approx(np.sqrt(np.mean(edt[p & known] ** 2)), rel=1e-5)


def test_likelihood_features_are_per_voxel(tiny):
    # loglik: the exact log-likelihood per known voxel; coarse_loglik: the stage-1 pooled
    # log-likelihood per pooled cell (N^3 / 8 of them), both of the class's best yaw
    from beo_ros.core.inference import FEATURE_NAMES
    _, part = views()
    eng = tiny.engine
    feats, per = tiny.features(part, yaw=0.4)
    pooled = eng.scores(eng.pooled(part), [0.4])[0]
    for c in range(eng.C):
        f = dict(zip(FEATURE_NAMES, feats[c]))
        ex = eng.exact(part, c, 0.4)
        assert ex['n_known'] == np.count_nonzero(part >= 0)
        assert f['loglik'] == pytest.approx(ex['loglik'] / ex['n_known'], rel=1e-9)
        assert f['coarse_loglik'] == pytest.approx(pooled[c] / (N ** 3 / 8), rel=1e-9)
        # the hypotheses: the 3 best stage-1 modes
        assert len(per[c]['hypotheses']) == 1   # a given yaw
    _, per = tiny.features(part)
    for c in range(eng.C):
        assert len(per[c]['hypotheses']) == 3


def test_features_of_a_prediction_with_no_occupied_known_voxel(tiny):
    # no predicted-occupied known voxel: no distance to average, the dt error is the grid size
    # (as far as anything can be), and recall 0
    _, part = views()
    eng = tiny.engine
    ex = dict(eng.exact(part, 0, 0.0))
    ex['pred'] = np.zeros_like(ex['pred'])
    f = eng.features(ex, 0, 0.0, np.ones(eng.d, np.float32))
    assert f[5] == eng.n and f[3] == 0.0 and f[4] == 0.0


def test_predictive_variance_formula(tiny):
    # var_i = w_i^T S w_i + v + m^T Sw m + tr(Sw S) + mu_var_i, S = G^-1 (loadings, noise, the
    # loadings' posterior covariance Sw and the mean's variance)
    _, part = views()
    eng = tiny.engine
    c = 0
    ex = eng.exact(part, c, 0.0)
    k = ex['G'].shape[0]
    Sw = 0.05 * np.eye(k)
    mu_var = np.full(eng.d, 0.01)
    _, mean, var = eng.predictive(ex, c, Sw, mu_var)
    W = eng.W[c].astype(np.float64)
    S = np.linalg.inv(ex['G'])
    m = ex['m']
    want = ((W @ S) * W).sum(axis=1) + eng.v[c] + m @ Sw @ m + np.trace(Sw @ S) + mu_var
    np.testing.assert_allclose(var, want, rtol=1e-5)
    # the occupancy probability: P(occupancy >= 0.5) under N(mean, var)
    from scipy.stats import norm
    prob, _, _ = eng.predictive(ex, c, Sw, mu_var)
    np.testing.assert_allclose(prob, norm.sf(0.5, mean.astype(np.float64), np.sqrt(want)),
                               rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(mean, W @ m + eng.mu[c], rtol=1e-5, atol=1e-6)


def test_completion_variance_includes_the_class_predictive_variance(tiny):
    # the unknown voxels' variance is at least the model noise: it is the mixture's variance,
    # predictive variances included, not only the spread of the class means
    _, part = views()
    e = tiny.estimate(part, yaw=0.0)
    assert e.variance[part < 0].min() >= min(m.noise_variance for m in tiny.models)
    assert (e.variance[part >= 0] == 0).all()


def test_completion_is_the_probability_weighted_mixture_of_the_likely_classes(tiny):
    # Bayesian model averaging over the classes of probability >= min_prob (at most
    # max_classes), weights renormalised; the variance is the mixture's (predictive variances
    # plus the spread of the class means); observed voxels are kept, with no variance
    _, part = views()
    eng = tiny.engine
    assert tiny.occupancy_calibration is None
    _, per = tiny.features(part, yaw=0.4)
    for c in range(eng.C):
        eng.add_prediction(per[c]['exact'], part, c)
    obs = []
    for c, m in enumerate(tiny.models):
        p, mean, var = eng.predictive(per[c]['exact'], c, m.loading_covariance.astype(np.float64),
                                      m.mean_variance)
        obs.append([eng.to_observed(a, 0.4).reshape(part.shape).astype(np.float64)
                    for a in (p, mean, var)])
    hidden, seen = part < 0, part >= 0
    assert hidden.any()
    for probs, w in (([0.6, 0.2], [0.75, 0.25]), ([0.9, 0.1], [0.9, 0.1]),
                     ([0.95, 0.05], [1.0, 0.0]), ([0.02, 0.03], [0.0, 1.0])):
        prob, var = tiny._completion(part, per, np.array(probs), int(np.argmax(probs)))
        want_p = w[0] * obs[0][0] + w[1] * obs[1][0]
        m1 = w[0] * obs[0][1] + w[1] * obs[1][1]
        m2 = sum(wc * (o[2] + o[1] ** 2) for wc, o in zip(w, obs))
        np.testing.assert_allclose(prob[hidden], want_p[hidden], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(var[hidden], (m2 - m1 ** 2)[hidden], rtol=1e-4, atol=1e-6)
        np.testing.assert_array_equal(prob[seen], (part == 1)[seen])
        assert (var[seen] == 0).all()
    # max_classes: only the most probable
    prob, _ = tiny._completion(part, per, np.array([0.6, 0.4]), 0, max_classes=1)
    np.testing.assert_allclose(prob[hidden], obs[0][0][hidden], rtol=1e-5, atol=1e-6)


def test_completion_of_a_rotated_partial_view_matches_the_shape(pose_case):
    # the completion of the *unknown* voxels is turned back into the observed frame by the yaw:
    # with the true yaw given, the hidden part of an asymmetric shape comes out where it is
    bank, _ = pose_case
    Xt, _ = asymmetric_shapes(2, np.random.default_rng(5))
    for x in Xt:
        shape = x.reshape((N,) * 3) > 0.5
        for yaw in (0.9, -2.0):
            rot = rotate_grid(shape.astype(np.uint8), yaw).astype(bool)
            pv = partial_view(rot, 0.3, np.deg2rad(30))
            e = bank.estimate(pv, yaw=yaw)
            hidden = pv < 0
            assert hidden.sum() > 50
            assert ((e.completion >= 0.5) == rot)[hidden].mean() >= 0.95


def test_parse_class_prior_refuses_an_unknown_name_in_the_text_form():
    # before: 'Uniform' passed through and was refused later with the API's wording
    from beo_ros.core.bank import parse_class_prior
    assert parse_class_prior(' uniform ') == 'uniform' and parse_class_prior('') is None
    assert parse_class_prior('a=1, b=2') == {'a': 1.0, 'b': 2.0}
    with pytest.raises(ValueError, match=r"'train', 'uniform' or 'name=weight,\.\.\.'.*'Uniform'"):
        parse_class_prior('Uniform')
    # a class named twice: refused, not the last weight kept
    for twice in ('a=1,b=2,a=3', '"a"=1,a=2'):
        with pytest.raises(ValueError, match='each class once'):
            parse_class_prior(twice)


def test_parse_class_prior_reads_a_class_name_with_an_equals_sign():
    # a legal class name; the text form split at the first '=' ("weight of 'w' is not a
    # number: '1=0.25'"), so the node's own prior text of such a bank could not be read back
    from beo_ros.core.bank import parse_class_prior, resolve_class_prior
    assert parse_class_prior('w=1=0.25, cup=0.75') == {'w=1': 0.25, 'cup': 0.75}
    np.testing.assert_allclose(resolve_class_prior(parse_class_prior('w=1=1,cup=3'),
                                                   ['w=1', 'cup']), [0.25, 0.75])
    with pytest.raises(ValueError, match="weight of 'cup' is not a number"):
        parse_class_prior('w=1=1,cup=x')


def test_parse_class_prior_reads_class_names_with_a_comma_in_double_quotes():
    # a legal class name (it names a file); the text split at every comma: 'a' had no weight
    from beo_ros.core.bank import format_class_prior, parse_class_prior
    assert parse_class_prior('"chair, office"=0.3, table=0.7') == {'chair, office': 0.3,
                                                                    'table': 0.7}
    assert parse_class_prior(r' "a\"b,c" = 1 ,"\\"=2') == {'a"b,c': 1.0, '\\': 2.0}
    # unquoted text reads as before, '"' in a name included
    assert parse_class_prior('x"y=1,"z=2,w=1=3,"q"=1=4') == {'x"y': 1.0, '"z': 2.0,
                                                              'w=1': 3.0, '"q"=1': 4.0}
    for bad in ('chair, office=0.3,table=0.7', '"a,b=1', '""=1', '"a,b"=1=2'):
        with pytest.raises(ValueError, match='each class once'):
            parse_class_prior(bad)
    with pytest.raises(ValueError, match="weight of 'a,b' is not a number: 'x'"):
        parse_class_prior('"a,b"=x')
    classes = ['chair, office', '"quoted"', 'w=1', 'table']
    text = format_class_prior(classes, [0.125, 0.25, 0.5, 0.125])
    assert text == '"chair, office"=0.125,"\\"quoted\\""=0.25,w=1=0.5,table=0.125'
    assert parse_class_prior(text) == dict(zip(classes, [0.125, 0.25, 0.5, 0.125]))


def test_save_gives_the_directory_the_umask_permissions_without_touching_the_umask(
        tmp_path, monkeypatch):
    """The model directory gets the permissions of the umask (not mkdtemp's 0o700), without
    setting the process umask to 0 for a moment (other threads then made world-writable
    files)."""
    import stat
    bank = make_tiny_bank()
    old = os.umask(0o027)
    try:
        def no_umask(mask):
            raise AssertionError(f'save set the umask to {mask:o}')
        monkeypatch.setattr(os, 'umask', no_umask)
        path = bank.save(tmp_path / 'm')
        bank.save(path)   # replacing a model too
    finally:
        monkeypatch.undo()
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o750
    assert ModelBank.load(path).classes == bank.classes


def test_estimate_solves_each_exact_posterior_once(pose_case, monkeypatch):
    # the refinement solved the stage-1 yaw of the chosen class again (at its stage-2 optimum
    # or in the climb): the same rotation maps, the same posterior, twice the time
    from beo_ros.core.inference import yaw_key
    bank, cases = pose_case
    eng = bank.engine
    calls = []
    exact = eng.exact

    def counted(obs, c, yaw, with_prediction=True):
        calls.append((c, yaw_key(-yaw), yaw_key(yaw)))
        return exact(obs, c, yaw, with_prediction)

    monkeypatch.setattr(eng, 'exact', counted)
    for g, _, _, _ in cases:
        calls.clear()
        bank.estimate(g)
        assert len(calls) == len(set(calls)), calls
