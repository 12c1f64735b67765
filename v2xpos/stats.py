"""Constant-memory latency statistics for long-running services.

``LatencyHistogram`` counts samples in logarithmic bins (``bins_per_decade`` per factor of ten
between ``lo`` and ``hi``), so a whole-run percentile costs O(bins) time and fixed memory however
long the service runs; its relative resolution is 10**(1/bins_per_decade) - 1 (1.2 % at 200 bins
per decade). The last ``recent`` samples are also kept exactly for windowed percentiles.
"""
from __future__ import annotations

from collections import deque
from math import log10

import numpy as np

_INF = float("inf")


class LatencyHistogram:
    """Whole-run histogram + a short exact window of positive durations (any unit, e.g. ms)."""

    def __init__(self, lo: float = 1e-3, hi: float = 1e6, bins_per_decade: int = 200, recent: int = 4096):
        self.lo, self.hi, self.bpd = lo, hi, bins_per_decade
        self._log_lo = log10(lo)
        self.n_bins = int(round((log10(hi) - self._log_lo) * bins_per_decade))
        self._counts = [0] * (self.n_bins + 2)     # a list: one increment per sample is cheap
        self.recent: deque = deque(maxlen=recent)
        self.count = 0

    def append(self, x: float) -> None:
        """Add one sample (non-finite samples are ignored)."""
        if not (x == x and x != _INF and x != -_INF):
            return
        if x < self.lo:
            k = 0
        elif x >= self.hi:
            k = self.n_bins + 1
        else:
            k = min(1 + int((log10(x) - self._log_lo) * self.bpd), self.n_bins)
        self._counts[k] += 1
        self.recent.append(x)
        self.count += 1

    @property
    def counts(self) -> np.ndarray:
        """Samples per bin: [0] underflow, [1..n_bins] the log bins, [-1] overflow."""
        return np.asarray(self._counts, dtype=np.int64)

    def __len__(self) -> int:
        return self.count

    def percentile(self, q: float, window: int | None = None) -> float | None:
        """q-th percentile (0-100): over the last ``window`` samples exactly when window is given
        (at most ``recent``), else over the whole run from the histogram (bin geometric centre)."""
        if window is not None:
            a = list(self.recent)[-window:]
            return float(np.percentile(a, q)) if a else None
        if self.count == 0:
            return None
        c = np.cumsum(self.counts)
        k = int(np.searchsorted(c, q / 100.0 * self.count, side="left"))
        if k == 0:
            return self.lo
        if k > self.n_bins:
            return self.hi
        return 10 ** (self._log_lo + (k - 0.5) / self.bpd)
