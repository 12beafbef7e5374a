"""One class's VBPCA model (``ClassModel``), the residual noise it is fitted with, and the error
raised for a bad model (``ModelError``); shared by the bank, its classifier and its files."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class ModelError(ValueError):
    """A model directory or file is missing, corrupt or inconsistent."""


@dataclass
class ClassModel:
    """One class's VBPCA model, float32. W: (d, k); mean, mean_variance: (d,);
    coarse_noise_map: optional (d / 8,) noise variance per voxel of the 2x-pooled grid (used by
    the pose refinement; without it the scalar coarse_noise_variance is used everywhere)."""

    name: str
    W: np.ndarray
    mean: np.ndarray
    noise_variance: float
    coarse_noise_variance: float
    loading_covariance: np.ndarray
    mean_variance: np.ndarray
    component_variance: np.ndarray
    coarse_noise_map: np.ndarray | None = None

    @classmethod
    def from_vbpca(cls, name, est, coarse_noise_variance, coarse_noise_map=None):
        return cls(name=name, W=est.components_.T.astype(np.float32),
                   mean=est.mean_.astype(np.float32), noise_variance=float(est.noise_variance_),
                   coarse_noise_variance=float(coarse_noise_variance),
                   coarse_noise_map=None if coarse_noise_map is None else np.asarray(
                       coarse_noise_map, dtype=np.float32),
                   loading_covariance=est.loading_covariance_.astype(np.float32),
                   mean_variance=np.broadcast_to(est.mean_variance_, est.mean_.shape).astype(
                       np.float32),
                   component_variance=est.component_variance_.astype(np.float32))


def coarse_noise(X, est, n, shrink=100.0, floor=1e-4, min_noise_variance=0.0):
    """Residual variance of 2x-pooled training grids X (m, n^3) under the fitted model: the
    scalar over all voxels, and per pooled voxel (n^3 / 8,), shrunk toward the scalar as if
    ``shrink`` extra objects had the scalar variance (few objects: noisy voxel estimates).
    ``min_noise_variance``: the floor of the full-resolution model's noise variance; the
    scalar is at least min_noise_variance / 8, that of the mean of 8 voxels with independent
    noise of that variance (a few noise-free objects: no absurdly sure pose scores)."""
    from .inference import pool2
    Z = est.transform(X)
    R = (X - est.inverse_transform(Z)).T.reshape(n, n, n, -1)
    r2 = ((pool2(R) / 8.0) ** 2).reshape(-1, len(X))
    v = max(float(r2.mean()) + 1e-6, min_noise_variance / 8.0)
    m = r2.shape[1]
    per = (m * r2.mean(axis=1) + shrink * v) / (m + shrink)
    return v, np.maximum(per, floor).astype(np.float32)
