"""``v2xpos replay --smooth`` on recordings: recording for the smoother leaves the forward filter
exactly as it was; the JSON says ``"smoothed": true`` and carries the inside-outage figures forward
and smoothed beside the end-of-outage ones; ``--solution`` writes the smoothed solution (column
``smoothed``) with its sds; and the accuracy targets of issue 32: a generated vehicle with nothing
undeclared (convoy_dev A and generated clean vehicles) inside-outage h RMS <= 0.10 m, drive_0708 (real)
<= 0.3 m RMS, <= 1.0 m max, >= 95 % within 3 sd -- scored at every RTK-fixed epoch inside the
outages, not only at their ends."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from v2xpos import geo
from v2xpos.cli import main
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, needs_shared, require_shared

pytestmark = pytest.mark.slow   # replays of whole recordings (make test-fast leaves them out)

DEV_A = SHARED_DATA / "convoy_dev" / "A" / "dataset.toml"
DRIVE = SHARED_DATA / "drive_0708" / "dataset.toml"


@pytest.fixture(scope="module")
def dev_a(tmp_path_factory):
    require_shared(DEV_A)
    d = tmp_path_factory.mktemp("smooth")
    assert main(["replay", str(DEV_A), "--no-progress", "--json", str(d / "plain.json")]) == 0
    assert main(["replay", str(DEV_A), "--no-progress", "--smooth", "--json", str(d / "smooth.json"),
                 "--solution", str(d / "sol.csv")]) == 0
    return d


def test_recording_for_the_smoother_does_not_change_the_filter(dev_a):
    a = json.loads((dev_a / "plain.json").read_text())
    b = json.loads((dev_a / "smooth.json").read_text())
    for k in ("outage_h_rms_m", "aided_h_rms_m", "outage_h_m", "effects", "counts"):
        assert a[k] == b[k], k
    assert "smoothed" not in a and b["smoothed"] is True


def test_smoothed_figures_of_a_vehicle_without_undeclared_effects(dev_a):
    """convoy_dev A has no undeclared effect: inside the outages the smoothed error is within the
    issue's 0.10 m and its sds honest; the forward error there is several times larger."""
    s = json.loads((dev_a / "smooth.json").read_text())
    assert s["inside_outage_epochs"] >= 10 * s["outage_count"]
    assert s["smoothed_inside_outage_not_smoothed"] == 0
    assert s["smoothed_inside_outage_h_rms_m"] <= 0.10, s
    assert s["smoothed_inside_outage_h_rms_m"] < 0.3 * s["inside_outage_h_rms_m"]
    assert s["smoothed_inside_outage_within_3sd"] >= 0.95
    assert s["smoothed_outage_h_rms_m"] < s["outage_h_rms_m"]
    assert len(s["smoothed_inside_outage_h_m"]) == s["inside_outage_epochs"]
    sm = s["smoothing"]
    assert sm["segments"] >= 1 and sm["nodes"] > 0 and sm["backward_s"] > 0


def test_smoothed_solution_rows(dev_a):
    """One row per GNSS epoch as without --smooth, a trailing column smoothed; the smoothed rows'
    IMU point agrees with the RTK fixes inside the outages within their own 3 sd (the lever arm
    added through the row's attitude), as the forward rows there do not."""
    from v2xpos.datasets import load_dataset
    from v2xpos.rotation import dcm_from_euler
    with open(dev_a / "sol.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[-1] == "smoothed"
    smoothed = [r for r in rows if r["smoothed"] == "1"]
    assert len(smoothed) > 0.8 * len(rows)
    ds = load_dataset(DEV_A)
    gt, fix = np.asarray(ds.gnss.t_s), np.asarray(ds.gnss.fix)
    z, times, n = [], [], 0
    for r in smoothed:
        if r["gnss_used"] != "0":
            continue
        t = float(r["t_gps_s"])
        k = int(np.argmin(np.abs(gt - t)))
        if abs(gt[k] - t) > 0.05 or fix[k] != FixStatus.FIXED:
            continue
        lla = np.array([np.radians(float(r["lat_deg"])), np.radians(float(r["lon_deg"])), float(r["height_m"])])
        C = dcm_from_euler(*np.radians([float(r["roll_deg"]), float(r["pitch_deg"]), float(r["yaw_deg"])]))
        lever = np.array([float(r[f"lever_arm_{a}_m"]) for a in "xyz"])
        v = np.array([float(r["vn_mps"]), float(r["ve_mps"]), float(r["vd_mps"])])
        e = geo.lla_to_ned(lla, ds.gnss.lla[k]) + C @ lever + v * (gt[k] - t)
        sd = np.array([float(r["sd_north_m"]), float(r["sd_east_m"])])
        z.append(np.abs(e[:2]) / np.hypot(sd, 0.01))
        times.append(t)
        n += 1
    z = np.array(z)
    assert n > 100
    # the rows of one outage share one error realisation (the smoothed error is a slowly varying
    # curve through it), so a share of rows counts a few outages, not n independent samples: each
    # outage's error as a whole (RMS of the normalised error over its rows) is within 3 of its sd,
    # and over all rows at least 90 % are within 3 sd (an outage 1.3 sd off, about one in five, puts
    # a fifth of its rows beyond)
    outage = np.cumsum(np.r_[0, np.diff(times) > 2.0])
    for k in np.unique(outage):
        assert np.sqrt(np.mean(z[outage == k] ** 2)) <= 3.0, (k, np.sqrt(np.mean(z[outage == k] ** 2, axis=0)))
    assert np.mean(np.all(z <= 3.0, axis=1)) >= 0.90


def _generated(tmp_path, seed: int):
    assert main(["simulate", "convoy", "--out", str(tmp_path), "--seed", str(seed), "--preset", "clean",
                 "--duration", "200"]) == 0
    return tmp_path


@pytest.mark.slow
@pytest.mark.parametrize("seed", [21, 22, 23])
def test_generated_vehicles_without_undeclared_effects(tmp_path, seed):
    """Fresh generated recordings (preset clean: nothing undeclared), both cars: the smoothed error
    inside the outages within 0.10 m RMS and 95 % within 3 sd."""
    d = _generated(tmp_path, seed)
    for v in ("A", "B"):
        out = tmp_path / f"{v}.json"
        assert main(["replay", str(d / v / "dataset.toml"), "--no-progress", "--smooth", "--json", str(out)]) == 0
        s = json.loads(out.read_text())
        assert s["smoothed_inside_outage_h_rms_m"] <= 0.10, (seed, v, s["smoothed_inside_outage_h_rms_m"])
        assert s["smoothed_inside_outage_within_3sd"] >= 0.95, (seed, v)


@pytest.mark.slow
@needs_shared(DRIVE)
def test_drive_0708_smoothed_inside_the_outages(tmp_path):
    """The real drive, 11 outages of 15 s, every RTK-fixed epoch inside them: h RMS <= 0.3 m, max
    <= 1.0 m, >= 95 % within 3 sd (the forward filter there: about 1.3 m RMS, 6.4 m max)."""
    out = tmp_path / "d.json"
    assert main(["replay", str(DRIVE), "--no-progress", "--smooth", "--json", str(out)]) == 0
    s = json.loads(out.read_text())
    assert s["outage_count"] == 11 and s["inside_outage_epochs"] > 500
    assert s["smoothed_inside_outage_not_smoothed"] == 0
    assert s["smoothed_inside_outage_h_rms_m"] <= 0.3, s["smoothed_inside_outage_h_rms_m"]
    assert s["smoothed_inside_outage_h_max_m"] <= 1.0, s["smoothed_inside_outage_h_max_m"]
    assert s["smoothed_inside_outage_within_3sd"] >= 0.95
    assert s["smoothed_inside_outage_h_rms_m"] < s["inside_outage_h_rms_m"]


@needs_shared(DRIVE)
def test_recorder_on_the_services_filter():
    """The services' filter (integrity configuration: gyro scale estimated, noise measured online,
    the declared set-up excluded when its separation test fails, the gyro biases reset at a stop
    that refutes them) on drive_0708: every transition lies in the block the recorder stores (no
    Phi stored whole), every bias reset is a transition inside a segment
    (``smoother.reset_transition``) and only the resets that move the state end one."""
    from v2xpos.commands.replay import load_for_command
    from v2xpos.ins.calibrated import dataset_ins_config
    from v2xpos.ins.replay import replay
    from v2xpos.ins.replay_engine import OutageSchedule
    ds = load_for_command(str(DRIVE), "replay")
    r = replay(ds, OutageSchedule(length_s=0.0), cfg=dataset_ins_config(ds, service=True), progress=False,
               keep_series=False, smooth=True)
    rec, c = r.filter.recorder, r.filter.counts
    assert "gyro_scale" in r.filter.layout.effects
    assert rec.phi_full == {} and rec.nodes > 1000
    assert len(rec.resets) == c.get("static_calibration_resets", 0)
    # the drive-off alignment takes the heading again (Initialization._finish_drive_off_alignment)
    aligned = int(r.filter.time_alignment is not None)
    assert len(rec.segments) == 1 + c.get("lever_arm_excluded", 0) + c["position_resets"] + aligned
