"""Smoke tests of the measurement scripts in scripts/ (they are not part of the package)."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from beo_ros.core.synthetic import make_tiny_bank, primitive_shapes

ROOT = Path(__file__).resolve().parents[1]


def load_script(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / 'scripts' / f'{name}.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def shapes_npz(path, count, seed):
    """A voxel npz (shared format, 16^3) of ``count`` generated shapes per class at ``path``."""
    X, y, classes = primitive_shapes(n=16, count=count, rng=np.random.default_rng(seed))
    np.savez(path, voxels=np.packbits(X > 0, axis=1), labels=y, classes=np.array(classes),
             shape=np.array([16, 16, 16]))
    return path


@pytest.fixture(scope='module')
def tiny(tmp_path_factory):
    """A tiny bank (16^3, box / cylinder) and a voxel npz of generated shapes."""
    root = tmp_path_factory.mktemp('latency')
    bank = root / 'bank'
    make_tiny_bank(bank)
    return bank, shapes_npz(root / 'shapes.npz', 3, 1)


@pytest.mark.parametrize('extra', [[], ['--between', 'render'], ['--points']])
def test_latency_script_prints_percentiles_and_stages(tiny, capsys, extra):
    bank, data = tiny
    latency = load_script('latency')
    assert latency.main([str(data), '--model', str(bank), '--views', '4', '--every', '1']
                        + extra) == 0
    out = capsys.readouterr().out
    what = 'estimate_points' if '--points' in extra else 'estimate'
    assert out.startswith(f'{what}: 4 calls (4 views')
    for stage in ('pose_and_features', 'pose_refinement', 'completion', 'total'):
        assert f'  {stage} ' in out
    assert ('voxelize' in out) == ('--points' in extra)


def test_latency_script_refuses_bad_counts(tiny):
    bank, data = tiny
    with pytest.raises(SystemExit) as exc:
        load_script('latency').main([str(data), '--model', str(bank), '--views', '0'])
    assert exc.value.code == 2


def run_one_fold_script(name, tmp_path, seed, capsys):
    """Run scripts/<name>.py on 12 + 12 generated shapes, fold 0 of 2, k = 2 -> (its printed
    output, its --json output)."""
    import json
    data = shapes_npz(tmp_path / 'shapes.npz', 12, seed)
    out_json = tmp_path / 'out.json'
    assert load_script(name).main([str(data), '--folds', '2', '--k', '2',
                                   '--json', str(out_json)]) == 0
    return capsys.readouterr().out, json.loads(out_json.read_text())


def test_symmetric_flag_script_scores_both_flags(capsys, tmp_path):
    out, rows = run_one_fold_script('symmetric_flag', tmp_path, 2, capsys)
    assert 'completion@0.9' in out and 'model@0.9' in out
    assert len(rows) == 12   # half of the 24 objects
    # generated boxes and cylinders are symmetric: every truth set has the half turn
    assert all(180 in r['truth'] for r in rows)
    assert all(r['symmetric_yaws_turns'] == r['completion@0.9'] for r in rows)
    # the class model's own prediction of a box or a cylinder has the half turn too
    assert sum(180 in r['model@0.9'] for r in rows) >= len(rows) // 2, rows


def test_uncertainty_script_scores_both_uncertainties(capsys, tmp_path):
    out, result = run_one_fold_script('uncertainty', tmp_path, 3, capsys)
    assert 'occupancy_variance' in out and '\nvariance ' in out
    assert result['views'] == 12 and result['voxels'] > 0
    for kind in ('variance', 'occupancy_variance'):
        s = result['scores'][kind]
        assert 0 <= s['error'] <= 1 and -1 <= s['change'] <= 1, s


def test_uncertainty_scores_rank_the_wrong_voxels():
    """The AUROCs are of the uncertainty for the wrong voxels (and the false ones shown)."""
    scores = load_script('uncertainty').scores
    p = np.array([0.9, 0.8, 0.6, 0.4, 0.2, 0.1])
    truth = np.array([True, True, False, True, False, False])   # 0.6 and 0.4 are wrong
    s = scores(p, truth, {'right': p * (1 - p), 'inverted': -p * (1 - p)}, p)
    assert s['right']['error'] == 1.0 and s['inverted']['error'] == 0.0
    assert s['right']['false_in_cloud'] == 1.0   # 0.6 is the false one among p >= 0.5
    assert np.isnan(s['right']['change'])   # p2 == p: no change to rank


def test_one_fold_arguments_split_like_beo_eval_and_refuse_bad_folds(tmp_path):
    from beo_ros.core.training import stratified_folds
    from beo_ros.evaluate import held_out_fold, one_fold_parser
    data = shapes_npz(tmp_path / 'shapes.npz', 10, 4)
    ap = one_fold_parser('test', 'json')
    args, X, y, names, n, tr, te = held_out_fold(ap, [str(data), '--fold', '1', '--folds', '2'])
    fold = stratified_folds(y, 2, np.random.default_rng(0))   # beo-eval --cv 2 --seed 0
    assert list(tr) == list(np.flatnonzero(fold == 0)) and list(te) == list(np.flatnonzero(fold == 1))
    assert n == 16 and len(X) == 20 and args.k == 20 and args.seed == 7
    _, _, _, _, _, _, every = held_out_fold(ap, [str(data), '--fold', '1', '--folds', '2',
                                                 '--every', '3'])
    assert list(every) == list(te[::3])
    for bad in (['--fold', '2', '--folds', '2'], ['--folds', '1'], ['--every', '0']):
        with pytest.raises(SystemExit) as exc:
            held_out_fold(ap, [str(data)] + bad)
        assert exc.value.code == 2
