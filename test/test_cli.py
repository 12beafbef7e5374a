"""beo-train and beo-eval command lines on a small generated voxel npz."""
import argparse
import json
import os

import numpy as np
import pytest

from beo_ros import evaluate, train
from beo_ros.core.bank import ModelBank
from beo_ros.core.grid import symmetric_turns
from beo_ros.core.synthetic import primitive_shapes
from beo_ros.core.training import load_voxel_npz
from _shapes import box_off

N = 16


def write_npz(path, count=8, seed=0):
    """Generated boxes and cylinders in the shared format (bit-packed rows)."""
    X, y, names = primitive_shapes(N, count, np.random.default_rng(seed))
    np.savez(path, voxels=np.packbits(X.astype(np.uint8), axis=1), labels=y,
             classes=np.array(names), shape=np.array([N, N, N]))
    return X, y, names


def test_npz_format_round_trip(tmp_path):
    X, y, names = write_npz(tmp_path / 'd.npz', count=3)
    X2, y2, names2, n = load_voxel_npz(tmp_path / 'd.npz')
    assert n == N and names2 == names
    np.testing.assert_array_equal(X2, X)
    np.testing.assert_array_equal(y2, y)


@pytest.fixture(scope='module')
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('cli')
    write_npz(tmp / 'train.npz', count=8, seed=0)
    write_npz(tmp / 'test.npz', count=4, seed=1)
    rc = train.main([str(tmp / 'train.npz'), '-o', str(tmp / 'model'), '--k', '3',
                     '--folds', '2', '--views', '1', '--pose-components', '3',
                     '--verifier-views', '0'])
    return tmp, rc


def test_train_writes_a_loadable_model(trained):
    tmp, rc = trained
    assert rc == 0
    bank = ModelBank.load(tmp / 'model')
    assert bank.classes == ['box', 'cylinder'] and bank.spec.size == N
    assert set(bank.classifier) == {'complete', 'partial'}
    assert bank.training['n_objects'] == 16 and bank.training['k'] == 3
    cv = bank.training['cross_validation']
    assert set(cv) == {'complete', 'partial'}
    assert all(0 <= cv[m]['accuracy'] <= 1 for m in cv)


def test_train_classifier_kind_is_passed_on(tmp_path):
    write_npz(tmp_path / 'd.npz', count=8)
    assert train.main([str(tmp_path / 'd.npz'), '-o', str(tmp_path / 'm'), '--k', '3',
                       '--folds', '2', '--pose-components', '3', '--verifier-views', '0',
                       '--classifier', 'logistic']) == 0
    bank = ModelBank.load(tmp_path / 'm')
    assert {r['kind'] for r in bank.training['cross_validation'].values()} == {'logistic'}
    assert not any('hidden_coef' in c for c in bank.classifier.values())


def test_eval_writes_json_and_png(trained, capsys):
    tmp, _ = trained
    out = tmp / 'eval'
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp / 'test.npz'),
                        '--max-objects', '6', '--out', str(out)])
    assert rc == 0
    s = json.loads((out / 'eval.json').read_text())
    assert s['classes'] == ['box', 'cylinder']
    for mode in ('complete', 'partial'):
        assert s[mode]['n'] == 6
        assert 0 <= s[mode]['accuracy'] <= 1
        cm = np.array(s[mode]['confusion'])
        assert cm.sum() == 6
        rows = cm.sum(axis=1) > 0  # balanced accuracy: mean recall over the classes present
        assert s[mode]['balanced_accuracy'] == pytest.approx(
            np.mean(np.diag(cm)[rows] / cm.sum(axis=1)[rows]))
    assert 0 <= s['partial']['iou'] <= 1
    assert 0 <= s['partial']['yaw_within_10'] <= 1
    # one record per complete object and per view, indexed into --data; the yaw error up to
    # the object's own quarter turns (cylinders: all three; boxes: at least the half turn)
    recs = [json.loads(line) for line in (out / 'records.jsonl').read_text().splitlines()]
    part = [r for r in recs if r['mode'] == 'partial']
    assert len(recs) == 12 and len(part) == 6
    X, y, names, n = load_voxel_npz(tmp / 'test.npz')
    for r in part:
        assert names[y[r['i']]] == r['truth']
        occ = X[r['i']].reshape((n,) * 3) > 0.5
        turns = [round(np.rad2deg(t)) for t in symmetric_turns(occ)]
        assert r['self_turns_deg'] == turns
        assert (turns == [90, 180, 270]) if r['truth'] == 'cylinder' else (180 in turns)
        err = [abs((r['est_yaw_deg'] - r['yaw_deg'] - t + 180) % 360 - 180) for t in [0] + turns]
        assert r['yaw_err_deg'] == pytest.approx(err[0])
        assert r['yaw_err_sym_deg'] == pytest.approx(min(err))
    assert s['partial']['yaw_within_10_up_to_symmetry'] == pytest.approx(
        np.mean([r['yaw_err_sym_deg'] <= 10 for r in part]))
    assert s['partial']['yaw_within_10_up_to_symmetry'] >= s['partial']['yaw_within_10']
    png = (out / 'eval.png').read_bytes()
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 1000
    out = capsys.readouterr().out
    assert 'wrote' in out and 'yaw<=10' in out   # the table goes to the current stdout


def test_corrupt_npz_exit_code_2(tmp_path, capsys):
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'this is not a zip file' * 10)
    assert train.main([str(bad), '-o', str(tmp_path / 'm')]) == 2
    assert 'beo-train: error' in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()
    assert evaluate.main(['--model', str(tmp_path / 'm'), '--data', str(bad), '--out',
                          str(tmp_path / 'o')]) == 2
    assert 'beo-eval: error' in capsys.readouterr().err


def _truncated_npz(tmp_path):
    write_npz(tmp_path / 'ok.npz', count=2)
    data = (tmp_path / 'ok.npz').read_bytes()
    (tmp_path / 'trunc.npz').write_bytes(data[:len(data) // 2])
    return tmp_path / 'trunc.npz'


def test_truncated_npz_exit_code_2(tmp_path, capsys):
    bad = _truncated_npz(tmp_path)
    assert train.main([str(bad), '-o', str(tmp_path / 'm')]) == 2
    assert 'trunc.npz' in capsys.readouterr().err


def test_not_an_npz_error_names_the_file(tmp_path, capsys):
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'this is not a zip file' * 10)
    assert train.main([str(bad), '-o', str(tmp_path / 'm')]) == 2
    assert 'bad.npz' in capsys.readouterr().err


def test_npz_missing_key_exit_code_2(tmp_path, capsys):
    np.savez(tmp_path / 'nokeys.npz', voxels=np.zeros((2, 512), np.uint8))
    assert train.main([str(tmp_path / 'nokeys.npz'), '-o', str(tmp_path / 'm')]) == 2
    err = capsys.readouterr().err
    assert 'nokeys.npz' in err and 'labels' in err


def test_eval_missing_model_exit_code_2(trained, tmp_path, capsys):
    tmp, _ = trained
    rc = evaluate.main(['--model', str(tmp_path / 'none'), '--data', str(tmp / 'test.npz'),
                        '--out', str(tmp_path / 'o')])
    assert rc == 2
    assert 'none' in capsys.readouterr().err


@pytest.mark.parametrize('main', [train.main, evaluate.main])
def test_help_exits_0(main, capsys):
    with pytest.raises(SystemExit) as ei:
        main(['--help'])
    assert ei.value.code == 0
    assert 'usage' in capsys.readouterr().out


def test_train_help_gives_the_defaults_it_trains_with(capsys):
    """--k, --views, --folds and --seed said nothing of their defaults (20, 1, 5, 0), so a
    user picking a small --k could not tell what the others did."""
    with pytest.raises(SystemExit):
        train.main(['--help'])
    entries = capsys.readouterr().out.split('\n  --')   # one per option
    ap = train._parser()
    for option, default in (('k K', 20), ('views VIEWS', 1), ('folds FOLDS', 5),
                            ('seed SEED', 0)):
        assert ap.get_default(option.split()[0]) == default
        (entry,) = [' '.join(e.split()) for e in entries if e.startswith(option + ' ')]
        assert entry.endswith(f'default: {default})') or entry.endswith(f'default: {default}'), \
            entry


@pytest.mark.parametrize('extra', [[], ['--scans'], ['--scans', '--views', '1']])
def test_train_mirror_needs_scans_without_classifier(tmp_path, capsys, extra):
    # mirror pairs split over out-of-fold folds would leak into the classifier features
    write_npz(tmp_path / 'd.npz', count=2)
    with pytest.raises(SystemExit) as ei:
        train.main([str(tmp_path / 'd.npz'), '-o', str(tmp_path / 'm'), '--mirror'] + extra)
    assert ei.value.code == 2
    assert '--mirror' in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


def test_class_prior_flags(trained, tmp_path, capsys):
    tmp, _ = trained
    assert ModelBank.load(tmp / 'model').class_prior == 'train'
    # beo-eval: the model's own prior unless told; a weight of 0 rules a class out
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp / 'test.npz'),
                        '--max-objects', '4', '--out', str(tmp_path / 'e'),
                        '--class-prior', 'box=0,cylinder=1'])
    assert rc == 0
    s = json.loads((tmp_path / 'e' / 'eval.json').read_text())
    assert s['class_prior'] == {'box': 0.0, 'cylinder': 1.0}
    assert all(row[0] == 0 for mode in ('complete', 'partial') for row in s[mode]['confusion'])
    # a class the model does not have: exit 2 naming it; malformed text: a usage error
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp / 'test.npz'),
                        '--out', str(tmp_path / 'e2'), '--class-prior', 'box=1,cup=1'])
    assert rc == 2 and "unknown ['cup']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        evaluate.main(['--data', 'x.npz', '--class-prior', 'box=one'])
    assert "weight of 'box' is not a number" in capsys.readouterr().err
    # beo-train records the prior in the manifest and picks the classifier under it
    rc = train.main([str(tmp / 'train.npz'), '-o', str(tmp_path / 'm'), '--k', '3',
                     '--folds', '2', '--views', '1', '--pose-components', '3',
                     '--class-prior', 'uniform', '--verifier-views', '1', '--jobs', '2'])
    assert rc == 0
    bank = ModelBank.load(tmp_path / 'm')
    assert bank.class_prior == 'uniform'
    assert bank.verifier is not None and bank.training['verifier_views'] == 1
    assert ModelBank.load(tmp / 'model').verifier is None
    cv = bank.training['cross_validation']['partial']
    assert cv['class_prior'] == 'uniform' and cv['prior_accuracy'] == cv['balanced_accuracy']


# ---------------------------------------------------------------------- bad input: voxel npz
def _save(path, X, y, names, shape=(N, N, N), packed=True):
    vox = np.packbits(X.astype(np.uint8), axis=1) if packed else X
    keys = dict(voxels=vox, labels=y, classes=np.array(names))
    if shape is not None:
        keys['shape'] = np.array(shape)
    np.savez(path, **keys)
    return path


def test_npz_unpacked_forms_load_like_packed(tmp_path):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    ref = load_voxel_npz(_save(tmp_path / 'p.npz', X, y, names))
    for name, vox, shape in (('u2.npz', X.astype(np.uint8), None),
                             ('u4.npz', X.reshape(-1, N, N, N) > 0.5, None),
                             ('u4s.npz', X.reshape(-1, N, N, N).astype(np.float32), (N, N, N))):
        X2, y2, names2, n = load_voxel_npz(_save(tmp_path / name, vox, y, names, shape, False))
        np.testing.assert_array_equal(X2, ref[0])
        np.testing.assert_array_equal(y2, ref[1])
        assert names2 == ref[2] and n == N



@pytest.mark.parametrize('shape', [(0, N ** 3), (0, N, N, N)])
def test_npz_of_no_objects_loads_empty(tmp_path, capsys, shape):
    # unpacked voxels of no objects failed with numpy's 'cannot reshape array of size 0 into
    # shape (0,newaxis)' (no file named), not beo-eval's 'no objects to evaluate'
    p = _save(tmp_path / 'none.npz', np.zeros(shape, np.uint8), np.zeros(0, int), ['a', 'b'],
              shape=None, packed=False)
    X, y, names, n = load_voxel_npz(p)
    assert X.shape == (0, N ** 3) and y.shape == (0,) and names == ['a', 'b'] and n == N
    assert evaluate.main(['--cv', '2', '--data', str(p), '--out', str(tmp_path / 'o')]) == 2
    assert 'none.npz: no objects to evaluate' in capsys.readouterr().err


def test_npz_bytes_class_names_load_as_str(tmp_path):
    # np.array([b'box', ...]) (an 'S' array, e.g. from h5py or Python 2 tools) used to give
    # the class names "b'box'", which then named the model's files and its answers
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    ref = load_voxel_npz(_save(tmp_path / 'str.npz', X, y, names))
    got = load_voxel_npz(_save(tmp_path / 'bytes.npz', X, y, [c.encode() for c in names]))
    assert got[2] == ref[2] == names
    np.testing.assert_array_equal(got[1], ref[1])
    p = _save(tmp_path / 'nested.npz', X, y, [[c] for c in names])
    with pytest.raises(ValueError, match="nested.npz: 'classes' must be a 1-D array"):
        load_voxel_npz(p)

def test_npz_repeated_class_name_refused(tmp_path, capsys):
    # a second 'box' at index 2: selecting 'box' kept only the objects of index 0, and the
    # objects labelled 2 were dropped without a word
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    y[0] = 2
    p = _save(tmp_path / 'twice.npz', X, y, names + ['box'])
    for classes in (None, ['box', 'cylinder']):
        with pytest.raises(ValueError, match=r"twice.npz: 'classes' names \['box'\] more than"):
            load_voxel_npz(p, classes)
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--classes', 'box', 'cylinder']) == 2
    assert "names ['box'] more than once" in capsys.readouterr().err


@pytest.mark.parametrize('bad, message', [
    (-1, 'labels must be in [0, 2)'),   # would silently become the last class
    (2, 'labels must be in [0, 2)'),    # == len(classes): an IndexError later
    (0.5, 'labels must be integers'),   # would be truncated to 0
])
def test_npz_label_out_of_range_refused(tmp_path, capsys, bad, message):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    y = y.astype(float if isinstance(bad, float) else int)
    y[0] = bad
    p = _save(tmp_path / 'badlabel.npz', X, y, names)
    with pytest.raises(ValueError, match='badlabel.npz') as ei:
        load_voxel_npz(p)
    assert message in str(ei.value)
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--verifier-views', '0']) == 2
    err = capsys.readouterr().err
    assert 'beo-train: error' in err and message in err
    assert not (tmp_path / 'm').exists()
    assert evaluate.main(['--model', str(tmp_path / 'm'), '--data', str(p),
                          '--out', str(tmp_path / 'o')]) == 2
    assert message in capsys.readouterr().err


def test_npz_label_count_must_match_objects(tmp_path, capsys):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    p = _save(tmp_path / 'short.npz', X, y[:2], names)
    with pytest.raises(ValueError, match='short.npz: 2 labels for 4 objects'):
        load_voxel_npz(p, ['cylinder'])
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--classes', 'box']) == 2
    assert '2 labels for 4 objects' in capsys.readouterr().err


def test_npz_packed_without_shape_refused(tmp_path, capsys):
    # 16^3 bits packed into 512 bytes per row: without 'shape', not a grid of byte values
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    p = _save(tmp_path / 'noshape.npz', X, y, names, shape=None)
    with pytest.raises(ValueError, match="noshape.npz: .*'shape' key"):
        load_voxel_npz(p)
    # 32^3 packed into 4096 bytes, whose count is itself a cube (16^3): the audit's case
    X32 = np.zeros((2, 32 ** 3), np.uint8)
    X32[:, ::3] = 1
    p = _save(tmp_path / 'noshape32.npz', X32, np.array([0, 1]), ['a', 'b'], shape=None)
    with pytest.raises(ValueError, match="voxel values must be 0 or 1.*'shape' key"):
        load_voxel_npz(p)
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--views', '0',
                       '--verifier-views', '0']) == 2
    assert "'shape' key" in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


@pytest.mark.parametrize('shape', [(8, 8, 8), (32, 32, 32), (16, 16), (8, 8, 64), (16.5, 16, 16)])
def test_npz_inconsistent_shape_key_refused(tmp_path, shape):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    p = _save(tmp_path / 'shape.npz', X, y, names, shape=shape)
    with pytest.raises(ValueError, match="shape.npz: .*'shape' key"):
        load_voxel_npz(p)


def test_npz_voxel_values_outside_0_1_refused(tmp_path):
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(0))
    X = X.astype(np.float32)
    X[1, 5] = 2
    p = _save(tmp_path / 'vals.npz', X.reshape(-1, N, N, N), y, names, shape=None, packed=False)
    with pytest.raises(ValueError, match='vals.npz: voxel values must be 0 or 1, found 2.0'):
        load_voxel_npz(p)


# ---------------------------------------------------------------------- bad input: arguments
@pytest.mark.parametrize('extra, message', [
    (['--pose-components', '0'], '--pose-components must be >= 1'),
    (['--pose-components', '-3'], '--pose-components must be >= 1'),
    (['--folds', '1'], '--folds must be >= 2'),
    (['--folds', '0'], '--folds must be >= 2'),
    (['--views', '-1'], '--views must be >= 0'),
])
def test_train_bad_arguments_refused(tmp_path, capsys, extra, message):
    write_npz(tmp_path / 'd.npz', count=2)
    with pytest.raises(SystemExit) as ei:
        train.main([str(tmp_path / 'd.npz'), '-o', str(tmp_path / 'm'), '--k', '2',
                    '--verifier-views', '0'] + extra)
    assert ei.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


@pytest.mark.parametrize('extra, message', [
    (['--views', '0', '--oof-out', 'oof.npz'], '--oof-out needs --views >= 1'),
    (['--scans', '--mirror', '--views', '0', '--seed', '3'], 'not used with --mirror: --seed'),
    (['--scans', '--mirror', '--views', '0', '--folds', '3', '--descriptors', 'on',
      '--row-standardize', 'off'],
     'not used with --mirror: --folds, --row-standardize, --descriptors'),
    (['--scans', '--mirror', '--views', '0', '--classifier', 'mlp'],
     'not used with --mirror: --classifier'),
])
def test_train_options_that_do_not_apply_refused(tmp_path, capsys, extra, message):
    write_npz(tmp_path / 'd.npz', count=2)
    with pytest.raises(SystemExit) as ei:
        train.main([str(tmp_path / 'd.npz'), '-o', str(tmp_path / 'm'),
                    '--verifier-views', '0'] + extra)
    assert ei.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


def test_train_mirror_passes_the_class_prior_on(trained, tmp_path, monkeypatch, capsys):
    from beo_ros.core import scan_training
    tmp, _ = trained
    calls = []

    def fake_train_scan_bank(*args, **kwargs):   # the trained box/cylinder bank stands in
        calls.append(args)
        bank = ModelBank.load(tmp / 'model')
        bank.training['n_training_grids'] = 32
        return bank
    monkeypatch.setattr(scan_training, 'train_scan_bank', fake_train_scan_bank)
    argv = ['learn0.pcd', '--scans', '--mirror', '--views', '0', '--k', '2']
    assert train.main([*argv, '-o', str(tmp_path / 'm'), '--class-prior', 'uniform']) == 0
    assert ModelBank.load(tmp_path / 'm').class_prior == 'uniform'
    assert train.main([*argv, '-o', str(tmp_path / 'm2'), '--class-prior', 'box=1,cup=1']) == 2
    assert "unknown ['cup']" in capsys.readouterr().err
    assert not (tmp_path / 'm2').exists() and len(calls) == 1   # refused before the fit


@pytest.mark.parametrize('count, extra, message', [
    # 2 boxes: 5 folds would leave a fold's training part 1 box
    (2, [], "class 'box' has 2 training objects; out-of-fold classifier features over 5 "
            'folds need >= 3 per class'),
    (3, ['--folds', '2'], 'need >= 4 per class (each fold trains class models on the other '
                          "folds' objects); use 3 or more folds"),
    # the way out named: 1 toilet among the shared meshes stopped beo-train without one
    (1, ['--views', '0'], "class 'box' has 1 training objects; a class model needs >= 2: add "
                          'objects of it, or leave the class out (--classes with the others)'),
    (1, [], "class 'box' has 1 training objects; a class model needs >= 2: add objects of it, "
            'or leave the class out (--classes with the others)'),
    (4, ['--classes', 'box', 'box', 'cylinder'], "classes ['box'] given more than once"),
])
def test_train_too_few_objects_explained(tmp_path, capsys, count, extra, message):
    write_npz(tmp_path / 'd.npz', count=count)
    rc = train.main([str(tmp_path / 'd.npz'), '-o', str(tmp_path / 'm'), '--k', '2',
                     '--verifier-views', '0'] + extra)
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


@pytest.mark.parametrize('extra, message', [
    (['--cv', '-2'], '--cv must be 0 (held-out mode) or a number of folds >= 2'),
    (['--cv', '1'], '--cv must be 0 (held-out mode) or a number of folds >= 2'),
    (['--cv', '2', '--folds', '3'], '--folds must be in [0, --cv]'),
    (['--cv', '2', '--folds', '-1'], '--folds must be in [0, --cv]'),
    (['--max-objects', '-2'], 'argument --max-objects: must be in [0, inf)'),
    (['--views', '-1'], 'argument --views: must be in [0, inf)'),
    (['--cv', '2', '--train-views', '-1'], 'argument --train-views: must be in [0, inf)'),
])
def test_eval_bad_arguments_refused(tmp_path, capsys, extra, message):
    write_npz(tmp_path / 'd.npz', count=2)
    with pytest.raises(SystemExit) as ei:
        evaluate.main(['--data', str(tmp_path / 'd.npz'), '--out', str(tmp_path / 'o'),
                       '--k', '2', '--verifier-views', '0'] + extra)
    assert ei.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'o').exists()


def test_eval_out_is_a_file_refused(tmp_path, capsys):
    write_npz(tmp_path / 'd.npz', count=2)
    (tmp_path / 'a_file').write_text('x')
    for out, message in ((tmp_path / 'a_file', 'exists and is not a directory'),
                         (tmp_path / 'a_file' / 'sub', 'cannot make the output directory')):
        with pytest.raises(SystemExit) as ei:
            evaluate.main(['--data', str(tmp_path / 'd.npz'), '--out', str(out)])
        assert ei.value.code == 2
        err = capsys.readouterr().err
        assert 'beo-eval: error: --out' in err and message in err


def test_eval_compares_the_classes_present(trained, tmp_path, capsys):
    """A file whose class list names more classes than its objects have (a subset of a
    larger set) is evaluated; objects of a class the model lacks are refused."""
    tmp, _ = trained
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(3))
    assert names == ['box', 'cylinder']
    more = ['box', 'cup', 'cylinder']
    y3 = np.where(y == 1, 2, 0)
    _save(tmp_path / 'subset.npz', X, y3, more)
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp_path / 'subset.npz'),
                        '--views', '0', '--out', str(tmp_path / 'e')])
    assert rc == 0
    s = json.loads((tmp_path / 'e' / 'eval.json').read_text())
    assert s['classes'] == ['box', 'cylinder'] and s['complete']['n'] == 4
    assert np.array(s['complete']['confusion']).sum(axis=1).tolist() == [2, 2]
    capsys.readouterr()
    y3[0] = 1  # one object of 'cup'
    _save(tmp_path / 'cup.npz', X, y3, more)
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp_path / 'cup.npz'),
                        '--views', '0', '--out', str(tmp_path / 'e2')])
    assert rc == 2
    assert "data classes ['cup']" in capsys.readouterr().err


def test_stratified_subset():
    rng = np.random.default_rng(0)
    y = np.array([0] * 12 + [1] * 12)
    idx = np.arange(24)
    for m, want in ((4, [2, 2]), (5, [3, 2]), (1, None), (24, [12, 12]), (30, [12, 12])):
        got = evaluate.stratified_subset(idx, y, m, rng)
        assert len(got) == min(m, 24) and (np.diff(got) > 0).all()
        if want is not None:
            assert sorted(np.bincount(y[got], minlength=2).tolist(), reverse=True) == want
    y = np.array([0] * 10 + [1] * 2 + [2])   # proportional, but every class once
    got = evaluate.stratified_subset(np.arange(13), y, 4, rng)
    assert np.bincount(y[got]).tolist() == [2, 1, 1]
    # a subset of the objects (a fold): indices into y
    te = np.array([1, 3, 13, 15, 20])
    got = evaluate.stratified_subset(te, np.array([0] * 12 + [1] * 12), 2, rng)
    assert set(got) <= set(te) and len(got) == 2 and (got[0] < 12) != (got[1] < 12)


def test_eval_max_objects_is_stratified(trained, tmp_path):
    tmp, _ = trained   # test.npz: 4 boxes, 4 cylinders (a uniform draw of seed 0: 3 + 1)
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp / 'test.npz'),
                        '--max-objects', '4', '--views', '0', '--out', str(tmp_path / 'e'),
                        '--seed', '0'])
    assert rc == 0
    s = json.loads((tmp_path / 'e' / 'eval.json').read_text())
    assert np.array(s['complete']['confusion']).sum(axis=1).tolist() == [2, 2]


def test_eval_grid_size_must_match_the_model(trained, tmp_path, capsys):
    tmp, _ = trained
    X, y, names = primitive_shapes(8, 2, np.random.default_rng(0))
    _save(tmp_path / 'd8.npz', X, y, names, shape=(8, 8, 8))
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp_path / 'd8.npz'),
                        '--out', str(tmp_path / 'e')])
    assert rc == 2
    err = capsys.readouterr().err
    assert 'objects on a 8^3 grid' in err and 'is for 16^3' in err and 'reshape' not in err
    assert not (tmp_path / 'e').exists()   # no empty --out left behind


def _strict_json(text):
    def refuse(c):
        raise AssertionError(f'not strict JSON: {c}')
    return json.loads(text, parse_constant=refuse)


def test_eval_json_is_strict_json(trained, tmp_path):
    """No partial view classified right: the yaw over the right ones is null, not NaN."""
    tmp, _ = trained
    X, y, names = primitive_shapes(N, 2, np.random.default_rng(5))
    _save(tmp_path / 'boxes.npz', X[y == 0], y[y == 0], names)
    rc = evaluate.main(['--model', str(tmp / 'model'), '--data', str(tmp_path / 'boxes.npz'),
                        '--out', str(tmp_path / 'e'), '--class-prior', 'box=0,cylinder=1'])
    assert rc == 0
    s = _strict_json((tmp_path / 'e' / 'eval.json').read_text())
    assert s['partial']['accuracy'] == 0 and s['partial']['yaw_within_10_correct_class'] is None
    for line in (tmp_path / 'e' / 'records.jsonl').read_text().splitlines():
        _strict_json(line)


def test_eval_cv_leaves_out_classes_without_objects(tmp_path, capsys):
    X, y, names = primitive_shapes(N, 4, np.random.default_rng(2))
    _save(tmp_path / 'gap.npz', X, np.where(y == 1, 2, 0), ['box', 'cup', 'cylinder'])
    rc = evaluate.main(['--cv', '2', '--data', str(tmp_path / 'gap.npz'), '--k', '2',
                        '--train-views', '0', '--verifier-views', '0', '--views', '0',
                        '--out', str(tmp_path / 'e')])
    assert rc == 0, capsys.readouterr().err
    assert "left out: ['cup']" in capsys.readouterr().err
    s = json.loads((tmp_path / 'e' / 'eval.json').read_text())
    assert s['classes'] == ['box', 'cylinder'] and s['complete']['n'] == 8


def test_train_on_meshes_of_several_classes(tmp_path, capsys):
    # every mesh used to be loaded on its own: the class list came from the first file and
    # the meshes of any other class got label -1 (beo-train failed)
    paths = []
    for i in range(3):
        for name, size in (('cube', (1, 1, 1 + 0.1 * i)), ('slab', (1 + 0.1 * i, 1, 0.2))):
            paths.append(tmp_path / f'{name}_{i:04d}.off')
            box_off(paths[-1], *size)
    rc = train.main([*map(str, paths), '-o', str(tmp_path / 'm'), '--grid', '16', '--k', '2',
                     '--views', '0', '--verifier-views', '0'])
    assert rc == 0, capsys.readouterr().err
    bank = ModelBank.load(tmp_path / 'm')
    assert bank.classes == ['cube', 'slab']
    slab = np.zeros((16,) * 3, dtype=np.int8)
    slab[2:14, 2:14, 6:9] = 1
    assert bank.estimate(slab).label == 'slab'


def test_eval_scans_forwards_k_and_refuses_what_it_does_not_use(monkeypatch, capsys):
    from beo_ros import scan_eval
    seen = []
    monkeypatch.setattr(scan_eval, 'main', lambda argv: seen.append(argv) or 0)
    assert evaluate.main(['--scans', 'a.pcd', '--out', 'o', '--k', '4', '--max-iter', '30']) == 0
    assert seen[-1] == ['--scans', 'a.pcd', '--out', 'o', '--k', '4', '--max-iter', '30']
    assert evaluate.main(['--scans', 'a.pcd', '--out', 'o']) == 0
    assert '--k' not in seen[-1]          # scan_eval's own default applies
    for extra in (['--seed', '3'], ['--views', '2'], ['--cv', '5']):
        with pytest.raises(SystemExit):
            evaluate.main(['--scans', 'a.pcd', *extra])
        assert 'not used with --scans: ' + extra[0] in capsys.readouterr().err
    # at the default value (--seed 0 was accepted without a word): named, and the run goes on
    for extra in (['--seed', '0'], ['--cv', '0']):
        assert evaluate.main(['--scans', 'a.pcd', '--out', 'o', *extra]) == 0
        assert seen[-1] == ['--scans', 'a.pcd', '--out', 'o']
        assert (f'beo-eval: warning: not used with --scans: {extra[0]} (given at the default '
                'value: ignored)') in capsys.readouterr().err


# ---------------------------------------------------------------------- beo-demo: arguments
@pytest.mark.parametrize('extra, message', [
    (['--views-per-class', '0'], 'argument --views-per-class: must be in [1, inf)'),
    (['--views-per-class', '-2'], 'argument --views-per-class: must be in [1, inf)'),
    (['--timeout', '-5'], 'argument --timeout: must be in (0, inf)'),
    (['--timeout', 'nan'], 'argument --timeout: must be a finite number'),
    (['--out', 'A_FILE'], 'exists and is not a directory'),
    # a link to nothing passed the check and failed with 'File exists' after the model loaded
    (['--out', 'A_LINK'], 'a_link is a broken symbolic link, to '),
    (['--out', 'A_LINK/sub'], 'a_link is a broken symbolic link, to '),
])
def test_demo_bad_arguments_refused_up_front(tmp_path, capsys, extra, message):
    from beo_ros.ros import demo
    (tmp_path / 'a_file').write_text('x')
    (tmp_path / 'a_link').symlink_to(tmp_path / 'nothing')
    extra = [str(tmp_path / 'a_file') if a == 'A_FILE' else
             a.replace('A_LINK', str(tmp_path / 'a_link')) for a in extra]
    argv = extra if '--out' in extra else ['--out', str(tmp_path / 'o'), *extra]
    with pytest.raises(SystemExit) as ei:
        demo.main(argv)
    assert ei.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'o').exists()


def test_fit_bank_refuses_oof_path_without_classifier(tmp_path):
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_bank
    X, y, names = primitive_shapes(N, 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match='oof_path needs classifier_views >= 1'):
        fit_bank(X, y, names, GridSpec(size=N), k=2, classifier_views=0,
                 oof_path=tmp_path / 'oof.npz')
    with pytest.raises(ValueError, match='class names must be unique'):
        fit_bank(X, y, ['box', 'box'], GridSpec(size=N), k=2, classifier_views=0)


def test_fit_bank_refuses_a_seed_that_is_no_integer_at_once(monkeypatch):
    # None was a TypeError ('object of type 'NoneType' has no len()') after the class models
    # and the classifier were fitted, -1 numpy's 'expected non-negative integer'
    from beo_ros.core import training
    from beo_ros.core.grid import GridSpec
    X, y, names = primitive_shapes(N, 3, np.random.default_rng(0))

    def no_fit(*a, **k):
        raise AssertionError('fitted before checking the seed')
    monkeypatch.setattr(training, 'fit_class_models', no_fit)
    for bad in (None, -1, 1.5, True):
        with pytest.raises(ValueError, match=f'seed must be an integer >= 0, got {bad!r}'):
            training.fit_bank(X, y, names, GridSpec(size=N), k=2, seed=bad)



def _fit_bank_refuses_before_fitting(monkeypatch, message, **kw):
    """fit_bank(**kw) on 3 primitive shapes per class raises ValueError matching ``message``
    before any class model is fitted."""
    from beo_ros.core import training
    from beo_ros.core.grid import GridSpec
    X, y, names = primitive_shapes(N, 3, np.random.default_rng(0))

    def no_fit(*a, **k):
        raise AssertionError('fitted before checking the options')
    monkeypatch.setattr(training, 'fit_class_models', no_fit)
    with pytest.raises(ValueError, match=message):
        training.fit_bank(X, y, names, GridSpec(size=N), k=2, verifier_views=0, **kw)

@pytest.mark.parametrize('kw, message', [
    (dict(classifier_views=1, folds=1), 'the out-of-fold classifier features need folds >= 2'),
    (dict(classifier_views=1, folds=0), 'the out-of-fold classifier features need folds >= 2'),
    (dict(classifier_views=1, folds=2.5), 'need folds >= 2, got 2.5'),
    (dict(classifier_views=1.5), 'classifier_views must be an integer >= 0, got 1.5'),
    (dict(classifier_views=-1), 'classifier_views must be an integer >= 0, got -1'),
])
def test_fit_bank_refuses_classifier_views_and_folds_it_cannot_use(monkeypatch, kw, message):
    # folds 1 was "class 'box' has 0 training objects", folds 0 a bank without the
    # classifier asked for (no word), 2.5 and 1.5 TypeErrors after the class models were
    # fitted, -1 no classifier
    _fit_bank_refuses_before_fitting(monkeypatch, message, calibration_views=0, **kw)


@pytest.mark.parametrize('kw, message', [
    (dict(pose_components=0), 'pose_components must be an integer >= 1, got 0'),
    (dict(training=['k', 2]), 'training settings must be a mapping'),
])
def test_fit_bank_refuses_bank_settings_before_the_fits(monkeypatch, kw, message):
    # the bank's ModelError (or dict()'s error of a list) came after the class models were
    # fitted (minutes on ModelNet)
    _fit_bank_refuses_before_fitting(monkeypatch, message, classifier_views=0, **kw)


def test_progress_in_a_file_or_pipe_is_whole_lines(capsys, monkeypatch):
    # before: tqdm's bars went to a log as they do to a terminal: carriage returns, cursor-up
    # escapes and a redrawn bar per step, several per line
    from beo_ros.core import training
    assert list(training.progress_bar(range(3), 'views')) == [0, 1, 2]
    err = capsys.readouterr().err
    assert '\r' not in err and '\x1b' not in err
    assert err.startswith('views: 3/3 in ') and err.count('\n') == 1
    monkeypatch.setattr(training, 'PROGRESS_LINE_S', 0.0)   # a line per step
    assert list(training.progress_bar(iter('ab'), 'fold 0', total=2)) == ['a', 'b']
    assert capsys.readouterr().err.splitlines()[:2] == ['fold 0: 1/2', 'fold 0: 2/2']
    assert list(training.progress_bar(range(2), 'x', disable=True)) == [0, 1]
    assert capsys.readouterr().err == ''


def test_eval_progress_in_a_log_is_lines(tmp_path, capsys):
    """beo-eval with stderr in a file: lines, not bars (beo-train's come from the same
    progress_bar)."""
    from beo_ros.core.synthetic import make_tiny_bank
    make_tiny_bank(tmp_path / 'm', n=N, k=2)
    write_npz(tmp_path / 'd.npz', count=2)
    assert evaluate.main(['--model', str(tmp_path / 'm'), '--data', str(tmp_path / 'd.npz'),
                          '--out', str(tmp_path / 'e')]) == 0
    err = capsys.readouterr().err
    assert '\r' not in err and '\x1b' not in err and 'evaluating: 4/4 in ' in err


class _GonePipe:
    """A stdout whose reader has gone: every write and flush raises BrokenPipeError."""
    def write(self, text):
        raise BrokenPipeError(32, 'Broken pipe')

    flush = write


@pytest.mark.parametrize('module, main', [
    ('beo_ros.evaluate', 'main'), ('beo_ros.train', 'main'), ('beo_ros.scan_eval', 'main'),
    ('beo_ros.bench', 'main'), ('beo_ros.ros.demo', 'main'), ('beo_ros.ros.bag', 'record_main'),
    ('beo_ros.ros.bag', 'replay_main'), ('beo_ros.ros.bag', 'pcd2bag_main'),
    ('beo_ros.ros.bag', 'recover_main'), ('beo_ros.ros.node', 'main')])
def test_help_into_a_closed_pipe_ends_quietly_with_141(module, main, monkeypatch):
    # argparse drops the error of its help's write: into a closed pipe, -h exited 0 or, the
    # help still buffered, with "Exception ignored ... BrokenPipeError" (120); beo-node's
    # print ended in a traceback
    import importlib
    import sys
    monkeypatch.setattr(sys, 'stdout', _GonePipe())
    assert getattr(importlib.import_module(module), main)(['-h']) == 141


@pytest.mark.parametrize('unbuffered', [False, True])
def test_help_into_a_closed_pipe_subprocess(unbuffered):
    """beo-node -h | head -0 and beo-eval -h | head -0, with stdout buffered or not."""
    import subprocess
    import sys
    from pathlib import Path
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    env.pop('PYTHONUNBUFFERED', None)
    if unbuffered:
        env['PYTHONUNBUFFERED'] = '1'
    for module in ('beo_ros.ros.node', 'beo_ros.evaluate'):
        r, w = os.pipe()
        os.close(r)
        p = subprocess.run([sys.executable, '-m', module, '-h'], stdout=w, env=env,
                           stderr=subprocess.PIPE, text=True, timeout=120)
        os.close(w)
        assert (p.returncode, p.stderr) == (141, ''), module


def test_stdout_reader_gone_ends_quietly_with_141_and_keeps_the_results(tmp_path):
    """stdout a pipe whose reader has exited (beo-eval ... | head -1). Before: beo-eval said
    'error: [Errno 32] Broken pipe' (exit 2) and removed the --out it had made, its results
    unwritten (the table was printed first); beo-train and beo-pcd2bag ended in a traceback
    (exit 1); beo-record and beo-replay said 'cannot write BAG' / 'cannot read BAG'."""
    import subprocess
    import sys
    from pathlib import Path
    from beo_ros.core.synthetic import make_tiny_bank
    make_tiny_bank(tmp_path / 'm', n=N, k=2)
    write_npz(tmp_path / 'd.npz', count=2)
    repo = Path(__file__).resolve().parents[1]
    for module, args, out in (
            ('beo_ros.evaluate', ['--model', 'm', '--data', 'd.npz', '--out', 'e'], 'e'),
            ('beo_ros.train', ['d.npz', '-o', 'm2', '--k', '2', '--views', '0',
                               '--verifier-views', '0'], 'm2')):
        r, w = os.pipe()
        os.close(r)   # the reader is gone before the first line
        p = subprocess.run([sys.executable, '-m', module, *args], stdout=w, cwd=tmp_path,
                           stderr=subprocess.PIPE, text=True, timeout=300,
                           env=dict(os.environ, PYTHONPATH=str(repo)))
        os.close(w)
        assert p.returncode == 141, p.stderr
        assert 'Traceback' not in p.stderr and 'error' not in p.stderr, p.stderr
        assert sorted(f.name for f in (tmp_path / out).iterdir()), module
    assert sorted(f.name for f in (tmp_path / 'e').iterdir()) == ['eval.json', 'eval.png',
                                                                  'records.jsonl']


def test_given_options_tells_a_default_value_given_from_none():
    from beo_ros.cli import given_options, number
    ap = argparse.ArgumentParser()
    ap.add_argument('--yaws', type=int, default=36)
    ap.add_argument('--rates', type=number(0), nargs='+', default=[1.0])
    ap.add_argument('--off', action='store_true')
    ap.add_argument('--name', default='x')
    assert given_options(ap, []) == set()
    assert given_options(ap, ['--yaws', '36', '--off', '--name=x', 'rest']) == {
        'yaws', 'off', 'name'}
    assert ap.parse_args([]).yaws == 36   # the parser's defaults are left as they were

