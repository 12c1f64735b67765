"""Online counter -> GPS time model for a live device clock: the lower envelope of
(counter, arrival) points of ``v2xpos.timebase.fit_clock_lower_envelope``, kept incrementally.

Every arrival is later than the sample's true time by a non-negative delay, so the model is the
line below all (counter, arrival) points that minimises the summed residual: the edge of the
lower convex hull that spans the mean counter value (``timebase`` module docstring; Moon, Skelly &
Towsley, IEEE INFOCOM 1999). Points arrive in counter order, so the lower hull is maintained by
Andrew's monotone chain one point at a time (a point popped from the hull can never return: every
later point lies to its right), in amortised O(1) per point; the fit is a binary search over the
hull for the edge spanning the running mean. With the same points the model equals the batch fit
(a test holds the two together).

Start-up guard: while the counter span is shorter than ``min_span_s`` the slope is not
observable against the arrival jitter (16 ms over 0.1 s would be a 16 % rate error), so the model
is the lower envelope with slope 1 (drift 0): ``offset = min(arrival - counter)``.

Limitation: one affine model over the whole run; a crystal whose rate wanders (temperature) by
1 ppm over an hour leaves up to a few ms of curvature, which the filter's ``imu_time_offset``
state absorbs slowly. ``reset()`` starts over (e.g. after a device restart).
"""
from __future__ import annotations

import bisect
import math

from v2xpos.timebase import ClockModel


class OnlineLowerEnvelope:
    """Incremental lower-envelope fit of ``arrival = offset + (1 + drift) * counter`` (see module doc).

    ``add(counter_s, arrival_s)`` with counters non-decreasing; ``to_gps(counter_s)`` the current
    model; ``model()`` a ``timebase.ClockModel`` snapshot (residual statistics not tracked: 0).
    """

    def __init__(self, min_span_s: float = 5.0):
        self.min_span_s = float(min_span_s)
        self.reset()

    def reset(self) -> None:
        self._c0: float | None = None     # conditioning origin (first point)
        self._t0 = 0.0
        self._hx: list[float] = []         # lower hull, x = counter - c0
        self._hy: list[float] = []         # y = arrival - t0
        self._sum_x = 0.0
        self._n = 0
        self._min_y_minus_x = math.inf
        self._last_x = -math.inf
        self._cache: tuple[float, float] | None = None   # (intercept, slope) in conditioned units
        self.rejected = 0

    @property
    def n_points(self) -> int:
        return self._n

    @property
    def span_s(self) -> float:
        return (self._hx[-1] - self._hx[0]) if self._hx else 0.0

    def add(self, counter_s: float, arrival_s: float) -> bool:
        """Add one point; False (and counted in ``rejected``) when not finite or the counter went back."""
        if not (math.isfinite(counter_s) and math.isfinite(arrival_s)):
            self.rejected += 1
            return False
        if self._c0 is None:
            self._c0, self._t0 = counter_s, arrival_s
        x, y = counter_s - self._c0, arrival_s - self._t0
        if x < self._last_x:
            self.rejected += 1
            return False
        self._n += 1
        self._sum_x += x
        self._min_y_minus_x = min(self._min_y_minus_x, y - x)
        self._cache = None
        hx, hy = self._hx, self._hy
        if hx and x == hx[-1]:            # same counter: keep the lowest arrival
            if y >= hy[-1]:
                return True
            hx.pop()
            hy.pop()
        while len(hx) >= 2:
            ax, ay, bx, by = hx[-2], hy[-2], hx[-1], hy[-1]
            if (bx - ax) * (y - ay) - (by - ay) * (x - ax) <= 0.0:
                hx.pop()
                hy.pop()
            else:
                break
        hx.append(x)
        hy.append(y)
        self._last_x = x
        return True

    def _fit(self) -> tuple[float, float]:
        if self._cache is not None:
            return self._cache
        hx, hy = self._hx, self._hy
        if len(hx) < 2 or self.span_s < self.min_span_s:
            fit = (self._min_y_minus_x, 1.0)
        else:
            x_mean = self._sum_x / self._n
            seg = bisect.bisect_right(hx, x_mean) - 1
            seg = min(max(seg, 0), len(hx) - 2)
            slope = (hy[seg + 1] - hy[seg]) / (hx[seg + 1] - hx[seg])
            fit = (hy[seg] - slope * hx[seg], slope)
        self._cache = fit
        return fit

    def ready(self) -> bool:
        """True once a point has been added (a model exists)."""
        return self._c0 is not None

    def to_gps(self, counter_s: float) -> float:
        """GPS time of ``counter_s`` on the current model (NaN before the first point)."""
        if self._c0 is None:
            return math.nan
        icpt, slope = self._fit()
        return self._t0 + icpt + slope * (counter_s - self._c0)

    def model(self) -> ClockModel | None:
        """The current model as a ``ClockModel`` (offset at counter 0), or None before any point."""
        if self._c0 is None:
            return None
        icpt, slope = self._fit()
        return ClockModel(offset_s=self._t0 + icpt - slope * self._c0, drift_ppm=(slope - 1.0) * 1e6,
                          n_points=self._n, counter_span_s=self.span_s)

    def status(self) -> dict:
        m = self.model()
        return {"points": self._n, "span_s": self.span_s, "hull_vertices": len(self._hx),
                "slope_fitted": bool(len(self._hx) >= 2 and self.span_s >= self.min_span_s),
                "drift_ppm": None if m is None else m.drift_ppm, "rejected": self.rejected}
