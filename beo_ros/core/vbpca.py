"""Variational Bayesian PCA (Bishop 1999; Ilin and Raiko, JMLR 2010).

Model, for a sample y (d,):  y = W x + mu + e,  x ~ N(0, I_k),  e ~ N(0, v I_d),
with priors  W[:, c] ~ N(0, alpha_c I_d)  (ARD: one variance per column, so surplus columns shrink
to zero) and  mu ~ N(0, v_mu I_d).  The posterior is factorised, q(X) q(W) q(mu); v and
alpha are point estimates maximising the variational bound. v_mu is a fixed, broad prior
(``mean_prior_variance``): re-estimating it lets mu collapse to zero while W absorbs the mean
through a shared offset of the scores, which biases completions towards empty space.

Two paths:
- fully observed data: every row of W shares one (k, k) covariance and every sample shares one,
  so an iteration is a few (n, d) x (d, k) products: seconds for a thousand 32^3 grids;
- missing data (``mask``): per-sample and per-row covariances, as in Ilin and Raiko section 3,
  plus, each iteration, the change of latent basis that the bound prefers (Ilin and Raiko's
  rotation, without their shift of the mean, which would change the likelihood): the fit is
  unchanged by it, and on a planted problem it converges in 50-80 iterations instead of 400-750.
"""
from __future__ import annotations

import datetime
import warnings

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.exceptions import ConvergenceWarning, NotFittedError

_EPS = 1e-10        # floor of the ARD variances, relative to the data's variance
_V_FLOOR = 1e-8     # floor of the noise variance, relative to the data's variance
_INIT_FLOOR = 1e-4  # floor of the initial noise variance, relative to the data's variance


class VBPCA(TransformerMixin, BaseEstimator):
    """Variational Bayesian PCA with ARD on the loading columns and optional missing data.

    Parameters:
        n_components: upper bound k on the number of components (ARD prunes the surplus).
        max_iter: maximum number of VB iterations.
        tol: stop when the change of the variational lower bound in one iteration falls below
            ``tol * max(|bound|, n_samples)`` (relative, or tol nats per sample for a bound
            near 0), or below the rounding error of the bound for dtype float32.
        prune_tol: a column whose ARD variance falls below ``prune_tol * max(alpha)`` is inactive;
            0 <= prune_tol < 1, so the column of largest variance is always kept. A column that
            ARD collapsed to the numerical floor of the variances is inactive for any prune_tol.
        init: 'pca' (SVD of the mean-imputed data) or 'random'.
        mean_prior_variance: variance v_mu of the Gaussian prior on mu (fixed), in squared units
            of X: every other quantity of the fit follows the scale of X (its numerical floors are
            relative to the data's variance), so fitting ``c * X`` with ``c**2 *
            mean_prior_variance`` (and ``c**2 * min_noise_variance``) gives the model of X scaled
            by c (the bound shifted by ``-n * d * log|c|``), up to the convergence tolerance.
        min_noise_variance: lower bound on v (>= 0, in squared units of X; 0: only the numerical
            floor). A modelling choice of the caller, e.g. for data known to be no more exact than
            some resolution: the bound is maximised over v >= min_noise_variance.
        random_state: seed for 'random' init.
        verbose: print the bound every iteration.
        dtype: np.float32 or np.float64, the dtype of the heavy products (float32 halves memory
            and time; use float64 for data of large magnitude).

    Attributes (after ``fit``):
        components_: (k_eff, d) posterior mean of W^T, columns ordered by decreasing variance.
        mean_: (d,) posterior mean of mu.
        noise_variance_: v.
        component_variance_: (k_eff,) ARD variances alpha of the kept columns.
        loading_covariance_: (k_eff, k_eff) shared posterior covariance of a row of W
            (fully observed path; for the missing path the average over rows).
        mean_variance_: (d,) posterior variance of mu.
        n_components_: k_eff, the number of columns ARD kept (collapsed ones never count).
        n_iter_, converged_, lower_bound_ (the bound at the last iteration).
    """

    def __init__(self, n_components=20, *, max_iter=200, tol=1e-5, prune_tol=1e-3, init='pca',
                 mean_prior_variance=1.0, min_noise_variance=0.0, random_state=None,
                 verbose=False, dtype=np.float32):
        self.n_components = n_components
        self.mean_prior_variance = mean_prior_variance
        self.min_noise_variance = min_noise_variance
        self.max_iter = max_iter
        self.tol = tol
        self.prune_tol = prune_tol
        self.init = init
        self.random_state = random_state
        self.verbose = verbose
        self.dtype = dtype

    # ------------------------------------------------------------------ validation
    def _validate(self, X, mask):
        for name in ('n_components', 'max_iter'):
            value = getattr(self, name)
            if (isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer))
                    or value < 1):
                raise ValueError(f'{name} must be a positive integer, got {value!r}')
        for name in ('tol', 'mean_prior_variance'):
            value = getattr(self, name)
            if (isinstance(value, (bool, np.bool_))
                    or not isinstance(value, (int, float, np.integer, np.floating))
                    or not (np.isfinite(value) and value > 0)):
                raise ValueError(f'{name} must be a finite number > 0, got {value!r}')
        mnv = self.min_noise_variance
        if (isinstance(mnv, (bool, np.bool_))
                or not isinstance(mnv, (int, float, np.integer, np.floating))
                or not (np.isfinite(mnv) and mnv >= 0)):
            raise ValueError(f'min_noise_variance must be a finite number >= 0, got {mnv!r}')
        if self.init not in ('pca', 'random'):
            raise ValueError(f"init must be 'pca' or 'random', got {self.init!r}")
        pt = self.prune_tol
        if (isinstance(pt, (bool, np.bool_)) or not isinstance(pt, (int, float, np.integer,
                                                                     np.floating))
                or not 0 <= pt < 1):
            raise ValueError(f'prune_tol must be a number with 0 <= prune_tol < 1, got {pt!r}')
        try:
            dt = np.dtype(self.dtype)
        except TypeError:
            dt = None
        if dt is None or dt.type not in (np.float32, np.float64):
            raise ValueError(f'dtype must be np.float32 or np.float64, got {self.dtype!r}')
        X = _real_array(X, 'X', objects=False)
        if X.ndim != 2:
            raise ValueError(f'X must be 2-D (n_samples, n_features), got shape {X.shape}')
        n, d = X.shape
        if n < 2:
            raise ValueError(f'VBPCA needs at least 2 samples, got {n}')
        if d < 1:
            raise ValueError(f'X needs at least 1 feature, got shape {X.shape}')
        X_in, X = X, X.astype(self.dtype, copy=False)
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != X.shape:
                raise ValueError(f'mask shape {mask.shape} differs from X shape {X.shape}')
            if mask.all():
                mask = None
        finite = np.isfinite(X) if mask is None else np.isfinite(np.where(mask, X, 0))
        if not finite.all():
            raw = np.asarray(X_in if mask is None else np.where(mask, X_in, 0))
            if np.issubdtype(raw.dtype, np.floating) and np.isfinite(raw).all():
                raise ValueError(f'X has values beyond the range of {np.dtype(self.dtype).name}; '
                                 'rescale X or use dtype=np.float64')
            raise ValueError('X has NaN or Inf in observed entries; mark them missing in mask')
        if mask is not None and (~mask.any(axis=1)).any():
            raise ValueError('every sample needs at least one observed entry')
        return X, mask

    # ------------------------------------------------------------------ fitting
    def fit(self, X, y=None, mask=None):
        """Fit on X (n, d). ``mask`` (n, d) bool: True where X is observed (None: all)."""
        X, mask = self._validate(X, mask)
        n, d = X.shape
        k = int(min(self.n_components, n - 1, d))
        try:
            if mask is None:
                self._fit_full(X, k)
            else:
                self._fit_missing(X, mask, k)
        except np.linalg.LinAlgError as e:   # e.g. values near the dtype's range
            raise ValueError(f'the fit failed numerically ({e}); rescale X') from None
        return self

    def fit_transform(self, X, y=None, mask=None):
        """``fit(X, mask=mask).transform(X, mask=mask)``: posterior mean scores (n, k)
        (TransformerMixin's would drop the mask)."""
        return self.fit(X, mask=mask).transform(X, mask=mask)

    def _init_params(self, X, mask, k):
        n, d = X.shape
        if mask is None:
            mu = X.mean(axis=0)
            Xc = X - mu
        else:
            cnt = np.maximum(mask.sum(axis=0), 1)
            mu = np.where(mask, X, 0).sum(axis=0) / cnt
            Xc = np.where(mask, X - mu, 0)
        # the data's variance per entry (1 for constant data): the unit of the numerical floors,
        # which in absolute units pruned every component of data in small units
        s2 = (float(Xc.var(dtype=np.float64)) if mask is None
              else float(np.square(Xc, dtype=np.float64).sum() / mask.sum()))
        s2 = s2 if np.isfinite(s2) and s2 > 0 else 1.0
        if self.init == 'pca':
            # eigen-decomposition in the smaller dimension: the dual (n, n) Gram for n << d
            if n < d:
                e, U = np.linalg.eigh((Xc @ Xc.T).astype(np.float64))
                e, U = e[::-1], U[:, ::-1]
                W = (Xc.T @ U[:, :k].astype(self.dtype)) / np.sqrt(n)
            else:
                Xc64 = Xc.astype(np.float64)
                e, V = np.linalg.eigh(Xc64.T @ Xc64)
                e, V = e[::-1], V[:, ::-1]
                W = V[:, :k] * np.sqrt(np.maximum(e[:k], 0) / n)
            W = W.astype(self.dtype)
            resid = max(np.maximum(e[k:], 0).sum() / (n * d), _INIT_FLOOR * s2)
        else:
            rng = np.random.default_rng(self.random_state)
            W = (rng.standard_normal((d, k)) * Xc.std() / np.sqrt(k)).astype(self.dtype)
            resid = float(Xc.var()) + _INIT_FLOOR * s2
        return mu.astype(self.dtype), W, max(float(resid), float(self.min_noise_variance)), s2

    def _fit_full(self, X, k):
        # Only two (n, d) x (d, k) products per iteration: every other term is expanded into
        # sufficient statistics, so no (n, d) temporary is ever formed.
        n, d = X.shape
        mu, W, v, s2 = self._init_params(X, None, k)
        a_floor, v_floor = _EPS * s2, max(_V_FLOOR * s2, float(self.min_noise_variance))
        mu = mu.astype(np.float64)
        col_sum = X.sum(axis=0, dtype=np.float64)                # (d,)
        sq_total = float(np.einsum('ij,ij->', X, X, dtype=np.float64))
        alpha = np.maximum((W.astype(np.float64) ** 2).sum(axis=0) / d, a_floor)
        v_mu = float(self.mean_prior_variance)
        Sw = np.zeros((k, k))
        mu_var = 0.0
        prev = -np.inf
        converged = False
        bound = np.nan
        eps = float(np.finfo(self.dtype).eps)
        for it in range(1, self.max_iter + 1):
            W64 = W.astype(np.float64)
            # q(X): shared covariance
            Sx = np.linalg.inv(np.eye(k) + (W64.T @ W64 + d * Sw) / v)
            B = (X @ W).astype(np.float64) - mu @ W64              # (n, k) = (Y - mu) W
            Xm = B @ Sx / v                                         # (n, k) posterior means
            # q(W): shared row covariance
            XX = Xm.T @ Xm
            Sw = np.linalg.inv(np.diag(1.0 / alpha) + (XX + n * Sx) / v)
            xs = Xm.sum(axis=0)
            XtXm = (X.T @ Xm.astype(self.dtype)).astype(np.float64)        # (d, k)
            W64 = (XtXm - np.outer(mu, xs)) @ Sw / v                        # (d, k)
            # q(mu)
            mu_var = 1.0 / (n / v + 1.0 / v_mu)
            mu = mu_var / v * (col_sum - W64 @ xs)
            # expected squared error, expanded: ||Y - mu - X W^T||^2 + uncertainty terms
            WtW = W64.T @ W64
            cross = float(np.einsum('ik,ik->', XtXm, W64)) - (mu @ W64) @ xs
            sq = (sq_total - 2 * mu @ col_sum + n * mu @ mu - 2 * cross + np.trace(XX @ WtW))
            sq += n * np.trace(WtW @ Sx) + d * np.trace(Sw @ XX)
            sq += n * d * np.trace(Sw @ Sx) + n * d * mu_var
            v = max(sq / (n * d), v_floor)
            if not np.isfinite(v):          # overflow: stop early, _finish raises
                break
            alpha = np.maximum((np.diag(WtW) + d * np.diag(Sw)) / d, a_floor)
            W = W64.astype(self.dtype)
            bound = self._bound_full(n, d, k, v, sq, Sx, Xm, Sw, W64, alpha, mu, mu_var, v_mu)
            if self.verbose:
                print(f'VBPCA iter {it}: bound {bound:.8g} v {v:.5g}')
            # X^T Xm is rounded to the dtype: the bound's error is about eps * |cross| / v (in
            # float32 often above tol * |bound|, and the test was then met only by chance)
            noise = 2 * eps * abs(cross) / v
            if np.isfinite(prev) and self._small_change(bound, prev, n, noise):
                converged = True
                break
            prev = bound
        self._finish(W, mu, v, alpha, Sw, np.full(d, mu_var, dtype=np.float32), it, converged,
                     bound, a_floor)

    def _small_change(self, bound, prev, n, noise=0.0):
        # relative to |bound| alone the test could not be met by a bound near 0 (its value
        # depends on the units of X: c * X shifts it by -n d log c); ``noise``: the bound's
        # rounding error
        return abs(bound - prev) <= max(self.tol * max(abs(bound), n), noise)

    @staticmethod
    def _bound_full(n, d, k, v, sq, Sx, Xm, Sw, W, alpha, mu, mu_var, v_mu):
        """Variational lower bound of log p(Y) for the fully observed path."""
        ll = -0.5 * n * d * np.log(2 * np.pi * v) - 0.5 * sq / v
        _, ldx = np.linalg.slogdet(Sx)
        kl_x = 0.5 * ((Xm ** 2).sum() + n * np.trace(Sx) - n * k - n * ldx)
        _, ldw = np.linalg.slogdet(Sw)
        kl_w = 0.5 * (((W ** 2).sum(axis=0) / alpha).sum() + d * (np.diag(Sw) / alpha).sum()
                      - d * k - d * ldw + d * np.log(alpha).sum())
        kl_mu = 0.5 * (float((mu.astype(np.float64) ** 2).sum()) / v_mu + d * mu_var / v_mu - d
                       - d * np.log(mu_var / v_mu))
        return float(ll - kl_x - kl_w - kl_mu)

    def _fit_missing(self, X, mask, k):
        n, d = X.shape
        mu, W, v, s2 = self._init_params(X, mask, k)
        a_floor, v_floor = _EPS * s2, max(_V_FLOOR * s2, float(self.min_noise_variance))
        W = W.astype(np.float64)
        mu = mu.astype(np.float64)
        M = mask.astype(np.float64)
        Xo = np.where(mask, X, 0).astype(np.float64)
        alpha = np.maximum((W ** 2).sum(axis=0) / d, a_floor)
        v_mu = float(self.mean_prior_variance)
        Sw = np.zeros((d, k, k))
        mu_var = np.zeros(d)
        iu = np.triu_indices(k)
        n_obs = M.sum()
        converged = False
        prev = -np.inf
        bound = np.nan
        for it in range(1, self.max_iter + 1):
            # q(x_j): Sx_j = (I + sum_{i in O_j} <w_i w_i^T> / v)^-1
            ww = (W[:, :, None] * W[:, None, :] + Sw)[:, iu[0], iu[1]]     # (d, k(k+1)/2)
            G = np.zeros((n, k, k))
            G[:, iu[0], iu[1]] = M @ ww
            G = G + np.triu(G, 1).transpose(0, 2, 1)
            Sx = np.linalg.inv(np.eye(k) + G / v)                           # (n, k, k)
            R0 = (Xo - M * mu)                                              # observed residual
            Xm = np.einsum('nab,nb->na', Sx, R0 @ W) / v                    # (n, k)
            # q(w_i): Sw_i = (diag(1/alpha) + sum_{j in O_i} <x_j x_j^T> / v)^-1
            xx = (Xm[:, :, None] * Xm[:, None, :] + Sx)[:, iu[0], iu[1]]   # (n, k(k+1)/2)
            H = np.zeros((d, k, k))
            H[:, iu[0], iu[1]] = M.T @ xx
            H = H + np.triu(H, 1).transpose(0, 2, 1)
            Sw = np.linalg.inv(np.diag(1.0 / alpha) + H / v)                # (d, k, k)
            W = np.einsum('iab,ib->ia', Sw, R0.T @ Xm) / v
            # q(mu_i)
            mu_var = 1.0 / (M.sum(axis=0) / v + 1.0 / v_mu)
            mu = mu_var / v * (M * (Xo - Xm @ W.T)).sum(axis=0)
            # noise variance over observed entries
            R = M * (Xo - Xm @ W.T - mu)
            sq = (R ** 2).sum()
            ww = (W[:, :, None] * W[:, None, :] + Sw)[:, iu[0], iu[1]]
            sx_flat = Sx[:, iu[0], iu[1]]
            sym = np.where(iu[0] == iu[1], 1.0, 2.0)
            sq += ((M @ ww) * sx_flat * sym).sum()                          # tr(<ww> Sx_j)
            xs = Xm[:, :, None] * Xm[:, None, :]
            sq += ((M.T @ xs[:, iu[0], iu[1]]) * Sw[:, iu[0], iu[1]] * sym).sum()
            sq += (M * mu_var).sum()
            v = max(sq / n_obs, v_floor)
            if not np.isfinite(v):          # overflow: stop early, _finish raises
                break
            # without this step the bound creeps for hundreds of iterations along directions
            # (scale and rotation of the scores) that barely change the fit (Ilin and Raiko 2010)
            W, Sw, Xm, Sx = _rotate_to_pca(W, Sw, Xm, Sx)
            alpha = np.maximum(((W ** 2).sum(axis=0) + Sw[:, range(k), range(k)].sum(axis=0)) / d,
                               a_floor)
            bound = self._bound_missing(n_obs, k, v, sq, Sx, Xm, Sw, W, alpha, mu, mu_var, v_mu)
            if self.verbose:
                print(f'VBPCA(missing) iter {it}: bound {bound:.8g} v {v:.5g}')
            if np.isfinite(prev) and self._small_change(bound, prev, n):
                converged = True
                break
            prev = bound
        self._finish(W.astype(self.dtype), mu.astype(self.dtype), v, alpha, Sw.mean(axis=0),
                     mu_var.astype(np.float32), it, converged, bound, a_floor)

    @staticmethod
    def _bound_missing(n_obs, k, v, sq, Sx, Xm, Sw, W, alpha, mu, mu_var, v_mu):
        """Variational lower bound of log p(observed Y) for the missing-data path.

        Sx: (n, k, k) and Sw: (d, k, k), one posterior covariance per row of X and of W.
        """
        n, d = Xm.shape[0], W.shape[0]
        ll = -0.5 * n_obs * np.log(2 * np.pi * v) - 0.5 * sq / v
        _, ldx = np.linalg.slogdet(Sx)
        kl_x = 0.5 * ((Xm ** 2).sum() + np.trace(Sx, axis1=1, axis2=2).sum() - n * k - ldx.sum())
        _, ldw = np.linalg.slogdet(Sw)
        sw_diag = Sw[:, range(k), range(k)].sum(axis=0)
        kl_w = 0.5 * ((((W ** 2).sum(axis=0) + sw_diag) / alpha).sum() - d * k - ldw.sum()
                      + d * np.log(alpha).sum())
        kl_mu = 0.5 * (((mu ** 2 + mu_var) / v_mu).sum() - d - np.log(mu_var / v_mu).sum())
        return float(ll - kl_x - kl_w - kl_mu)

    def _finish(self, W, mu, v, alpha, Sw, mu_var, n_iter, converged, bound, a_floor=0.0):
        # overflow (e.g. float32 products of data of large magnitude) turns the whole model into
        # NaN, and NaN ARD variances would then silently prune every column: refuse it
        if not (np.isfinite(v) and np.isfinite(mu).all() and np.isfinite(W).all()
                and np.isfinite(alpha).all() and np.isfinite(Sw).all()):
            hint = (' or use dtype=np.float64' if np.dtype(self.dtype).type is not np.float64
                    else '')
            raise ValueError('VBPCA fit produced non-finite noise variance, mean or loadings '
                             f'(numerical overflow): rescale X{hint}')
        if not converged:
            warnings.warn(f'VBPCA did not converge in {n_iter} iterations; raise max_iter or tol',
                          ConvergenceWarning)
        W64 = np.asarray(W, dtype=np.float64)
        # a column at the floor is collapsed (prune_tol=0 kept it, as zeros in components_)
        keep = (alpha > self.prune_tol * alpha.max()) & (alpha > a_floor)
        keep[np.argmax(alpha)] = True   # all collapsed: the model still has one column
        # order kept columns by the variance they explain
        order = np.argsort(-(W64 ** 2).sum(axis=0))
        order = order[keep[order]]
        # rotate the kept subspace to orthogonal columns (principal axes), as PCA reports them
        Wk = W64[:, order]
        U, s, Vt = np.linalg.svd(Wk, full_matrices=False)
        Wrot = U * s
        self.components_ = Wrot.T.astype(np.float32)
        self.mean_ = np.asarray(mu, dtype=np.float32)
        self.noise_variance_ = float(v)
        self.component_variance_ = (s ** 2 / W64.shape[0]).astype(np.float32)
        Swk = Sw[np.ix_(order, order)]
        self.loading_covariance_ = (Vt @ Swk @ Vt.T).astype(np.float32)
        self.mean_variance_ = np.asarray(mu_var, dtype=np.float32)
        self.n_components_ = int(len(order))
        self.n_iter_ = int(n_iter)
        self.converged_ = bool(converged)
        self.lower_bound_ = float(bound)
        self.n_features_in_ = W64.shape[0]

    # ------------------------------------------------------------------ queries
    def _check_fitted(self):
        if not hasattr(self, 'components_'):
            raise NotFittedError(f'This {type(self).__name__} instance is not fitted yet. Call '
                                 "'fit' with appropriate arguments before using this estimator.")

    def _check_query(self, X, mask):
        """Validated (X float64 (n, d), mask bool (n, d) or None) for the query methods.

        ``mask`` is True where X is observed; NaN or Inf is allowed only where it is False.
        Cheap on the hot path: one ``isfinite`` pass over X when X is all finite.
        """
        self._check_fitted()
        X = np.asarray(_real_array(X, 'X'), dtype=np.float64)
        if X.ndim != 2:
            hint = '; use X.reshape(1, -1) for a single sample' if X.ndim == 1 else ''
            raise ValueError(f'X must be 2-D (n_samples, n_features), got shape {X.shape}{hint}')
        if X.shape[1] != self.n_features_in_:
            raise ValueError(f'X has {X.shape[1]} features, model has {self.n_features_in_}')
        if mask is not None:
            try:
                mask = np.asarray(mask, dtype=bool)
            except (TypeError, ValueError) as e:
                raise ValueError(f'mask must be a boolean array of X shape {X.shape}: '
                                 f'{e}') from None
            if mask.shape != X.shape:
                raise ValueError(f'mask shape {mask.shape} differs from X shape {X.shape}')
        if not np.isfinite(X).all():
            if mask is None:
                raise ValueError('X has NaN or Inf; pass a mask (True where observed) to mark '
                                 'them missing')
            if (mask & ~np.isfinite(X)).any():
                raise ValueError('X has NaN or Inf in observed entries; mark them missing in mask')
        return X, mask

    def transform(self, X, mask=None):
        """Posterior mean of the scores (n, k_eff), using only observed entries when masked."""
        return self._posterior(*self._check_query(X, mask))[0]

    def posterior(self, X, mask=None):
        """Posterior of the scores: means (n, k_eff) and covariances (n, k_eff, k_eff)."""
        return self._posterior(*self._check_query(X, mask))

    def _posterior(self, X, mask):
        W = self.components_.T.astype(np.float64)
        v = self.noise_variance_
        k = W.shape[1]
        Sw = self.loading_covariance_.astype(np.float64)
        if mask is None:
            # fully observed: one shared covariance
            S1 = np.linalg.inv(np.eye(k) + (W.T @ W + X.shape[1] * Sw) / v)
            m = (X - self.mean_) @ W @ S1 / v
            return m, np.broadcast_to(S1, (len(X), k, k))
        M = mask.astype(np.float64)
        R = M * (np.nan_to_num(X) - self.mean_)
        G = np.einsum('nd,da,db->nab', M, W, W) + M.sum(axis=1)[:, None, None] * Sw
        S = np.linalg.inv(np.eye(k) + G / v)
        m = np.einsum('nab,nb->na', S, R @ W) / v
        return m, S

    def inverse_transform(self, Z):
        """Reconstruction W z + mu, (n, d), from scores (n, k_eff)."""
        self._check_fitted()
        Z = np.asarray(Z)
        if Z.ndim not in (1, 2) or Z.shape[-1] != self.n_components_:
            raise ValueError(f'Z must be (n_samples, {self.n_components_}) scores, got shape '
                             f'{Z.shape}')
        return Z @ self.components_ + self.mean_

    def score_samples(self, X, mask=None):
        """Log-likelihood (n,) of each sample's observed entries y_O, with the scores integrated
        out under their variational posterior (the loadings' posterior covariance enters through
        E[W^T W]): the exact marginal p(y_O | W, mu, v) when ``loading_covariance_`` is zero,
        an approximation of it otherwise."""
        X, mask = self._check_query(X, mask)
        W = self.components_.T.astype(np.float64)
        v = self.noise_variance_
        M = np.ones_like(X) if mask is None else mask.astype(np.float64)
        R = M * (np.nan_to_num(X) - self.mean_)
        m, S = self._posterior(X, mask)
        nobs = M.sum(axis=1)
        # Woodbury: r^T C^-1 r = r^T r / v - b^T S b / v^2, log|C| = nobs log v - log|S|
        quad = (R ** 2).sum(axis=1) / v - np.einsum('na,na->n', m, R @ W) / v
        _, lds = np.linalg.slogdet(S)
        return -0.5 * (nobs * np.log(2 * np.pi * v) - lds + quad)


def _real_array(X, name, objects=True):
    """``X`` as an array of real numbers (bool, integer or float dtype; with ``objects`` also
    an object array, cast to float64 as the query methods did); ValueError for complex
    numbers, strings, bytes and times (numpy counts timedelta64 as an integer: its values
    became numbers of its unit)."""
    X = np.asarray(X)
    if X.dtype.kind == 'O' and objects:
        # the cast would parse strings such as '1.5' and take timedelta64 as numbers
        bad = next((v for v in X.flat if isinstance(v, _NOT_REAL)), None)
        if bad is not None:
            raise ValueError(f'{name} must hold real numbers, got {type(bad).__name__} '
                             f'{bad!r}')
        return X.astype(np.float64)
    if X.dtype.kind not in 'biuf':
        raise ValueError(f'{name} must hold real numbers, got dtype {X.dtype}')
    return X


_NOT_REAL = (str, bytes, complex, np.complexfloating, np.timedelta64, np.datetime64,
             datetime.timedelta, datetime.date)


def _rotate_to_pca(W, Sw, Xm, Sx):
    """The linear change of latent basis x -> R x, W -> W R^-1 that maximises the bound.

    W: (d, k), Sw: (d, k, k), Xm: (n, k), Sx: (n, k, k). The expected likelihood is invariant
    under it (W x and every variance term are), and of the priors' terms, with the ARD variances
    re-estimated after it, the best R whitens the scores' second moment and then turns W to
    orthogonal columns (Hadamard's inequality). Returns the new (W, Sw, Xm, Sx).
    """
    n, d = Xm.shape[0], W.shape[0]
    D, VS = np.linalg.eigh((Xm.T @ Xm + Sx.sum(axis=0)) / n)
    D = np.maximum(D, 1e-12)
    RA = VS * np.sqrt(D)
    W = W @ RA
    Sw = np.einsum('ab,ibc,cd->iad', RA.T, Sw, RA, optimize=True)
    _, VA = np.linalg.eigh((W.T @ W + Sw.sum(axis=0)) / d)
    VA = VA[:, ::-1]
    W = W @ VA
    Sw = np.einsum('ab,ibc,cd->iad', VA.T, Sw, VA, optimize=True)
    R = VA.T @ (VS / np.sqrt(D)).T
    Xm = Xm @ R.T
    Sx = np.einsum('ab,jbc,dc->jad', R, Sx, R, optimize=True)
    return W, Sw, Xm, Sx
