"""beo-train and beo-eval command lines on a small generated voxel npz."""
import json

import numpy as np
import pytest

from beo_ros import evaluate, train
from beo_ros.core.bank import ModelBank
from beo_ros.core.synthetic import primitive_shapes
from beo_ros.core.training import load_voxel_npz

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
    png = (out / 'eval.png').read_bytes()
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 1000
    assert 'wrote' in capsys.readouterr().out


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
