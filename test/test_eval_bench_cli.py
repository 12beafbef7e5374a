"""beo-eval, beo-bench and beo-demo on bad input: exit codes, messages, no empty --out left."""
import json
import types
from pathlib import Path

import numpy as np
import pytest

from beo_ros import bench, cli, evaluate, scan_eval
from beo_ros.core.synthetic import make_tiny_bank, primitive_shapes

N = 16
QUICK = ['--quick', '--no-paper', '--no-icp', '--no-scaling', '--no-node', '--no-plots']


def save_npz(path, X, y, names):
    """Voxel rows in the shared format (bit-packed)."""
    np.savez(path, voxels=np.packbits(np.asarray(X, dtype=np.uint8), axis=1),
             labels=np.asarray(y, dtype=np.uint8), classes=np.array(names),
             shape=np.array([N, N, N]))
    return path


def write_npz(path, count=3, seed=0):
    X, y, names = primitive_shapes(N, count, np.random.default_rng(seed))
    return save_npz(path, X, y, names)


@pytest.fixture(scope='module')
def model(tmp_path_factory):
    """A tiny bank of boxes and cylinders at 16^3 (the classes of ``write_npz``)."""
    path = tmp_path_factory.mktemp('eval_model') / 'model'
    make_tiny_bank(path, n=N, k=2)
    return path


def call(main, argv):
    """``main(argv)``'s exit code; a KeyboardInterrupt that gets out fails the test (instead of
    ending the pytest session)."""
    try:
        return main(argv)
    except KeyboardInterrupt:
        pytest.fail('KeyboardInterrupt escaped main()')
    except SystemExit as e:
        return e.code


# ---------------------------------------------------------------------- the shared helper
def test_output_dir_removes_only_what_it_made_and_left_empty(tmp_path):
    out = tmp_path / 'a' / 'b'
    with pytest.raises(RuntimeError):
        with cli.output_dir(out):
            assert out.is_dir()
            raise RuntimeError
    assert not (tmp_path / 'a').exists()       # the made parent goes too
    (tmp_path / 'old').mkdir()
    with pytest.raises(KeyboardInterrupt):
        with cli.output_dir(tmp_path / 'old'):
            raise KeyboardInterrupt
    assert (tmp_path / 'old').is_dir()          # existed before: kept
    with pytest.raises(RuntimeError):
        with cli.output_dir(tmp_path / 'new') as d:
            (d / 'partial.json').write_text('{}')
            raise RuntimeError
    assert (tmp_path / 'new' / 'partial.json').is_file()   # holds files: kept


# ---------------------------------------------------------------------- beo-eval
def test_eval_zero_objects_refused(model, tmp_path, capsys):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    data = save_npz(tmp_path / 'none.npz', X[:0], y[:0], names)
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--model', str(model), '--data', str(data),
                                '--out', str(out)]) == 2
    assert 'no objects to evaluate' in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize('extra, named', [
    (['--cv', '2', '--model', 'MODEL'], '--model'),
    (['--k', '3'], '--k'),
    (['--verifier-views', '3'], '--verifier-views'),
    (['--train-views', '4'], '--train-views'),
    (['--jobs', '3'], '--jobs'),
    (['--folds', '3'], '--folds'),
    (['--k', '3', '--jobs', '2'], '--k, --jobs'),
    # one at its default value among them: still refused, naming both
    (['--train-views', '1', '--folds', '2'], '--folds, --train-views'),
])
def test_eval_options_of_the_other_mode_refused(model, tmp_path, capsys, extra, named):
    extra = [str(model) if a == 'MODEL' else a for a in extra]
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--data', str(write_npz(tmp_path / 'd.npz')),
                                '--out', str(out), *extra]) == 2
    err = capsys.readouterr().err
    why = ('not used with --cv (each fold trains its own bank): ' if '--cv' in extra else
           'used only with --cv, not in held-out mode: ')   # the mode's own reason
    assert why + named in err, err
    assert not out.exists()


@pytest.mark.parametrize('extra, named', [
    (['--verifier-views', '6'], '--verifier-views'),
    (['--train-views', '1', '--folds', '0'], '--folds, --train-views'),
])
def test_eval_options_of_the_other_mode_at_their_defaults_are_named_and_run(
        model, tmp_path, capsys, extra, named):
    # the check compared values with defaults: they passed without a word; refusing them
    # would break a script that spells the defaults out, so they are named in a warning
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--model', str(model), '--data',
                                str(write_npz(tmp_path / 'd.npz')), '--out', str(out),
                                '--max-objects', '2', *extra]) == 0
    err = capsys.readouterr().err
    assert (f'beo-eval: warning: used only with --cv, not in held-out mode: {named} (given at '
            'the default value: ignored)') in err
    assert (out / 'eval.json').exists()


def test_eval_cv_jobs_without_verifier_views_refused(tmp_path, capsys):
    # before: --cv 2 --verifier-views 0 --jobs 2 ran, --jobs ignored (it makes verifier views)
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--data', str(write_npz(tmp_path / 'd.npz')), '--out', str(out),
                                '--cv', '2', '--verifier-views', '0', '--jobs', '2']) == 2
    assert ("--jobs makes the orientation verifier's views: not used with --verifier-views 0"
            in capsys.readouterr().err)
    assert not out.exists()


def test_eval_held_out_still_takes_its_own_options(model, tmp_path):
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--model', str(model), '--data',
                                str(write_npz(tmp_path / 'd.npz')), '--max-objects', '2',
                                '--views', '1', '--seed', '3', '--out', str(out)]) == 0
    assert (out / 'eval.json').is_file()


@pytest.mark.parametrize('extra', [
    ['--cv', '2', '--k', '0'], ['--cv', '2', '--jobs', '0'], ['--seed', '-1'],
    ['--views', 'nan'], ['--cv', '2', '--verifier-views', '-1'], ['--max-objects', '1.5'],
])
def test_eval_numbers_checked_by_the_parser(tmp_path, capsys, extra):
    with pytest.raises(SystemExit) as ei:
        evaluate.main(['--data', str(tmp_path / 'missing.npz'), '--out', str(tmp_path / 'e'),
                       *extra])
    assert ei.value.code == 2
    assert f'argument {extra[-2]}' in capsys.readouterr().err


def test_eval_model_that_is_a_file(tmp_path, capsys):
    (tmp_path / 'afile').write_text('x')
    assert call(evaluate.main, ['--model', str(tmp_path / 'afile'), '--data',
                                str(write_npz(tmp_path / 'd.npz')),
                                '--out', str(tmp_path / 'e')]) == 2
    err = capsys.readouterr().err
    assert 'afile: is not a directory' in err and 'does not exist' not in err
    assert not (tmp_path / 'e').exists()


def test_eval_objects_without_voxels_are_named_so(model, tmp_path, capsys):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    data = save_npz(tmp_path / 'blank.npz', np.zeros_like(X), y, names)
    assert call(evaluate.main, ['--model', str(model), '--data', str(data),
                                '--out', str(tmp_path / 'e')]) == 0
    printed = capsys.readouterr().out
    assert f'{len(X)} object(s) have no occupied voxel at all' in printed
    assert 'lost to the rotation' not in printed
    recs = (tmp_path / 'e' / 'records.jsonl').read_text().splitlines()
    recs = [json.loads(line) for line in recs]
    assert all(r['empty_object'] for r in recs)


def test_eval_view_that_lost_its_object_has_no_yaw_to_score(model):
    # a one-voxel object in a corner column, lost to the rotation at yaws 355 and 175 deg:
    # the 'unknown' answer's placeholder yaw 0 used to count as within 10 deg and as a flip
    class Scripted:   # the protocol's draws: yaw, azimuth, elevation (degrees)
        def __init__(self, values):
            self.values = list(values)

        def uniform(self, lo, hi):
            return self.values.pop(0)

    bank = evaluate.load_models(str(model))
    occ = np.zeros((N,) * 3, np.float32)
    occ[0, 0, N // 2] = 1
    rng = Scripted([np.deg2rad(355.0), 0.3, 30.0, np.deg2rad(175.0), 0.3, 30.0])
    s, recs, _ = evaluate.evaluate_bank(bank, np.stack([occ.ravel()] * 2), np.array([0, 0]),
                                        bank.classes, rng, progress=False)
    part = [r for r in recs if r['mode'] == 'partial']
    assert [r['empty_view'] for r in part] == [True, True]
    assert all(np.isnan(r['yaw_err_deg']) and np.isnan(r['yaw_err_sym_deg']) for r in part)
    p = s['partial']
    assert p['empty_views'] == 2
    assert p['yaw_within_10'] == p['yaw_within_10_or_flip'] == 0
    assert p['yaw_within_10_up_to_symmetry'] == p['per_class']['box']['yaw_within_10'] == 0
    assert p['yaw_median_deg'] == 180.0


def test_eval_latency_leaves_out_the_banks_one_off_warm_up(model, monkeypatch):
    # the first estimate of a bank pays one-off costs (rotation maps, lazy imports): it was
    # timed as the first object's latency (183 ms against 45). A fake clock: the bank's first
    # estimate takes 100 s, every estimate 0.01 s
    clock = [0.0]
    monkeypatch.setattr(evaluate, 'time', types.SimpleNamespace(perf_counter=lambda: clock[0]))
    bank = evaluate.load_models(str(model))

    class FirstCallSlow:
        spec, classes = bank.spec, bank.classes

        def __init__(self):
            self.calls = 0

        def estimate(self, grid, **kw):
            clock[0] += (100.0 if not self.calls else 0.0) + 0.01
            self.calls += 1
            return bank.estimate(grid, **kw)

    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    s, recs, _ = evaluate.evaluate_bank(FirstCallSlow(), X, y, names, np.random.default_rng(3),
                                        views=2, progress=False)
    assert [r['latency'] for r in recs] == pytest.approx([0.01] * len(recs))
    assert s['complete']['latency_p95_ms'] == pytest.approx(10.0)
    # the warm-up draws nothing from the protocol's RNG: the same views as before
    rng = np.random.default_rng(3)
    yaws = [np.rad2deg(evaluate.random_partial_view(x.reshape((N,) * 3) > 0.5, rng)[1])
            for x in X for _ in range(2)]
    assert [r['yaw_deg'] for r in recs if r['mode'] == 'partial'] == pytest.approx(yaws)


def test_eval_cv_needs_two_classes_up_front(tmp_path, capsys, monkeypatch):
    X, y, names = primitive_shapes(N, 4, np.random.default_rng(0))
    data = save_npz(tmp_path / 'one.npz', X[y == 0], y[y == 0], names[:1])
    monkeypatch.setattr(evaluate, 'fit_bank', lambda *a, **k: pytest.fail('trained anyway'))
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--cv', '2', '--folds', '1', '--data', str(data),
                                '--verifier-views', '0', '--out', str(out)]) == 2
    assert "--cv needs objects of at least 2 classes" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize('args', [['--cv', '5'], ['--cv', '10', '--folds', '5']])
def test_eval_cv_refuses_folds_that_hold_no_object(tmp_path, capsys, monkeypatch, args):
    # before: with 4 objects per class, --cv 5 trained a bank for fold 4 (every object in its
    # training set) and evaluated nothing with it; 'folds' listed it with 'test': 0
    data = write_npz(tmp_path / 'd.npz', count=4)   # 4 boxes, 4 cylinders
    monkeypatch.setattr(evaluate, 'fit_bank', lambda *a, **k: pytest.fail('trained anyway'))
    out = tmp_path / 'e'
    assert call(evaluate.main, [*args, '--data', str(data), '--verifier-views', '0',
                                '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert 'has at most 4 objects of a class' in err and 'no object to evaluate' in err
    assert not out.exists()


@pytest.mark.parametrize('args, way_out', [(['--cv', '3'], True), (['--cv', '2'], False)])
def test_eval_cv_too_few_objects_per_class_names_the_way_out(tmp_path, capsys, monkeypatch,
                                                            args, way_out):
    # 3 objects per class: --cv 3 trains each fold's bank on 2 of a class, too few for the
    # out-of-fold classifier features (3 over 5 folds), which --train-views 0 leaves out;
    # --cv 2 trains on 1, too few for a class model, whatever --train-views. The message
    # named 'views 0', not beo-eval's option
    data = write_npz(tmp_path / 'd.npz', count=3)
    monkeypatch.setattr(evaluate, 'fit_bank', lambda *a, **k: pytest.fail('trained anyway'))
    out = tmp_path / 'e'
    assert call(evaluate.main, [*args, '--data', str(data), '--verifier-views', '0',
                                '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'beo-eval: error: --cv {args[1]}: the bank of fold 0 ')
    assert ('--train-views 0' in err) == way_out
    assert ('a class model needs >= 2' in err) != way_out
    assert not out.exists()


def test_eval_cv_trains_without_objects_that_have_no_occupied_voxel(tmp_path, capsys):
    # fit_bank refuses them (beo-train drops them): --cv used to end with "grid has no
    # occupied voxel"; they are left out of the training folds and still evaluated
    X, y, names = primitive_shapes(N, 8, np.random.default_rng(0))
    X[[0, 1]] = 0
    data = save_npz(tmp_path / 'd.npz', X, y, names)
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--cv', '2', '--k', '2', '--data', str(data),
                                '--verifier-views', '0', '--out', str(out)]) == 0
    assert '2 objects with no occupied voxel left out' in capsys.readouterr().err
    recs = [json.loads(line) for line in (out / 'records.jsonl').read_text().splitlines()]
    empty = [r for r in recs if r['mode'] == 'complete' and r['empty_object']]
    assert sorted(r['i'] for r in empty) == [0, 1] and all(r['label'] == 'unknown'
                                                         for r in empty)
    folds = json.loads((out / 'eval.json').read_text())['folds']
    assert sum(f['train'] for f in folds) == len(X) - 2   # each object trains one fold of 2


def test_eval_ctrl_c_one_line_130_and_no_empty_out(model, tmp_path, capsys, monkeypatch):
    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(evaluate, 'evaluate_bank', interrupted)
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--model', str(model), '--data',
                                str(write_npz(tmp_path / 'd.npz')), '--out', str(out)]) == 130
    err = capsys.readouterr().err
    assert 'beo-eval: interrupted' in err and 'Traceback' not in err
    assert not out.exists()


def test_eval_held_out_json_sections_in_order(model, tmp_path, capsys):
    out = tmp_path / 'e'
    assert call(evaluate.main, ['--model', str(model), '--data',
                                str(write_npz(tmp_path / 'd.npz')), '--out', str(out)]) == 0
    res = json.loads((out / 'eval.json').read_text())
    assert list(res) == ['complete', 'partial', 'classes', 'protocol', 'class_prior', 'command']
    assert res['protocol'].startswith('held-out: model ')
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].split()[:3] == ['mode', 'n', 'acc'] and printed[-1].startswith('wrote ')



def test_eval_on_the_models_own_training_data_says_it_is_in_sample(tmp_path, capsys):
    """The shipped model on the shared train split (the only npz a new user has) printed its
    in-sample numbers as held-out ones (complete accuracy 1.0 on 10 objects) without a word:
    the manifest's data hash now names them in-sample; other data is still held-out."""
    from beo_ros.core.datasets import training_data_hash
    X, y, names = primitive_shapes(N, 15, np.random.default_rng(0))
    bank = make_tiny_bank(n=N, k=2)   # fitted on these objects
    bank.training['data_sha256'] = training_data_hash(X, y, names)
    bank.save(tmp_path / 'model')
    for data, own in ((save_npz(tmp_path / 'train.npz', X, y, names), True),
                      (write_npz(tmp_path / 'other.npz', seed=1), False)):
        out = tmp_path / data.stem
        assert call(evaluate.main, ['--model', str(tmp_path / 'model'), '--data', str(data),
                                    '--max-objects', '2', '--out', str(out)]) == 0
        err = capsys.readouterr().err
        assert ('in-sample, not held-out' in err) == own, err
        protocol = json.loads((out / 'eval.json').read_text())['protocol']
        assert protocol.startswith('in-sample: ' if own else 'held-out: '), protocol


# ---------------------------------------------------------------------- beo-eval --scans
@pytest.mark.parametrize('extra', [['--grid', '0'], ['--yaw-step', '0'], ['--max-iter', '0'],
                                   ['--yaw-step', 'nan'], ['--voxel-size', '-1'],
                                   ['--figures', '-1'], ['--k', '0'],
                                   # steps estimate refuses (it did so after the first fit)
                                   ['--yaw-step', '100'], ['--yaw-step', '0.01']])
def test_scans_bad_numbers_leave_no_out(tmp_path, capsys, extra):
    out = tmp_path / 'se'
    assert call(evaluate.main, ['--scans', str(tmp_path / 'learn1.pcd'), '--out', str(out),
                                *extra]) == 2
    assert f'argument {extra[0]}' in capsys.readouterr().err
    assert not out.exists()


def test_scans_odd_grid_refused_before_any_work(tmp_path, capsys):
    # the 2x2x2 pooling of the pose search failed with numpy's 'cannot reshape array' after
    # the scans had loaded
    out = tmp_path / 'se'
    assert call(evaluate.main, ['--scans', str(tmp_path / 'learn1.pcd'), '--out', str(out),
                                '--grid', '17']) == 2
    assert '--grid: the grid size must be an even integer' in capsys.readouterr().err
    assert not out.exists()


def test_scans_unreadable_scan_leaves_no_out(tmp_path, capsys):
    (tmp_path / 'learn1.pcd').write_text('not a point cloud\n')
    out = tmp_path / 'se'
    assert call(evaluate.main, ['--scans', str(tmp_path / 'learn1.pcd'), '--out', str(out)]) == 2
    assert 'beo-eval: error:' in capsys.readouterr().err
    assert not out.exists()


def test_scans_ctrl_c_one_line_130_and_no_empty_out(tmp_path, capsys, monkeypatch):
    import beo_ros.core.scan_training as st

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(st, 'load_scan_objects', lambda *a, **k: None)
    monkeypatch.setattr(scan_eval, '_run', interrupted)
    out = tmp_path / 'se'
    assert call(evaluate.main, ['--scans', 'learn1.pcd', '--out', str(out)]) == 130
    assert 'beo-eval: interrupted' in capsys.readouterr().err
    assert not out.exists()


def test_scans_default_out_is_the_same_for_beo_eval_and_python_m_scan_eval(tmp_path,
                                                                           monkeypatch):
    # before: beo-eval --scans X wrote beo_eval_out, python -m beo_ros.scan_eval --scans X
    # (prog 'beo-eval --scans', the help beo-eval points to) wrote beo_scan_eval
    monkeypatch.chdir(tmp_path)
    outs = []
    monkeypatch.setattr(scan_eval, 'run', lambda args: outs.append(args.out))
    assert call(evaluate.main, ['--scans', 'learn1.pcd']) == 0
    assert call(scan_eval.main, ['--scans', 'learn1.pcd']) == 0
    assert outs == ['beo_eval_out', 'beo_eval_out']


# ---------------------------------------------------------------------- beo-bench
@pytest.mark.parametrize('case', ['data', 'classes', 'k', 'model'])
def test_bench_bad_input_leaves_no_out(tmp_path, capsys, case):
    data = str(write_npz(tmp_path / 'd.npz'))
    extra = {'data': ['--data', str(tmp_path / 'nope.npz')],
             'classes': ['--data', data, '--classes', 'box', 'sofaa'],
             'k': ['--data', data, '--k', '0'],
             'model': ['--data', data, '--model', str(tmp_path / 'no_model')]}[case]
    out = tmp_path / 'b'
    assert call(bench.main, QUICK + ['--out', str(out), *extra]) == 2
    assert 'beo-bench: error' in capsys.readouterr().err
    assert not out.exists()


def test_bench_failure_keeps_an_existing_out(tmp_path):
    (tmp_path / 'b').mkdir()
    assert call(bench.main, QUICK + ['--data', str(tmp_path / 'nope.npz'),
                                     '--out', str(tmp_path / 'b')]) == 2
    assert (tmp_path / 'b').is_dir()


@pytest.mark.parametrize('extra', [
    ['--icp-db-per-class', '0'], ['--paper-yaws', '0'], ['--test-frac', 'nan'],
    ['--test-frac', '0'], ['--test-frac', '-0.5'], ['--test-frac', '1'],
    ['--queries-per-class', '0'], ['--node-duration', '0'], ['--node-duration', 'nan'],
    ['--node-max-drop', 'nan'], ['--node-max-drop', '2'], ['--node-workers', '-3'],
    ['--node-workers', '65'], ['--node-worker-processes', '-2'], ['--node-objects', '0'],
    ['--node-rounds', '0'], ['--repeats', '0'], ['--seed', '-1'], ['--k', '0'],
    ['--scaling-yaw-steps', '0'], ['--scaling-grids', '0'], ['--node-blas-threads', '-1'],
    # yaw steps estimate refuses (the scaling phase did, after the peers had run)
    ['--scaling-yaw-steps', '100'], ['--scaling-yaw-steps', '1', '0.01'],
    # empty lists (ran with the defaults)
    ['--classes'], ['--scaling-train'], ['--scaling-grids'], ['--scaling-yaw-steps'],
    ['--scaling-classes'],
    # a class model needs 2 objects: the grid curve failed after the peers had run
    ['--scaling-per-class', '1'], ['--train-per-class', '1'],
])
def test_bench_numbers_checked_by_the_parser(tmp_path, capsys, extra):
    with pytest.raises(SystemExit) as ei:
        bench.parse_args(['--out', str(tmp_path / 'b'), *extra])
    assert ei.value.code == 2
    assert f'argument {extra[0]}' in capsys.readouterr().err
    assert not (tmp_path / 'b').exists()


@pytest.mark.parametrize('extra, named', [
    (['--no-node', '--node-rates', '5'], '--node-rates'),
    (['--no-scaling', '--scaling-grids', '16'], '--scaling-grids'),
    (['--no-paper', '--paper-yaws', '12'], '--paper-yaws'),
    (['--no-icp', '--icp-db-per-class', '3'], '--icp-db-per-class'),
    (['--model', 'm', '--beo-verifier-views', '2'], '--beo-verifier-views'),
    # given at the default value: the check compared values with defaults and let them pass
    (['--no-paper', '--paper-yaws', '36'], '--paper-yaws'),
    (['--no-icp', '--icp-db-per-class', '10'], '--icp-db-per-class'),
    (['--no-node', '--node-worker-processes', '2'], '--node-worker-processes'),
    (['--no-scaling', '--scaling-classes', '2', '5', '10'], '--scaling-classes'),
    (['--model', 'm', '--beo-verifier-views', '6'], '--beo-verifier-views'),
])
def test_bench_options_of_a_phase_not_run_refused(tmp_path, capsys, extra, named):
    # they were silently ignored (README: options the mode does not use are refused)
    with pytest.raises(SystemExit) as ei:
        bench.parse_args(['--out', str(tmp_path / 'b'), *extra])
    assert ei.value.code == 2
    err = capsys.readouterr().err
    assert f'not used in this run ({extra[0]}): {named}' in err


@pytest.mark.parametrize('extra, named', [
    (['--no-icp', '--no-scaling', '--icp-init-yaws', '2'], '(--no-icp, --no-scaling): '
                                                          '--icp-init-yaws'),
    (['--no-paper', '--no-icp', '--slow-repeats', '3'], '(--no-paper, --no-icp): --slow-repeats'),
    (['--model', 'm', '--no-paper', '--no-scaling', '--k', '5'],
     '(--model, --no-paper, --no-scaling): --k'),
    (['--no-paper', '--no-icp', '--slow-repeats', '1'], '(--no-paper, --no-icp): --slow-repeats'),
    # nothing is trained on the split (before: accepted, and only setup.train_objects changed)
    (['--model', 'm', '--no-paper', '--no-icp', '--no-scaling', '--train-per-class', '5'],
     '(--model, --no-paper, --no-icp, --no-scaling): --train-per-class'),
])
def test_bench_options_of_several_phases_none_run_refused(tmp_path, capsys, extra, named):
    # before: silently ignored (--no-icp --no-scaling --icp-init-yaws 2 ran the whole bench)
    with pytest.raises(SystemExit) as ei:
        bench.parse_args(['--out', str(tmp_path / 'b'), *extra])
    assert ei.value.code == 2
    assert f'not used in this run {named}' in capsys.readouterr().err


def test_bench_options_of_several_phases_used_by_one_still_accepted(tmp_path):
    for extra, key, value in (
            (['--no-icp', '--icp-init-yaws', '2'], 'icp_init_yaws', 2),
            (['--no-scaling', '--icp-init-yaws', '2'], 'icp_init_yaws', 2),
            (['--no-paper', '--slow-repeats', '3'], 'slow_repeats', 3),
            (['--model', 'm', '--k', '5'], 'k', 5),
            (['--model', 'm', '--no-paper', '--k', '5'], 'k', 5),
            (['--model', 'm', '--no-paper', '--no-icp', '--train-per-class', '5'],
             'train_per_class', 5),
            (['--no-paper', '--no-icp', '--no-scaling', '--train-per-class', '5'],
             'train_per_class', 5)):
        args = bench.parse_args(['--out', str(tmp_path / 'b'), *extra])
        assert getattr(args, key) == value, (extra, vars(args))   # taken, not reset


def test_bench_odd_scaling_grid_refused_by_the_parser(tmp_path, capsys):
    # the scaling phase failed at that size with numpy's 'cannot reshape array', after the
    # peers had run
    with pytest.raises(SystemExit) as ei:
        bench.parse_args(['--out', str(tmp_path / 'b'), '--scaling-grids', '16', '17'])
    assert ei.value.code == 2
    assert '--scaling-grids: the grid size must be an even integer' in capsys.readouterr().err


def test_bench_failing_node_phase_exit_1_with_results(tmp_path, capsys, monkeypatch):
    def broken(*a, **k):
        raise RuntimeError('workers out of range')
    monkeypatch.setattr(bench, 'node_bench', broken)
    out = tmp_path / 'b'
    args = [a for a in QUICK if a != '--no-node']
    assert call(bench.main, args + ['--data', str(write_npz(tmp_path / 'd.npz')),
                                    '--out', str(out)]) == 1
    assert 'node benchmark failed' in capsys.readouterr().err
    res = json.loads((out / 'bench.json').read_text())
    assert res['node']['skipped'].startswith('failed: RuntimeError') and 'beo' in res


def test_bench_json_sections_in_order_and_skipped_phases_named(tmp_path, capsys):
    out = tmp_path / 'b'
    assert call(bench.main, QUICK + ['--data', str(write_npz(tmp_path / 'd.npz')),
                                     '--out', str(out)]) == 0
    res = json.loads((out / 'bench.json').read_text())
    assert list(res) == ['setup', 'beo', 'paper', 'icp', 'scaling', 'node']
    assert list(res['setup'])[-3:] == ['load_average_1min', 'beo_model', 'wall_s']
    assert res['paper'] == {'skipped': '--no-paper'} and res['icp'] == {'skipped': '--no-icp'}
    assert res['scaling'] == {'skipped': '--no-scaling'} and res['node'] == {'skipped': '--no-node'}
    lines = capsys.readouterr().out.splitlines()
    assert lines[:2] == bench.table(res).splitlines()[:2] and lines[2].startswith('| beo | ')
    assert lines[3:] == ['| paper | not run (--no-paper) | | | | | | |',
                         '| icp | not run (--no-icp) | | | | | | |',
                         'speedup vs icp (p50): n/a (not run (--no-icp)), '
                         'vs paper: n/a (not run (--no-paper))',
                         'node: skipped (--no-node)', f'wrote {out / "bench.json"}']


@pytest.mark.parametrize('off, ran', [('--no-icp', 'paper'), ('--no-paper', 'icp')])
def test_bench_one_peer_off_keeps_the_others_results(tmp_path, capsys, off, ran):
    # bench.md, the summary and the PNGs held the peers only when all three ran: --no-icp
    # measured beo and paper and reported neither
    pytest.importorskip('open3d')
    out = tmp_path / 'b'
    argv = [a for a in QUICK if a not in (f'--no-{ran}', '--no-plots')]
    assert call(bench.main, argv + ['--data', str(write_npz(tmp_path / 'd.npz')),
                                    '--out', str(out)]) == 0
    res = json.loads((out / 'bench.json').read_text())
    gone = off[len('--no-'):]
    assert res[gone] == {'skipped': off} and res[ran]['queries'] == res['beo']['queries']
    assert f'speedup_vs_{gone}' not in res and res[f'speedup_vs_{ran}'] > 0
    speedup = {p: (f"{res[f'speedup_vs_{p}']:.1f}x" if p == ran else f'n/a (not run ({off}))')
               for p in ('icp', 'paper')}
    row = f"| {ran} | {res[ran]['accuracy']:.3f} | "
    stdout = capsys.readouterr().out
    md = (out / 'bench.md').read_text()
    for text in (stdout, md):
        assert f'| {gone} | not run ({off}) |' in text and row in text and '| beo | ' in text
    assert (f"speedup vs icp (p50): {speedup['icp']}, vs paper: {speedup['paper']}"
            in stdout)
    assert f"- speedup vs icp (p50) {speedup['icp']}\n- vs paper {speedup['paper']}\n" in md
    assert f'{ran} index ' in md and f'{gone} index' not in md
    for png in ('latency.png', 'accuracy.png'):
        assert (out / png).stat().st_size > 1000
    # --no-scaling: no scaling.png (it was eight empty panels)
    assert not (out / 'scaling.png').exists()


def test_bench_without_the_scaling_phase_leaves_no_scaling_png(tmp_path, capsys):
    # an earlier run's scaling.png in the same --out would pass for this run's
    out = tmp_path / 'b'
    out.mkdir()
    (out / 'scaling.png').write_bytes(b'an earlier run')
    argv = [a for a in QUICK if a != '--no-plots']
    assert call(bench.main, argv + ['--data', str(write_npz(tmp_path / 'd.npz')),
                                    '--out', str(out)]) == 0
    assert (out / 'latency.png').is_file() and not (out / 'scaling.png').exists()
    assert f'removed {out / "scaling.png"} of an earlier run' in capsys.readouterr().err


def test_bench_quick_with_a_model_keeps_the_models_classes(tmp_path, capsys):
    # --quick picked two of the file's classes, which a --model of more classes never has:
    # 'beo-bench --quick --model models/modelnet10_32' ended in '--model classes ... differ'
    X, y, names = primitive_shapes(N, 6, np.random.default_rng(0))
    names = [*names, 'tube']
    y = np.where((y == 1) & (np.cumsum(y == 1) % 2 == 0), 2, y)   # half the cylinders: tubes
    data = save_npz(tmp_path / 'd.npz', X, y, names)
    bench.fit_class_bank(X, y, names, N, 2).save(tmp_path / 'm')
    out = tmp_path / 'b'
    assert call(bench.main, QUICK + ['--data', str(data), '--model', str(tmp_path / 'm'),
                                     '--out', str(out)]) == 0, capsys.readouterr().err
    assert json.loads((out / 'bench.json').read_text())['setup']['classes'] == names


def test_bench_ctrl_c_one_line_130_and_no_empty_out(tmp_path, capsys, monkeypatch):
    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(bench, 'make_queries', interrupted)
    out = tmp_path / 'b'
    assert call(bench.main, QUICK + ['--data', str(write_npz(tmp_path / 'd.npz')),
                                     '--out', str(out)]) == 130
    err = capsys.readouterr().err
    assert 'beo-bench: interrupted' in err and 'Traceback' not in err
    assert not out.exists()


# ---------------------------------------------------------------------- beo-demo
@pytest.mark.parametrize('extra', [['--seed', '-1'], ['--views-per-class', '0'],
                                   ['--timeout', 'inf']])
def test_demo_numbers_checked_by_the_parser(tmp_path, capsys, extra):
    from beo_ros.ros import demo
    with pytest.raises(SystemExit) as ei:
        demo.main(['--out', str(tmp_path / 'd'), *extra])
    assert ei.value.code == 2
    assert f'argument {extra[0]}' in capsys.readouterr().err
    assert not (tmp_path / 'd').exists()


def test_demo_ctrl_c_one_line_130_and_no_empty_out(model, tmp_path, capsys, monkeypatch):
    from beo_ros.ros import demo

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(demo, 'render_inputs', interrupted)
    out = tmp_path / 'd'
    assert call(demo.main, ['--model', str(model), '--out', str(out)]) == 130
    err = capsys.readouterr().err
    assert 'beo-demo: interrupted' in err and 'Traceback' not in err
    assert not out.exists()


def test_demo_keep_bag_replaces_the_previous_bag(model, tmp_path, monkeypatch):
    pytest.importorskip('rosbags')
    from beo_ros.ros import demo
    # no node: every input goes without an estimate (exit 1), the bag is kept all the same
    monkeypatch.setattr(demo, 'run_node_on_bag', lambda *a, **k: (
        {}, {}, types.SimpleNamespace(to_dict=dict), {}))
    out = tmp_path / 'd'
    for storage, suffix in (('mcap', '.mcap'), ('sqlite3', '.db3')):
        assert call(demo.main, ['--model', str(model), '--out', str(out), '--keep-bag',
                                '--storage', storage]) == 1
        bags = sorted(p.suffix for p in (out / 'demo_bag').iterdir() if p.suffix != '.yaml')
        assert bags == [suffix], bags


def test_demo_results_name_the_kept_bag(model, tmp_path, monkeypatch):
    # results.json did not say whether a bag was kept, nor which file (.mcap or .db3)
    pytest.importorskip('rosbags')
    from beo_ros.ros import demo
    monkeypatch.setattr(demo, 'run_node_on_bag', lambda *a, **k: (
        {}, {}, types.SimpleNamespace(to_dict=dict), {}))
    out = tmp_path / 'd'
    for keep, storage, bag in (([], 'mcap', None),
                               (['--keep-bag'], 'sqlite3', out / 'demo_bag' / 'demo_bag.db3')):
        assert call(demo.main, ['--model', str(model), '--out', str(out), *keep,
                                '--storage', storage]) == 1
        res = json.loads((out / 'results.json').read_text())
        assert res['bag'] == (None if bag is None else str(bag))
    assert (out / 'demo_bag' / 'demo_bag.db3').is_file()


SHIPPED = Path(__file__).resolve().parents[1] / 'models'


@pytest.mark.parametrize('seed', [0, 1])
def test_demo_inputs_of_the_tabletop_model_get_their_class(seed):
    # tabletop_32's demo box was labelled a cylinder (p 0.8-0.98 for every seed): the voxel
    # render had no box-like surface normals for its 'points' classifier, and from most
    # azimuths its mean (views from the front only) was no view the model was taught
    from beo_ros.core.bank import ModelBank
    from beo_ros.ros import demo
    bank = ModelBank.load(SHIPPED / 'tabletop_32')
    inputs = demo.render_inputs(bank, seed=seed, size=bank.spec.size * bank.spec.voxel_size)
    labels = [bank.estimate_points(i['points'], (0, 0, 0), (0, 0, 1)).label for i in inputs]
    assert labels == [i['true_class'] for i in inputs] == ['box', 'cylinder']


def test_demo_sees_partial_view_models_from_their_training_side():
    from beo_ros.core.bank import ModelBank
    from beo_ros.ros import demo
    # the scans' grids have x from the camera toward the object: the camera at -x, azimuth pi
    sides = demo.seen_from(ModelBank.load(SHIPPED / 'tabletop_32'))
    assert set(sides) == {'box', 'cylinder'}
    for az in sides.values():
        assert abs(az - np.pi) <= np.deg2rad(15)
    # complete shapes: no side, so the default model's demo renders as before
    bank = ModelBank.load(SHIPPED / 'modelnet10_32')
    assert set(demo.seen_from(bank).values()) == {None}


def test_figure_takes_class_names_with_dollar_signs(tmp_path):
    # class names are file names: '$' is legal, but matplotlib read '$...$' in the titles and
    # tick labels as mathtext ('p$$q' or 'a$_$': a ParseException from savefig, after
    # eval.json and records.jsonl were written) and rendered 'a$x$' as math
    names = ['p$$q', 'a$_$']
    g = np.zeros((8, 8, 8), np.int8)
    g[3:5, 3:5, 3:5] = 1
    summary = {'classes': names, 'partial': {'confusion': [[1, 0, 0], [0, 1, 0]]}}
    evaluate.write_figure(summary, [(names[0], names[1], g, g.astype(np.float32), g == 1, 3.0)],
                          tmp_path / 'eval.png')
    assert (tmp_path / 'eval.png').stat().st_size > 0
    comp = np.zeros((8, 8, 8), np.float32)
    comp[3:5, 3:5, 3:5] = 0.9
    scan_eval.plot_completions(tmp_path / 'scan.png', [('p$$q s0/1 -> a$_$',
                                                         np.argwhere(g == 1), comp)],
                               types.SimpleNamespace(size=8))
    assert (tmp_path / 'scan.png').stat().st_size > 0


@pytest.mark.parametrize('existing', [False, True])
def test_eval_interrupted_while_writing_leaves_no_partial_result(model, tmp_path, monkeypatch,
                                                                existing):
    # Ctrl-C or SIGTERM while eval.png was drawn left eval.json and records.jsonl in --out
    # (a result set without its figure; in an existing --out, beside an older eval.png)
    data = write_npz(tmp_path / 'd.npz', count=2)
    out = tmp_path / 'e'
    if existing:
        out.mkdir()
        (out / 'notes.txt').write_text('mine')

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(evaluate, 'write_figure', interrupted)
    assert call(evaluate.main, ['--model', str(model), '--data', str(data),
                                '--out', str(out)]) == cli.INTERRUPTED
    assert (sorted(p.name for p in out.iterdir()) == ['notes.txt'] if existing
            else not out.exists())
