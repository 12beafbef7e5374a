"""Class models from real partial Kinect scans (OSD learn scenes): training set and shipped model."""
import os
from pathlib import Path

import numpy as np
import pytest

from beo_ros.core.scan_training import (
    load_scan_objects, load_scan_training_set, parse_scan_classes, scene_number)

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get('BEO_DATA_DIR') or ROOT.parent / 'shared' / 'data')
OSD = DATA / 'osd' / 'learn'
MODEL = ROOT / 'models' / 'tabletop_32'


def test_parse_scan_classes():
    names, table = parse_scan_classes('box:0-2,cylinder:33-34+40')
    assert names == ['box', 'cylinder']
    assert table == {0: 0, 1: 0, 2: 0, 33: 1, 34: 1, 40: 1}
    assert scene_number('/x/learn33.pcd') == 33
    for bad, why in (('box', 'is not name:first-last'), ('box:3-1', 'empty range'),
                     ('box:a', 'bad range'), ('box:1,cyl:1', 'scene 1 is in two classes'),
                     (':1', 'has no name'), (' , ', 'no scan classes')):
        with pytest.raises(ValueError, match=why):
            parse_scan_classes(bad)


def test_parse_scan_classes_names_a_class_once_and_takes_the_last_number():
    # a class named twice is one class, a scene given twice to one class is no clash
    names, table = parse_scan_classes('box:0-1,cyl:5,box:3+1')
    assert names == ['box', 'cyl'] and table == {0: 0, 1: 0, 3: 0, 5: 1}
    assert parse_scan_classes({'box': '0-1', 'cyl': 5}) == (['box', 'cyl'], {0: 0, 1: 0, 5: 1})
    # the scene number is the one that ends the file stem
    assert scene_number('/x/scan2_learn33.pcd') == 33
    assert scene_number('/x/learn.pcd') is None


@pytest.fixture(scope='module')
def small_set():
    files = [OSD / f'learn{i}.pcd' for i in (0, 1, 33, 34)]
    if not all(f.is_file() for f in files):
        pytest.skip(f'OSD scenes not found under {OSD}')
    return load_scan_objects(files)


def test_scan_training_set(small_set):
    s = small_set
    assert s.names == ['box', 'cylinder'] and set(s.y) == {0, 1}
    assert s.X.shape == s.masks.shape == (len(s), 32 ** 3) and s.X.dtype == np.float32
    assert (s.X[~s.masks] == 0).all()            # unknown entries are 0 in X
    assert (~s.masks).sum(axis=1).min() > 100      # every object has unknown voxels
    assert set(s.scenes) == {'learn0', 'learn1', 'learn33', 'learn34'}
    g = s.grids
    assert g.dtype == np.int8 and set(np.unique(g)) == {-1, 0, 1}
    # the 5-tuple of beo-train --scans
    X, y, names, masks, spec = load_scan_training_set(
        [OSD / 'learn0.pcd', OSD / 'learn33.pcd'])
    assert spec.units == 'metric' and spec.anchor == 'bottom' and len(X) == len(y) == len(masks)


def test_points_outside_the_grid_are_counted_and_said(small_set):
    # with --grid 16 at the default voxel size the grid cut objects silently (learn0 object 3
    # lost 2379 of its 8177 points); the default 32^3 grid holds every point of the scans
    with pytest.warns(UserWarning, match=r'learn0\.pcd: points outside the 16\^3 grid of '
                      r'0\.015625 m voxels, not voxelized \(object id: points outside/all '
                      r'3: 2379/8177\)'):
        s = load_scan_objects([OSD / 'learn0.pcd', OSD / 'learn1.pcd'], 'box:0-1', grid=16)
    assert s.n_outside[(s.scenes == 'learn0') & (s.object_ids == 3)].tolist() == [2379]
    assert small_set.n_outside.tolist() == [0] * len(small_set)
    assert small_set.scene_notes['learn0'] == dict(small_objects={}, unassigned_points=0,
                                                   table_points=153323)
    assert s.subset([0]).n_outside.tolist() == s.n_outside[:1].tolist()


def test_vbpca_with_masks_trains(small_set):
    from beo_ros.core.vbpca import VBPCA
    s = small_set.subset(small_set.y == 0)
    est = VBPCA(n_components=2, max_iter=3).fit(s.X, mask=s.masks)
    assert np.isfinite(est.components_).all() and est.mean_.shape == (32 ** 3,)
    # the unknown voxels are missing data, not free space: another mean than without masks
    assert (~s.masks).any()
    assert not np.allclose(est.mean_, VBPCA(n_components=2, max_iter=3).fit(s.X).mean_)


def test_shipped_tabletop_model_classifies_a_real_object():
    from beo_ros import load_models
    from beo_ros.core.scans import fit_table_plane, load_scene, segment_objects
    if not (MODEL / 'manifest.json').is_file():
        pytest.skip('models/tabletop_32 is not trained')
    bank = load_models(MODEL)
    assert bank.classes == ['box', 'cylinder'] and bank.spec.units == 'metric'
    path = OSD / 'learn33.pcd'
    if not path.is_file():
        pytest.skip(f'{path} not found')
    scene = load_scene(path)
    up, _ = fit_table_plane(scene)
    pts = max(segment_objects(scene).values(), key=len)  # the biggest mug/can, camera frame
    est = bank.estimate_points(pts, sensor_origin=(0, 0, 0), up=up, yaw_step_deg=3.0)
    assert est.label == 'cylinder', est.scores
    # the shipped rule: the 'points' classifier on loglik + the raw points' normal descriptors
    assert bank.has_point_classifier and est.classifier_mode == 'points', est.classifier_note
    assert np.isfinite(est.point_features).all() and est.point_features[0] < 0.5  # round front
    assert est.completed_points.shape[1] == 3 and len(est.completed_points) > 50


def test_mirror_training_set_and_train_scan_bank(small_set, tmp_path):
    from beo_ros import load_models
    from beo_ros.core.scan_training import mirror_augment, train_scan_bank
    s = small_set
    n = s.spec.size
    X, y, M = mirror_augment(s.X, s.y, s.masks, n)
    m = len(s)
    assert X.shape == (2 * m, n ** 3) and (y[:m] == y[m:]).all()
    assert np.array_equal(X[m:].reshape(m, n, n, n), s.X.reshape(m, n, n, n)[:, :, ::-1])
    assert M[m:].sum() == s.masks.sum()  # as many observed voxels as the originals
    X5, y5, names, M5, spec = load_scan_training_set([OSD / 'learn0.pcd', OSD / 'learn33.pcd'],
                                                     mirror=True)
    assert len(X5) == len(y5) == len(M5) and len(X5) % 2 == 0
    files = [OSD / f'learn{i}.pcd' for i in (0, 1, 33, 34)]
    bank = train_scan_bank(files, k=2, max_iter=3)
    assert bank.classes == ['box', 'cylinder'] and not bank.classifier  # max-likelihood rule
    assert bank.training['mirror'] and bank.training['n_training_grids'] == 2 * m
    bank.save(tmp_path / 'm')
    assert load_models(tmp_path / 'm').classes == ['box', 'cylinder']


def test_train_scan_bank_with_a_points_classifier(small_set, tmp_path):
    from beo_ros import load_models
    from beo_ros.core.inference import FEATURE_NAMES
    from beo_ros.core.scan_training import scan_point_descriptors, train_scan_bank
    s = small_set
    D = scan_point_descriptors(s)
    assert D.shape == (len(s), 2) and np.isfinite(D).all()
    # boxes show perpendicular flat faces, cylinders a round front
    assert np.median(D[s.y == 0, 0]) > 0.5 > np.median(D[s.y == 1, 0])
    rng = np.random.default_rng(0)
    oof = tmp_path / 'oof_features.npz'
    F = rng.normal(0, 1, (len(s), 2, len(FEATURE_NAMES)))
    order = rng.permutation(len(s))                   # rows are matched by scene and object id
    np.savez(oof, features=F[order], y=s.y[order], scenes=s.scenes[order],
             object_ids=s.object_ids[order], classes=np.array(s.names))
    files = [OSD / f'learn{i}.pcd' for i in (0, 1, 33, 34)]
    bank = train_scan_bank(files, k=2, max_iter=3, point_classifier=oof)
    assert bank.has_point_classifier and bank.classifier['points']['coef'].shape == (2, 4)
    assert bank.training['point_classifier']['n_objects'] == len(s)
    bank.save(tmp_path / 'm')
    back = load_models(tmp_path / 'm')
    assert back.has_point_classifier
    est = back.estimate_points(s.points[0], sensor_origin=(0, 0, 0), up=s.ups[0],
                               yaw_step_deg=5.0)
    assert est.classifier_mode == 'points'
    np.testing.assert_allclose(est.point_features, D[0])
    # an npz without every object is refused
    np.savez(oof, features=F[1:], y=s.y[1:], scenes=s.scenes[1:], object_ids=s.object_ids[1:],
             classes=np.array(s.names))
    with pytest.raises(ValueError, match='no out-of-fold features'):
        train_scan_bank(files, k=2, max_iter=3, point_classifier=oof)


def test_train_scan_bank_records_generator_inputs(small_set, monkeypatch):
    # a generator of paths was consumed by load_scan_objects: the manifest said inputs=[]
    import beo_ros.core.bank as bank_mod
    import beo_ros.core.scan_training as st
    import beo_ros.core.training as training
    seen = {}
    monkeypatch.setattr(st, 'load_scan_objects', lambda paths, *a: (list(paths), small_set)[1])
    monkeypatch.setattr(training, 'fit_class_models', lambda *a, **k: None)
    monkeypatch.setattr(bank_mod, 'ModelBank', lambda *a: seen.setdefault('info', a[3]))
    st.train_scan_bank((f'learn{i}.pcd' for i in (0, 33)), mirror=False)
    assert seen['info']['inputs'] == ['learn0.pcd', 'learn33.pcd']


def test_load_scan_objects_errors_name_the_scan_and_object(tmp_path):
    from beo_ros.core.pcd import write_pcd
    rng = np.random.default_rng(0)

    def write(name, pts, labels):
        write_pcd(tmp_path / name, {'x': pts[:, 0].astype(np.float32),
                                    'y': pts[:, 1].astype(np.float32),
                                    'z': pts[:, 2].astype(np.float32),
                                    'label': np.asarray(labels, np.uint32)})
        return tmp_path / name

    # a table in the plane y = 0, through the camera: seen edge-on
    edge = np.c_[rng.uniform(-0.5, 0.5, 500), np.zeros(500), rng.uniform(0.5, 1.5, 500)]
    cup = rng.normal([0, 0.05, 1.0], 0.01, (20, 3))
    with pytest.raises(ValueError, match=r'learn0\.pcd: the fitted support plane is seen edge-on'):
        load_scan_objects([write('learn0.pcd', np.r_[edge, cup],
                                 np.r_[np.ones(500), np.full(20, 20)])])
    # a table z = 1 seen face-on and object 2 in two clusters 10 m apart: none inside its grid
    table = np.c_[rng.uniform(-0.5, 0.5, (500, 2)), np.ones(500)]
    obj = np.r_[rng.normal([-5, 0, 0.9], 0.01, (10, 3)), rng.normal([5, 0, 0.9], 0.01, (10, 3))]
    path = write('learn1.pcd', np.r_[table, obj], np.r_[np.ones(500), np.full(20, 20)])
    with pytest.raises(ValueError, match=r'learn1\.pcd: object 2: none of the 20 points'):
        load_scan_objects([path])


def test_points_below_the_table_are_dropped_counted_and_said(tmp_path):
    # a segmentation leak under the table moved the object's grid floor down with it silently
    from test_scans import synthetic_scene
    from beo_ros.core.pcd import write_pcd
    scene, up, d = synthetic_scene()
    box = scene.labels == 20
    leak = scene.points[box][:30].astype(np.float64)
    leak -= np.outer(leak @ up + d + 0.04, up)   # 4 cm below the table
    pts = np.r_[scene.points, leak.astype(np.float32)]
    labels = np.r_[scene.labels, np.full(30, 20, np.uint32)]
    ok = np.isfinite(pts).all(axis=1)
    write_pcd(tmp_path / 'learn0.pcd', {'x': pts[ok, 0], 'y': pts[ok, 1], 'z': pts[ok, 2],
                                        'label': labels[ok]})
    with pytest.warns(UserWarning, match=r'learn0\.pcd: points more than 0\.01 m below the '
                      r'table plane, dropped \(object id: points dropped/all 2: 30/3030\)'):
        s = load_scan_objects([tmp_path / 'learn0.pcd'], 'box:0')
    assert s.n_outside.tolist() == [0, 0]   # not counted as outside the grid too
    c = (s.spec.size - 1) / 2
    floor = s.grid_to_input[0] @ [c, c, -0.5, 1]
    assert floor[:3] @ s.ups[0] + s.plane_d[0] == pytest.approx(0, abs=2e-3)


def test_load_scan_objects_says_when_a_scene_has_no_objects(tmp_path, capsys):
    """A labelled scene with only table labels is skipped with a line, never silently."""
    from beo_ros.core.pcd import write_pcd
    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.5, 0.5, (500, 2)), np.ones(500)].astype(np.float32)
    write_pcd(tmp_path / 'learn0.pcd', {'x': table[:, 0], 'y': table[:, 1], 'z': table[:, 2],
                                        'label': np.ones(500, np.uint32)})
    with pytest.raises(ValueError, match=r'no object labels \(>= 20\)'):
        load_scan_objects([tmp_path / 'learn0.pcd'])
    assert 'learn0.pcd: no objects (labels >= 20), skipped' in capsys.readouterr().err


def test_load_scan_objects_refuses_a_scene_given_twice(tmp_path):
    # a scene is its file stem: a scan given twice counted its objects twice (and trained on
    # them twice in the other folds), two scans of one name were held out as one scene
    from beo_ros.core.pcd import write_pcd
    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.5, 0.5, (2000, 2)), np.ones(2000)]
    cube = rng.uniform([-0.05, -0.05, 0.9], [0.05, 0.05, 0.95], (300, 3))
    pts = np.r_[table, cube].astype(np.float32)
    for d in ('a', 'b'):
        (tmp_path / d).mkdir()
        write_pcd(tmp_path / d / 'learn0.pcd', {
            'x': pts[:, 0], 'y': pts[:, 1], 'z': pts[:, 2],
            'label': np.r_[np.ones(2000), np.full(300, 20)].astype(np.uint32)})
    a, b = tmp_path / 'a' / 'learn0.pcd', tmp_path / 'b' / 'learn0.pcd'
    with pytest.raises(ValueError, match="'box' has 1 objects; need >= 2"):
        load_scan_objects([a], scan_classes='box:0')
    for paths in ([a, a], [a, b]):
        with pytest.raises(ValueError, match=r"learn0\.pcd: scene 'learn0' given twice "
                                             r'\(also .*learn0\.pcd\)'):
            load_scan_objects(paths, scan_classes='box:0')


@pytest.mark.parametrize('bad, message', [('learn.pcd', 'no such file'),
                                          ('lern3.pcd', 'no such file'),
                                          ('scans', 'a directory, not a PCD file')])
def test_load_scan_objects_refuses_a_path_that_is_no_file(tmp_path, bad, message):
    # before: a path without a scene number of the classes was skipped unopened ('scene None
    # is in no class' with beo-train's verbose note, nothing with beo-eval --scans): a typo
    # or an unmatched glob ('learn*.pcd') left a scan out, or ended in 'no scan matched the
    # scan classes' naming no file
    (tmp_path / 'scans').mkdir()
    good = [tmp_path / 'good' / f'learn{i}.pcd' for i in (0, 1)]   # checked before any is read
    good[0].parent.mkdir()
    for path in good:
        path.write_bytes(b'')
    with pytest.raises(ValueError, match=f'{bad}: {message}'):
        load_scan_objects(good + [tmp_path / bad], 'box:0-1')
    with pytest.raises(ValueError, match=f'{bad}: {message}'):
        load_scan_objects(iter([tmp_path / bad]))


def _cube_scene(path):
    """A table z = 1 seen face-on and one 10 cm cube on it (labels 1 and 20)."""
    from beo_ros.core.pcd import write_pcd
    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.5, 0.5, (2000, 2)), np.ones(2000)]
    cube = rng.uniform([-0.05, -0.05, 0.9], [0.05, 0.05, 0.95], (300, 3))
    pts = np.r_[table, cube].astype(np.float32)
    write_pcd(path, {'x': pts[:, 0], 'y': pts[:, 1], 'z': pts[:, 2],
                     'label': np.r_[np.ones(2000), np.full(300, 20)].astype(np.uint32)})
    return path


def test_load_scan_objects_skips_scenes_of_no_class_and_orders_by_scene_number(tmp_path,
                                                                             capsys):
    files = [_cube_scene(tmp_path / f'learn{i}.pcd') for i in (10, 7, 2)]
    s = load_scan_objects(files, 'box:2+10', verbose=True)
    assert s.scenes.tolist() == ['learn2', 'learn10']   # by number, not by name or argument
    assert 'learn7.pcd: scene 7 is in no class, skipped' in capsys.readouterr().err
    assert set(s.scene_notes) == {'learn2', 'learn10'}


def test_subset_keeps_every_field_of_the_objects_it_selects(small_set):
    s = small_set
    for sel in (s.y == 1, np.flatnonzero(s.y == 1)):
        sub = s.subset(sel)
        idx = np.flatnonzero(s.y == 1)
        assert len(sub) == len(idx) == len(sub.points) and set(sub.y) == {1}
        for a, i in zip(sub.points, idx):
            assert a is s.points[i]
        np.testing.assert_array_equal(sub.grid_to_input, s.grid_to_input[idx])


def test_point_classifier_from_oof_matches_rows_by_scene_and_object(small_set, tmp_path):
    # rows of the npz in another order than the objects: each object must get its own row's
    # log-likelihoods (feature 0), not the row at its index
    from beo_ros.core.scan_training import (point_classifier_from_oof, scan_point_descriptors,
                                            train_point_classifier)
    s = small_set
    rng = np.random.default_rng(2)
    F = rng.normal(0, 1, (len(s), 2, 3))
    F[:, :, 0] += np.where(s.y == 0, 1.0, -1.0)[:, None] * [1, -1]
    order = rng.permutation(len(s))
    oof = tmp_path / 'oof_features.npz'
    np.savez(oof, features=F[order], scenes=s.scenes[order], object_ids=s.object_ids[order],
             classes=np.array(s.names), grid_source=np.array('estimate_points'))
    clf, info = point_classifier_from_oof(oof, s, C=0.5)
    want = train_point_classifier(F[:, :, 0], scan_point_descriptors(s), s.y, 2, C=0.5)
    for key in ('mean', 'scale', 'coef', 'intercept', 'unknown_threshold'):
        np.testing.assert_allclose(clf[key], want[key], rtol=1e-9, err_msg=key)
    assert info['point_classifier']['oof_grid_source'] == 'estimate_points'
    np.savez(oof, features=F, scenes=s.scenes, object_ids=s.object_ids,
             classes=np.array(['cylinder', 'box']))
    with pytest.raises(ValueError, match=r"classes \['cylinder', 'box'\] differ from the scans"):
        point_classifier_from_oof(oof, s)
