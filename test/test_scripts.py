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


@pytest.fixture(scope='module')
def tiny(tmp_path_factory):
    """A tiny bank (16^3, box / cylinder) and a voxel npz of generated shapes."""
    root = tmp_path_factory.mktemp('latency')
    bank = root / 'bank'
    make_tiny_bank(bank)
    X, y, classes = primitive_shapes(n=16, count=3, rng=np.random.default_rng(1))
    data = root / 'shapes.npz'
    np.savez(data, voxels=np.packbits(X > 0, axis=1), labels=y, classes=np.array(classes),
             shape=np.array([16, 16, 16]))
    return bank, data


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
