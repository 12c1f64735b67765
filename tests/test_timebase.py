"""Time scales against known date pairs; clock fits and stream offsets on synthetic clocks."""
import calendar
import datetime as dt

import numpy as np
import pytest
from scipy.optimize import linprog

from v2xpos import timebase as tb

UTC = dt.timezone.utc


def test_gps_epoch():
    assert tb.GPS_UNIX_OFFSET_S == calendar.timegm((1980, 1, 6, 0, 0, 0))
    assert tb.utc_to_gps_seconds(dt.datetime(1980, 1, 6, tzinfo=UTC)) == 0.0
    assert tb.gps_seconds_to_utc(0.0) == dt.datetime(1980, 1, 6, tzinfo=UTC)
    assert tb.unix_to_gps_seconds(315964800.0) == 0.0
    assert tb.week_tow_from_gps_seconds(0.0) == (0, 0.0)


def test_drive_0708_week_2374():
    # RTKLIB prints GPST 2025/07/08 19:34:18.499 = GPS week 2374 (began Sunday 2025-07-06), TOW
    # 2 d + 19:34:18.499; UTC is 18 s behind.
    gps_s = tb.gpst_calendar_to_gps_seconds(2025, 7, 8, 19, 34, 18.499)
    week, tow = tb.week_tow_from_gps_seconds(gps_s)
    assert week == 2374
    assert tow == pytest.approx(2 * 86400 + 19 * 3600 + 34 * 60 + 18.499, abs=1e-6)
    assert tb.gps_seconds_from_week_tow(week, tow) == pytest.approx(gps_s, abs=1e-6)
    utc = tb.gps_seconds_to_utc(gps_s)
    assert utc == dt.datetime(2025, 7, 8, 19, 34, 0, 499000, tzinfo=UTC)
    unix = calendar.timegm((2025, 7, 8, 19, 34, 0)) + 0.499
    assert tb.gps_seconds_to_unix(gps_s) == pytest.approx(unix, abs=1e-6)
    assert tb.unix_to_gps_seconds(unix) == pytest.approx(gps_s, abs=1e-6)


def test_leap_second_2016_12_31():
    before = dt.datetime(2016, 12, 31, 23, 59, 59, tzinfo=UTC)
    after = dt.datetime(2017, 1, 1, 0, 0, 0, tzinfo=UTC)
    assert tb.gps_minus_utc_at_utc((before - tb.UNIX_EPOCH_UTC).total_seconds()) == 17
    assert tb.gps_minus_utc_at_utc((after - tb.UNIX_EPOCH_UTC).total_seconds()) == 18
    # 23:59:60 was inserted between them: 2 s elapsed on the GPS axis.
    assert tb.utc_to_gps_seconds(after) - tb.utc_to_gps_seconds(before) == 2.0
    # GPS week 1930 began 2017-01-01 00:00:00 GPST, i.e. UTC midnight is TOW 18 s.
    assert tb.week_tow_from_gps_seconds(tb.utc_to_gps_seconds(after)) == (1930, 18.0)
    assert tb.gps_seconds_to_utc(tb.utc_to_gps_seconds(after)) == after
    assert tb.gps_seconds_to_utc(tb.utc_to_gps_seconds(before)) == before


def test_week_1024_rollover_and_table():
    # Week 1024 began 1999-08-22 00:00:00 GPST = 1999-08-21 23:59:47 UTC (GPS - UTC = 13 s).
    assert tb.gps_seconds_to_utc(1024 * 604800) == dt.datetime(1999, 8, 21, 23, 59, 47, tzinfo=UTC)
    assert len(tb.LEAP_SECONDS_TABLE) == 18
    assert [n for _, n in tb.LEAP_SECONDS_TABLE] == list(range(1, 19))
    assert tb.gps_minus_utc_at_gps(0.0) == 0.0
    assert tb.gps_minus_utc_at_gps(1e10) == 18.0


def test_vectorised_round_trip():
    gps = np.linspace(0.0, 1.5e9, 2001)
    back = tb.unix_to_gps_seconds(tb.gps_seconds_to_unix(gps))
    # Instants inside an inserted leap second have no Unix representation; all others round-trip.
    inside_leap = np.isin(np.floor(gps), tb._STEP_GPS_S - 1)
    assert np.all(np.abs(back - gps)[~inside_leap] < 1e-6)


def _synthetic_clock(rng, n=60000, offset_s=1.436e9 + 200.074, drift_ppm=12.7, rate_hz=100.0):
    counter_s = 261.906 + np.cumsum(rng.integers(8, 12, n)) * 1e-3
    true_s = offset_s + (1 + drift_ppm * 1e-6) * counter_s
    delay_s = 0.002 + rng.exponential(0.006, n)          # one-sided: bytes arrive late
    record_s = 0.016
    arrival_s = np.ceil((true_s + delay_s) / record_s) * record_s  # tag record granularity
    return counter_s, true_s, arrival_s


def test_lower_envelope_recovers_offset_and_drift():
    rng = np.random.default_rng(7)
    counter_s, true_s, arrival_s = _synthetic_clock(rng)
    model = tb.fit_clock_lower_envelope(counter_s, arrival_s)
    assert model.drift_ppm == pytest.approx(12.7, abs=0.3)
    err = model.to_gps(counter_s) - true_s
    # Above truth by the minimum delay (2 ms) at most plus quantisation; never below it by more
    # than the slope error over the span.
    assert np.all(err > -0.001) and np.all(err < 0.006)
    residual = arrival_s - model.to_gps(counter_s)
    assert residual.min() == pytest.approx(0.0, abs=1e-7)
    assert model.residual_min_s == pytest.approx(0.0, abs=1e-9)
    assert model.residual_median_s > 0.0
    # A least-squares line through the arrivals would be biased by the mean delay instead.
    ls = tb.fit_clock_least_squares(counter_s, arrival_s)
    assert np.mean(ls.to_gps(counter_s) - true_s) > 0.008


def test_lower_envelope_is_the_lp_optimum():
    rng = np.random.default_rng(3)
    # small offset: at 1.4e9 s float64 resolves only ~2.4e-7 s, too coarse for an exact LP check
    counter_s, _, arrival_s = _synthetic_clock(rng, n=4000, offset_s=1000.0)
    x = counter_s - counter_s[0]
    y = arrival_s - arrival_s[0]
    # min sum(y - a - b x)  s.t.  a + b x_i <= y_i   <=>  min -(n a + b sum x)
    lp = linprog(c=[-len(x), -x.sum()], A_ub=np.column_stack([np.ones_like(x), x]), b_ub=y,
                 bounds=[(None, None), (None, None)], method="highs")
    model = tb.fit_clock_lower_envelope(counter_s, arrival_s)
    a, b = lp.x
    fitted = model.to_gps(counter_s) - arrival_s[0]
    assert (model.scale - 1.0) * 1e6 == pytest.approx((b - 1.0) * 1e6, abs=1e-3)
    assert np.sum(y - fitted) == pytest.approx(np.sum(y - (a + b * x)), abs=len(x) * 1e-12)


def test_lower_envelope_rejects_degenerate_input():
    with pytest.raises(ValueError):
        tb.fit_clock_lower_envelope(np.ones(5), np.arange(5.0))


def test_xcorr_offset_between_streams():
    rng = np.random.default_rng(11)
    t_fine = np.arange(0.0, 60.0, 0.001)
    signal = np.convolve(rng.standard_normal(t_fine.size), np.hanning(201), mode="same")
    true_offset_s = 0.137
    t_a = np.arange(0.0, 59.0, 1 / 100.0)
    t_b = np.arange(0.3, 59.5, 1 / 120.0) + 0.0031
    x_a = np.interp(t_a, t_fine, signal) + 0.01 * rng.standard_normal(t_a.size)
    # b's clock reads true_offset_s more than a's for the same physical instant
    x_b = np.interp(t_b - true_offset_s, t_fine, signal) + 0.01 * rng.standard_normal(t_b.size)
    res = tb.estimate_offset_xcorr(t_a, x_a, t_b, x_b, max_lag_s=0.5)
    assert res.offset_s == pytest.approx(true_offset_s, abs=0.002)
    assert res.peak_corr > 0.9
    neg = tb.estimate_offset_xcorr(t_b, x_b, t_a, x_a, max_lag_s=0.5)
    assert neg.offset_s == pytest.approx(-true_offset_s, abs=0.002)
