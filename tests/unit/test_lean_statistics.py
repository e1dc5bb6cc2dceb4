"""The statistics computed without importing scipy.stats (~0.4 s of every process's start-up) equal
scipy.stats' own, bit for bit."""

import numpy as np
import scipy.stats as st
from scipy.special import ndtr, ndtri

from v2i.scoring.detection_metrics import chi2_ppf
from link_emulator.distributions import NormalJitter, _normal_pdf


def test_chi2_quantiles_equal_scipy_stats():
    q = np.array([1e-6, 0.025, 0.1, 0.5, 0.9, 0.975, 1 - 1e-6])
    for df in (1, 2, 3, 10, 200, 2001):
        assert np.array_equal(chi2_ppf(q, df), st.chi2.ppf(q, df=df)), df


def test_normal_pdf_cdf_and_quantile_equal_scipy_stats():
    for z in np.linspace(-8.0, 8.0, 1601):
        assert _normal_pdf(float(z)) == st.norm.pdf(float(z))
        assert ndtr(float(z)) == st.norm.cdf(float(z))
    for q in np.linspace(0.001, 0.999, 999):
        assert ndtri(q) == st.norm.ppf(q)


def test_a_clipped_normal_jitter_s_mean_and_median_are_scipy_s():
    """mean_clipped_ms = mu Phi(mu / s) + s phi(mu / s), the summary's median: as with scipy.stats.norm."""
    for mean_ms, std_ms, base_ms in ((0.0, 3.0, 10.0), (1.5, 8.0, 2.0), (-4.0, 2.0, 1.0)):
        jitter = NormalJitter(distribution="normal", mean_ms=mean_ms, std_ms=std_ms)
        mu, z = base_ms + mean_ms, (base_ms + mean_ms) / std_ms
        assert jitter.mean_clipped_ms(base_ms) == float(mu * st.norm.cdf(z) + std_ms * st.norm.pdf(z))
        for q in (0.1, 0.5, 0.9):
            want = max(0.0, base_ms + float(jitter.from_normal(np.array(st.norm.ppf(q)))))
            assert jitter.quantile_ms(base_ms, q) == want
