"""Fréchet distance between Gaussians fitted to feature sets (FID's formula; FRID / FPVD of LiDM).

    FD = |μ_a - μ_b|² + tr Σ_a + tr Σ_b - 2 tr (Σ_a^{1/2} Σ_b Σ_a^{1/2})^{1/2}

The usual code (pytorch-fid) takes ``scipy.linalg.sqrtm(Σ_a Σ_b)``: a non-symmetric product
whose square root goes complex, or fails, when the covariances are singular — which they are
whenever there are fewer samples than feature dimensions, the normal case for LiDAR sets of
a few dozen scans. Here every square root is of a symmetric positive semi-definite matrix,
taken by its eigendecomposition with the eigenvalues that round-off pushed below zero
clipped to 0: ``M^{1/2} = V diag(sqrt(max(λ, 0))) Vᵀ``. ``tr (Σ_a^{1/2} Σ_b Σ_a^{1/2})^{1/2}``
equals pytorch-fid's ``tr sqrtm(Σ_a Σ_b)`` (the two matrices are similar), so the numbers
agree with the published formula wherever that one is defined; everything is float64.
"""
from __future__ import annotations

import numpy as np

from typ.errors import TypError

__all__ = ["frechet_distance", "frechet_from_features", "gaussian_stats", "sqrtm_psd"]

WHERE = "frechet_distance"


def _symmetric(m, field: str) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] == 0:
        raise TypError(WHERE, field, "a non-empty square matrix", getattr(a, "shape", a))
    if not np.isfinite(a).all():
        raise TypError(WHERE, field, "finite entries (no NaN/Inf)", "non-finite entries")
    scale = max(np.abs(a).max(), 1e-300)
    if np.abs(a - a.T).max() > 1e-8 * scale:
        raise TypError(WHERE, field, "a symmetric covariance matrix", f"max |M - Mᵀ| = {np.abs(a - a.T).max():.3g}")
    return (a + a.T) / 2.0


def sqrtm_psd(m) -> np.ndarray:
    """Square root of a symmetric positive semi-definite matrix, float64, symmetric PSD itself.

    Eigenvalues below 0 (round-off of a singular covariance) are clipped to 0; a matrix with
    a clearly negative eigenvalue (below -1e-8 of the largest magnitude) is not a covariance
    and raises TypError.
    """
    a = _symmetric(m, "matrix")
    lam, vec = np.linalg.eigh(a)
    top = max(np.abs(lam).max(), 1e-300)
    if lam.min() < -1e-8 * top:
        raise TypError(WHERE, "matrix", "a positive semi-definite matrix", f"eigenvalue {lam.min():.3g}")
    root = (vec * np.sqrt(np.clip(lam, 0.0, None))) @ vec.T
    return (root + root.T) / 2.0


def gaussian_stats(features) -> tuple[np.ndarray, np.ndarray]:
    """(N, D) features -> mean (D,) and covariance (D, D) with N - 1 in the denominator
    (numpy's ``cov``, as pytorch-fid); N >= 2."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 2 or f.shape[1] < 1:
        raise TypError(WHERE, "features", "an (N >= 2, D >= 1) array", getattr(f, "shape", f))
    if not np.isfinite(f).all():
        raise TypError(WHERE, "features", "finite features (no NaN/Inf)", "non-finite entries")
    return f.mean(axis=0), np.atleast_2d(np.cov(f, rowvar=False))


def frechet_distance(mu_a, sigma_a, mu_b, sigma_b) -> float:
    """Fréchet distance between N(mu_a, sigma_a) and N(mu_b, sigma_b) (see the module doc); >= 0."""
    mu_a, mu_b = np.asarray(mu_a, dtype=np.float64), np.asarray(mu_b, dtype=np.float64)
    sa, sb = _symmetric(sigma_a, "sigma_a"), _symmetric(sigma_b, "sigma_b")
    d = sa.shape[0]
    if mu_a.shape != (d,) or mu_b.shape != (d,) or sb.shape != (d, d):
        raise TypError(WHERE, "shapes", f"means ({d},) and covariances ({d}, {d})",
                       [mu_a.shape, sa.shape, mu_b.shape, sb.shape])
    if not (np.isfinite(mu_a).all() and np.isfinite(mu_b).all()):
        raise TypError(WHERE, "mu", "finite means", "non-finite entries")
    root_a = sqrtm_psd(sa)
    inner = root_a @ sb @ root_a
    lam = np.linalg.eigvalsh((inner + inner.T) / 2.0)
    cross = np.sqrt(np.clip(lam, 0.0, None)).sum()
    diff = mu_a - mu_b
    value = float(diff @ diff + np.trace(sa) + np.trace(sb) - 2.0 * cross)
    # the exact value is >= 0; round-off can leave -1e-12 when the two sets coincide
    return max(value, 0.0)


def frechet_from_features(a, b) -> float:
    """Fréchet distance between Gaussians fitted to feature sets a (N_a, D) and b (N_b, D)."""
    return frechet_distance(*gaussian_stats(a), *gaussian_stats(b))
