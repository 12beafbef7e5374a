"""The one-layer network classifier (classifier_training.fit_mlp) in the shipped classifier format."""
import numpy as np
import pytest

from beo_ros.core.bank import ModelBank, ModelError, classifier_probabilities
from beo_ros.core.grid import GridSpec
from beo_ros.core.inference import FEATURE_NAMES
from beo_ros.core.synthetic import primitive_shapes
from beo_ros.core.training import (MLP_ALPHA, MLP_HIDDEN, fit_bank, fit_mlp,
                                   select_classifier, train_classifier)
from _models import save_with_classifier

N = 16
NF = len(FEATURE_NAMES)


def _rows(n_classes, m=90, seed=0):
    rng = np.random.default_rng(seed)
    y = np.arange(m) % n_classes
    F = rng.normal(size=(m, n_classes * NF))
    F[np.arange(m), y * NF] += 2.0    # the true class's first feature stands out
    F[:, 1] *= 50.0                    # one input on another scale: standardisation matters
    return F, y


@pytest.mark.parametrize('n_classes', [2, 4])
def test_network_probabilities_are_scikit_learns(n_classes):
    """classifier_probabilities on the stored arrays reproduces the fitted network's own
    predict_proba, for the softmax output and for the one logistic unit of a binary fit."""
    from sklearn.neural_network import MLPClassifier
    F, y = _rows(n_classes)
    clf = fit_mlp(F, y, n_classes, hidden=16, alpha=0.5, seed=3)
    assert clf['hidden_coef'].shape == (16, F.shape[1]) and clf['coef'].shape == (n_classes, 16)
    p, _ = classifier_probabilities(dict(clf, unknown_threshold=np.full(n_classes, -np.inf)),
                                    F, F[:, 0::NF])
    Z = (F - F.mean(axis=0)) / (F.std(axis=0) + 1e-9)
    want = MLPClassifier((16,), alpha=0.5, max_iter=1000, random_state=3).fit(Z, y)
    np.testing.assert_allclose(p, want.predict_proba(Z), atol=1e-9)
    assert np.mean(p.argmax(axis=1) == y) > 0.9


def test_network_with_an_absent_class_never_chooses_it():
    F, y = _rows(3)
    keep = y != 1
    clf = fit_mlp(F[keep], y[keep], 3, hidden=8)
    p, _ = classifier_probabilities(dict(clf, unknown_threshold=np.full(3, -np.inf)),
                                    F, F[:, 0::NF])
    assert p[:, 1].max() < 1e-9 and clf['class_counts'][1] == 0


def test_select_classifier_tries_both_kinds_and_says_which_won():
    F, y = _rows(3, m=120, seed=1)
    objects = np.arange(len(y))
    clf, rep = select_classifier(F, y, [], objects, None, 3, C=0.3, descriptors=False,
                                 row_standardize=False)
    by = rep['accuracy_by_input']
    assert set(by) == {'raw', f'raw, MLP {MLP_HIDDEN} alpha={MLP_ALPHA:g}'}
    assert rep['accuracy'] == max(by.values())
    assert ('hidden_coef' in clf) == (rep['kind'] == 'mlp')
    assert ('C' in rep) == (rep['kind'] == 'logistic') != ('alpha' in rep)
    only_net, rep_net = select_classifier(F, y, [], objects, None, 3, descriptors=False,
                                          row_standardize=False, kind='mlp')
    assert rep_net['kind'] == 'mlp' and rep_net['hidden'] == MLP_HIDDEN
    assert only_net['hidden_coef'].shape == (MLP_HIDDEN, F.shape[1])
    only_lr, rep_lr = select_classifier(F, y, [], objects, None, 3, descriptors=False,
                                        row_standardize=False, kind='logistic')
    assert rep_lr['kind'] == 'logistic' and 'hidden_coef' not in only_lr
    with pytest.raises(ValueError, match='kind must be'):
        select_classifier(F, y, [], objects, None, 3, kind='forest')


@pytest.fixture(scope='module')
def net_bank():
    X, y, names = primitive_shapes(N, 8, np.random.default_rng(0))
    return fit_bank(X, y, names, GridSpec(size=N), k=3, pose_components=3, classifier_views=1,
                    folds=2, seed=0, classifier_kind='mlp'), X, y


def test_bank_with_network_classifiers_round_trips_and_classifies(net_bank, tmp_path):
    bank, X, y = net_bank
    for mode, clf in bank.classifier.items():
        assert clf['hidden_coef'].shape[0] == MLP_HIDDEN
        assert bank.training['cross_validation'][mode]['kind'] == 'mlp'
    assert "classifier ['complete: mlp', 'partial: mlp']" in repr(bank)
    again = ModelBank.load(bank.save(tmp_path / 'net'))
    for i in range(0, len(X), 3):
        g = X[i].reshape((N,) * 3).astype(np.int8)
        e1, e2 = bank.estimate(g, yaw=0.0), again.estimate(g, yaw=0.0)
        assert e1.label == e2.label and e1.scores == pytest.approx(e2.scores)
    labels = [bank.estimate(X[i].reshape((N,) * 3).astype(np.int8), yaw=0.0).label
              for i in range(len(X))]
    assert np.mean(np.array(labels) == np.array(bank.classes)[y]) >= 0.75
    with pytest.raises(ValueError, match='classifier_kind'):
        fit_bank(X, y, bank.classes, GridSpec(size=N), k=3, classifier_kind='svm')


@pytest.mark.parametrize('change, match', [
    (lambda c: c.pop('hidden_intercept'), "'hidden_coef' without 'hidden_intercept'"),
    (lambda c: c.pop('hidden_coef'), "'hidden_intercept' without 'hidden_coef'"),
    (lambda c: c.update(hidden_coef=c['hidden_coef'][:, :-1]), "'hidden_coef' has shape"),
    (lambda c: c.update(coef=c['coef'][:, :-1]), "'coef' has shape"),
    (lambda c: c.update(hidden_intercept=np.zeros((0,))), 'H >= 1'),
    (lambda c: c['hidden_coef'].__setitem__((0, 0), np.nan), 'NaN or Inf'),
])
def test_broken_hidden_layer_is_refused_on_load(net_bank, tmp_path, change, match):
    bank, _, _ = net_bank
    clf = {m: {k: np.array(v, copy=True) for k, v in c.items()}
           for m, c in bank.classifier.items()}
    change(clf['partial'])
    with pytest.raises(ModelError, match="model bank: classifier 'partial'.*" + match):
        ModelBank(bank.models, bank.spec, clf, bank.training)
    path = save_with_classifier(bank, clf, tmp_path / 'bad')
    with pytest.raises(ModelError, match=match):
        ModelBank.load(path)


def test_logistic_train_classifier_is_unchanged_by_the_new_arguments():
    F, y = _rows(3)
    a = train_classifier(F, y, 3, C=0.3)
    b = train_classifier(F, y, 3, C=0.3, hidden=0, alpha=5.0, seed=9)
    assert 'hidden_coef' not in a and set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_a_column_constant_in_training_does_not_decide_the_class():
    """A network input that was constant in every training row (mean_height and column_fill
    of the primitive shapes) has scale 1, not 1e-9: a query 0.01 off the constant kept its
    probabilities (std + 1e-9 made them 1 / 0 through the small hidden weights on it)."""
    F, y = _rows(3)
    F = np.hstack([F, np.full((len(F), 1), 0.5)])
    clf = dict(fit_mlp(F, y, 3, hidden=16), unknown_threshold=np.full(3, -np.inf))
    q = F[:10].copy()
    p, _ = classifier_probabilities(clf, q, q[:, 0:3 * NF:NF])
    q[:, -1] += 0.01
    p_off, _ = classifier_probabilities(clf, q, q[:, 0:3 * NF:NF])
    np.testing.assert_allclose(p_off, p, atol=1e-3)
    assert clf['scale'][-1] == 1.0


def test_select_classifier_keeps_the_logistic_regression_on_a_tie_and_reports_the_runner_up():
    # separable rows: every option is right on all of them, and the first of equals (the
    # logistic regression) wins; accuracy_other_input is the best of the others, not the winner
    F, y = _rows(3, m=60, seed=2)
    F[np.arange(len(y)), y * NF] += 20.0
    clf, rep = select_classifier(F, y, [], np.arange(len(y)), None, 3, C=0.3,
                                 descriptors=False, row_standardize=False)
    assert set(rep['accuracy_by_input'].values()) == {1.0}
    assert rep['kind'] == 'logistic' and 'hidden_coef' not in clf
    F, y = _rows(3, m=120, seed=1)
    _, rep = select_classifier(F, y, [], np.arange(len(y)), None, 3, C=(0.01, 1.0),
                               descriptors=False, row_standardize=False, kind='logistic')
    by = rep['accuracy_by_input']
    winner = 'raw, C=' + format(rep['C'], 'g')
    assert rep['accuracy_other_input'] == max(a for k, a in by.items() if k != winner)


def test_cross_validated_network_takes_its_penalty():
    from beo_ros.core.training import cross_validated_report
    F, y = _rows(3, m=90, seed=4)
    light = cross_validated_report(F, y, [], hidden=16, alpha=1.0)
    heavy = cross_validated_report(F, y, [], hidden=16, alpha=300.0)
    # a heavy L2 penalty pulls the probabilities towards uniform
    assert heavy['log_loss'] > light['log_loss'] + 0.1
