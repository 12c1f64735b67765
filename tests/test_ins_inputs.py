"""Malformed inputs are counted and skipped, never fatal; the stop calibration; CLI."""
import argparse
import json

import numpy as np
import pytest

from sim.sensors import ImuErrorModel, simulate_imu
from sim.trajectory import Segment, generate, static
from v2xpos import geo
from v2xpos.ins import InsConfig, InsFilter, StaticCalibrationConfig, StaticCalibrator
from v2xpos.commands import replay as replay_cmd
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA


def _started_filter():
    tr = static(2.0)
    f = InsFilter(InsConfig(setup={"platform": "car"}))
    f.initialize(tr.t_s[0], tr.lla[0], np.zeros(3), np.zeros(3))
    imu = simulate_imu(tr)
    return f, tr, imu


def test_malformed_imu_samples_are_counted_not_fatal():
    f, tr, imu = _started_filter()
    acc, gyr = imu.acc_mps2.copy(), imu.gyro_rps.copy()
    acc[50, 1] = np.nan
    gyr[60, 2] = np.inf
    t = imu.t_s.copy()
    t[70] = t[69]            # duplicate stamp
    f.process_imu_batch(t[:100], acc[:100], gyr[:100])
    f.process_imu(t[50], acc[0], gyr[0])        # back in time
    f.process_imu_batch(t[100:], acc[100:], gyr[100:])
    assert f.counts["malformed_inputs"] == 4
    assert np.linalg.norm(geo.lla_to_ned(f.lla, tr.lla[0])) < 0.01


def test_batch_rejects_every_sample_behind_a_jump_like_single_samples():
    """A stamp jumping ahead inside a batch: every later sample not after it is malformed, as
    sample by sample (process_imu_batch is documented as equivalent to process_imu in order)."""
    f_batch, _, imu = _started_filter()
    f_single, _, _ = _started_filter()
    t = imu.t_s[:40].copy()
    t[20] = t[25]                                   # samples 21..25 are not after sample 20
    f_batch.process_imu_batch(t, imu.acc_mps2[:40], imu.gyro_rps[:40])
    for k in range(40):
        f_single.process_imu(t[k], imu.acc_mps2[k], imu.gyro_rps[k])
    assert f_batch.counts["malformed_inputs"] == f_single.counts["malformed_inputs"] == 5
    np.testing.assert_allclose(f_batch.nav, f_single.nav, rtol=0, atol=1e-12)


@pytest.mark.parametrize("bad", [
    dict(lla=np.array([np.nan, 0.0, 0.0])),
    dict(lla=np.array([1.0, 2.0])),
    dict(sd_ned_m="x"),
    dict(fix=99),
    dict(vel_ned_mps=[1.0, 2.0]),
    dict(t_s=np.nan),
    dict(t_s="x"),
])
def test_malformed_gnss_is_rejected_with_a_reason(bad):
    f, tr, imu = _started_filter()
    f.process_imu_batch(imu.t_s, imu.acc_mps2, imu.gyro_rps)
    kw = dict(t_s=tr.t_s[-1], lla=tr.lla[-1], sd_ned_m=np.full(3, 0.01), fix=FixStatus.FIXED)
    kw.update(bad)
    res = f.update_gnss(**kw)
    assert not res.accepted and "malformed" in res.reason
    assert f.counts["malformed_inputs"] == 1
    ok = f.update_gnss(tr.t_s[-1], tr.lla[-1], np.full(3, 0.01), FixStatus.FIXED)
    assert ok.accepted          # the filter goes on


def test_malformed_wheel_speed_is_counted():
    f, tr, imu = _started_filter()
    f.process_imu_batch(imu.t_s, imu.acc_mps2, imu.gyro_rps)
    for t, v in ((tr.t_s[-1], np.nan), (np.nan, 1.0), ("x", 1.0), (tr.t_s[-1], None)):
        assert not f.update_wheel_speed(t, v).accepted
    assert f.counts["malformed_inputs"] == 4 and np.all(np.isfinite(f.nav))
    assert f.update_wheel_speed(tr.t_s[-1], 0.0).accepted


def test_outlier_position_is_gated():
    f, tr, imu = _started_filter()
    f.process_imu_batch(imu.t_s, imu.acc_mps2, imu.gyro_rps)
    far = geo.ned_to_lla(np.array([30.0, 0.0, 0.0]), tr.lla[-1])
    res = f.update_gnss(tr.t_s[-1], far, np.full(3, 0.02), FixStatus.FIXED)
    assert not res.accepted and res.nis > 100 and f.counts["gnss_pos_rejected"] == 1


def test_seed001_static_calibration_estimates_biases():
    """Without a filter (``standalone_prior``: samples in vehicle axes, no attitude) the calibrator
    measures the gyro bias (Earth rate included, in its sd) and the accelerometer bias along gravity;
    the horizontal accelerometer bias cannot be told from tilt and keeps its prior; a 5-degree
    pitched stop is not level and yields no estimate."""
    tr = generate([Segment(5.0), Segment(3.0, accel_mps2=1.0), Segment(3.0), Segment(3.0, accel_mps2=-1.0),
                   Segment(6.0)])
    bg, ba = np.array([0.01, -0.02, 0.005]), np.array([0.05, -0.08, 0.1])
    model = ImuErrorModel(gyro_bias_rps=bg, accel_bias_mps2=ba, gyro_noise_rps_rthz=2e-4,
                          accel_noise_mps2_rthz=2e-3)
    imu = simulate_imu(tr, model, rng=np.random.default_rng(2))
    g = geo.normal_gravity_mps2(tr.lla0[0], tr.lla0[2])
    cfg = StaticCalibrationConfig(gravity_mps2=g)
    cal = StaticCalibrator(cfg)
    for k in range(0, len(imu), 10):      # the filter vetoes chunks with its speed estimate
        cal.feed(imu.t_s[k:k + 10], imu.acc_mps2[k:k + 10], imu.gyro_rps[k:k + 10],
                 moving=bool(tr.speed_mps[k:k + 10].max() > 0.1))
    cal.finish()
    assert len(cal.estimates) == 2 and cal.stops_not_level == 0     # one per stop, none while moving
    for est in cal.estimates:
        assert not est.attitude and est.filter_gyro_bias_rps is None
        assert np.all(np.abs(est.gyro_bias_rps - bg) < 3 * est.gyro_sd_rps)
        assert np.all(est.gyro_sd_rps < 6e-4)
        assert abs(est.accel_bias_mps2[2] - ba[2]) < 3e-3              # along gravity (level stop)
        np.testing.assert_allclose(est.accel_bias_mps2[:2], 0.0, atol=1e-3)   # the prior
        np.testing.assert_allclose(est.accel_sd_mps2[:2], cfg.accel_bias_prior_sd_mps2, rtol=1e-3)
        assert est.t_start_s < tr.t_s[0] + 5.0 or est.t_start_s > tr.t_s[0] + 14.0
    tilted = simulate_imu(static(5.0, pitch0_rad=np.radians(5.0)), model)
    cal2 = StaticCalibrator(cfg)
    cal2.feed(tilted.t_s, tilted.acc_mps2, tilted.gyro_rps)
    cal2.finish()
    assert cal2.estimates == [] and cal2.stops_not_level == 1
    assert abs(np.degrees(cal2.not_level[0].tilt_rad[1]) - 5.0) < 1.0


@pytest.mark.slow
def test_replay_cli_writes_json_and_plots(tmp_path):
    toml = DATA / "walk_0827" / "dataset.toml"
    require_shared(toml)
    p = argparse.ArgumentParser()
    replay_cmd.add_arguments(p)
    args = p.parse_args([str(toml), "--json", str(tmp_path / "r.json"), "--plots", str(tmp_path / "plots"),
                         "--no-progress", "--outage-first", "30", "--outage-every", "40", "--outage-length", "10"])
    assert replay_cmd.run(args) == 0
    s = json.loads((tmp_path / "r.json").read_text())
    assert s["dataset"] == "walk_0827" and s["outage_count"] == 2
    assert sorted(x.name for x in (tmp_path / "plots").glob("*.png")) == [
        "bias_estimates.png", "error_vs_time.png", "innovations.png", "trajectory.png"]


def test_replay_cli_reports_unloadable_dataset(tmp_path, capsys):
    bad = tmp_path / "dataset.toml"
    bad.write_text('name = "x"\nplatform = "car"\n[imu]\nfile = "missing.csv"\nformat = "csv_g_dps_ms"\n'
                   '[gnss]\nfile = "missing.pos"\nformat = "rtklib_pos"\n')
    p = argparse.ArgumentParser()
    replay_cmd.add_arguments(p)
    assert replay_cmd.run(p.parse_args([str(bad), "--no-progress"])) == 2
    assert "cannot load" in capsys.readouterr().err


@pytest.mark.slow
def test_replay_survives_a_truncated_and_corrupted_pos_file(tmp_path):
    """A copy of walk_0827 (outside the repo) whose .pos has a garbage line and is cut mid-line:
    the bad records are counted and the replay runs to the end."""
    src = DATA / "walk_0827"
    require_shared(src / "dataset.toml")
    import shutil
    for name in ("imu_1730.csv", "imu_1730.csv.tag"):
        shutil.copy(src / name, tmp_path / name)
    lines = (src / "gnss_1730.pos").read_text().splitlines(keepends=True)
    body = [i for i, ln in enumerate(lines) if not ln.startswith("%")]
    lines.insert(body[100], "2025/08/28 garbage line with no numbers\n")
    text = "".join(lines)
    (tmp_path / "gnss_1730.pos").write_text(text[: len(text) - 70])       # cut inside the last record
    toml = (src / "dataset.toml").read_text().replace('raw = "gnss_1730.ubx"', "").replace(
        'raw_timetag = "gnss_1730.ubx.tag"', "")
    (tmp_path / "dataset.toml").write_text(toml)
    from v2xpos.datasets import load_dataset
    from v2xpos.ins.replay import replay
    from v2xpos.ins.replay_engine import OutageSchedule
    clean = load_dataset(src / "dataset.toml")
    ds = load_dataset(tmp_path / "dataset.toml")
    assert ds.malformed_lines >= clean.malformed_lines + 2
    assert len(ds.gnss) == len(clean.gnss) - 1
    res = replay(ds, OutageSchedule(15.0, 45.0, 40.0), progress=False)
    assert res.summary["malformed_lines"] == ds.malformed_lines
    assert res.summary["imu_samples"] == len(clean.imu) and res.summary["aided_h_rms_m"] < 1.0


def test_filter_far_off_after_a_long_gap_resets_position():
    """A 300-m jump (e.g. the filter coasted far off) is gated, then after the consecutive-rejection
    limit the position is re-taken from GNSS instead of a linear update that cannot reach it."""
    f, tr, imu = _started_filter()
    f.process_imu_batch(imu.t_s, imu.acc_mps2, imu.gyro_rps)
    far = geo.ned_to_lla(np.array([300.0, 0.0, 0.0]), tr.lla[-1])
    for k in range(f.cfg.gnss.gnss_max_consecutive_rejections + 1):
        res = f.update_gnss(tr.t_s[-1], far, np.full(3, 0.02), FixStatus.FIXED)
    assert f.counts["gnss_pos_rejected"] == f.cfg.gnss.gnss_max_consecutive_rejections
    assert f.counts["position_resets"] == 1 and "reset" in res.reason
    assert np.linalg.norm(geo.lla_to_ned(f.lla, far)) < 0.1
    assert f.update_gnss(tr.t_s[-1], far, np.full(3, 0.02), FixStatus.FIXED).accepted
