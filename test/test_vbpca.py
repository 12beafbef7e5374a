"""VBPCA: planted subspace and noise recovery, ARD pruning, missing data, validation, sklearn API,
and the batched Cholesky helper of the inference engine."""
import warnings

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.exceptions import ConvergenceWarning

from beo_ros.core.inference import batched_cholesky_terms
from beo_ros.core.vbpca import VBPCA

RANK = 3


def planted(n=200, d=30, noise=0.3, seed=0):
    """Rank-3 data with a known orthonormal basis Q (d, 3), an offset and isotropic noise."""
    rng = np.random.default_rng(seed)
    Q = np.linalg.qr(rng.standard_normal((d, RANK)))[0]
    Z = rng.standard_normal((n, RANK)) * np.array([5.0, 4.0, 3.0])
    X = Z @ Q.T + rng.standard_normal(d) + noise * rng.standard_normal((n, d))
    return X, Q, noise ** 2


def principal_cosines(A, B):
    qa = np.linalg.qr(A)[0]
    qb = np.linalg.qr(B)[0]
    return np.linalg.svd(qa.T @ qb, compute_uv=False)


def fit_quiet(est, X, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ConvergenceWarning)
        return est.fit(X, **kw)


@pytest.mark.parametrize('dtype', [np.float64, np.float32])
def test_recovers_planted_subspace_and_noise(dtype):
    X, Q, v = planted()
    est = VBPCA(n_components=RANK, dtype=dtype).fit(X)
    assert est.converged_
    assert est.components_.shape == (RANK, X.shape[1])
    cos = principal_cosines(Q, est.components_.T)
    assert cos.min() > 0.99, cos
    assert abs(est.noise_variance_ - v) < 0.2 * v, est.noise_variance_
    # the mean is the column mean of the data for a fully observed fit (up to the weak prior)
    np.testing.assert_allclose(est.mean_, X.mean(axis=0), atol=0.05)
    # columns are ordered by decreasing variance
    cv = est.component_variance_
    assert np.all(np.diff(cv) <= 0), cv


def test_ard_prunes_surplus_components():
    X, Q, v = planted()
    est = VBPCA(n_components=10, max_iter=500).fit(X)
    # on this data ARD keeps exactly the planted rank (observed: 3 of 10)
    assert est.n_components_ == RANK
    assert est.components_.shape == (RANK, X.shape[1])
    assert est.loading_covariance_.shape == (RANK, RANK)
    assert principal_cosines(Q, est.components_.T).min() > 0.99
    assert abs(est.noise_variance_ - v) < 0.2 * v


def _missing_problem():
    X, Q, v = planted(n=120, d=30, noise=0.1, seed=1)
    rng = np.random.default_rng(2)
    M = rng.random(X.shape) > 0.3
    return X, M


def test_missing_values_beat_mean_imputation():
    X, M = _missing_problem()
    Xh = np.where(M, X, np.nan)          # hidden entries must not be read
    est = VBPCA(n_components=5, dtype=np.float64).fit(Xh, mask=M)
    assert est.converged_
    assert est.n_components_ == RANK
    R = est.inverse_transform(est.transform(Xh, mask=M))
    H = ~M
    rmse = np.sqrt(((R - X)[H] ** 2).mean())
    col_mean = np.where(M, X, 0).sum(axis=0) / M.sum(axis=0)
    rmse_mean = np.sqrt(((col_mean[None, :] - X)[H] ** 2).mean())
    # observed: 0.11 vs 1.19
    assert rmse * 5 < rmse_mean, (rmse, rmse_mean)


def test_masked_transform_ignores_hidden_entries():
    X, M = _missing_problem()
    est = VBPCA(n_components=RANK, dtype=np.float64).fit(X)
    Z = est.transform(X, mask=M)
    X2 = X.copy()
    X2[~M] = 1e3
    X2[0, ~M[0]] = np.nan
    np.testing.assert_array_equal(est.transform(X2, mask=M), Z)
    # ... while changing an observed entry does change the scores
    X3 = X.copy()
    j = np.flatnonzero(M[0])[0]
    X3[0, j] += 10.0
    assert not np.allclose(est.transform(X3, mask=M)[0], Z[0])
    # the masked log-likelihood also ignores hidden entries
    np.testing.assert_allclose(est.score_samples(X2, mask=M), est.score_samples(X, mask=M))


def _planted_missing():
    X, _, _ = planted(n=200, d=60, noise=0.3, seed=3)
    return X, np.random.default_rng(4).random(X.shape) > 0.3


@pytest.mark.parametrize('init,seed', [('pca', 0), ('random', 0), ('random', 1), ('random', 2)])
def test_missing_path_keeps_the_planted_rank_from_any_start(init, seed):
    # the old stopping rule (subspace direction only, no change of latent basis) stopped while
    # surplus columns still had variance: 4, 4 and 6 of 8 kept from the random starts
    X, M = _planted_missing()
    est = VBPCA(8, init=init, random_state=seed).fit(np.where(M, X, np.nan), mask=M)
    assert est.converged_ and est.n_iter_ < 150     # observed: 57-58
    assert est.n_components_ == RANK
    assert np.isfinite(est.lower_bound_)


def test_missing_path_bound_never_decreases():
    X, M = _planted_missing()
    bounds = []
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ConvergenceWarning)
        for t in range(1, 41):
            est = VBPCA(8, max_iter=t, init='random', random_state=1, dtype=np.float64)
            bounds.append(est.fit(X, mask=M).lower_bound_)
    steps = np.diff(bounds)
    assert (steps >= -1e-9 * np.abs(bounds[1:])).all(), steps.min()
    assert bounds[-1] > bounds[0]


def test_rotation_leaves_the_fit_unchanged_and_raises_the_bound():
    from beo_ros.core.vbpca import _rotate_to_pca
    rng = np.random.default_rng(0)
    n, d, k = 15, 9, 4

    def spd(m):
        A = rng.standard_normal((m, k, k))
        return A @ A.transpose(0, 2, 1) / k + 0.1 * np.eye(k)

    W, Sw = rng.standard_normal((d, k)), spd(d)
    Xm, Sx = rng.standard_normal((n, k)) * 3 + 1, spd(n)

    def expected_products(W, Sw, Xm, Sx):
        # E[w_i . x_j] and Var[w_i . x_j] for every entry: all the likelihood depends on
        mean = W @ Xm.T
        var = (np.einsum('ia,jab,ib->ij', W, Sx, W) + np.einsum('ja,iab,jb->ij', Xm, Sw, Xm)
               + np.einsum('iab,jba->ij', Sw, Sx))
        return mean, var

    def priors_bound(W, Sw, Xm, Sx):
        alpha = ((W ** 2).sum(axis=0) + Sw[:, range(k), range(k)].sum(axis=0)) / d
        mu, mu_var = np.zeros(d), np.ones(d)
        return VBPCA._bound_missing(n * d, k, 1.0, 0.0, Sx, Xm, Sw, W, alpha, mu, mu_var, 1.0)

    after = _rotate_to_pca(W, Sw, Xm, Sx)
    for a, b in zip(expected_products(W, Sw, Xm, Sx), expected_products(*after)):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9)
    assert priors_bound(*after) > priors_bound(W, Sw, Xm, Sx) + 1.0
    W2, Sw2, Xm2, Sx2 = after
    np.testing.assert_allclose((Xm2.T @ Xm2 + Sx2.sum(axis=0)) / n, np.eye(k), atol=1e-9)
    G = W2.T @ W2 + Sw2.sum(axis=0)
    np.testing.assert_allclose(G - np.diag(np.diag(G)), 0, atol=1e-9)


def test_score_samples_matches_dense_gaussian():
    X, Q, v = planted(n=100, d=12)
    est = VBPCA(n_components=RANK, dtype=np.float64).fit(X)
    W = est.components_.T.astype(np.float64)
    C = W @ W.T + est.noise_variance_ * np.eye(X.shape[1])
    # the posterior adds the loading uncertainty; compare with the plain marginal loosely and
    # exactly where the loading covariance is set to zero
    est.loading_covariance_ = np.zeros_like(est.loading_covariance_)
    r = X[:5] - est.mean_
    _, ld = np.linalg.slogdet(C)
    dense = -0.5 * (X.shape[1] * np.log(2 * np.pi) + ld
                    + np.einsum('nd,nd->n', r, np.linalg.solve(C, r.T).T))
    np.testing.assert_allclose(est.score_samples(X[:5]), dense, rtol=1e-5)


@pytest.mark.parametrize('kwargs,args,msg', [
    (dict(n_components=0), None, 'n_components'),
    (dict(n_components=2.5), None, 'n_components'),
    (dict(n_components=-1), None, 'n_components'),
    (dict(max_iter=0), None, 'max_iter'),
    (dict(init='bogus'), None, 'init'),
    (dict(n_components=True), None, 'n_components'),
    (dict(max_iter=True), None, 'max_iter'),
    (dict(tol='1e-5'), None, 'tol'),
    (dict(tol=0.0), None, 'tol'),
    (dict(tol=float('nan')), None, 'tol'),
    (dict(mean_prior_variance=None), None, 'mean_prior_variance'),
    (dict(mean_prior_variance='1'), None, 'mean_prior_variance'),
    (dict(mean_prior_variance=-1.0), None, 'mean_prior_variance'),
    (dict(min_noise_variance=-1e-4), None, 'min_noise_variance'),
    (dict(min_noise_variance=float('nan')), None, 'min_noise_variance'),
    (dict(min_noise_variance=float('inf')), None, 'min_noise_variance'),
    (dict(min_noise_variance=None), None, 'min_noise_variance'),
    (dict(min_noise_variance='1e-4'), None, 'min_noise_variance'),
    (dict(min_noise_variance=True), None, 'min_noise_variance'),
])
def test_parameter_validation(kwargs, args, msg):
    X, _, _ = planted(n=20, d=6)
    with pytest.raises(ValueError, match=msg):
        VBPCA(**kwargs).fit(X)


def test_input_validation():
    X, _, _ = planted(n=20, d=6)
    with pytest.raises(ValueError, match='2-D'):
        VBPCA(2).fit(X[0])
    with pytest.raises(ValueError, match='mask shape'):
        VBPCA(2).fit(X, mask=np.ones((20, 5), dtype=bool))
    Xn = X.copy()
    Xn[3, 2] = np.nan
    with pytest.raises(ValueError, match='NaN'):
        VBPCA(2).fit(Xn)
    M = np.ones_like(X, dtype=bool)
    with pytest.raises(ValueError, match='NaN'):
        VBPCA(2).fit(Xn, mask=M)
    M[3, 2] = False                      # the NaN is now hidden: accepted
    fit_quiet(VBPCA(2), Xn, mask=M)
    M[5] = False
    with pytest.raises(ValueError, match='at least one observed'):
        VBPCA(2).fit(X, mask=M)
    with pytest.raises(ValueError, match='2 samples'):
        VBPCA(2).fit(X[:1])


def test_convergence_warning():
    X, M = _missing_problem()
    with pytest.warns(ConvergenceWarning):
        est = VBPCA(RANK, max_iter=1).fit(X)
    assert not est.converged_ and est.n_iter_ == 1
    with pytest.warns(ConvergenceWarning):
        est = VBPCA(RANK, max_iter=1).fit(X, mask=M)
    assert not est.converged_
    with warnings.catch_warnings():
        warnings.simplefilter('error', ConvergenceWarning)
        assert VBPCA(RANK).fit(X).converged_


def test_sklearn_api():
    X, _, _ = planted(n=60, d=10)
    est = VBPCA(n_components=4, tol=1e-4)
    p = est.get_params()
    assert p['n_components'] == 4 and p['tol'] == 1e-4 and p['init'] == 'pca'
    assert est.set_params(n_components=RANK) is est and est.n_components == RANK
    c = clone(est)
    assert c is not est and c.get_params() == est.get_params()
    assert not hasattr(c, 'components_')
    assert est.fit(X) is est
    Z = est.fit_transform(X)
    assert Z.shape == (60, RANK)
    np.testing.assert_allclose(est.transform(X), Z, rtol=1e-6, atol=1e-6)
    assert est.inverse_transform(Z).shape == X.shape
    assert est.n_features_in_ == 10
    m, S = est.posterior(X[:4])
    assert m.shape == (4, RANK) and S.shape == (4, RANK, RANK)
    assert np.all(np.linalg.eigvalsh(S) > 0)
    with pytest.raises(ValueError, match='features'):
        est.transform(X[:, :5])
    from sklearn.exceptions import NotFittedError
    with pytest.raises(NotFittedError):
        clone(est).transform(X)


def test_random_init_also_recovers_subspace():
    X, Q, v = planted(n=150, d=20)
    est = fit_quiet(VBPCA(n_components=RANK, init='random', random_state=0, max_iter=500,
                          dtype=np.float64), X)
    assert principal_cosines(Q, est.components_.T).min() > 0.99


@pytest.mark.parametrize('k', [1, 3, 8])
def test_batched_cholesky_terms_matches_numpy(k):
    rng = np.random.default_rng(k)
    B = 7
    A = rng.standard_normal((B, k, k + 3))
    G = A @ A.swapaxes(1, 2) + 0.1 * np.eye(k)
    b = rng.standard_normal((B, k))
    quad, logdet, x = batched_cholesky_terms(G, b)
    xs = np.linalg.solve(G, b[..., None])[..., 0]
    np.testing.assert_allclose(x, xs, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(quad, np.einsum('bi,bi->b', b, xs), rtol=1e-8)
    sign, ld = np.linalg.slogdet(G)
    assert np.all(sign > 0)
    np.testing.assert_allclose(logdet, ld, rtol=1e-8, atol=1e-10)


def test_mean_does_not_collapse_into_the_loadings():
    # With a re-estimated prior variance on mu, mu used to shrink to zero over the iterations
    # while W absorbed the mean through a shared offset of the scores (seen on ModelNet bathtubs:
    # mu max 0.004 vs data mean max 0.55). The fixed broad prior keeps mu at the data mean.
    rng = np.random.default_rng(3)
    n, d = 60, 400
    base = (rng.random(d) < 0.3).astype(float)
    X = np.clip(base + 0.3 * rng.standard_normal((n, 2)) @ rng.standard_normal((2, d)), 0, 1)
    est = VBPCA(n_components=5, max_iter=300, tol=1e-9).fit(X)
    np.testing.assert_allclose(est.mean_, X.mean(axis=0), atol=0.02)
    assert np.linalg.norm(est.transform(X).mean(axis=0)) < 0.05


# ---------------------------------------------------------------- refused inputs (fit)
_DTYPE_MSG = 'dtype must be np.float32 or np.float64'
_PRUNE_MSG = 'prune_tol must be a number with 0 <= prune_tol < 1'


@pytest.mark.parametrize('kwargs,msg', [
    pytest.param(dict(dtype=np.int32), _DTYPE_MSG, id='dtype-int32'),     # truncated X to ints
    pytest.param(dict(dtype=np.float16), _DTYPE_MSG, id='dtype-float16'),  # overflowed to NaN
    pytest.param(dict(dtype=np.complex128), _DTYPE_MSG, id='dtype-complex128'),
    pytest.param(dict(dtype=int), _DTYPE_MSG, id='dtype-int'),
    pytest.param(dict(dtype='bogus'), _DTYPE_MSG, id='dtype-bogus-string'),
    pytest.param(dict(prune_tol=2.0), _PRUNE_MSG, id='prune_tol-2'),      # pruned every column
    pytest.param(dict(prune_tol=1.0), _PRUNE_MSG, id='prune_tol-1'),
    pytest.param(dict(prune_tol=-0.1), _PRUNE_MSG, id='prune_tol-negative'),
    pytest.param(dict(prune_tol=float('nan')), _PRUNE_MSG, id='prune_tol-nan'),
    pytest.param(dict(prune_tol=float('inf')), _PRUNE_MSG, id='prune_tol-inf'),
    pytest.param(dict(prune_tol='0.1'), _PRUNE_MSG, id='prune_tol-string'),
    pytest.param(dict(prune_tol=None), _PRUNE_MSG, id='prune_tol-None'),
    pytest.param(dict(prune_tol=True), _PRUNE_MSG, id='prune_tol-bool'),
])
def test_fit_refuses_bad_dtype_and_prune_tol(kwargs, msg):
    X, _, _ = planted(n=30, d=8)
    with pytest.raises(ValueError, match=msg):
        VBPCA(3, **kwargs).fit(X)


@pytest.mark.parametrize('kwargs', [dict(dtype='float64'), dict(dtype=np.dtype('float32')),
                                    dict(prune_tol=0), dict(prune_tol=np.float32(0.5))],
                         ids=['dtype-str', 'dtype-np.dtype', 'prune_tol-0', 'prune_tol-np.float32'])
def test_fit_accepts_valid_dtype_and_prune_tol(kwargs):
    X, _, _ = planted(n=30, d=8)
    est = VBPCA(3, **kwargs).fit(X)
    assert est.n_components_ >= 1 and np.isfinite(est.noise_variance_)


def test_fit_refuses_numerical_overflow():
    # finite in float32, but the float32 products overflow: the model used to come back with
    # noise_variance_ and mean_ of NaN and every component pruned
    # (the missing-data path runs in float64 and stays finite on this data)
    X, _, _ = planted(n=30, d=8)
    X = (X * 1e30).astype(np.float32)
    for mask in (None, np.ones(X.shape, dtype=bool)):      # an all-True mask: the full path
        with np.errstate(all='ignore'), pytest.raises(
                ValueError, match='non-finite.*rescale X or use dtype=np.float64'):
            VBPCA(3).fit(X, mask=mask)


def test_fit_names_values_beyond_float32_and_complex_data():
    # finite float64 values that the float32 cast turns into inf are not "NaN or Inf"
    X, _, _ = planted(n=30, d=8)
    for mask in (None, np.ones(X.shape, dtype=bool) & (np.arange(8) > 0)):
        with np.errstate(all='ignore'), pytest.raises(
                ValueError, match='beyond the range of float32; rescale X or use dtype'):
            VBPCA(3).fit(X * 1e39, mask=mask)
    with pytest.raises(ValueError, match='real numbers'):
        VBPCA(3).fit(X + 1j)
    with pytest.raises(ValueError, match='real numbers'):
        VBPCA(3).fit(X.astype(str))


@pytest.mark.parametrize('kind', ['complex', 'str', 'timedelta', 'datetime', 'object-str',
                                  'object-timedelta'])
def test_fit_and_queries_refuse_data_of_no_real_numbers(kind):
    # fit took timedelta64 (numpy counts it as an integer); transform, posterior and
    # score_samples cast complex (dropping the imaginary part), numeric strings and times to
    # float64 without a word
    X, _, _ = planted(n=30, d=8)
    bad = {'complex': X + 1j, 'str': X.astype(str), 'timedelta': X.astype('m8[s]'),
           'datetime': X.astype('M8[s]'), 'object-str': X.astype(str).astype(object),
           'object-timedelta': X.astype('m8[s]').astype(object)}[kind]
    est = fit_quiet(VBPCA(3), X)
    for method in (VBPCA(3).fit, est.transform, est.posterior, est.score_samples):
        with pytest.raises(ValueError, match='X must hold real numbers'):
            method(bad)
    # an object array of numbers is cast as before
    np.testing.assert_allclose(est.transform(X.astype(object)), est.transform(X))


def test_fit_refuses_no_features():
    with pytest.raises(ValueError, match='at least 1 feature'):
        VBPCA(2).fit(np.zeros((20, 0)))


def test_pure_noise_keeps_at_least_one_component():
    # pruning is relative to the largest ARD variance (prune_tol < 1), so zero components is not
    # a legitimate outcome of fit: it only ever came from NaN (refused above)
    X = np.random.default_rng(0).standard_normal((100, 20))
    est = fit_quiet(VBPCA(5), X)
    assert est.n_components_ >= 1 and np.isfinite(est.noise_variance_)


# ---------------------------------------------------------------- refused inputs (queries)
def _fitted_8():
    X = np.random.default_rng(0).normal(size=(30, 8))
    return fit_quiet(VBPCA(3), X), X


def _nan00(X):
    X = X.copy()
    X[0, 0] = np.nan
    return X


def _inf00(X):
    X = X.copy()
    X[0, 0] = -np.inf
    return X


_OBS = np.ones((30, 8), dtype=bool)
_QUERY_CASES = {
    # id: (X from the training X, mask or None, message)
    'nan-no-mask': (_nan00, None, 'NaN or Inf; pass a mask'),
    'inf-no-mask': (_inf00, None, 'NaN or Inf; pass a mask'),
    'nan-observed': (_nan00, _OBS, 'NaN or Inf in observed entries'),
    'inf-observed': (_inf00, _OBS.astype(np.uint8), 'NaN or Inf in observed entries'),
    'too-few-features': (lambda X: X[:, :5], None, 'X has 5 features, model has 8'),
    'too-many-features': (lambda X: np.hstack([X, X]), None, 'X has 16 features, model has 8'),
    'mask-wrong-columns': (lambda X: X, np.ones((30, 7), dtype=bool), r'mask shape \(30, 7\)'),
    'mask-wrong-rows': (lambda X: X, np.ones((29, 8), dtype=bool), r'mask shape \(29, 8\)'),
    'mask-flat': (lambda X: X, np.ones(240, dtype=bool), r'mask shape \(240,\)'),
    'mask-ragged': (lambda X: X, [[True] * 8] * 29 + [[True] * 7], 'mask must be a boolean'),
    'X-3d': (lambda X: X[None], None, r'2-D .*got shape \(1, 30, 8\)'),
    'X-1d': (lambda X: X[0], None, r'2-D .*got shape \(8,\).*reshape\(1, -1\)'),
    'X-0d': (lambda X: X[0, 0], None, '2-D'),
}


@pytest.mark.parametrize('method', ['transform', 'posterior', 'score_samples'])
@pytest.mark.parametrize('case', list(_QUERY_CASES))
def test_query_refuses_bad_input(method, case):
    est, X = _fitted_8()
    make, mask, msg = _QUERY_CASES[case]
    with pytest.raises(ValueError, match=msg):
        getattr(est, method)(make(X), mask=mask)


@pytest.mark.parametrize('method', ['transform', 'posterior', 'score_samples'])
def test_query_accepts_nan_where_hidden_and_castable_masks(method):
    est, X = _fitted_8()
    M = np.random.default_rng(1).random(X.shape) > 0.3
    ref = getattr(est, method)(X, mask=M)
    Xh = np.where(M, X, np.nan)
    Xh[0, ~M[0]] = np.inf
    for m in (M, M.astype(np.uint8), M.astype(np.float64), M.tolist()):
        out = getattr(est, method)(Xh, mask=m)
        for a, b in zip(np.atleast_1d(ref) if method != 'posterior' else ref,
                        np.atleast_1d(out) if method != 'posterior' else out):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('Z,msg', [
    pytest.param(np.zeros((4, 2)), r'Z must be \(n_samples, 3\).*\(4, 2\)', id='wrong-columns'),
    pytest.param(np.zeros((1, 4, 3)), r'Z must be \(n_samples, 3\)', id='3-D'),
    pytest.param(np.zeros(5), r'Z must be \(n_samples, 3\)', id='1-D-wrong-length'),
])
def test_inverse_transform_refuses_bad_scores(Z, msg):
    est, _ = _fitted_8()
    with pytest.raises(ValueError, match=msg):
        est.inverse_transform(Z)


@pytest.mark.parametrize('method', ['transform', 'posterior', 'score_samples',
                                    'inverse_transform'])
def test_query_requires_fitted_model(method):
    from sklearn.exceptions import NotFittedError
    with pytest.raises(NotFittedError, match='not fitted'):
        getattr(VBPCA(3), method)(np.zeros((2, 8)))


def test_fit_transform_uses_the_mask():
    # TransformerMixin.fit_transform passed the mask to fit only, not to transform
    rng = np.random.default_rng(0)
    X = rng.normal(size=(60, 3)) @ rng.normal(size=(3, 12)) + 0.05 * rng.normal(size=(60, 12))
    M = rng.random(X.shape) > 0.3
    Xn = np.where(M, X, np.nan)
    Z = VBPCA(5, random_state=0).fit_transform(Xn, mask=M)
    ref = VBPCA(5, random_state=0).fit(Xn, mask=M).transform(Xn, mask=M)
    np.testing.assert_allclose(Z, ref)
    np.testing.assert_allclose(VBPCA(5, random_state=0).fit_transform(X),
                               VBPCA(5, random_state=0).fit(X).transform(X))


def test_a_numerical_failure_of_the_fit_is_named():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(20, 8)) * 1e200
    with pytest.raises(ValueError, match='numerically'):
        VBPCA(3, dtype=np.float64).fit(X)


def test_full_and_missing_paths_agree_on_fully_observed_data():
    # the two paths are the same model: with every entry observed they reach the same fit
    # (each path's mean, noise and bound terms checked against the other's)
    X, _, _ = planted()
    a = VBPCA(RANK, dtype=np.float64, tol=1e-12, max_iter=3000).fit(X)
    b = VBPCA(RANK, dtype=np.float64, tol=1e-12, max_iter=3000)
    Xv, _ = b._validate(X, None)
    b._fit_missing(Xv, np.ones(X.shape, bool), RANK)
    assert a.converged_ and b.converged_
    np.testing.assert_allclose(b.noise_variance_, a.noise_variance_, rtol=1e-6)
    np.testing.assert_allclose(b.lower_bound_, a.lower_bound_, rtol=1e-6)
    np.testing.assert_allclose(b.mean_, a.mean_, atol=1e-4)
    np.testing.assert_allclose(b.mean_variance_, a.mean_variance_, rtol=1e-4)


def _posterior_case():
    """A fitted model with a non-trivial loadings' covariance, and explicit posterior terms."""
    X, _, _ = planted(n=60, d=12)
    est = VBPCA(RANK, dtype=np.float64).fit(X)
    k, d = est.n_components_, X.shape[1]
    est.loading_covariance_ = (0.05 * np.eye(k) + 0.02).astype(np.float32)
    W = est.components_.T.astype(np.float64)
    Sw = est.loading_covariance_.astype(np.float64)
    v = est.noise_variance_
    S = np.linalg.inv(np.eye(k) + (W.T @ W + d * Sw) / v)
    m = (X - est.mean_) @ W @ S / v
    return est, X, S, m


def test_posterior_includes_the_loading_covariance():
    est, X, S, m = _posterior_case()
    for mask in (None, np.ones(X.shape, bool)):
        got_m, got_S = est.posterior(X, mask=mask)
        np.testing.assert_allclose(got_m, m, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(got_S, np.broadcast_to(S, got_S.shape), rtol=1e-6, atol=1e-10)


def test_finish_keeps_the_posterior_of_the_unrotated_model():
    # _finish turns W to orthogonal columns; the rotated Sw must describe the same posterior
    rng = np.random.default_rng(3)
    d, k, v = 12, 3, 0.2
    W = rng.standard_normal((d, k)) @ np.array([[1.0, 0.6, 0.0], [0.0, 1.0, 0.4], [0.0, 0.0, 1.0]])
    A = rng.standard_normal((k, k))
    Sw = 0.01 * (A @ A.T + np.diag([1.0, 3.0, 0.5]))
    mu = rng.standard_normal(d)
    est = VBPCA(k, dtype=np.float64)
    est._finish(W, mu, v, np.ones(k), Sw, np.zeros(d, np.float32), 1, True, 0.0)
    X = rng.standard_normal((5, d))
    S = np.linalg.inv(np.eye(k) + (W.T @ W + d * Sw) / v)
    want = (X - mu) @ W @ S @ W.T / v + mu
    np.testing.assert_allclose(est.inverse_transform(est.transform(X)), want, atol=1e-5)
    np.testing.assert_allclose(est.component_variance_,
                               np.linalg.svd(W, compute_uv=False) ** 2 / d, rtol=1e-5)


@pytest.mark.parametrize('masked', [False, True], ids=['full', 'missing'])
def test_min_noise_variance_floors_the_noise_variance(masked):
    # a caller's modelling floor (class-model training's for occupancies): noise-free data fit
    # v at the numerical floor, far below it
    X, Q, _ = planted(noise=0.0)
    mask = np.random.default_rng(3).random(X.shape) > 0.2 if masked else None
    free = fit_quiet(VBPCA(n_components=RANK, dtype=np.float64), X, mask=mask)
    assert free.noise_variance_ < 1e-6
    est = fit_quiet(VBPCA(n_components=RANK, dtype=np.float64, min_noise_variance=1e-2), X,
                    mask=mask)
    assert est.noise_variance_ == 1e-2
    assert est.n_components_ == RANK
    assert principal_cosines(Q, est.components_.T).min() > 0.9999
    # above the data's own noise variance the floor does nothing
    X, _, v = planted(noise=0.3)
    ref = VBPCA(n_components=RANK, dtype=np.float64).fit(X, mask=mask)
    low = VBPCA(n_components=RANK, dtype=np.float64, min_noise_variance=1e-3 * v).fit(
        X, mask=mask)
    assert low.noise_variance_ == ref.noise_variance_
    np.testing.assert_array_equal(low.components_, ref.components_)


def _fit_at_scale(c, mask=None, **kw):
    """The planted problem fitted on c * X (mean prior scaled with it, as documented)."""
    X, Q, v = planted(n=120, d=30, noise=0.3, seed=1)
    return Q, fit_quiet(VBPCA(n_components=8, max_iter=500, dtype=np.float64,
                              mean_prior_variance=c * c, **kw), X * c, mask=mask)


@pytest.mark.parametrize('masked', [False, True], ids=['full', 'missing'])
@pytest.mark.parametrize('c', [1e-4, 1e-3, 1e-2, 1e2, 1e3])
def test_fit_is_equivariant_under_the_scale_of_the_data(c, masked):
    # the floors of the noise variance, the ARD variances and the initial noise variance were
    # absolute: in small units (1e-3) the fit started from 100 times the data's noise variance
    # and ended with other component variances, and at 1e-4 ARD collapsed every component
    mask = None
    if masked:
        mask = np.random.default_rng(3).random((120, 30)) > 0.2
    Q, ref = _fit_at_scale(1.0, mask)
    _, est = _fit_at_scale(c, mask)
    assert ref.n_components_ == RANK
    assert est.n_components_ == ref.n_components_
    assert principal_cosines(ref.components_.T, est.components_.T).min() > 0.9999
    np.testing.assert_allclose(est.noise_variance_ / c ** 2, ref.noise_variance_, rtol=5e-3)
    np.testing.assert_allclose(est.component_variance_ / c ** 2, ref.component_variance_,
                               rtol=5e-3)
    np.testing.assert_allclose(est.mean_ / c, ref.mean_, atol=0.05)


@pytest.mark.parametrize('masked', [False, True], ids=['full', 'missing'])
def test_collapsed_columns_do_not_count_even_with_prune_tol_0(masked):
    # exactly rank-3 data: ARD holds the 5 surplus columns at the floor of the variances, and
    # prune_tol=0 kept them as zero rows of components_ in n_components_ (8)
    X, Q, _ = planted(noise=0.0)
    mask = np.random.default_rng(3).random(X.shape) > 0.2 if masked else None
    est = fit_quiet(VBPCA(n_components=8, prune_tol=0, dtype=np.float64), X, mask=mask)
    assert est.n_components_ == RANK
    assert est.components_.shape == (RANK, X.shape[1])
    assert est.loading_covariance_.shape == (RANK, RANK)
    assert principal_cosines(Q, est.components_.T).min() > 0.999
    assert est.component_variance_.min() > 0.1


@pytest.mark.parametrize('masked', [False, True], ids=['full', 'missing'])
def test_converges_when_the_bound_is_near_zero(masked):
    # the bound shifts by -n d log c when X is scaled by c: at the scale where it is ~0, a change
    # relative to |bound| alone could not fall below tol and the fit ran to max_iter
    X, Q, _ = planted()
    mask = np.random.default_rng(3).random(X.shape) > 0.2 if masked else None
    n_obs = X.size if mask is None else mask.sum()
    ref = VBPCA(n_components=RANK, dtype=np.float64).fit(X, mask=mask)
    c = np.exp(ref.lower_bound_ / n_obs)
    est = VBPCA(n_components=RANK, dtype=np.float64, mean_prior_variance=c * c,
                max_iter=4 * ref.n_iter_)
    est = fit_quiet(est, X * c, mask=mask)
    assert abs(est.lower_bound_) < 1e-3 * abs(ref.lower_bound_)
    assert est.converged_
    assert principal_cosines(Q, est.components_.T).min() > 0.99


def test_float32_convergence_allows_for_the_rounding_of_the_bound():
    # noise-free data: v is tiny, and the float32 rounding of X^T Xm moves the bound by far more
    # than tol * |bound| every iteration, so the fit never met the test (or met it by chance)
    X, Q, _ = planted(noise=0.0)
    est = fit_quiet(VBPCA(n_components=RANK, dtype=np.float32, max_iter=100), X)
    assert est.converged_
    assert principal_cosines(Q, est.components_.T).min() > 0.9999
    assert est.noise_variance_ < 1e-4 * np.var(X)


# ---------------------------------------------------------------- mutation audit
@pytest.mark.parametrize('n,d', [(8, 20), (40, 6)], ids=['dual', 'primal'])
def test_pca_init_is_the_top_principal_subspace(n, d):
    # both eigen-decompositions (the (n, n) Gram for n < d, the (d, d) scatter otherwise) give
    # W = V_k s_k / sqrt(n) and the discarded variance per entry as the initial noise variance
    rng = np.random.default_rng(5)
    X = rng.normal(size=(n, 3)) @ rng.normal(size=(3, d)) * 3 + rng.normal(size=(n, d)) + 2
    k = 3
    Xc = X - X.mean(axis=0)
    _, s, Vt = np.linalg.svd(Xc, full_matrices=False)
    want = Vt[:k].T * (s[:k] / np.sqrt(n))
    mu, W, v, _ = VBPCA(k, dtype=np.float64)._init_params(X, None, k)
    np.testing.assert_allclose(mu, X.mean(axis=0))
    np.testing.assert_allclose(W @ W.T, want @ want.T, atol=1e-9)       # signs are free
    np.testing.assert_allclose(W.T @ W, np.diag(s[:k] ** 2 / n), atol=1e-9)
    np.testing.assert_allclose(v, (s[k:] ** 2).sum() / (n * d), rtol=1e-9)
    # the caller's floor of the noise variance holds from the start
    assert VBPCA(k, dtype=np.float64, min_noise_variance=50.0)._init_params(X, None, k)[2] == 50.0


def _brute_force_sq(X, M, W, Sw, Xm, Sx, mu, mu_var):
    """sum over observed (j, i) of E[(y_ji - w_i . x_j - mu_i)^2] under the factorised posterior;
    Sw (d, k, k), Sx (n, k, k), mu_var (d,)."""
    r = X - Xm @ W.T - mu
    var = (np.einsum('ia,jab,ib->ji', W, Sx, W) + np.einsum('ja,iab,jb->ji', Xm, Sw, Xm)
           + np.einsum('iab,jba->ji', Sw, Sx) + mu_var)
    return float((M * (r ** 2 + var)).sum())


@pytest.mark.parametrize('masked', [False, True], ids=['full', 'missing'])
def test_expected_squared_error_matches_brute_force(masked, monkeypatch):
    # the noise variance and the bound use sq, the expected squared error of the observed
    # entries, expanded into sufficient statistics: checked at every iteration against the
    # entry-by-entry expectation of the posterior passed to the bound
    X, _, _ = planted(n=40, d=9, seed=2)
    M = (np.random.default_rng(6).random(X.shape) > 0.3 if masked
         else np.ones(X.shape, bool))
    n, d = X.shape
    calls = []
    name = '_bound_missing' if masked else '_bound_full'
    orig = getattr(VBPCA, name)

    def spy(*args):
        calls.append(args)
        return orig(*args)

    monkeypatch.setattr(VBPCA, name, staticmethod(spy))
    fit_quiet(VBPCA(4, max_iter=6, init='random', random_state=0, dtype=np.float64), X,
              mask=M if masked else None)
    assert len(calls) == 6
    for args in calls:
        if masked:
            _, k, _, sq, Sx, Xm, Sw, W, _, mu, mu_var, _ = args
        else:
            _, _, k, _, sq, Sx, Xm, Sw, W, _, mu, mu_var, _ = args
            Sx, Sw = np.broadcast_to(Sx, (n, k, k)), np.broadcast_to(Sw, (d, k, k))
            mu_var = np.full(d, mu_var)
        np.testing.assert_allclose(sq, _brute_force_sq(X, M, W, Sw, Xm, Sx, mu, mu_var),
                                   rtol=1e-9)


@pytest.mark.parametrize('masked', [False, True], ids=['full', 'missing'])
def test_constant_data_keeps_one_collapsed_component(masked):
    # no variance: the floors fall back to unit variance (else v = 0), and ARD collapses every
    # column, of which the model still keeps one
    X = np.tile(np.arange(6.0), (10, 1))
    mask = np.random.default_rng(0).random(X.shape) > 0.2 if masked else None
    est = fit_quiet(VBPCA(3), X, mask=mask)
    assert est.n_components_ == 1 and est.components_.shape == (1, 6)
    assert 0 < est.noise_variance_ < 1e-6
    np.testing.assert_allclose(est.mean_, np.arange(6.0), atol=1e-6)
    assert np.isfinite(est.transform(X)).all()


def test_a_feature_never_observed_follows_the_mean_prior():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(40, 3)) @ rng.normal(size=(3, 10)) + 0.1 * rng.normal(size=(40, 10)) + 2
    M = rng.random(X.shape) > 0.2
    M[:, 4] = False
    est = VBPCA(5, dtype=np.float64, mean_prior_variance=2.0).fit(np.where(M, X, np.nan), mask=M)
    assert est.n_components_ == RANK and np.isfinite(est.noise_variance_)
    assert est.mean_[4] == 0 and est.mean_variance_[4] == 2.0
    assert np.isfinite(est.transform(np.where(M, X, np.nan), mask=M)).all()


def test_masked_posterior_counts_each_samples_observed_entries():
    est, X, _, _ = _posterior_case()
    M = np.random.default_rng(7).random(X.shape) > 0.4
    k = est.n_components_
    W = est.components_.T.astype(np.float64)
    Sw = est.loading_covariance_.astype(np.float64)
    v = est.noise_variance_
    got_m, got_S = est.posterior(np.where(M, X, np.nan), mask=M)
    for j in range(len(X)):
        o = M[j]
        S = np.linalg.inv(np.eye(k) + (W[o].T @ W[o] + o.sum() * Sw) / v)
        np.testing.assert_allclose(got_S[j], S, rtol=1e-6, atol=1e-10)
        np.testing.assert_allclose(got_m[j], S @ W[o].T @ (X[j, o] - est.mean_[o]) / v,
                                   rtol=1e-6, atol=1e-8)


def test_masked_score_samples_is_the_marginal_of_the_observed_entries():
    X, _, _ = planted(n=30, d=12)
    est = VBPCA(n_components=RANK, dtype=np.float64).fit(X)
    est.loading_covariance_ = np.zeros_like(est.loading_covariance_)
    M = np.random.default_rng(8).random(X.shape) > 0.3
    W = est.components_.T.astype(np.float64)
    want = []
    for j in range(len(X)):
        o = M[j]
        C = W[o] @ W[o].T + est.noise_variance_ * np.eye(o.sum())
        r = X[j, o] - est.mean_[o]
        want.append(-0.5 * (o.sum() * np.log(2 * np.pi) + np.linalg.slogdet(C)[1]
                            + r @ np.linalg.solve(C, r)))
    np.testing.assert_allclose(est.score_samples(np.where(M, X, np.nan), mask=M), want,
                               rtol=1e-6)


def test_fit_takes_bool_data_as_numbers_and_refuses_object_arrays():
    X = np.random.default_rng(0).random((30, 8)) > 0.5
    a = fit_quiet(VBPCA(3, dtype=np.float64), X)
    b = fit_quiet(VBPCA(3, dtype=np.float64), X.astype(np.float64))
    np.testing.assert_array_equal(a.components_, b.components_)
    # the query methods cast an object array of numbers; fit takes no object arrays
    with pytest.raises(ValueError, match='X must hold real numbers, got dtype object'):
        VBPCA(3).fit(X.astype(np.float64).astype(object))


@pytest.mark.parametrize('n,d', [(3, 10), (5, 40)])
def test_n_samples_give_at_most_n_minus_1_components(n, d):
    # centred, n samples span n - 1 dimensions: a random start with n columns kept n
    X = np.random.default_rng(0).normal(size=(n, d))
    est = fit_quiet(VBPCA(8, init='random', random_state=0, dtype=np.float64), X)
    assert est.n_components_ == n - 1
