"""Shape descriptors (beo_ros.core.shape) and the classifiers that take them."""
import numpy as np
import pytest

from beo_ros.core.bank import ModelBank, ModelError, classifier_input, uses_descriptors
from beo_ros.core.grid import rotate_grid
from beo_ros.core.shape import DESCRIPTOR_NAMES, shape_descriptors
from beo_ros.core.synthetic import partial_view, primitive_shapes
from _models import save_with_classifier

N = 16


def _box(n=N):
    g = np.zeros((n,) * 3, dtype=np.int8)
    g[3:13, 5:10, 2:9] = 1
    return g


def test_descriptors_are_yaw_invariant_and_describe_the_shape():
    g = _box()
    d = shape_descriptors(g)
    assert d.shape == (len(DESCRIPTOR_NAMES),) and np.isfinite(d).all()
    # exact quarter turns about z: identical
    for k in (1, 2, 3):
        np.testing.assert_allclose(shape_descriptors(np.rot90(g, k, axes=(0, 1))), d,
                                   atol=1e-12)
    # any yaw: equal up to the voxel resampling
    np.testing.assert_allclose(shape_descriptors(rotate_grid(g, np.deg2rad(37.0))), d,
                               atol=0.12)
    named = dict(zip(DESCRIPTOR_NAMES, d))
    assert named['height'] == pytest.approx(7 / N)
    assert named['elongation'] < 0.6               # a 10 x 5 footprint
    assert named['log_count'] == pytest.approx(np.log(10 * 5 * 7))
    # a taller object is taller
    tall = np.zeros_like(g)
    tall[3:13, 5:10, 0:15] = 1
    assert dict(zip(DESCRIPTOR_NAMES, shape_descriptors(tall)))['height'] > named['height']


def test_descriptors_use_only_occupied_voxels_and_check_input():
    g = _box()
    labelled = np.where(g == 1, 1, -1).astype(np.int8)      # unknown around: same voxels
    np.testing.assert_allclose(shape_descriptors(labelled), shape_descriptors(g))
    assert not shape_descriptors(np.zeros((N,) * 3, dtype=np.int8)).any()
    for shape in ((N, N), (N, N, 2 * N)):
        with pytest.raises(ValueError, match='N, N, N'):
            shape_descriptors(np.zeros(shape, dtype=np.int8))


def test_classifier_with_descriptors_is_trained_saved_checked_and_used(tmp_path):
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.training import fit_bank
    X, y, names = primitive_shapes(N, 8, np.random.default_rng(2))
    bank = fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3, classifier_views=1,
                    folds=2, seed=0, descriptors=True)
    for mode, clf in bank.classifier.items():
        assert uses_descriptors(clf) and clf['coef'].shape == (2, 2 * 6 + len(DESCRIPTOR_NAMES))
        assert bank.training['cross_validation'][mode]['descriptors'] is True
    again = ModelBank.load(bank.save(tmp_path / 'd'))
    g = partial_view(X[0].reshape((N,) * 3) > 0.5, 0.3, 0.5)
    e1, e2 = bank.estimate(g), again.estimate(g)
    assert e1.label == e2.label and e1.scores == pytest.approx(e2.scores)
    # the descriptors are part of the input: other descriptors, other probabilities
    f, _ = again.features(g)
    clf = again.classifier['partial']
    p1 = again.classify_features(f, 'partial', g)[0]
    z = classifier_input(f, 2, bool(clf['row_standardize']), shape_descriptors(g) * 0 + 5.0)
    from beo_ros.core.bank import classifier_probabilities
    p2 = classifier_probabilities(clf, z, f[:, 0])[0][0]
    assert not np.allclose(p1, p2)
    # and they are the grid's own descriptors
    z = classifier_input(f, 2, bool(clf['row_standardize']), shape_descriptors(g))
    np.testing.assert_allclose(p1, classifier_probabilities(clf, z, f[:, 0],
                                                            again._prior_offset(clf))[0][0])
    with pytest.raises(ValueError, match='pass the grid'):
        again.classify_features(f, 'partial')
    # a descriptor classifier whose weights do not fit is refused on load, naming the file
    bad = {m: dict(c, coef=np.asarray(c['coef'])[:, :12]) for m, c in again.classifier.items()}
    with pytest.raises(ModelError, match='model bank: .*shape descriptors'):
        ModelBank(again.models, again.spec, bad, again.training)
    path = save_with_classifier(again, bad, tmp_path / 'bad')
    with pytest.raises(ModelError, match='classifier.npz: .*shape descriptors'):
        ModelBank.load(path)
    with pytest.raises(ValueError, match='descriptors'):
        fit_bank(X, y, names, GridSpec(size=N), k=3, descriptors='yes')
    # the regularisation strength is cross-validated too, and the report says which won
    from beo_ros.core.training import C_OPTIONS
    for rep in bank.training['cross_validation'].values():
        assert rep['C'] in C_OPTIONS if rep['kind'] == 'logistic' else rep['alpha'] > 0
        assert 0 <= rep['ece'] <= 1 and rep['log_loss'] > 0
        # every C of the logistic regression and the one-layer network
        assert len(rep['accuracy_by_input']) == len(C_OPTIONS) + 1
    with pytest.raises(ValueError, match='C must be'):
        fit_bank(X, y, names, GridSpec(size=N), k=3, C=-1.0)


def test_expected_calibration_error():
    from beo_ros.core.training import expected_calibration_error
    # confidence 0.9 everywhere, right 9 times in 10: calibrated
    assert expected_calibration_error(np.full(10, 0.9), np.arange(10) < 9) == pytest.approx(0)
    # confidence 0.9, right half the time: off by 0.4
    assert expected_calibration_error(np.full(10, 0.9), np.arange(10) < 5) == pytest.approx(0.4)


def test_classifier_stores_its_descriptor_count_and_old_classifiers_take_the_first_set(tmp_path):
    """New classifiers record how many descriptors they take; one saved before the second
    set (no count, 12 inputs) is fed the first 12 of the grid's descriptors, and a bad count
    is refused on load."""
    from beo_ros.core.bank import classifier_probabilities, descriptor_count
    from beo_ros.core.grid import GridSpec
    from beo_ros.core.shape import BASIC_NAMES
    from beo_ros.core.training import fit_bank, train_classifier
    X, y, names = primitive_shapes(N, 8, np.random.default_rng(2))
    bank = fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3, classifier_views=1,
                    folds=2, seed=0, descriptors=True)
    for clf in bank.classifier.values():
        assert int(clf['descriptor_count']) == len(DESCRIPTOR_NAMES) == descriptor_count(clf)
    # an old-style classifier: trained on the first 12 descriptors, saved without the count
    grids = [partial_view(X[i].reshape((N,) * 3) > 0.5, 0.3 + i, 0.5) for i in range(len(X))]
    F = np.array([bank.features(g)[0].ravel() for g in grids])
    D12 = np.array([shape_descriptors(g)[:len(BASIC_NAMES)] for g in grids])
    old = train_classifier(F, y, 2, row_standardize=False, descriptors=D12)
    del old['descriptor_count']
    assert descriptor_count(old) == len(BASIC_NAMES) == 12
    path = ModelBank(bank.models, bank.spec, {'partial': old}, bank.training).save(tmp_path / 'o')
    again = ModelBank.load(path)
    g = grids[3]
    f, _ = again.features(g)
    z = classifier_input(f, 2, False, shape_descriptors(g)[:12])
    np.testing.assert_allclose(again.classify_features(f, 'partial', g)[0],
                               classifier_probabilities(old, z, f[:, 0],
                                                        again._prior_offset(old))[0][0])
    for bad in (0, len(DESCRIPTOR_NAMES) + 1, 12.0, True):
        clf = dict(old, descriptor_count=np.asarray(bad))
        with pytest.raises(ModelError, match='model bank: .*descriptor_count'):
            ModelBank(bank.models, bank.spec, {'partial': clf}, bank.training)
        p = save_with_classifier(bank, {'partial': clf}, tmp_path / f'bad{bad!r}')
        with pytest.raises(ModelError, match='descriptor_count'):
            ModelBank.load(p)


def test_second_set_describes_how_the_voxels_are_built():
    """Height profile and height x radius histogram are shares of the voxels; a solid block
    is stacked and fills its columns, a shelf (two slabs joined by a wall) leaves gaps in its
    columns, and a pedestal (thin column under a wide top) spreads out at the top."""
    names = DESCRIPTOR_NAMES
    block = np.zeros((N,) * 3, dtype=np.int8)
    block[4:12, 4:12, 0:6] = 1
    shelf = np.zeros_like(block)
    shelf[4:12, 4:12, 0:2] = 1
    shelf[4:12, 4:12, 8:10] = 1
    shelf[4:5, 4:12, 0:10] = 1
    pedestal = np.zeros_like(block)
    pedestal[7:9, 7:9, 0:8] = 1
    pedestal[2:14, 2:14, 8:10] = 1
    d = {k: dict(zip(names, shape_descriptors(g)))
         for k, g in (('block', block), ('shelf', shelf), ('pedestal', pedestal))}
    for k, v in d.items():
        assert sum(v[f'z_profile_{i}'] for i in range(8)) == pytest.approx(1.0), k
        assert sum(v[f'height_radius_{i}_{j}'] for i in range(4) for j in range(4)) == \
            pytest.approx(1.0), k
    # the block: all voxels in the lowest eighths of the grid (z < 6 of 16), 5 of 6 stacked
    assert d['block']['z_profile_0'] + d['block']['z_profile_1'] + \
        d['block']['z_profile_2'] == pytest.approx(1.0)
    assert d['block']['supported'] == pytest.approx(5 / 6)
    assert d['block']['column_fill'] == pytest.approx(1.0)
    assert d['block']['columns'] == pytest.approx(1 / 6)
    assert d['shelf']['column_fill'] < 0.7 < d['block']['column_fill']
    assert d['pedestal']['spread_q3'] > 3 * d['pedestal']['spread_q0']
    assert d['block']['spread_q3'] == pytest.approx(d['block']['spread_q0'])


def test_every_descriptor_of_a_box_by_hand():
    # the box's voxels: x 3..12, y 5..9, z 2..8 (350); only height, elongation, log_count and
    # (in the second set) the block's stacking were pinned: a swapped quartile, another
    # length unit or mean_height over the object's height passed
    d = dict(zip(DESCRIPTOR_NAMES, shape_descriptors(_box())))
    m = 10 * 5 * 7
    var_x, var_y = 82.5 * 35 / (m - 1), 10.0 * 70 / (m - 1)   # np.cov of the voxels' x, y
    assert d['extent_major'] == pytest.approx(np.sqrt(var_x) / (N / 2))
    assert d['extent_minor'] == pytest.approx(np.sqrt(var_y) / (N / 2))
    assert d['elongation'] == pytest.approx(np.sqrt(var_y / var_x))
    # 7 z layers at relative heights 0, 1/7, ..., 6/7: 2, 2, 2 and 1 of them per quarter
    layers = np.array([2, 2, 2, 1]) / 7
    assert [d[f'height_q{i}'] for i in (1, 2, 3)] == pytest.approx(layers[:3])
    assert d['mean_height'] == pytest.approx(5 / N)
    # z 2..8 over the eighths of 16: 2, 2, 2, 1 layers in eighths 1..4
    assert [d[f'z_profile_{i}'] for i in range(8)] == pytest.approx(
        [0, 2 / 7, 2 / 7, 2 / 7, 1 / 7, 0, 0, 0])
    # radius from the footprint's centre (7.5, 7), relative to its farthest cell
    x, y = np.meshgrid(np.arange(3, 13) - 7.5, np.arange(5, 10) - 7.0)
    r = np.hypot(x, y).ravel()
    share = np.histogram(r / r.max(), bins=4, range=(0, 1))[0] / r.size
    assert [d[f'radius_q{i}'] for i in (1, 2, 3)] == pytest.approx(share[:3])
    # a box: the height and radius quarters are independent
    joint = [[d[f'height_radius_{i}_{j}'] for j in range(4)] for i in range(4)]
    np.testing.assert_allclose(joint, np.outer(layers, share), atol=1e-12)
    assert d['supported'] == pytest.approx(6 / 7) and d['column_fill'] == pytest.approx(1.0)
    assert d['columns'] == pytest.approx(50 / m)
    rms = np.sqrt(np.mean(r ** 2)) / (N / 2)
    assert [d[f'spread_q{i}'] for i in range(4)] == pytest.approx([rms] * 4)


def test_two_voxels_are_too_few_and_three_are_enough():
    g = np.zeros((N,) * 3, dtype=np.int8)
    g[4, 4, 0:2] = 1
    assert not shape_descriptors(g).any()
    g[4, 4, 2] = 1   # a column of 3: height 3 / N, all stacked but the top one
    d = dict(zip(DESCRIPTOR_NAMES, shape_descriptors(g)))
    assert d['height'] == pytest.approx(3 / N) and d['supported'] == pytest.approx(2 / 3)
    assert d['log_count'] == pytest.approx(np.log(3))
