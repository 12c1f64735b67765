"""Time scales and clock-domain alignment.

Time scales (IS-GPS-200, sec. 3.3.4 and 20.3.3.5.2.4; IERS Bulletin C for the leap seconds):

- GPS seconds: continuous seconds since the GPS epoch 1980-01-06 00:00:00 (GPST, no leap
  seconds). This is the project's common time axis (``t_s`` everywhere).
- GPS week + time of week (TOW): ``gps_s = week * 604800 + tow_s``.
- UTC: ``utc = gpst - (GPS - UTC)``, with GPS - UTC = 0 s at the GPS epoch, +1 s at each leap
  second since, 18 s since 2017-01-01.
- Unix seconds: seconds since 1970-01-01 00:00:00 UTC, not counting leap seconds (POSIX).
  The GPS epoch is Unix second ``GPS_UNIX_OFFSET_S = 315964800``.
- "GPST as seconds since 1970 without leap seconds" (RTKLIB ``gtime_t`` in GPST, used by the
  TIMETAG files): ``gps_s = value - GPS_UNIX_OFFSET_S``.

Clock-domain alignment: a device counter (IMU milliseconds since power-up, a phone's boot clock)
is mapped to GPS time by an affine model ``t_gps = offset_s + (1 + drift) * counter_s``.
When the only GPS-time information is the *arrival* time of the bytes at a logging computer,
every arrival is later than the sample's true time by a non-negative delay (transport,
buffering, scheduling). The model is therefore fitted as the lower envelope of the
(counter, arrival) points: the line below all points that minimises the summed residual, which is
a supporting line of the lower convex hull (a linear program; see e.g. S. B. Moon, P. Skelly,
D. Towsley, "Estimation and removal of clock skew from network delay measurements",
IEEE INFOCOM 1999). The remaining constant minimum delay is not observable from the arrivals
alone and must be estimated downstream (the filter's ``imu_time_offset_s``).
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

import numpy as np

GPS_UNIX_OFFSET_S = 315964800
"""Unix seconds at the GPS epoch 1980-01-06 00:00:00 UTC (GPS - UTC was 0 s then)."""
SECONDS_PER_WEEK = 604800
SECONDS_PER_DAY = 86400
GPS_EPOCH_UTC = _dt.datetime(1980, 1, 6, tzinfo=_dt.timezone.utc)
UNIX_EPOCH_UTC = _dt.datetime(1970, 1, 1, tzinfo=_dt.timezone.utc)

# UTC dates from which GPS - UTC takes the given value [s] (IERS Bulletin C, all steps since 1980).
_LEAP_STEPS_UTC = (
    ((1981, 7, 1), 1), ((1982, 7, 1), 2), ((1983, 7, 1), 3), ((1985, 7, 1), 4),
    ((1988, 1, 1), 5), ((1990, 1, 1), 6), ((1991, 1, 1), 7), ((1992, 7, 1), 8),
    ((1993, 7, 1), 9), ((1994, 7, 1), 10), ((1996, 1, 1), 11), ((1997, 7, 1), 12),
    ((1999, 1, 1), 13), ((2006, 1, 1), 14), ((2009, 1, 1), 15), ((2012, 7, 1), 16),
    ((2015, 7, 1), 17), ((2017, 1, 1), 18),
)
LEAP_SECONDS_TABLE: tuple[tuple[_dt.datetime, int], ...] = tuple(
    (_dt.datetime(y, m, d, tzinfo=_dt.timezone.utc), n) for (y, m, d), n in _LEAP_STEPS_UTC)
"""(UTC instant from which it applies, GPS - UTC [s]) for every leap second since 1980."""

_STEP_UNIX_S = np.array([(t - UNIX_EPOCH_UTC).total_seconds() for t, _ in LEAP_SECONDS_TABLE])
_STEP_VALUE_S = np.array([n for _, n in LEAP_SECONDS_TABLE], dtype=float)
# The same steps expressed on the GPS time axis: the UTC instant t maps to gps = t_unix - offset + n.
_STEP_GPS_S = _STEP_UNIX_S - GPS_UNIX_OFFSET_S + _STEP_VALUE_S


# --------------------------------------------------------------------------------------------
# Scalar and vectorised conversions
# --------------------------------------------------------------------------------------------
def gps_seconds_from_week_tow(week: int | np.ndarray, tow_s: float | np.ndarray) -> float | np.ndarray:
    """GPS week number (continuous, not modulo 1024) and time of week [s] -> GPS seconds."""
    if np.ndim(week) or np.ndim(tow_s):
        return np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(tow_s, dtype=float)
    return float(week) * SECONDS_PER_WEEK + float(tow_s)


def week_tow_from_gps_seconds(gps_s: float) -> tuple[int, float]:
    """GPS seconds -> (week, time of week [s])."""
    week = int(np.floor(gps_s / SECONDS_PER_WEEK))
    return week, float(gps_s - week * SECONDS_PER_WEEK)


def gps_minus_utc_at_utc(unix_s: float | np.ndarray) -> float | np.ndarray:
    """GPS - UTC [s] in force at the UTC instant given as Unix seconds (0 before 1981-07-01)."""
    idx = np.searchsorted(_STEP_UNIX_S, unix_s, side="right")
    values = np.concatenate(([0.0], _STEP_VALUE_S))[idx]
    return float(values) if np.ndim(values) == 0 else values


def gps_minus_utc_at_gps(gps_s: float | np.ndarray) -> float | np.ndarray:
    """GPS - UTC [s] in force at the instant given in GPS seconds."""
    idx = np.searchsorted(_STEP_GPS_S, gps_s, side="right")
    values = np.concatenate(([0.0], _STEP_VALUE_S))[idx]
    return float(values) if np.ndim(values) == 0 else values


def unix_to_gps_seconds(unix_s: float | np.ndarray) -> float | np.ndarray:
    """Unix seconds (UTC, POSIX) -> GPS seconds: ``gps = unix - 315964800 + (GPS - UTC)``."""
    unix_s = np.asarray(unix_s, dtype=float) if np.ndim(unix_s) else float(unix_s)
    return unix_s - GPS_UNIX_OFFSET_S + gps_minus_utc_at_utc(unix_s)


def gps_seconds_to_unix(gps_s: float | np.ndarray) -> float | np.ndarray:
    """GPS seconds -> Unix seconds (UTC, POSIX). During an inserted leap second (23:59:60 UTC)
    POSIX has no representation; the result repeats the following second's start."""
    gps_s = np.asarray(gps_s, dtype=float) if np.ndim(gps_s) else float(gps_s)
    return gps_s + GPS_UNIX_OFFSET_S - gps_minus_utc_at_gps(gps_s)


def gps_seconds_to_utc(gps_s: float) -> _dt.datetime:
    """GPS seconds -> timezone-aware UTC datetime (microsecond resolution)."""
    return UNIX_EPOCH_UTC + _dt.timedelta(seconds=float(gps_seconds_to_unix(gps_s)))


def utc_to_gps_seconds(utc: _dt.datetime) -> float:
    """UTC datetime (naive values are taken as UTC) -> GPS seconds."""
    if utc.tzinfo is None:
        utc = utc.replace(tzinfo=_dt.timezone.utc)
    return float(unix_to_gps_seconds((utc - UNIX_EPOCH_UTC).total_seconds()))


def gpst_calendar_to_gps_seconds(year: int, month: int, day: int, hour: int = 0, minute: int = 0,
                                 second: float = 0.0) -> float:
    """A calendar date/time *expressed in GPST* (as RTKLIB prints it, no leap seconds) -> GPS s."""
    days = (_dt.date(year, month, day) - GPS_EPOCH_UTC.date()).days
    return days * SECONDS_PER_DAY + hour * 3600 + minute * 60 + float(second)


def gps_seconds_to_gpst_calendar(gps_s: float) -> _dt.datetime:
    """GPS seconds -> naive datetime holding the GPST calendar reading (no leap seconds)."""
    return GPS_EPOCH_UTC.replace(tzinfo=None) + _dt.timedelta(seconds=float(gps_s))


def gpst_unix_style_to_gps_seconds(seconds_since_1970: float | np.ndarray) -> float | np.ndarray:
    """GPST counted as seconds since 1970-01-01 without leap seconds (RTKLIB gtime_t) -> GPS s."""
    return seconds_since_1970 - GPS_UNIX_OFFSET_S


# --------------------------------------------------------------------------------------------
# Clock models
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ClockModel:
    """Affine map from a device counter to GPS time: ``t_gps = offset_s + (1 + drift) * counter_s``.

    drift_ppm = drift * 1e6 (positive: the device clock runs slow against GPS time).
    Residual statistics describe ``arrival - model`` over the fitted points [s]; for a lower
    envelope fit the minimum is 0 and the rest is the one-sided arrival delay spread.
    """
    offset_s: float
    drift_ppm: float
    n_points: int = 0
    residual_min_s: float = 0.0
    residual_median_s: float = 0.0
    residual_p95_s: float = 0.0
    residual_max_s: float = 0.0
    counter_span_s: float = 0.0

    @property
    def scale(self) -> float:
        """d t_gps / d counter = 1 + drift."""
        return 1.0 + self.drift_ppm * 1e-6

    def to_gps(self, counter_s: float | np.ndarray) -> float | np.ndarray:
        """Counter [s] -> GPS seconds."""
        if np.ndim(counter_s):
            return self.offset_s + self.scale * np.asarray(counter_s, dtype=float)
        return self.offset_s + self.scale * float(counter_s)

    def as_dict(self) -> dict:
        return {k: float(v) if isinstance(v, float) else v for k, v in self.__dict__.items()}


def _lower_hull_indices(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Indices of the lower convex hull of points sorted by x (Andrew's monotone chain)."""
    hull: list[int] = []
    for i in range(len(x)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            cross = (x[b] - x[a]) * (y[i] - y[a]) - (y[b] - y[a]) * (x[i] - x[a])
            if cross <= 0.0:
                hull.pop()
            else:
                break
        hull.append(i)
    return np.asarray(hull, dtype=int)


def _lower_hull_candidates(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Lower hull indices of many points: qhull (C) picks the hull vertices, the exact monotone
    chain then runs on those few; falls back to the chain on all points if qhull fails."""
    from scipy.spatial import ConvexHull, QhullError
    scale_x, scale_y = max(float(np.ptp(x)), 1e-300), max(float(np.ptp(y)), 1e-300)
    try:
        vertices = ConvexHull(np.column_stack([x / scale_x, y / scale_y])).vertices
    except (QhullError, ValueError):
        return _lower_hull_indices(x, y)
    cand = np.unique(np.concatenate([vertices, [0, x.size - 1]]))
    return cand[_lower_hull_indices(x[cand], y[cand])]


def _finite_pairs(counter_s: np.ndarray, t_s: np.ndarray, caller: str) -> tuple[np.ndarray, np.ndarray]:
    """The (counter, time) pairs where both are finite; ValueError unless two counters differ."""
    c = np.asarray(counter_s, dtype=float)
    t = np.asarray(t_s, dtype=float)
    ok = np.isfinite(c) & np.isfinite(t)
    c, t = c[ok], t[ok]
    if c.size < 2 or np.ptp(c) <= 0.0:
        raise ValueError(f"{caller}: need at least two distinct counter values")
    return c, t


def _clock_model(offset_s: float, slope: float, counter_s: np.ndarray, residual_s: np.ndarray) -> ClockModel:
    """ClockModel of ``t = offset_s + slope * counter`` with the statistics of its residuals [s]."""
    return ClockModel(offset_s=float(offset_s), drift_ppm=float((slope - 1.0) * 1e6),
                      n_points=int(counter_s.size), residual_min_s=float(residual_s.min()),
                      residual_median_s=float(np.median(residual_s)),
                      residual_p95_s=float(np.percentile(residual_s, 95)),
                      residual_max_s=float(residual_s.max()), counter_span_s=float(np.ptp(counter_s)))


def fit_clock_lower_envelope(counter_s: np.ndarray, arrival_s: np.ndarray) -> ClockModel:
    """Fit ``arrival = offset + (1 + drift) * counter`` as the lower envelope of the points.

    Solves  min_{a,b} sum_i (arrival_i - a - b counter_i)  s.t.  a + b counter_i <= arrival_i,
    whose optimum is the edge of the lower convex hull spanning the mean counter value (the
    objective is the vertical distance from the line to the centroid). The line lies below every
    point and touches the hull. Requires at least 2 distinct counter values.

    counter_s: device counter [s]; arrival_s: GPS time at which each sample was seen [s].
    """
    c, t = _finite_pairs(counter_s, arrival_s, "fit_clock_lower_envelope")
    c0, t0 = c.min(), t[np.argmin(c)]
    x, y = c - c0, t - t0  # condition the numbers; the rates are unchanged
    order = np.lexsort((y, x))
    x, y = x[order], y[order]
    keep = np.ones(x.size, dtype=bool)
    keep[1:] = x[1:] != x[:-1]  # lowest arrival per counter value
    x, y = x[keep], y[keep]
    hull = _lower_hull_indices(x, y) if x.size < 2000 else _lower_hull_candidates(x, y)
    x_mean = float(np.mean(c - c0))
    if hull.size == 1:
        slope, icpt = 1.0, y[hull[0]] - x[hull[0]]
    else:
        seg = int(np.clip(np.searchsorted(x[hull], x_mean, side="right") - 1, 0, hull.size - 2))
        i, j = hull[seg], hull[seg + 1]
        slope = (y[j] - y[i]) / (x[j] - x[i])
        icpt = y[i] - slope * x[i]
    residual = (t - t0) - (icpt + slope * (c - c0))
    residual_floor = float(residual.min())
    icpt += residual_floor  # exact touching despite rounding
    residual -= residual_floor
    return _clock_model(t0 + icpt - slope * c0, slope, c, residual)


def fit_clock_least_squares(counter_s: np.ndarray, gps_s: np.ndarray) -> ClockModel:
    """Fit ``gps = offset + (1 + drift) * counter`` by least squares, for time pairs whose errors
    are symmetric (e.g. a boot clock stamped against receiver solutions of known GPS time)."""
    c, t = _finite_pairs(counter_s, gps_s, "fit_clock_least_squares")
    c0, t0 = c.mean(), t.mean()
    slope = float(np.sum((c - c0) * (t - t0)) / np.sum((c - c0) ** 2))
    offset = t0 - slope * c0
    return _clock_model(offset, slope, c, t - (offset + slope * c))


# --------------------------------------------------------------------------------------------
# Offset between two data streams
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class XcorrOffset:
    """Result of :func:`estimate_offset_xcorr`: ``x_b(t + offset_s) ~ x_a(t)``; peak_corr is the
    normalised correlation coefficient at the peak (1 = identical shapes)."""
    offset_s: float
    peak_corr: float
    rate_hz: float


def estimate_offset_xcorr(t_a_s: np.ndarray, x_a: np.ndarray, t_b_s: np.ndarray, x_b: np.ndarray,
                          max_lag_s: float = 1.0, rate_hz: float | None = None) -> XcorrOffset:
    """Time offset between two streams that observe the same signal, from their data.

    Both signals (1-D, e.g. a gyro-rate norm) are linearly resampled onto a common grid at
    ``rate_hz`` (default: the faster of the two median rates) over their overlap, de-meaned and
    normalised; the normalised cross-correlation is evaluated for lags within ``max_lag_s`` (FFT)
    and its peak refined by a parabola through the three samples around it.

    Returns offset_s such that ``x_b(t + offset_s) ~ x_a(t)``: subtract it from ``t_b_s`` to put
    stream b on stream a's clock.
    """
    t_a, a = np.asarray(t_a_s, float), np.asarray(x_a, float)
    t_b, b = np.asarray(t_b_s, float), np.asarray(x_b, float)
    if rate_hz is None:
        rate_hz = 1.0 / min(np.median(np.diff(t_a)), np.median(np.diff(t_b)))
    dt = 1.0 / rate_hz
    start, stop = max(t_a[0], t_b[0] - max_lag_s), min(t_a[-1], t_b[-1] + max_lag_s)
    if stop - start < 4 * max_lag_s:
        raise ValueError("estimate_offset_xcorr: the streams overlap less than 4 x max_lag_s")
    grid = np.arange(start, stop, dt)
    ga = np.interp(grid, t_a, a)
    max_lag = int(np.ceil(max_lag_s * rate_hz))
    grid_b = grid[0] + dt * np.arange(-max_lag, grid.size + max_lag)
    gb = np.interp(grid_b, t_b, b)
    valid_b = (grid_b >= t_b[0]) & (grid_b <= t_b[-1])
    ga = ga - ga.mean()
    mean_b = gb[valid_b].mean()
    gb = np.where(valid_b, gb - mean_b, 0.0)
    n = ga.size
    lags = np.arange(-max_lag, max_lag + 1)
    size = 1 << int(np.ceil(np.log2(n + gb.size)))
    spec = np.fft.rfft(gb, size) * np.conj(np.fft.rfft(ga, size))
    full = np.fft.irfft(spec, size)
    # full[k] = sum_i ga[i] * gb[i + k]; gb index i + max_lag + lag aligns with ga index i.
    raw = full[lags + max_lag]
    cs = np.concatenate(([0.0], np.cumsum(gb ** 2)))
    energy_b = cs[lags + max_lag + n] - cs[lags + max_lag]
    denom = np.sqrt(np.sum(ga ** 2) * np.maximum(energy_b, 1e-300))
    corr = raw / denom
    k = int(np.argmax(corr))
    frac = 0.0
    if 0 < k < corr.size - 1:
        y0, y1, y2 = corr[k - 1], corr[k], corr[k + 1]
        den = y0 - 2.0 * y1 + y2
        if den < 0.0:
            frac = 0.5 * (y0 - y2) / den
    return XcorrOffset(offset_s=float((lags[k] + frac) * dt), peak_corr=float(corr[k]),
                       rate_hz=float(rate_hz))
