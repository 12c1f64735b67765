"""Calibration results written back: the [calibration] table of a fit, the dataset descriptor, the
summary a person reads."""
from __future__ import annotations


import numpy as np
import pytest

from v2xpos.diagnose.identify import Fit
from v2xpos.diagnose.inject import N_PARAMS, P_GNSS_LATENCY, P_LEVER_ARM, P_MISALIGN, P_TIME_OFFSET
from v2xpos.diagnose.writeback import calibration_table, theta_from_table, write_dataset
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA


def _fit_vectors():
    theta = np.zeros(N_PARAMS)
    sd = np.full(N_PARAMS, 0.01)
    theta[P_TIME_OFFSET], sd[P_TIME_OFFSET] = -0.025, 0.002
    theta[P_MISALIGN] = np.radians([0.4, -0.6, -1.0])
    sd[P_MISALIGN] = np.radians([0.5, 0.01, 0.02])
    theta[P_LEVER_ARM], sd[P_LEVER_ARM] = [0.5, 0.3, 1.2], [0.02, 0.03, 0.45]
    sig = np.zeros(N_PARAMS, bool)
    sig[[P_TIME_OFFSET, P_MISALIGN.start + 1, P_MISALIGN.start + 2, P_LEVER_ARM.start, P_LEVER_ARM.start + 1]] = True
    det = np.ones(N_PARAMS, bool)
    det[[P_GNSS_LATENCY, P_LEVER_ARM.start + 2]] = False
    prior = np.full(N_PARAMS, 0.02)
    prior[P_LEVER_ARM] = 0.5
    prior[P_GNSS_LATENCY] = 1e-3
    return theta, sd, sig, det, prior


def test_table_writes_significant_values_and_honest_sds():
    theta, sd, sig, det, prior = _fit_vectors()
    t = calibration_table(theta, sd, sig, det, prior, declared_lever_sd_m=0.02, source="B/dataset.toml",
                          date="2026-11-24", software="v2xpos test")
    e = t.effects
    assert e["imu_time_offset_s"].value == -0.025 and e["imu_time_offset_s"].sd == 0.002
    # roll not significant (0.4 deg at 0.5 deg sd): value 0, its sd kept; pitch/yaw in degrees
    assert e["imu_misalignment_deg"].value == pytest.approx((0.0, -0.6, -1.0))
    assert e["imu_misalignment_deg"].sd == pytest.approx((0.5, 0.01, 0.02))
    # vertical lever arm not determined: no value, the declared sd stands
    assert e["gnss_lever_arm_m"].value == pytest.approx((0.5, 0.3, 0.0))
    assert e["gnss_lever_arm_m"].sd == pytest.approx((0.02, 0.03, 0.02))
    # GNSS latency not determined: the prior's sd
    assert e["gnss_latency_s"].value == 0.0 and e["gnss_latency_s"].sd == pytest.approx(1e-3)
    th, s = theta_from_table(t)
    assert th[P_TIME_OFFSET] == -0.025 and th[P_MISALIGN.start + 2] == pytest.approx(np.radians(-1.0))


@pytest.mark.slow
def test_written_descriptor_loads_with_paths_and_calibration(tmp_path):
    src = DATA / "convoy_dev" / "B" / "dataset.toml"
    require_shared(src)
    from v2xpos.datasets import load_dataset
    from v2xpos.datasets.loader import read_descriptor
    theta, sd, sig, det, prior = _fit_vectors()
    table = calibration_table(theta, sd, sig, det, prior, 0.02, source=str(src), date="2026-11-24", software="t")
    out = write_dataset(src, tmp_path / "deeper" / "B_calibrated.toml", table)
    d_in, d_out = read_descriptor(src), read_descriptor(out)
    assert d_out["imu"]["imu_to_body"] == d_in["imu"]["imu_to_body"]
    assert d_out["gnss"]["lever_arm_m"] == d_in["gnss"]["lever_arm_m"]
    assert (out.parent / d_out["imu"]["file"]).resolve() == (src.parent / d_in["imu"]["file"]).resolve()
    ds = load_dataset(out)
    assert ds.calibration is not None and ds.calibration.date == "2026-11-24"
    assert ds.calibration.effects["gnss_lever_arm_m"].value == pytest.approx((0.5, 0.3, 0.0))
    assert len(ds.imu) == len(load_dataset(src).imu)
    # writing again from the written file replaces its table, it does not add a second one
    out2 = write_dataset(out, tmp_path / "again.toml", table)
    assert out2.read_text().count("[calibration]") == 1


def test_summary_shows_degrees_and_not_determined():
    from types import SimpleNamespace
    from v2xpos.diagnose.summary import summary_text
    theta, sd, sig, det, prior = _fit_vectors()
    f = Fit(theta=theta, cov=np.diag(sd ** 2), sd=sd, sd_stat=sd, cost_before=0.0, cost_after=0.0, n_rows=1,
            reduced_chi2=1.0, significant=sig, determined=det)
    cal = SimpleNamespace(fit=f, dataset="B", source="B/dataset.toml", problem=SimpleNamespace(active=np.ones(N_PARAMS, bool)),
                          before={"outage_h_rms_m": 2.3, "outage_h_max_m": 3.7, "aided_h_rms_m": 0.13, "nis_mean": 2.2},
                          after={"outage_h_rms_m": 1.6, "outage_h_max_m": 3.2, "aided_h_rms_m": 0.09, "nis_mean": 2.1},
                          tuning={}, replays=30)
    text = summary_text(cal)
    line = {ln.split("  ")[0].strip(): ln for ln in text.splitlines() if "  " in ln}
    assert "-0.6" in line["mounting pitch"] and "deg" in line["mounting pitch"] and "YES" in line["mounting pitch"]
    assert "-25" in line["IMU time offset"] and "ms" in line["IMU time offset"]
    assert "not determined" in line["lever arm z (down)"]
    assert "2.300" in line["outage horizontal RMS"] and "1.600" in line["outage horizontal RMS"]


def test_not_determined_rows_are_never_judged_in_summary_report_or_agreement():
    """An effect the recording cannot determine is shown as "not determined" in the verdict of the
    summary, report.md and the online-agreement rows -- not "no"/"YES", and not "NO" agreement
    even when its (prior-pulled) offline value is far from the online state."""
    from types import SimpleNamespace
    from v2xpos.diagnose.calibrate import agreement, to_json
    from v2xpos.diagnose.summary import markdown_tables, summary_text
    theta, sd, sig, det, prior = _fit_vectors()
    lz = P_LEVER_ARM.start + 2
    sig_flags = sig.copy()
    sig_flags[lz] = True                       # a stale flag must not make it "YES"
    f = Fit(theta=theta, cov=np.diag(sd ** 2), sd=sd, sd_stat=sd, cost_before=0.0, cost_after=0.0, n_rows=1,
            reduced_chi2=1.0, significant=sig_flags, determined=det)
    online = {lz: (theta[lz] + 10 * sd[lz], 0.01),                                      # |z| ~ 10
              P_LEVER_ARM.start: (theta[P_LEVER_ARM.start] + 10 * sd[P_LEVER_ARM.start], 0.001)}
    rows = agreement(f, online, 100.0)
    by = {r["index"]: r for r in rows}
    assert by[lz]["agree"] is None and not by[lz]["determined"]
    assert by[P_LEVER_ARM.start]["agree"] is False                # a determined row is still judged
    metrics = {"outage_h_rms_m": 2.3, "outage_h_max_m": 3.7, "aided_h_rms_m": 0.13, "nis_mean": 2.2}
    cal = SimpleNamespace(fit=f, dataset="B", source="B/dataset.toml", problem=SimpleNamespace(active=np.ones(N_PARAMS, bool)),
                          before=metrics, after=metrics, tuning={}, replays=30, online=rows)
    text = summary_text(cal)
    z_lines = [ln for ln in text.splitlines() if ln.startswith("lever arm z (down)")]
    assert len(z_lines) == 2                                      # the effect row and the agreement row
    for ln in z_lines:
        verdict = ln.rsplit("  ", 1)[-1].strip()
        assert verdict == "not determined", ln
    x_agree = [ln for ln in text.splitlines() if ln.startswith("lever arm x (forward)")][-1]
    assert x_agree.rstrip().endswith("NO")
    md = [ln for ln in markdown_tables(cal) if ln.startswith("| lever arm z (down)")]
    assert len(md) == 2 and all(ln.rstrip(" |").endswith("not determined") for ln in md)
    js = to_json(SimpleNamespace(dataset="B", fit=f, before=metrics, after=metrics, online=rows))
    assert js["online_agreement"]["lever_arm_z_m"]["agree"] is None


def test_report_signal_table_has_no_nan_rows_and_reads_yaw_rates_in_degrees():
    """The report's residual-against-signal table: an effect whose correlation cannot be computed
    (the clock drift's 60-s blocks on a short drive: 3 blocks) says "not determined" and why,
    never "nan"; yaw rates are shown in deg/s."""
    from v2xpos.diagnose import report
    rng = np.random.default_rng(0)
    t = np.arange(400) * 0.1
    r, x = rng.normal(size=400), rng.normal(size=400)
    yr = np.radians(10.0) * np.sin(t)
    pairs = {"lever_arm_x_m": (r, np.degrees(yr), "lateral vel. innovation [m/s]", "yaw rate [deg/s]", t),
             "imu_clock_drift_ppm": (np.array([0.01, 0.02, 0.015]), np.array([30.0, 90.0, 150.0]),
                                     "slope dv/a_x per 60 s block [s]", "time [s]", np.array([30.0, 90.0, 150.0]))}
    st = {"lever_arm_x_m": {"correlation": report.structure.correlation(r, x).as_dict()}}
    rows = report.signal_rows(pairs, pairs, st, st)
    assert len(rows) == 2
    text = "\n".join(rows)
    assert "nan" not in text.lower()
    drift = [row for row in rows if row.startswith("| IMU clock drift")]
    assert drift and "not determined (3 60-s blocks" in drift[0], rows
    assert "yaw rate [deg/s]" in text and "rad/s" not in text
