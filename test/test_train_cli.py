"""beo-train robustness: atomic model directories, class names, options that do not apply."""
import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from beo_ros import bench, evaluate, train
from beo_ros.core import bank as bank_module
from beo_ros.core.bank import ModelBank, ModelError
from beo_ros.core.synthetic import primitive_shapes
from beo_ros.core.training import load_voxel_npz
from _shapes import box_off

N = 16
FAST = ['--k', '2', '--views', '0', '--verifier-views', '0']


def write_npz(path, count=4, seed=0, names=None, empty=()):
    """Generated boxes and cylinders (bit-packed), optionally renamed; ``empty``: indices of
    objects whose voxels are cleared."""
    X, y, default = primitive_shapes(N, count, np.random.default_rng(seed))
    X = X.astype(np.uint8)
    X[list(empty)] = 0
    np.savez(path, voxels=np.packbits(X, axis=1), labels=y,
             classes=np.array(names or default), shape=np.array([N, N, N]))
    return path


def snapshot(path):
    """{file name: bytes} of a directory."""
    return {p.name: p.read_bytes() for p in sorted(path.iterdir())}


@pytest.fixture
def model(tmp_path):
    """A trained model directory m in tmp_path and its files."""
    assert train.main([str(write_npz(tmp_path / 'd.npz')), '-o', str(tmp_path / 'm')]
                      + FAST) == 0
    return tmp_path / 'm', snapshot(tmp_path / 'm')


def main_no_escape(argv):
    """train.main(argv), failing the test (not ending the session) when Ctrl-C escapes it."""
    try:
        return train.main(argv)
    except KeyboardInterrupt:
        pytest.fail('KeyboardInterrupt escaped beo-train')


def leftovers(tmp_path):
    return [p.name for p in tmp_path.iterdir() if p.name.startswith('.')]


# ---------------------------------------------------------------------- 1, 2: class names
@pytest.mark.parametrize('name, message', [
    ('ta/ble', "cannot contain '/'"),   # used to fail in save, half-way over the old model
    ('ta\\ble', "cannot contain '/'"),
    ('', 'non-empty'),                  # used to write a model its own loader refused
    ('..', "cannot be '.' or '..'"),
    (' table', 'whitespace'),
    ('t' * 250, 'at most 200 bytes'),   # trained, then save failed: 'File name too long'
    ('ta\ud800', 'file system can encode'),   # trained, then save raised UnicodeEncodeError
    # the label of no class: beo-eval counted an object seen as nothing as one of this class
    ('unknown', "cannot be 'unknown'"),
])
def test_bad_class_names_refused_before_training(model, tmp_path, capsys, name, message):
    path, before = model
    capsys.readouterr()
    p = write_npz(tmp_path / 'bad.npz', names=['chair', name])
    assert train.main([str(p), '-o', str(path)] + FAST) == 2
    err = capsys.readouterr().err
    assert 'beo-train: error: ' in err and message in err and 'bad.npz' in err
    assert snapshot(path) == before
    assert ModelBank.load(path).classes == ['box', 'cylinder']
    # --classes leaves the bad name out: fine
    assert train.main([str(p), '-o', str(tmp_path / 'ok'), '--classes', 'chair'] + FAST) == 0


def test_loader_applies_the_same_class_name_rule(model):
    path, _ = model
    bank = ModelBank.load(path)
    bank.models[0].name = ' box'
    with pytest.raises(ModelError, match='whitespace'):
        bank.save(path.parent / 'new')
    assert not (path.parent / 'new').exists()
    # a manifest edited by hand to a name train refuses is refused on load as well
    mf = json.loads((path / 'manifest.json').read_text())
    mf['classes'][0] = ' box'
    (path / 'class_00_box.npz').rename(path / 'class_00_ box.npz')
    mf['files']['class_00_ box.npz'] = mf['files'].pop('class_00_box.npz')
    (path / 'manifest.json').write_text(json.dumps(mf))
    with pytest.raises(ModelError, match='whitespace'):
        ModelBank.load(path)


# ---------------------------------------------------------------------- 1, 11: atomic save
def test_a_failed_save_keeps_the_old_model(model, tmp_path, monkeypatch):
    path, before = model
    X, y, names = primitive_shapes(N, 5, np.random.default_rng(7))
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_bank
    new = fit_bank(X, y, names, GridSpec(size=N), k=2, pose_components=2, classifier_views=0)
    real, calls = np.savez_compressed, []

    def fail_second(*args, **kwargs):   # a full disk after the first class file
        calls.append(args[0])
        if len(calls) == 2:
            raise OSError(28, 'No space left on device')
        return real(*args, **kwargs)
    monkeypatch.setattr(np, 'savez_compressed', fail_second)
    with pytest.raises(OSError, match='No space'):
        new.save(path)
    assert snapshot(path) == before and leftovers(tmp_path) == []
    ModelBank.load(path)
    monkeypatch.setattr(np, 'savez_compressed', real)
    assert new.save(path) == path   # and a complete save replaces it
    assert ModelBank.load(path).training['n_objects'] == 10 and leftovers(tmp_path) == []


def test_ctrl_c_while_saving_exits_130_and_keeps_the_old_model(model, tmp_path, monkeypatch,
                                                               capsys):
    path, before = model
    capsys.readouterr()

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(np, 'savez_compressed', interrupt)
    p = write_npz(tmp_path / 'other.npz', seed=3)
    assert main_no_escape([str(p), '-o', str(path)] + FAST) == 130
    err = capsys.readouterr().err
    assert 'beo-train: interrupted' in err and 'Traceback' not in err
    assert snapshot(path) == before and leftovers(tmp_path) == []


def test_calibrate_only_failure_keeps_the_model(tmp_path, monkeypatch, capsys):
    p = write_npz(tmp_path / 'd.npz')
    m = tmp_path / 'm'
    assert train.main([str(p), '-o', str(m), '--k', '2', '--folds', '2',
                       '--verifier-views', '0', '--classifier', 'logistic',
                       '--descriptors', 'off', '--row-standardize', 'off']) == 0
    before = snapshot(m)

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(np, 'savez_compressed', interrupt)
    assert main_no_escape([str(p), '-o', str(m), '--calibrate-only']) == 130
    assert snapshot(m) == before and leftovers(tmp_path) == []
    monkeypatch.undo()
    # 8: other objects with the same classes and count are not its training set
    other = write_npz(tmp_path / 'other.npz', seed=5)
    assert train.main([str(other), '-o', str(m), '--calibrate-only']) == 2
    assert 'trained on other data' in capsys.readouterr().err
    assert snapshot(m) == before
    assert train.main([str(p), '-o', str(m), '--calibrate-only']) == 0
    assert ModelBank.load(m).occupancy_calibration is not None


# ---------------------------------------------------------------------- 3: the -o directory
def test_an_existing_model_is_replaced_as_a_whole(model, tmp_path, capsys):
    path, _ = model
    (path / 'classifier.npz').write_bytes(b'left over from an older model')
    (path / 'class_02_cup.npz').write_bytes(b'left over from an older model')
    capsys.readouterr()
    assert train.main([str(write_npz(tmp_path / 'o.npz', seed=2)), '-o', str(path)] + FAST) == 0
    assert 'replacing the model in' in capsys.readouterr().err
    mf = json.loads((path / 'manifest.json').read_text())
    assert sorted(p.name for p in path.iterdir()) == sorted(mf['files']) + ['manifest.json']
    assert ModelBank.load(path).classifier is None


def test_a_directory_that_is_not_a_model_is_never_replaced(tmp_path, capsys):
    p = write_npz(tmp_path / 'd.npz')
    (tmp_path / 'mine').mkdir()
    (tmp_path / 'mine' / 'notes.txt').write_text('keep me')
    assert train.main([str(p), '-o', str(tmp_path / 'mine')] + FAST) == 2
    err = capsys.readouterr().err
    assert 'holds no beo_ros model' in err and len(err.strip().splitlines()) == 1
    assert [f.name for f in (tmp_path / 'mine').iterdir()] == ['notes.txt']
    (tmp_path / 'afile').write_text('x')
    assert train.main([str(p), '-o', str(tmp_path / 'afile')] + FAST) == 2
    assert 'not a directory' in capsys.readouterr().err
    (tmp_path / 'empty').mkdir()
    assert train.main([str(p), '-o', str(tmp_path / 'empty')] + FAST) == 0
    ModelBank.load(tmp_path / 'empty')


# ---------------------------------------------------------------------- 4: empty objects
def test_objects_without_occupied_voxels_are_dropped_with_a_warning(tmp_path, capsys):
    X, y, names = primitive_shapes(N, 4, np.random.default_rng(0))
    empty = [int(np.flatnonzero(y == 0)[0]), int(np.flatnonzero(y == 1)[0])]
    p = write_npz(tmp_path / 'd.npz', empty=empty)
    assert train.main([str(p), '-o', str(tmp_path / 'm')] + FAST) == 0
    assert ('dropped 2 objects with no occupied voxel (box: 1, cylinder: 1)'
            in capsys.readouterr().err)
    assert ModelBank.load(tmp_path / 'm').training['n_objects'] == len(y) - 2
    p = write_npz(tmp_path / 'e.npz', empty=np.flatnonzero(y == 1))
    assert train.main([str(p), '-o', str(tmp_path / 'm2')] + FAST) == 2
    assert "classes ['cylinder'] have no object with an occupied voxel" in \
        capsys.readouterr().err
    assert not (tmp_path / 'm2').exists()


# ---------------------------------------------------------------------- 5, 6: options
@pytest.mark.parametrize('extra, message', [
    (['--grid', '0'], '--grid: must be in [4, 256]'),
    (['--grid', '-4'], '--grid: must be in [4, 256]'),
    (['--grid', '7'], 'even integer'),
    (['--grid', '12', '--verifier-views', '1'], 'multiple of 8, got 12; train without an '
                                                'orientation verifier (--verifier-views 0'),
    (['--max-iter', '0'], '--max-iter: must be in [1, inf)'),
    (['--max-iter', '5'], '--max-iter is for --scans --mirror only'),
    (['--voxel-size', '-5'], '--voxel-size: must be in (0, inf)'),
    (['--voxel-size', '0.1'], '--voxel-size is for --scans only'),
    (['--scan-classes', 'junk'], '--scan-classes is for --scans only'),
    (['--scans', '--classes', 'box'], '--classes is for npz and mesh input'),
    (['--k', '0'], '--k: must be in [1, inf)'),
    (['--seed', '-1'], '--seed: must be in [0, inf)'),
    # before: ignored (the views it makes are the verifier's, and there is none)
    (['--jobs', '2'], "--jobs makes the orientation verifier's views: not used with "
                      '--verifier-views 0'),
])
def test_options_that_do_not_apply_or_are_out_of_range_refused(tmp_path, capsys, extra,
                                                               message):
    p = write_npz(tmp_path / 'd.npz', count=2)
    with pytest.raises(SystemExit) as ei:
        train.main([str(p), '-o', str(tmp_path / 'm'), '--views', '0',
                    '--verifier-views', '0'] + extra)
    assert ei.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


@pytest.mark.parametrize('where', ['under_a_file', 'a_directory', 'in_the_model'])
def test_oof_out_checked_before_training(tmp_path, capsys, monkeypatch, where):
    # it is written after all the training (minutes on the shared data); in -o it made a new
    # model directory one the save refused (all the training lost), or was deleted with the
    # model it replaced
    from beo_ros.core import training
    p = write_npz(tmp_path / 'd.npz', count=2)
    (tmp_path / 'afile').write_text('x')
    (tmp_path / 'adir').mkdir()
    oof = {'under_a_file': tmp_path / 'afile' / 'oof.npz',
           'a_directory': tmp_path / 'adir',
           'in_the_model': tmp_path / 'm' / 'sub' / 'oof.npz'}[where]

    def no_training(*a, **k):
        raise AssertionError('trained before checking --oof-out')
    monkeypatch.setattr(training, 'fit_class_models', no_training)
    rc = main_no_escape([str(p), '-o', str(tmp_path / 'm'), '--views', '1',
                         '--verifier-views', '0', '--oof-out', str(oof)])
    assert rc == 2
    assert '--oof-out' in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


def test_pool_workers_end_quietly_on_ctrl_c():
    # the verifier views' process pool: Ctrl-C reaches every process of the group; each
    # worker printed a KeyboardInterrupt traceback under the parent's one-line message
    import subprocess
    import sys
    code = ('import os, signal, time\n'
            'from beo_ros.core.training import _quiet_on_sigint\n'
            '_quiet_on_sigint()\n'
            'os.kill(os.getpid(), signal.SIGINT)\n'
            'time.sleep(10)\n'
            'print("still running")\n')
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 130 and p.stdout == '' and 'Traceback' not in p.stderr, p


def test_grid_must_match_the_npz(tmp_path, capsys):
    p = write_npz(tmp_path / 'd.npz', count=2)
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--grid', '32'] + FAST) == 2
    assert 'd.npz: grid 16 differs from 32 (--grid)' in capsys.readouterr().err


@pytest.mark.parametrize('n', [3, 5])
def test_an_npz_grid_size_a_model_cannot_use_is_refused_naming_the_file(tmp_path, capsys, n):
    # 3^3 grids were refused as 'GridSpec.size must be an integer in [4, 256], got 3', naming
    # neither the file nor where the size came from
    X = np.zeros((4, n ** 3), np.uint8)
    X[:, 0] = 1
    p = tmp_path / 'd.npz'
    np.savez(p, voxels=X, labels=[0, 0, 1, 1], classes=np.array(['a', 'b']))
    assert train.main([str(p), '-o', str(tmp_path / 'm')] + FAST) == 2
    assert f'd.npz: grids of {n}^3: the grid size must be an even integer in [4, 256]' in \
        capsys.readouterr().err


def test_classes_apply_to_meshes(tmp_path, capsys):
    paths = []
    for i in range(3):
        for name, size in (('cube', (1, 1, 1 + 0.1 * i)), ('slab', (1 + 0.1 * i, 1, 0.2))):
            paths.append(tmp_path / f'{name}_{i:04d}.off')
            box_off(paths[-1], *size)
    rc = train.main([*map(str, paths), '-o', str(tmp_path / 'm'), '--grid', '16',
                     '--classes', 'slab'] + FAST)
    assert rc == 0, capsys.readouterr().err
    bank = ModelBank.load(tmp_path / 'm')
    assert bank.classes == ['slab'] and bank.training['n_objects'] == 3
    assert train.main([*map(str, paths), '-o', str(tmp_path / 'm2'), '--grid', '16',
                       '--classes', 'cup'] + FAST) == 2
    assert "classes ['cup'] not in ['cube', 'slab']" in capsys.readouterr().err


def test_classes_read_only_their_meshes(tmp_path, capsys, monkeypatch):
    # every mesh was voxelized before --classes dropped the others: minutes on ModelNet, and
    # a broken mesh of a class not asked for stopped the training
    from beo_ros.core import meshes
    paths = []
    for i in range(3):
        for name, size in (('cube', (1, 1, 1 + 0.1 * i)), ('slab', (1 + 0.1 * i, 1, 0.2))):
            paths.append(tmp_path / f'{name}_{i:04d}.off')
            box_off(paths[-1], *size)
    broken = tmp_path / 'cube_0009.off'
    broken.write_text('OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n')   # no faces
    read = []
    real = meshes.load_mesh
    monkeypatch.setattr(meshes, 'load_mesh', lambda p: read.append(p.name) or real(p))
    argv = [*map(str, paths), str(broken), '--grid', '16'] + FAST
    assert train.main(argv + ['-o', str(tmp_path / 'm'), '--classes', 'slab']) == 0, \
        capsys.readouterr().err
    assert sorted(read) == [f'slab_{i:04d}.off' for i in range(3)]
    assert ModelBank.load(tmp_path / 'm').training['n_objects'] == 3
    # the class asked for still stops at its broken mesh, naming it
    assert train.main(argv + ['-o', str(tmp_path / 'm2'), '--classes', 'cube']) == 2
    assert f'{broken}: mesh has no triangles' in capsys.readouterr().err
    # npz objects with --classes of no mesh: no mesh is read
    read.clear()
    p = write_npz(tmp_path / 'd.npz')
    assert train.main([str(p), *map(str, paths), '-o', str(tmp_path / 'm3'), '--classes',
                       'cylinder', 'box'] + FAST) == 0, capsys.readouterr().err
    assert read == [] and ModelBank.load(tmp_path / 'm3').classes == ['cylinder', 'box']


def test_mesh_class_names(tmp_path, monkeypatch):
    from beo_ros.core.training import mesh_class_name
    assert mesh_class_name('chair/train/chair_0001.off') == 'chair'
    assert mesh_class_name('x/night_stand_0012.off') == 'night_stand'
    assert mesh_class_name('mugs/red_mug.off') == 'mugs'      # not 'red'
    assert mesh_class_name('mugs/mug.obj') == 'mugs'
    assert mesh_class_name('cans/can_7b.stl') == 'cans'
    monkeypatch.chdir(tmp_path)
    assert mesh_class_name('mug.ply') == tmp_path.name        # a bare name: the working folder
    # '..' is the folder above, not a class '..' (refused after every mesh was voxelized)
    (tmp_path / 'mugs' / 'sub').mkdir(parents=True)
    monkeypatch.chdir(tmp_path / 'mugs' / 'sub')
    assert mesh_class_name('../mug.ply') == 'mugs'
    assert mesh_class_name('../../mugs/sub/../mug.ply') == 'mugs'
    assert mesh_class_name('../sub/./mug.ply') == 'sub'


# ---------------------------------------------------------------------- 7: one class
def test_one_class_needs_views_0(tmp_path, capsys, monkeypatch):
    from beo_ros.core import training
    p = write_npz(tmp_path / 'd.npz')
    fits = []
    real = training.fit_class_models
    monkeypatch.setattr(training, 'fit_class_models',
                        lambda *a, **k: fits.append(1) or real(*a, **k))
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--classes', 'box', '--k', '2',
                       '--verifier-views', '0']) == 2
    err = capsys.readouterr().err
    assert 'the classifier needs 2 or more classes' in err and '--views 0' in err
    assert fits == [] and not (tmp_path / 'm').exists()
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--classes', 'box'] + FAST) == 0
    assert ModelBank.load(tmp_path / 'm').classes == ['box']


# ---------------------------------------------------------------------- 9: --point-classifier
def test_point_classifier_npz_checked_before_the_scans(tmp_path, monkeypatch, capsys):
    from beo_ros.core import scan_training
    calls = []
    monkeypatch.setattr(scan_training, 'train_scan_bank', lambda *a, **k: calls.append(a))
    argv = ['learn0.pcd', '--scans', '--mirror', '--views', '0', '-o', str(tmp_path / 'm')]
    voxels = write_npz(tmp_path / 'small.npz')
    assert train.main(argv + ['--point-classifier', str(voxels)]) == 2
    assert 'small.npz: not an oof_features.npz of beo-eval --scans' in capsys.readouterr().err
    oof = tmp_path / 'oof.npz'
    np.savez(oof, features=np.zeros((2, 2, 4)), scenes=np.array(['a', 'b']),
             object_ids=np.array([0, 1]), classes=np.array(['box', 'cup']))
    assert train.main(argv + ['--point-classifier', str(oof)]) == 2
    assert "classes ['box', 'cup'] differ from the scan classes" in capsys.readouterr().err
    assert train.main(argv + ['--point-classifier', str(tmp_path / 'none.npz')]) == 2
    assert 'none.npz' in capsys.readouterr().err
    assert calls == []


def test_scans_manifest_records_scan_classes_and_no_unused_folds(tmp_path, monkeypatch):
    # the non-mirror --scans manifest had no scan_classes and claimed folds 5 / seed 0, which
    # --views 0 never uses
    from beo_ros.core import scan_training
    from beo_ros.core.grid import GridSpec
    rng = np.random.default_rng(0)
    X = (rng.random((6, 8 ** 3)) < 0.3).astype(np.float32)
    masks = rng.random(X.shape) < 0.8
    X[~masks] = 0
    spec = GridSpec(size=8, units='metric', voxel_size=0.05, anchor='bottom')
    seen = []
    monkeypatch.setattr(scan_training, 'load_scan_training_set', lambda *a, **k: seen.append(a)
                        or (X, np.array([0, 0, 0, 1, 1, 1]), ['box', 'can'], masks, spec))
    assert train.main(['learn0.pcd', 'learn33.pcd', '--scans', '--scan-classes',
                       'box:0-16,can:33-44', '--views', '0', '--k', '1', '--grid', '8',
                       '-o', str(tmp_path / 'm')]) == 0
    assert seen[0][1] == 'box:0-16,can:33-44'
    info = json.loads((tmp_path / 'm' / 'manifest.json').read_text())['training']
    assert info['scan_classes'] == 'box:0-16,can:33-44' and info['voxel_size'] == 0.5 / 32
    assert 'folds' not in info and 'seed' not in info and info['classifier_views'] == 0


# ---------------------------------------------------------------------- 10: a bare array
def test_an_npy_named_npz_is_refused_by_every_loader(tmp_path, capsys):
    p = tmp_path / 'bare.npz'
    with open(p, 'wb') as f:
        np.save(f, np.zeros((2, 512), np.uint8))
    with pytest.raises(ValueError, match='bare.npz: holds a single array'):
        load_voxel_npz(p)
    assert train.main([str(p), '-o', str(tmp_path / 'm')] + FAST) == 2
    assert 'bare.npz: holds a single array' in capsys.readouterr().err
    assert evaluate.main(['--model', str(tmp_path / 'm'), '--data', str(p),
                          '--out', str(tmp_path / 'o')]) == 2
    assert 'bare.npz: holds a single array' in capsys.readouterr().err
    with pytest.raises(ValueError, match='bare.npz: holds a single array'):
        bench.load_data(SimpleNamespace(data=str(p), classes=None), None)


def test_save_target_rule(tmp_path):
    (tmp_path / 'd').mkdir()
    (tmp_path / 'd' / 'manifest.json').write_text('{"format": "something else"}')
    with pytest.raises(ValueError, match='holds no beo_ros model'):
        bank_module.check_save_target(tmp_path / 'd')
    bank_module.check_save_target(tmp_path / 'new')
    shutil.rmtree(tmp_path / 'd')


def test_a_text_file_named_npz_is_called_so(tmp_path):
    p = tmp_path / 'notes.npz'
    p.write_text('voxels, labels, classes\n')
    with pytest.raises(ValueError, match=r"notes\.npz: not an npz file \(it starts with b'voxels, '\)"):
        load_voxel_npz(p)


def test_congeal_checks_the_class_counts_first(tmp_path, capsys, monkeypatch):
    # a class with one object is refused before the congealing, not after it
    from beo_ros.core import congeal
    p = write_npz(tmp_path / 'd.npz', count=1)
    calls = []
    monkeypatch.setattr(congeal, 'congeal_classes', lambda *a, **k: calls.append(1))
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--congeal'] + FAST) == 2
    assert 'has 1 training objects' in capsys.readouterr().err
    assert calls == [] and not (tmp_path / 'm').exists()


def test_congeal_with_views_0_needs_only_two_objects_per_class(tmp_path, capsys, monkeypatch):
    # no classifier and no calibration: 2 objects per class do, as without --congeal (the
    # check before congealing used to ask for the out-of-fold folds' count)
    from beo_ros.core import congeal
    p = write_npz(tmp_path / 'd.npz', count=2)
    monkeypatch.setattr(congeal, 'congeal_classes', lambda X, *a, **k: X)
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--congeal'] + FAST) == 0
    assert ModelBank.load(tmp_path / 'm').training['congeal'] is True
    # with a calibration the folds count again
    assert train.main([str(p), '-o', str(tmp_path / 'm2'), '--congeal',
                       '--calibration-views', '1'] + FAST) == 2
    assert 'has 2 training objects' in capsys.readouterr().err


def test_an_upper_case_npz_extension_is_an_npz(tmp_path):
    # 'D.NPZ' went to the mesh loader: "unsupported mesh format '.npz'"
    p = write_npz(tmp_path / 'd.npz')
    upper = p.rename(tmp_path / 'D.NPZ')
    assert train.main([str(upper), '-o', str(tmp_path / 'm')] + FAST) == 0
    assert ModelBank.load(tmp_path / 'm').classes == ['box', 'cylinder']


def test_an_input_given_twice_is_refused(tmp_path, capsys):
    # its objects would be trained on twice (before: 8 objects per class instead of 4)
    p = write_npz(tmp_path / 'd.npz', count=4)
    (tmp_path / 'link.npz').symlink_to(p)
    for second, message in ((p, f'input {p} given twice'),
                            (tmp_path / 'link.npz', f'(as {p})')):
        with pytest.raises(SystemExit) as ei:
            train.main([str(p), str(second), '-o', str(tmp_path / 'm')] + FAST)
        assert ei.value.code == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / 'm').exists()


def test_shipped_model_records_its_training_data(monkeypatch):
    """The shipped modelnet10_32 names the hash of the shared train split it was trained on
    (so that ``--calibrate-only`` on other data is refused), and the hash is that of the file."""
    import os
    from pathlib import Path
    from beo_ros.core.datasets import training_data_hash
    data = Path(os.environ.get('BEO_DATA_DIR') or Path(train.__file__).resolve().parents[2]
                / 'shared' / 'data') / 'modelnet10' / 'modelnet10_vox32_train.npz'
    if not data.is_file():
        pytest.skip(f'{data} not found')
    info = json.loads((bank_module.default_model_dir() / 'manifest.json').read_text())
    args = SimpleNamespace(inputs=[str(data)], grid=None, classes=None)
    X, y, names, _ = train._load_objects(args)
    assert info['training']['data_sha256'] == training_data_hash(X, y, names)


def test_sigterm_does_not_wait_for_the_queued_verifier_chunks():
    # SIGTERM to beo-train alone (kill PID, docker stop) while --jobs 2 made the verifier's
    # views: leaving the process pool's 'with' block made every chunk still queued first
    # (67 s here, minutes on ModelNet) before 'terminated'
    import signal
    import subprocess
    import sys
    import time
    code = ('import sys\n'
            'from beo_ros.cli import interruptible\n'
            'from beo_ros.core.synthetic import primitive_shapes\n'
            'from beo_ros.core.training import verifier_training_set\n'
            'X = primitive_shapes(16, 320)[0]\n'
            "@interruptible('t')\n"
            'def main():\n'
            "    print('start', flush=True)\n"
            '    verifier_training_set(X, 16, views=20, processes=2)\n'
            'sys.exit(main())\n')
    p = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline() == 'start\n'
        time.sleep(2.0)
        p.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        _, err = p.communicate(timeout=30)
        assert p.returncode == 143 and time.monotonic() - t0 < 10, err
        assert 'Traceback' not in err, err
    finally:
        p.kill()
        p.wait()


def test_oof_out_is_written_under_the_name_given(tmp_path):
    # np.savez appended '.npz' to a name without it: --oof-out oof.dat wrote oof.dat.npz
    p = write_npz(tmp_path / 'd.npz', count=5)
    oof = tmp_path / 'oof.dat'
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--k', '2', '--views', '1',
                       '--verifier-views', '0', '--calibration-views', '0',
                       '--classifier', 'logistic', '--descriptors', 'off',
                       '--oof-out', str(oof)]) == 0
    assert sorted(q.name for q in tmp_path.iterdir()) == ['d.npz', 'm', 'oof.dat']
    with np.load(oof) as z:
        assert len(z['partial_labels']) == len(z['complete_labels']) == 10


@pytest.mark.parametrize('extra, message', [
    (['--row-standardize', 'on'], 'row_standardize needs at least 3 classes'),
    # the verifier (on by default), on a 12^3 npz; the way out named
    (['--grid12'], 'a grid of a multiple of 8 (got 12); train without an orientation verifier '
                   '(--verifier-views 0'),
])
def test_fit_options_checked_before_congealing(tmp_path, capsys, monkeypatch, extra, message):
    # fit_bank's checks ran after the congealing (minutes on ModelNet)
    from beo_ros.core import congeal

    def no_congealing(*a, **k):
        raise AssertionError('congealed before checking the fit options')
    monkeypatch.setattr(congeal, 'congeal_classes', no_congealing)
    if extra == ['--grid12']:
        X, y, names = primitive_shapes(12, 4, np.random.default_rng(0))
        p = tmp_path / 'd.npz'
        np.savez(p, voxels=X.astype(np.uint8), labels=y, classes=np.array(names))
        extra = []
    else:
        p = write_npz(tmp_path / 'd.npz')
    assert train.main([str(p), '-o', str(tmp_path / 'm'), '--k', '2', '--congeal',
                       *extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'm').exists()


# ---------------------------------------------------------------------- the noise variance floor
def _noise_free_boxes_bank(tmp_path):
    """The bank beo-train makes of three noise-free mesh boxes per class (cube, slab)."""
    paths = []
    for i in range(3):
        for name, size in (('cube', (1, 1, 1 + 0.1 * i)), ('slab', (1 + 0.1 * i, 1, 0.2))):
            paths.append(tmp_path / f'{name}_{i:04d}.off')
            box_off(paths[-1], *size)
    assert train.main([*map(str, paths), '-o', str(tmp_path / 'm'), '--grid', str(N)]
                      + FAST) == 0
    return ModelBank.load(tmp_path / 'm')


def test_class_models_have_the_occupancy_floor_of_the_noise_variance(tmp_path):
    # three noise-free boxes per class fitted v ~ 1e-8: a class absurdly sure of itself, whose
    # likelihood against another such class hung on numerical noise
    from beo_ros.core.training import OCCUPANCY_MIN_NOISE_VARIANCE
    bank = _noise_free_boxes_bank(tmp_path)
    assert 1e-8 < OCCUPANCY_MIN_NOISE_VARIANCE < 5e-4     # below every shipped model's v
    assert [m.noise_variance for m in bank.models] == [OCCUPANCY_MIN_NOISE_VARIANCE] * 2
    assert bank.training['min_noise_variance'] == OCCUPANCY_MIN_NOISE_VARIANCE


def test_calibrate_only_refits_with_the_floor_the_model_was_trained_with(tmp_path, monkeypatch):
    from beo_ros.core import training
    from beo_ros.core.training import OCCUPANCY_MIN_NOISE_VARIANCE
    p = write_npz(tmp_path / 'd.npz')
    m = tmp_path / 'm'
    assert train.main([str(p), '-o', str(m), '--k', '2', '--folds', '2', '--views', '0',
                       '--verifier-views', '0', '--calibration-views', '1']) == 0
    floors = []
    real = training.fit_class_models
    monkeypatch.setattr(training, 'fit_class_models', lambda *a, **k: floors.append(
        k['min_noise_variance']) or real(*a, **k))
    assert train.main([str(p), '-o', str(m), '--calibrate-only']) == 0
    assert floors == [OCCUPANCY_MIN_NOISE_VARIANCE] * 2
    # a manifest from before the floor: its models were fitted without one
    mf = json.loads((m / 'manifest.json').read_text())
    del mf['training']['min_noise_variance']
    (m / 'manifest.json').write_text(json.dumps(mf))
    floors.clear()
    assert train.main([str(p), '-o', str(m), '--calibrate-only']) == 0
    assert floors == [0.0] * 2


def test_coarse_noise_variance_has_the_floor_of_the_pooled_occupancy_noise(tmp_path):
    # the pooled model's scalar noise of a class of noise-free boxes was ~1e-6 under the 1e-4
    # floor of the full-resolution one, so its stage-1 pose scores were -1e7..-1e8; the mean of
    # 8 voxels of independent noise at the floor has variance floor / 8
    from beo_ros.core.class_model import coarse_noise
    from beo_ros.core.training import OCCUPANCY_MIN_NOISE_VARIANCE
    bank = _noise_free_boxes_bank(tmp_path)
    floor = OCCUPANCY_MIN_NOISE_VARIANCE / 8
    assert [m.coarse_noise_variance for m in bank.models] == [floor] * 2
    # the floor is that of the fit (none: as before), and a residual above it is kept as is
    X = np.random.default_rng(0).random((4, N ** 3)).astype(np.float32)
    est = SimpleNamespace(transform=lambda X: X, inverse_transform=lambda Z: np.zeros_like(Z))
    v, per = coarse_noise(X, est, N)
    assert v > 1e-2 and coarse_noise(X, est, N, min_noise_variance=1e-4)[0] == v
    assert coarse_noise(X * 0, est, N)[0] == 1e-6
    assert coarse_noise(X * 0, est, N, min_noise_variance=1e-4)[0] == 1e-4 / 8
