"""Stop detection of the GNSS/INS filter: is the vehicle standing still?

The IMU arrives in chunks of ``cov_every`` samples. For each chunk one row of sums is kept, over
the last ``static_window_s`` (``static_window_s x constraint_rate_hz`` chunks): the number of
samples N, sum |f|, sum |f|^2, sum w (3 axes) and, once the filter has an attitude, the horizontal
specific force in NED summed over the chunk, C_nb[:2] (sum f - N b_a). Over the full window the
platform is static when (the moving-variance and angular-rate tests of zero-velocity detection,
Skog et al. 2010, "Zero-velocity detection -- an algorithm evaluation", IEEE TBME 57(11);
Groves 2013 sec. 15.3.1):

    sd(|f|) = sqrt(mean |f|^2 - (mean |f|)^2) < static_acc_std_max_mps2   (no driving vibration)
    |mean w - b_g|                           < static_gyro_mean_max_rps   (not turning)

and, with a navigation solution, |v| < static_max_speed_mps and |mean f_h^n| <
static_acc_h_max_mps2 (a stop has no horizontal acceleration), and, with a GNSS speed at most
``static_gnss_speed_max_age_s`` old, that speed < static_max_gnss_speed_mps. A window that is not
yet full is never static. The window's mean rate is also what the ZARU measures
(``updates.zaru``).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .config import InsConfig

# columns of a window row
_N, _SUM_F, _SUM_F2, _SUM_W, _SUM_FH = 0, 1, 2, 3, 6


class StopDetector:
    """The window of chunk sums and the static test of the module docstring (thresholds from
    ``InsConfig``: ``static_*``, ``constraint_rate_hz``)."""

    def __init__(self, cfg: InsConfig):
        self.cfg = cfg
        self.window = np.zeros((max(1, int(round(cfg.stops.static_window_s * cfg.constraints.constraint_rate_hz))), 8))
        self.filled = 0
        self._next = 0
        self.gnss_speed_mps: float | None = None
        self.gnss_speed_t_s = -np.inf

    def feed(self, f_b: np.ndarray, w_b: np.ndarray, C_nb: np.ndarray | None = None,
             accel_bias_mps2: np.ndarray | None = None) -> None:
        """One chunk of raw specific force [m/s^2] and rate [rad/s] in body axes (N x 3); with an
        attitude C_nb (body -> NED) and accelerometer bias, also its horizontal specific force."""
        f2 = np.einsum("ij,ij->i", f_b, f_b)
        row = self.window[self._next]
        row[_N] = len(f_b)
        row[_SUM_F] = np.sqrt(f2).sum()
        row[_SUM_F2] = f2.sum()
        row[_SUM_W:_SUM_W + 3] = w_b.sum(axis=0)
        if C_nb is not None:
            row[_SUM_FH:_SUM_FH + 2] = (C_nb[:2] @ (f_b.sum(axis=0) - len(f_b) * accel_bias_mps2))
        else:
            row[_SUM_FH:_SUM_FH + 2] = 0.0
        self._next = (self._next + 1) % len(self.window)
        self.filled = min(self.filled + 1, len(self.window))

    def note_gnss_speed(self, t_s: float, speed_mps: float) -> None:
        """The receiver's latest speed [m/s] at GPS time t_s."""
        self.gnss_speed_mps = speed_mps
        self.gnss_speed_t_s = t_s

    def is_static(self, t_s: float, gyro_bias_rps: np.ndarray, v_ned_mps: np.ndarray | None = None,
                  rate_test: bool = True) -> bool:
        """The static test at GPS time t_s; ``v_ned_mps`` None before the filter has a solution;
        ``rate_test`` False leaves out the one test that needs the gyro bias (the stop
        calibration's veto, which must work before the bias is known)."""
        c = self.cfg
        if self.filled < len(self.window):
            return False
        tot = self.window.sum(axis=0)
        n, s1, s2, sw = tot[_N], tot[_SUM_F], tot[_SUM_F2], tot[_SUM_W:_SUM_W + 3]
        acc_sd = math.sqrt(max(s2 / n - (s1 / n) ** 2, 0.0))
        dw = sw / n - gyro_bias_rps
        w_mean = math.sqrt(float(dw @ dw))
        ok = acc_sd < c.stops.static_acc_std_max_mps2 and (w_mean < c.stops.static_gyro_mean_max_rps or not rate_test)
        if ok and v_ned_mps is not None:
            fh = tot[_SUM_FH:_SUM_FH + 2] / n
            ok = (float(v_ned_mps @ v_ned_mps) < c.stops.static_max_speed_mps ** 2
                  and float(fh @ fh) < c.stops.static_acc_h_max_mps2 ** 2)
        if (ok and self.gnss_speed_mps is not None
                and t_s - self.gnss_speed_t_s < c.stops.static_gnss_speed_max_age_s):
            ok = self.gnss_speed_mps < c.stops.static_max_gnss_speed_mps
        return bool(ok)

    def mean_rate_rps(self) -> np.ndarray:
        """Mean raw body rate [rad/s] over the window."""
        tot = self.window.sum(axis=0)
        return tot[_SUM_W:_SUM_W + 3] / tot[_N]
