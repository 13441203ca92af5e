"""Fréchet distance: the PSD square root against scipy, the formula against closed forms and
pytorch-fid's way of computing it, and singular covariances (fewer samples than dimensions)."""
import numpy as np
import pytest
import scipy.linalg

from typ.errors import TypError
from typ.metrics.frechet import frechet_distance, frechet_from_features, gaussian_stats, sqrtm_psd


def _spd(rng, d, rank=None):
    a = rng.standard_normal((d, rank or d))
    return a @ a.T + (0 if rank else 0.1 * np.eye(d))


def _fid_reference(mu1, s1, mu2, s2):
    """pytorch-fid's calculate_frechet_distance (scipy sqrtm of the product), for full-rank inputs."""
    covmean = scipy.linalg.sqrtm(s1 @ s2)
    covmean = covmean.real
    diff = mu1 - mu2
    return diff @ diff + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean)


@pytest.mark.parametrize("d", [1, 3, 16, 64])
def test_sqrtm_psd_matches_scipy_on_spd_matrices(d):
    m = _spd(np.random.default_rng(d), d)
    root = sqrtm_psd(m)
    np.testing.assert_allclose(root, scipy.linalg.sqrtm(m).real, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(root @ root, m, rtol=1e-9, atol=1e-9)
    assert np.allclose(root, root.T)


def test_sqrtm_psd_clips_round_off_negative_eigenvalues():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.standard_normal((8, 8)))
    lam = np.array([4.0, 2.0, 1.0, 0.5, 0.0, 0.0, -1e-15, -3e-14])  # what round-off does to a rank-6 covariance
    m = (q * lam) @ q.T
    root = sqrtm_psd(m)
    assert np.isfinite(root).all() and np.linalg.eigvalsh(root).min() > -1e-12
    np.testing.assert_allclose(root @ root, (q * np.clip(lam, 0, None)) @ q.T, atol=1e-12)
    # scipy's general sqrtm returns a complex (or inaccurate) root of the same matrix
    assert np.iscomplexobj(scipy.linalg.sqrtm(m)) or not np.allclose(scipy.linalg.sqrtm(m) @ scipy.linalg.sqrtm(m), m)


def test_not_a_covariance_is_named():
    with pytest.raises(TypError, match="positive semi-definite"):
        sqrtm_psd(np.diag([1.0, -1.0]))
    with pytest.raises(TypError, match="symmetric"):
        sqrtm_psd(np.array([[1.0, 2.0], [0.0, 1.0]]))
    with pytest.raises(TypError, match="features"):
        gaussian_stats(np.ones((1, 4)))
    with pytest.raises(TypError, match="shapes"):
        frechet_distance(np.zeros(3), np.eye(3), np.zeros(2), np.eye(2))


@pytest.mark.parametrize("d", [2, 8, 32])
def test_frechet_matches_the_pytorch_fid_formula_on_full_rank_inputs(d):
    rng = np.random.default_rng(100 + d)
    mu1, mu2 = rng.standard_normal(d), rng.standard_normal(d)
    s1, s2 = _spd(rng, d), _spd(rng, d)
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(_fid_reference(mu1, s1, mu2, s2), rel=1e-9)


def test_closed_forms():
    # 1-D: (mu1 - mu2)^2 + (sigma1 - sigma2)^2
    assert frechet_distance([1.0], [[4.0]], [3.0], [[9.0]]) == pytest.approx(4.0 + 1.0)
    # commuting (diagonal) covariances: sum (sqrt a - sqrt b)^2
    a, b = np.array([1.0, 4.0, 9.0, 0.0]), np.array([4.0, 4.0, 1.0, 2.0])
    expected = ((np.sqrt(a) - np.sqrt(b)) ** 2).sum() + 3.0
    assert frechet_distance(np.zeros(4), np.diag(a), np.array([1.0, 1.0, 1.0, 0.0]), np.diag(b)) == pytest.approx(expected)
    # a set against itself is 0; a shifted copy costs exactly the squared shift
    f = np.random.default_rng(1).standard_normal((50, 6))
    assert frechet_from_features(f, f) == pytest.approx(0.0, abs=1e-9)
    assert frechet_from_features(f, f + np.arange(6)) == pytest.approx(float((np.arange(6) ** 2).sum()), rel=1e-9)


@pytest.mark.parametrize("n_a,n_b,d", [(5, 7, 32), (20, 3, 16), (2, 2, 64)])
def test_singular_covariances_give_the_nuclear_norm_form(n_a, n_b, d):
    """Fewer samples than dimensions: tr (A^½ B A^½)^½ = ||B^½ A^½||_* computed by SVD instead."""
    rng = np.random.default_rng(n_a * 100 + n_b)
    fa, fb = rng.standard_normal((n_a, d)), rng.standard_normal((n_b, d)) + 0.5
    (mu_a, sa), (mu_b, sb) = gaussian_stats(fa), gaussian_stats(fb)
    nuclear = np.linalg.svd(sqrtm_psd(sb) @ sqrtm_psd(sa), compute_uv=False).sum()
    expected = ((mu_a - mu_b) ** 2).sum() + np.trace(sa) + np.trace(sb) - 2 * nuclear
    value = frechet_from_features(fa, fb)
    assert np.isfinite(value) and value >= 0.0
    assert value == pytest.approx(expected, rel=1e-8, abs=1e-9)
    assert value == pytest.approx(frechet_from_features(fb, fa), rel=1e-8)  # symmetric
