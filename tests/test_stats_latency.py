"""Constant-memory latency percentiles agree with exact ones to the histogram's resolution."""
import numpy as np

from v2xpos.stats import LatencyHistogram


def test_histogram_percentiles_match_exact_within_resolution():
    rng = np.random.default_rng(0)
    x = rng.lognormal(mean=0.0, sigma=1.0, size=50_000)          # ms-like durations
    h = LatencyHistogram(recent=1000)
    for v in x:
        h.append(float(v))
    for q in (50, 90, 99, 99.9):
        assert abs(h.percentile(q) / np.percentile(x, q) - 1) < 0.015
    assert np.isclose(h.percentile(99, window=1000), np.percentile(x[-1000:], 99))
    assert len(h) == len(x) and len(h.recent) == 1000


def test_memory_is_constant_and_edges_handled():
    h = LatencyHistogram(lo=1e-3, hi=1e3)
    nbytes = h.counts.nbytes
    for v in (0.0, 1e-6, 5e3, float("nan"), float("inf"), 1.0):
        h.append(v)
    assert h.counts.nbytes == nbytes and len(h) == 4
    assert h.percentile(0) == 1e-3 and h.percentile(100) == 1e3
    assert LatencyHistogram().percentile(50) is None
