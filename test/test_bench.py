"""beo-bench: a quick in-process smoke run and unit tests of the peers on generated shapes."""
import json
import math
import re

import numpy as np
import pytest

from beo_ros.core.synthetic import primitive_shapes, random_partial_view

N = 16


@pytest.fixture(scope='module')
def shapes():
    X, y, names = primitive_shapes(N, 12, np.random.default_rng(0))
    Xq, yq, _ = primitive_shapes(N, 6, np.random.default_rng(1))
    rng = np.random.default_rng(2)
    queries = [random_partial_view(Xq[i].reshape((N,) * 3) > 0.5, rng)[:2] + (int(yq[i]),)
               for i in range(len(Xq))]
    return X, y, names, queries


def _finite_numbers(o):
    if isinstance(o, dict):
        return all(_finite_numbers(v) for v in o.values())
    if isinstance(o, list):
        return all(_finite_numbers(v) for v in o)
    if isinstance(o, float):
        return math.isfinite(o)
    return True


def test_paper_baseline_classifies_boxes_and_cylinders(shapes):
    from beo_ros.core.baselines import PaperPCA
    X, y, names, queries = shapes
    paper = PaperPCA(k=4).fit(X, y, names, N)
    assert paper.nbytes > 0
    hits = 0
    for grid, yaw, label in queries:
        c, est_yaw, completion = paper.predict(grid)
        assert 0 <= c < 2 and 0 <= est_yaw < 2 * np.pi
        assert completion.shape == (N,) * 3 and np.isfinite(completion).all()
        hits += c == label
    assert hits >= 0.75 * len(queries)


def test_paper_baseline_without_ridge_answers_a_view_of_few_known_voxels(shapes):
    """ridge 0 is accepted; a view with fewer known voxels than components made A singular
    (LinAlgError 'Singular matrix')."""
    from beo_ros.core.baselines import PaperPCA
    X, y, names, _ = shapes
    paper = PaperPCA(k=5, n_yaws=4, ridge=0).fit(X, y, names, N)
    grid = np.full((N,) * 3, -1, np.int8)
    grid[8, 8, 8], grid[8, 8, 9] = 1, 0
    c, yaw, completion = paper.predict(grid)
    assert 0 <= c < 2 and np.isfinite(completion).all()


def test_paper_baseline_recovers_yaw_of_a_complete_asymmetric_object():
    """A complete L-shaped object rotated by a candidate yaw: the paper's search finds it."""
    from beo_ros.core.baselines import PaperPCA
    from beo_ros.core.grid import rotate_grid
    rng = np.random.default_rng(0)
    X = []
    for _ in range(6):
        occ = np.zeros((N,) * 3, dtype=bool)
        a = rng.integers(3, 5)
        occ[3:13, 3:3 + a, 4:12] = True
        occ[3:3 + a, 3:11, 4:12] = True
        X.append(occ.ravel())
    X = np.array(X, dtype=np.float32)
    paper = PaperPCA(k=3).fit(X, np.zeros(len(X), int), ['L'], N)
    yaw = 2 * np.pi * 9 / 36
    grid = rotate_grid(X[0].reshape((N,) * 3).astype(np.int8), yaw)
    c, est_yaw, _ = paper.predict(grid)
    assert c == 0
    assert abs(np.rad2deg(est_yaw - yaw)) < 1e-6


def test_icp_baseline_classifies_and_reports_db_size(shapes):
    pytest.importorskip('open3d')
    from beo_ros.core.baselines import ICPDatabase
    X, y, names, queries = shapes
    db = ICPDatabase(per_class=4, n_init_yaws=4).fit(X, y, names, N)
    assert db.size == 8 and db.nbytes > 0
    hits = 0
    for grid, yaw, label in queries:
        c, est_yaw, fitness = db.predict(grid)
        assert 0 <= c < 2 and np.isfinite(est_yaw) and 0 <= fitness <= 1
        hits += c == label
    assert hits >= 0.75 * len(queries)


@pytest.mark.parametrize('peer', ['paper', 'icp'])
def test_baselines_refuse_a_wrong_size_or_empty_grid(shapes, peer):
    from beo_ros.core.baselines import ICPDatabase, PaperPCA
    if peer == 'icp':
        pytest.importorskip('open3d')
    X, y, names, _ = shapes
    model = (PaperPCA(k=2, n_yaws=4) if peer == 'paper' else
             ICPDatabase(per_class=1, n_init_yaws=1)).fit(X, y, names, N)
    with pytest.raises(ValueError, match=r'grid must have shape \(16, 16, 16\)'):
        model.predict(np.zeros((8,) * 3, np.int8))
    for fill in (-1, 0):   # all unknown (a matmul error), all free (ICP: a silent (0, 0, 0))
        with pytest.raises(ValueError, match='no occupied voxel'):
            model.predict(np.full((N,) * 3, fill, np.int8))


def _peer(peer, **params):
    from beo_ros.core.baselines import ICPDatabase, PaperPCA
    return (PaperPCA if peer == 'paper' else ICPDatabase)(**params)


@pytest.mark.parametrize('peer, params', [
    ('paper', dict(k=3, n_yaws=5, ridge=0.1)),
    ('icp', dict(per_class=None, n_init_yaws=2, max_dist=1.5, max_iter=7, seed=None)),
])
def test_baselines_store_their_arguments_and_learn_attributes_ending_in_underscore(
        shapes, peer, params):
    """scikit-learn style: __init__ only stores the arguments; fit adds ``name_`` attributes
    only, and returns the estimator."""
    if peer == 'icp':
        pytest.importorskip('open3d')
    X, y, names, _ = shapes
    model = _peer(peer, **params)
    assert vars(model) == params
    assert model.fit(X, y, names, N) is model
    learned = {a for a in vars(model) if a not in params}
    assert learned and all(a.endswith('_') and not a.startswith('_') for a in learned), learned
    assert model.n_ == N and model.classes_ == list(names)


@pytest.mark.parametrize('peer, params, message', [
    ('paper', dict(k=0), 'k must be an integer >= 1, got 0'),
    ('paper', dict(k=2.5), 'k must be an integer >= 1, got 2.5'),
    ('paper', dict(n_yaws=True), 'n_yaws must be an integer >= 1, got True'),
    ('paper', dict(ridge=-1.0), 'ridge must be a finite number >= 0, got -1.0'),
    ('paper', dict(ridge=float('nan')), 'ridge must be a finite number >= 0, got nan'),
    ('icp', dict(per_class=0), 'per_class must be an integer >= 1, got 0'),
    ('icp', dict(n_init_yaws=0), 'n_init_yaws must be an integer >= 1, got 0'),
    ('icp', dict(max_dist=0), 'max_dist must be a finite number > 0, got 0'),
    ('icp', dict(max_iter='30'), "max_iter must be an integer >= 1, got '30'"),
    ('icp', dict(seed=-1), 'seed must be an integer >= 0, got -1'),
])
def test_baselines_refuse_bad_parameters_at_fit(shapes, peer, params, message):
    X, y, names, _ = shapes
    model = _peer(peer, **params)   # stored as given, checked by fit
    with pytest.raises(ValueError, match=re.escape(message)):
        model.fit(X, y, names, N)


@pytest.mark.parametrize('peer', ['paper', 'icp'])
def test_baselines_refuse_training_data_that_does_not_fit_together(shapes, peer):
    X, y, names, _ = shapes
    model = _peer(peer)
    with pytest.raises(ValueError, match=r'X must have shape \(objects, 512\) \(flattened 8'):
        model.fit(X, y, names, 8)
    with pytest.raises(ValueError, match=r'n must be an integer >= 1, got 0'):
        model.fit(X, y, names, 0)
    with pytest.raises(ValueError, match=r'y must have shape \(24,\) \(one label per row'):
        model.fit(X, y[:-1], names, N)
    with pytest.raises(ValueError, match=r'y must hold class indices 0\.\.1 \(into names\), '
                                         r'got \[2\]'):
        model.fit(X, np.where(y == 1, 2, y), names, N)
    with pytest.raises(ValueError, match='names must name at least one class'):
        model.fit(X, y, [], N)


def test_icp_baseline_refuses_an_empty_database():
    """Objects too small for a surface (< 4 voxels): predict would answer class 0, yaw 0."""
    pytest.importorskip('open3d')
    X = np.zeros((2, N ** 3), np.float32)
    X[:, 0] = 1
    with pytest.raises(ValueError, match='the database would be empty'):
        _peer('icp').fit(X, np.array([0, 1]), ['a', 'b'], N)


@pytest.mark.parametrize('peer', ['paper', 'icp'])
def test_baselines_used_before_fit_say_so(peer):
    from sklearn.exceptions import NotFittedError
    model = _peer(peer)
    calls = [lambda: model.predict(np.ones((N,) * 3, np.int8)), lambda: model.nbytes]
    if peer == 'icp':
        calls.append(lambda: model.size)
    for call in calls:
        with pytest.raises(NotFittedError, match=f'This {type(model).__name__} instance is '
                                                 'not fitted yet'):
            call()
    assert issubclass(NotFittedError, ValueError)


def test_yaw_error_wraps():
    from beo_ros.bench import yaw_error_deg
    assert yaw_error_deg(np.deg2rad(359), np.deg2rad(1)) == pytest.approx(2)
    assert yaw_error_deg(np.deg2rad(-170), np.deg2rad(170)) == pytest.approx(20)
    assert yaw_error_deg(0.0, np.pi) == pytest.approx(180)


def test_summary_yaw_of_the_correct_class_is_nan_when_no_class_is_right():
    from beo_ros.bench import summarize
    yerr = [5.0, 170.0, 30.0]
    s = summarize([0.01] * 3, [False, True, True], yerr, [1, 2, 3])
    assert s['yaw_median_deg_correct_class'] == 100.0 and s['yaw_median_deg'] == 30.0
    none = summarize([0.01] * 3, [False] * 3, yerr, [1, 2, 3])
    assert math.isnan(none['yaw_median_deg_correct_class']) and none['accuracy'] == 0.0


def test_query_that_lost_its_object_has_no_yaw_to_score():
    # the view of a one-voxel object lost to the rotation at yaw 355: the predictor's
    # placeholder yaw 0 (no object, no pose) used to count as within 10 deg
    from beo_ros.bench import run_peer
    grid = np.zeros((16,) * 3, np.int8)
    q = dict(grid=grid, yaw=float(np.deg2rad(355.0)), label=0)
    r = run_peer('p', lambda g: (0, 0.0), [q], 1, mem_queries=0)
    assert r['yaw_within_10deg'] == r['yaw_within_10deg_flip'] == 0.0
    assert r['yaw_median_deg'] == r['yaw_median_deg_correct_class'] == 180.0


def test_quick_bench_smoke(tmp_path, capsys):
    pytest.importorskip('open3d')
    from beo_ros.bench import main
    out = tmp_path / 'bench'
    assert main(['--quick', '--data', 'none', '--out', str(out)]) == 0
    res = json.loads((out / 'bench.json').read_text())
    for peer in ('beo', 'paper', 'icp'):
        for key in ('p50_ms', 'p95_ms', 'accuracy', 'yaw_median_deg', 'yaw_within_10deg',
                    'yaw_within_10deg_flip', 'peak_mem_mb'):
            assert isinstance(res[peer][key], float) and math.isfinite(res[peer][key]), (peer, key)
        assert res[peer]['p50_ms'] > 0 and 0 <= res[peer]['accuracy'] <= 1
    assert res['icp']['db_size'] > 0
    assert math.isfinite(res['speedup_vs_icp']) and res['speedup_vs_icp'] > 0
    sc = res['scaling']
    for key in ('train_objects', 'grid', 'yaw_step', 'classes'):
        assert sc[key], key
    assert {'n_train', 'beo_ms', 'icp_ms', 'beo_mb', 'icp_mb'} <= set(sc['train_objects'][0])
    assert 'node' in res
    node = res['node']
    # --quick runs the node phase; only a missing ROS install may skip it (a failure of
    # the phase itself is recorded as 'skipped: failed: ...')
    assert ('skipped' not in node
            or node['skipped'].startswith(('ModuleNotFoundError', 'ImportError'))), node
    if 'skipped' not in node:
        assert node['objects'] > 0 and node['objects_per_s'] > 0
        for key in ('e2e_p50_ms', 'e2e_p95_ms', 'max_objects_per_s'):
            assert math.isfinite(node[key]) and node[key] > 0, key
        assert node['workers'] >= 1 and node['rates']
        for row in node['rates']:  # open loop: every cloud accounted for
            assert row['sent'] > 0
            assert row['received'] + row['lost'] == row['sent']
            assert (row['estimates'] + row['dropped_stale'] + row['rejected'] + row['errors']
                    + row['missing_estimates'] == row['received'])
            assert row['sustained'] == (row['dropped_stale'] <= 0.05 * row['sent']
                                        and row['lost'] == 0 and row['rejected'] == 0
                                        and row['errors'] == 0
                                        and row['missing_estimates'] == 0)
        assert node['closed_loop']['objects'] > 0
        assert 'Node (real rclpy, bag replay' in (out / 'bench.md').read_text()
    assert _finite_numbers({k: v for k, v in res.items() if k != 'node'})
    for png in ('latency.png', 'accuracy.png', 'scaling.png'):
        assert (out / png).stat().st_size > 1000
    assert 'speedup vs icp' in capsys.readouterr().out


# ---------------------------------------------------------------------- bad input
QUICK = ['--quick', '--no-paper', '--no-icp', '--no-scaling', '--no-node', '--no-plots']


def _npz(path, names=('box', 'cylinder')):
    X, y, _ = primitive_shapes(N, 3, np.random.default_rng(0))
    np.savez(path, voxels=np.packbits(X.astype(np.uint8), axis=1), labels=y,
             classes=np.array(names), shape=np.array([N, N, N]))
    return path


def test_generated_shapes_only_for_none_or_a_missing_default(tmp_path, monkeypatch):
    import argparse
    from beo_ros.bench import load_data
    args = argparse.Namespace(data='', classes=None, train_per_class=None)
    monkeypatch.setenv('BEO_DATA_DIR', str(tmp_path / 'no_data_here'))
    for data in ('', 'none'):  # the default file absent, or asked for
        args.data = data
        assert load_data(args, np.random.default_rng(0))[-1].startswith('generated')
    args.data = str(tmp_path / 'TYPO.npz')  # a given file that does not exist: an error
    with pytest.raises(ValueError, match='TYPO.npz: no such file'):
        load_data(args, np.random.default_rng(0))
    args.data = str(_npz(tmp_path / 'd.npz'))
    assert load_data(args, np.random.default_rng(0))[-1] == args.data
    # --classes selects among the generated classes too, and refuses the others
    args.data, args.classes = 'none', ['cylinder']
    X, y, names = load_data(args, np.random.default_rng(0))[:3]
    assert names == ['cylinder'] and set(y) == {0} and len(X) == len(y) > 0
    args.classes = ['chair']
    with pytest.raises(ValueError, match=r"generated boxes/cylinders.*\['chair'\] not in"):
        load_data(args, np.random.default_rng(0))


def test_bench_missing_data_file_exit_2(tmp_path, capsys):
    from beo_ros.bench import main
    assert main(QUICK + ['--data', str(tmp_path / 'TYPO.npz'), '--out', str(tmp_path / 'b')]) == 2
    err = capsys.readouterr().err
    assert 'beo-bench: error: --data' in err and 'TYPO.npz: no such file' in err
    assert not (tmp_path / 'b' / 'bench.json').exists()


def test_bench_missing_model_exit_2(tmp_path, capsys):
    from beo_ros.bench import main
    assert main(QUICK + ['--data', 'none', '--model', str(tmp_path / 'no_model'),
                         '--out', str(tmp_path / 'b')]) == 2
    err = capsys.readouterr().err
    assert 'beo-bench: error:' in err and 'no_model' in err and 'Traceback' not in err


def test_bench_unknown_class_exit_2(tmp_path, capsys):
    from beo_ros.bench import main
    assert main(QUICK + ['--data', str(_npz(tmp_path / 'd.npz')), '--classes', 'sofa',
                         '--out', str(tmp_path / 'b')]) == 2
    assert "beo-bench: error: " in capsys.readouterr().err


def test_bench_model_classes_differ_exit_2(tmp_path, capsys):
    from beo_ros.bench import main
    from beo_ros.core.synthetic import make_tiny_bank
    make_tiny_bank(tmp_path / 'bank', k=2)
    assert main(QUICK + ['--data', str(_npz(tmp_path / 'd.npz', ('a', 'b'))), '--classes', 'a',
                         'b', '--model', str(tmp_path / 'bank'), '--out', str(tmp_path / 'b')]) == 2
    assert 'beo-bench: error: --model classes' in capsys.readouterr().err


def test_bench_model_grid_differs_exit_2(tmp_path, capsys):
    # the same classes on another grid used to fail at the first query, after --out was
    # made, with a message about 'grid' naming neither the model nor the data
    from beo_ros.bench import main
    from beo_ros.core.synthetic import make_tiny_bank
    make_tiny_bank(tmp_path / 'bank', k=2, n=8)
    assert main(QUICK + ['--data', str(_npz(tmp_path / 'd.npz')), '--model',
                         str(tmp_path / 'bank'), '--out', str(tmp_path / 'b')]) == 2
    assert 'is for a 8^3 grid, the data' in capsys.readouterr().err
    assert not (tmp_path / 'b').exists()


def test_bench_data_without_objects_exit_2(tmp_path, capsys):
    from beo_ros.bench import main
    p = tmp_path / 'none.npz'
    np.savez(p, voxels=np.zeros((0, N ** 3 // 8), np.uint8), labels=np.zeros(0, int),
             classes=np.array(['box', 'cylinder']), shape=np.array([N, N, N]))
    assert main(QUICK + ['--data', str(p), '--out', str(tmp_path / 'b')]) == 2
    assert 'none.npz: no objects' in capsys.readouterr().err
    assert not (tmp_path / 'b').exists()


def test_bench_drops_objects_without_occupied_voxels(tmp_path, capsys):
    # their queries made the paper and icp peers fail the bench: "grid has no occupied voxel"
    import argparse
    from beo_ros.bench import load_data
    X, y, _ = primitive_shapes(N, 3, np.random.default_rng(0))
    X[[0, 3]] = 0
    p = tmp_path / 'd.npz'
    np.savez(p, voxels=np.packbits(X.astype(np.uint8), axis=1), labels=y,
             classes=np.array(['box', 'cylinder']), shape=np.array([N, N, N]))
    args = argparse.Namespace(data=str(p), classes=None, train_per_class=None)
    X2, y2, names, n, _ = load_data(args, np.random.default_rng(0))
    assert len(X2) == len(X) - 2 and (X2 > 0.5).any(axis=1).all()
    np.testing.assert_array_equal(y2, np.delete(y, [0, 3]))
    assert 'dropped 2 objects with no occupied voxel' in capsys.readouterr().err


def test_bench_out_is_a_file_exit_2(tmp_path, capsys):
    from beo_ros.bench import main
    (tmp_path / 'a_file').write_text('x')
    assert main(QUICK + ['--data', 'none', '--out', str(tmp_path / 'a_file')]) == 2
    assert 'beo-bench: error:' in capsys.readouterr().err


def test_quick_takes_the_files_own_classes_without_chair_and_monitor(tmp_path):
    from beo_ros.bench import parse_args
    args = parse_args(['--quick', '--data', str(_npz(tmp_path / 'd.npz', ('mug', 'bowl')))])
    assert args.classes == ['mug', 'bowl']
    # bytes names (an 'S' array) are the same classes, not "b'mug'"
    args = parse_args(['--quick', '--data', str(_npz(tmp_path / 'b.npz', (b'mug', b'bowl')))])
    assert args.classes == ['mug', 'bowl']


@pytest.mark.parametrize('rates', [['0'], ['10', '-2'], ['nan']])
def test_bench_node_rates_must_be_positive(rates, capsys):
    from beo_ros.bench import parse_args
    with pytest.raises(SystemExit):
        parse_args(['--node-rates', *rates])
    err = capsys.readouterr().err
    assert 'argument --node-rates:' in err
    assert 'must be in (0, inf)' in err or 'must be a finite number' in err


@pytest.mark.parametrize('rates', [['1e6'], ['10', '1000.5']])
def test_bench_node_rates_are_bounded(rates, capsys):
    # 1e6 Hz was taken: the bench bag holds rate x --node-duration clouds (8 million)
    from beo_ros.bench import parse_args
    with pytest.raises(SystemExit):
        parse_args(['--node-rates', *rates])
    assert f'argument --node-rates: must be at most 1000 Hz, got {rates[-1]}' in \
        capsys.readouterr().err
    assert parse_args(['--node-rates', '5', '1000']).node_rates == [5.0, 1000.0]


def test_bench_node_bag_size_is_bounded(capsys):
    # 1000 Hz for 3600 s passed each option's own bound: 3.6 million clouds in the bench bag
    from beo_ros.bench import MAX_NODE_MESSAGES, parse_args
    with pytest.raises(SystemExit):
        parse_args(['--node-rates', '10', '1000', '--node-duration', '3600'])
    err = capsys.readouterr().err
    assert '--node-rates x --node-duration' in err and '3600000 clouds' in err
    assert f'at most {MAX_NODE_MESSAGES}' in err
    args = parse_args(['--node-rates', '1000', '--node-duration', str(MAX_NODE_MESSAGES / 1000)])
    assert args.node_rates == [1000.0]
    # without the node phase the options are not used (refused as such, not by the bound)
    with pytest.raises(SystemExit):
        parse_args(['--no-node', '--node-duration', '3600'])
    assert 'not used in this run' in capsys.readouterr().err


def test_a_failing_node_phase_keeps_the_other_results(tmp_path, monkeypatch):
    import beo_ros.bench as bench

    def broken(*a, **k):
        raise RuntimeError('bag player failed')
    monkeypatch.setattr(bench, 'node_bench', broken)
    out = tmp_path / 'b'
    args = [a for a in QUICK if a != '--no-node']
    # exit 1: the node phase failed; the other results are written all the same
    assert bench.main(args + ['--data', str(_npz(tmp_path / 'd.npz')), '--out', str(out)]) == 1
    res = json.loads((out / 'bench.json').read_text())
    assert res['node'] == {'skipped': 'failed: RuntimeError: bag player failed'}
    assert 'beo' in res and (out / 'bench.md').is_file()


def test_markdown_writes_n_a_for_missing_latencies():
    from beo_ros.bench import markdown
    node = {'objects_per_s': 0.0, 'sustained_rate_hz': None, 'dropped_stale': 0, 'lost': 4,
            'e2e_p50_ms': None, 'e2e_p95_ms': None, 'max_objects_per_s': None, 'mode': 'm',
            'workers': 1, 'rates': [{'rate_hz': 2.0, 'sent': 4, 'estimates': 0,
                                     'objects_per_s': 0.0, 'dropped_stale': 0, 'lost': 4,
                                     'e2e_p50_ms': None, 'e2e_p95_ms': None}],
            'closed_loop': {'objects': 4, 'lost': 4, 'objects_per_s': 0.0, 'e2e_p50_ms': None,
                            'e2e_p95_ms': None}}
    md = markdown({'node': node})
    assert 'p50 n/a ms' in md and '| n/a | n/a |' in md


def test_markdown_of_a_peer_that_classified_no_query_right():
    # its yaw median on correctly classified queries is NaN (null in bench.json): bench.md's
    # ':.1f' raised a TypeError traceback after bench.json (no bench.md, no PNGs, exit 1)
    from beo_ros.bench import json_safe, markdown, summarize
    ok = summarize([0.01, 0.02], [True, True], [3.0, 50.0], [1000])
    none = json_safe(summarize([0.01, 0.02], [False, False], [3.0, 50.0], [1000]))
    assert none['yaw_median_deg_correct_class'] is None
    res = {p: dict(ok, fit_s=1.0, index_mb=0.5) for p in ('beo', 'paper')}
    res['icp'] = dict(none, fit_s=1.0, index_mb=0.5, db_size=2, db_per_class=1, init_yaws=4)
    res.update(speedup_vs_icp=2.0, speedup_vs_paper=1.0, node={'skipped': '--no-node'})
    md = markdown(res)
    assert 'icp yaw median on correctly classified n/a deg' in md
    assert 'beo yaw median on correctly classified 26.5 deg' in md


def test_bench_domain_is_in_the_linux_safe_range():
    """The node phase's domain keeps its DDS ports clear of Linux's ephemeral ports
    (215-232) and of the tests' own subprocess domains (10-99)."""
    from beo_ros.bench_node import bench_domain
    domains = {bench_domain(pid) for pid in range(1, 5000)}
    assert domains == set(range(215, 233))


def test_rate_row_of_a_replay():
    """Sent / arrived matched by stamp, counter increments, sustained only without losses."""
    from beo_ros.bench_node import _rate_row
    probe = {'sent': {'1': 0.0, '2': 0.1, '3': 0.2}, 'got': {'1': 0.05, '2': 0.2, '9': 0.3},
             'wall_s': 0.2}
    d = {'received': 3, 'processed': 2, 'dropped_stale': 1, 'rejected': 0, 'errors': 0}
    row = _rate_row(10.0, probe, d, 0.5)
    assert list(row) == ['rate_hz', 'sent', 'sent_per_s', 'received', 'estimates',
                         'dropped_stale', 'rejected', 'errors', 'lost', 'missing_estimates',
                         'order_waits', 'objects_per_s', 'e2e_p50_ms', 'e2e_p95_ms',
                         'e2e_max_ms', 'sustained']
    assert (row['sent'], row['estimates'], row['lost'], row['missing_estimates']) == (3, 2, 0, 0)
    assert row['sent_per_s'] == pytest.approx(10.0) and row['objects_per_s'] == pytest.approx(
        1 / 0.15)
    assert row['e2e_max_ms'] == pytest.approx(100.0) and row['order_waits'] == 0
    assert row['sustained'] and not _rate_row(10.0, probe, d, 0.2)['sustained']


class _FakeNode:
    """counters() and backlog() of a node that finishes one cloud per call."""

    def __init__(self):
        self.calls = 0

    def counters(self):
        self.calls += 1
        done = min(self.calls, 3)
        return {'received': 3, 'processed': done, 'dropped_stale': 0, 'rejected': 0,
                'errors': 0}

    def backlog(self):
        return {'waiting': int(self.calls < 3), 'in_flight': int(self.calls < 3)}


def test_bench_node_settles_through_the_public_api(monkeypatch):
    import time
    import types

    import beo_ros.bench_node as bench
    # bench's own reference only: the time module's sleep serves every thread of the session
    monkeypatch.setattr(bench, 'time', types.SimpleNamespace(sleep=lambda s: None,
                                                             monotonic=time.monotonic))
    b = bench._BenchNode(None, None, [])
    b.node = _FakeNode()
    b.settle(timeout=5.0)
    assert b.node.calls == 4   # idle at the third call, confirmed by a fourth


def test_bench_node_renders_its_clouds_at_a_metric_models_scale(monkeypatch):
    """The node phase's clouds were rendered 1 m across whatever the model: a metric model's
    objects (its grid 16 * 0.02 m here) came twice their size or more, partly outside its
    grid."""
    import types

    import beo_ros.bench_node as bench
    from beo_ros.core.grid import GridSpec
    pytest.importorskip('rclpy')
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')   # node_bench sets it
    seen = []
    render = bench._node_clouds

    def clouds(*a, **kw):   # the bag's clouds, then stop before the bag and the node
        seen.extend(render(*a, **kw))
        raise KeyboardInterrupt

    monkeypatch.setattr(bench, '_node_clouds', clouds)
    X, _, _ = primitive_shapes(N, 2, np.random.default_rng(0))
    bank = types.SimpleNamespace(spec=GridSpec(size=N, units='metric', voxel_size=0.02))
    args = types.SimpleNamespace(node_objects=4, node_rates=[2.0], node_duration=1.0)
    try:
        bench.node_bench(bank, X, N, np.arange(len(X)), args, np.random.default_rng(0))
    except KeyboardInterrupt:
        pass
    if not seen:
        pytest.skip('the node phase needs ROS, rosbags and beo_interfaces')
    extent = max((c.max(axis=0) - c.min(axis=0)).max() for c in seen)
    assert 0.1 < extent <= N * 0.02 + 0.01


def test_peers_answer_a_view_with_no_occupied_voxel_as_a_miss(shapes, capsys):
    """The paper and icp peers refuse a grid with no occupied voxel (ValueError): such a
    query (a view of a few-voxel object the rotation lost) ended the bench with 'beo-bench:
    error: grid has no occupied voxel' after beo had run; it is a miss, as for beo."""
    import types

    from beo_ros.bench import _bench_icp, _bench_paper, _scaling_train_objects, markdown
    pytest.importorskip('open3d')
    X, y, names, views = shapes
    queries = [dict(grid=np.zeros((N,) * 3, np.int8), yaw=1.0, label=0)] + [
        dict(grid=g, yaw=float(yaw), label=label) for g, yaw, label in views[:2]]
    args = types.SimpleNamespace(k=2, paper_yaws=4, slow_repeats=1, icp_db_per_class=1,
                                 icp_init_yaws=1, seed=0, scaling_train=[4], model=None,
                                 repeats=1)
    tr = np.arange(len(X))
    res = {'paper': _bench_paper(args, X, y, tr, names, N, queries),
           'icp': _bench_icp(args, X, y, tr, names, N, queries)}
    for r in res.values():
        assert r['queries'] == 3 and r['empty_views'] == 1 and r['accuracy'] <= 2 / 3
    assert '[paper] 1 of 3 views have no occupied voxel' in capsys.readouterr().err
    # the scaling phase's icp database too (the empty view first: its warm-up query)
    from beo_ros.bench import fit_class_bank
    bank = fit_class_bank(X, y, names, N, 2)
    pts = _scaling_train_objects(args, X, y, names, N, queries[:2], bank,
                                 np.random.default_rng(0))
    assert all(np.isfinite(p['icp_ms']) for p in pts)
    res['beo'] = dict(res['paper'], fit_s=1.0, index_mb=0.5)
    res.update(speedup_vs_icp=1.0, speedup_vs_paper=1.0, node={'skipped': '--no-node'})
    assert '1 of the 3 views have no occupied voxel' in markdown(res)


def _node_entry(sustained_hz, rates=(2.0, 4.0)):
    """A bench.json 'node' entry as json_safe leaves it (NaN -> None)."""
    rows = [{'rate_hz': r, 'sent': 4, 'estimates': 3, 'objects_per_s': 1.5, 'dropped_stale': 1,
             'lost': 0, 'e2e_p50_ms': 40.0, 'e2e_p95_ms': 60.0} for r in rates]
    return {'objects_per_s': 1.5, 'sustained_rate_hz': sustained_hz, 'dropped_stale': 1,
            'lost': 0, 'e2e_p50_ms': 40.0, 'e2e_p95_ms': 60.0, 'max_objects_per_s': 1.5,
            'mode': 'm', 'workers': 1, 'worker_processes': 0, 'rates': rows}


def test_node_summary_line_says_when_no_rate_is_sustained(capsys):
    # it read 'sustains 0 Hz replay, 1.50 objects/s out' (the figures of the lowest rate)
    from beo_ros.bench import _print_summary
    _print_summary({'node': _node_entry(None)})
    out = capsys.readouterr().out
    assert 'sustains none of the replay rates; at the lowest (2 Hz): 1.50 objects/s out' in out
    assert '0 Hz' not in out
    _print_summary({'node': _node_entry(4.0)})
    assert 'sustains 4 Hz replay, 1.50 objects/s out' in capsys.readouterr().out


def test_rate_row_of_a_single_estimate_has_no_latency_percentiles(capsys):
    """One estimate gave p50 = p95 = its latency, a spread from one sample; they are n/a
    (NaN, null in bench.json) and the one latency stays the row's maximum."""
    from beo_ros.bench import _print_summary, json_safe, markdown
    from beo_ros.bench_node import _rate_row
    probe = {'sent': {'1': 0.0, '2': 0.1, '3': 0.2}, 'got': {'1': 0.05}, 'wall_s': 0.2}
    d = {'received': 3, 'processed': 1, 'dropped_stale': 2, 'rejected': 0, 'errors': 0}
    row = _rate_row(10.0, probe, d, 0.05)
    assert row['estimates'] == 1 and row['e2e_max_ms'] == pytest.approx(50.0)
    assert math.isnan(row['e2e_p50_ms']) and math.isnan(row['e2e_p95_ms'])
    two = _rate_row(10.0, dict(probe, got={'1': 0.05, '2': 0.17}), dict(d, processed=2), 0.05)
    assert two['e2e_p50_ms'] == pytest.approx(60.0) and two['e2e_p95_ms'] == pytest.approx(69.0)
    # the headline's are the row's (here the lowest rate's: none sustained)
    node = json_safe(dict(_node_entry(None), rates=[row], e2e_p50_ms=row['e2e_p50_ms'],
                          e2e_p95_ms=row['e2e_p95_ms']))
    assert '| 10 | 3 | 1 | 0.00 | 2 | 0 | n/a | n/a |' in markdown({'node': node})
    _print_summary({'node': node})
    assert 'end-to-end p50 n/a ms, p95 n/a ms' in capsys.readouterr().out


def test_scaling_note_says_what_each_curve_measures(shapes):
    """The note said every point had the scaling queries (icp's training-object points have
    half of them, one run each) and that beo's latency 'does not depend on the training set
    size' (a class gets min(k, objects - 1) components: fewer objects, a faster model; and
    the whole split's point is the beo peer's own bank)."""
    import types

    from beo_ros.bench import fit_class_bank, markdown, scaling
    pytest.importorskip('open3d')
    X, y, names, views = shapes
    queries = [dict(grid=g, yaw=float(yaw), label=label, index=i)
               for i, (g, yaw, label) in enumerate(views[:4])]
    args = types.SimpleNamespace(scaling_queries=4, scaling_per_class=3, scaling_train=[6],
                                 scaling_grids=[16], scaling_yaw_steps=[10.0],
                                 scaling_classes=[2], k=2, repeats=1, icp_init_yaws=1, seed=0,
                                 model=None)
    bank = fit_class_bank(X, y, names, N, 2)
    sc = scaling(args, X, y, names, N, np.arange(len(X)), queries, bank,
                 np.random.default_rng(0))
    note = sc['note']
    assert 'does not depend' not in note
    assert note.startswith('4 queries per point for beo (1 run each), the first 2 for icp (1 run)')
    assert 'min(k=2, objects per class - 1) components' in note
    assert "at the whole split the beo peer's bank" in note
    assert f'({note})' in markdown({'scaling': sc})
