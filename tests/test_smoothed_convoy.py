"""``v2xpos convoy --in-process --smooth`` and ``v2xpos bench real-pair --smooth``: relative results
from the vehicles' smoothed states. The smoothed fix of a state in a GNSS gap; results.csv with the
trailing column ``smoothed`` beside the forward results; on a generated pair with nothing undeclared
and GNSS outages in the follower, the smoothed results inside the outages exist (the forward pipeline
has none there: dead reckoning) and are within their sds of the truth, and everywhere both exist the
smoothed ones are at least as accurate; on the real pair (drive_0708 and itself 1.5 s later, an
outage in B) over the epochs both runs computed."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from master.smoothed_convoy import smoothed_fix
from v2xpos.cli import main
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, needs_shared

DRIVE = SHARED_DATA / "drive_0708" / "dataset.toml"
OUTAGES_B = ((70.0, 15.0), (130.0, 15.0))
"""GNSS outages of the generated follower [s from its first epoch, length s]."""
F, FL, DR = int(FixStatus.FIXED), int(FixStatus.FLOAT), int(FixStatus.DEAD_RECKONING)


def test_smoothed_fix_in_a_gap_is_the_worse_of_the_two_sides():
    # states in time order: fixed, then a gap (dead reckoning), then float, a gap with no fix after it
    forward = np.array([F, F, DR, DR, DR, FL, FL, DR, DR])
    last_fix = np.array([F, F, F, F, F, FL, FL, FL, FL])
    last_t = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 5.0, 5.0, 5.0, 5.0])
    assert smoothed_fix(forward, last_fix, last_t).tolist() == [F, F, FL, FL, FL, FL, FL, DR, DR]


def _outage_pair(tmp_path):
    """A generated clean pair whose follower B has no GNSS for 15 s twice (``real_pair.restamp_dataset``
    with no delay), B's truth beside it."""
    from bench.real_pair import restamp_dataset
    gen = tmp_path / "gen"
    assert main(["simulate", "convoy", "--out", str(gen), "--seed", "31", "--preset", "clean", "--duration", "200",
                 "--no-float"]) == 0
    b = restamp_dataset(gen / "B" / "dataset.toml", 0.0, tmp_path / "B", "B", OUTAGES_B)
    shutil.copy(gen / "B" / "truth.csv", tmp_path / "B" / "truth.csv")
    return gen, b


@pytest.mark.slow
def test_smoothed_convoy_on_a_generated_pair_with_outages(tmp_path):
    gen, b = _outage_pair(tmp_path)
    out = tmp_path / "run"
    assert main(["convoy", str(gen / "A" / "dataset.toml"), str(b), "--in-process", "--smooth", "--out", str(out),
                 "--truth", str(gen / "truth_rel.csv")]) == 0
    from v2xpos.output.results_csv import COLUMNS, read_results_csv
    header = (out / "results.csv").read_text().splitlines()[0].split(",")
    assert header == list(COLUMNS) + ["smoothed"]
    assert (out / "results_forward.csv").read_text().splitlines()[0].split(",") == list(COLUMNS)
    report = json.loads((out / "report.json").read_text())
    assert report["smoothed"] is True and report["smoothing"]["B"]["smoothed"] > 0
    sm, fw = read_results_csv(out / "results.csv"), read_results_csv(out / "results_forward.csv")
    assert np.nanmean(sm["smoothed"]) > 0.8
    from v2xpos.datasets import load_dataset
    from v2xpos.diagnose.truth import read_truth_rel, week_of
    tr = read_truth_rel(gen / "truth_rel.csv", week_of(sm["t_gps_s"]))
    t0_b = float(np.min(load_dataset(b).gnss.t_s))

    def errors(r: dict) -> dict:
        """Per computed row of B (attitude determined): horizontal error against the truth, the
        larger per-axis error in sds, VALID or not, inside B's outages or not."""
        ok = np.isfinite(r["x_m"]) & (r["target"] == "B") & (r["status"] != "ATTITUDE_UNCERTAIN")
        t = r["t_gps_s"][ok]
        ex, ey = r["x_m"][ok] - tr.at("x_m", t), r["y_m"][ok] - tr.at("y_m", t)
        keep = np.isfinite(ex) & np.isfinite(ey)
        z = np.maximum(np.abs(ex) / r["sd_x_m"][ok], np.abs(ey) / r["sd_y_m"][ok])
        inside = np.zeros(len(t), bool)
        for a, n in OUTAGES_B:
            inside |= (t - t0_b >= a) & (t - t0_b < a + n)
        return {"h": np.hypot(ex, ey)[keep], "z": z[keep], "inside": inside[keep], "valid": (r["status"][ok] == "VALID")[keep]}

    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(x ** 2)))
    es, ef = errors(sm), errors(fw)
    out_s, out_f = ~es["inside"], ~ef["inside"]
    assert out_s.sum() > 0.9 * out_f.sum() > 5000
    assert rms(es["h"][out_s]) <= rms(ef["h"][out_f]) and es["h"][out_s].max() <= ef["h"][out_f].max()
    assert rms(es["h"][out_s & es["valid"]]) <= rms(ef["h"][out_f & ef["valid"]])
    # inside B's outages the forward pipeline stops after the first second (dead reckoning: FIX_INVALID)
    assert es["inside"].sum() > 5 * max(1, ef["inside"].sum())
    assert rms(es["h"][es["inside"]]) <= 0.10
    assert np.mean(es["z"][es["inside"]] <= 3.0) >= 0.95


@pytest.mark.slow
@needs_shared(DRIVE)
def test_real_pair_smoothed_at_least_as_accurate_as_forward(tmp_path):
    """drive_0708 and itself 1.5 s later, B without GNSS for 15 s: over the epochs both runs computed
    the smoothed range error is not worse than the forward one (RMS and max), nor over those VALID in
    both; inside B's outage the smoothed pair gives results where the forward one gives none; no
    smoothed VALID row beyond max(0.3 m, 4 sd)."""
    out = tmp_path / "rp.json"
    assert main(["bench", "real-pair", str(DRIVE), "--delay", "1.5", "--smooth", "--outage", "100:15",
                 "--json", str(out)]) == 0
    d = json.loads(out.read_text())["delays"]["1.5"]
    both = d["smoothing"]["both_computed"]
    assert both["forward"]["n"] > 300
    assert both["smoothed"]["rms_m"] <= both["forward"]["rms_m"]
    assert both["smoothed"]["max_m"] <= both["forward"]["max_m"]
    valid = d["smoothing"]["both_valid"]
    assert valid["forward"]["n"] > 100 and valid["smoothed"]["rms_m"] <= valid["forward"]["rms_m"]
    ins = d["smoothing"]["inside_outages"]
    assert ins["smoothed"]["n"] > ins["forward_computed"]
    assert d["smoothed"]["violations"] == 0


DEV = SHARED_DATA / "convoy_dev"


@needs_shared(DEV)
def test_smooth_needs_in_process(tmp_path, capsys):
    """The smoother needs each whole recording: --smooth without --in-process (a live link) and
    real-pair --smooth --link are refused as usage errors, with nothing run."""
    assert main(["convoy", str(DEV / "A" / "dataset.toml"), str(DEV / "B" / "dataset.toml"), "--smooth",
                 "--out", str(tmp_path / "run")]) == 2
    assert "--smooth needs --in-process" in capsys.readouterr().err
    assert not (tmp_path / "run" / "results.csv").exists()
    assert main(["bench", "real-pair", str(DEV / "A" / "dataset.toml"), "--smooth", "--link"]) == 2
    assert main(["bench", "real-pair", str(DEV / "A" / "dataset.toml"), "--smooth", "--outage", "10"]) == 2
    assert "START:LENGTH" in capsys.readouterr().err


def test_smoothed_flags_cover_the_data_after_the_state():
    """A smoothed state is consistent only if the forward filter stayed consistent from it until one
    test window after the first fix that follows it: in a gap, after the gap's end."""
    from master.smoothed_convoy import smoothed_flags
    from v2xpos.types import FilterReason, NavState
    t = np.arange(0.0, 20.0, 1.0)
    bad = t == 12.0                        # the forward test fails at 12 s
    states = [NavState(t_s=float(x), lla=np.zeros(3), v_ned_mps=np.zeros(3), acc_body_mps2=np.zeros(3),
                       rate_body_rps=np.zeros(3), rpy_rad=np.zeros(3), consistent=not b,
                       reason=FilterReason.TEST_POSITION if b else FilterReason.OK) for x, b in zip(t, bad)]
    last_gnss = np.where(t < 3, t, np.where(t < 10, 2.0, t))   # a gap from 3 s to 10 s, fixes after it
    cons, ver, reason = smoothed_flags(states, last_gnss, window_s=2.0)
    # from the last fix before the gap (2 s) the next fix is the gap's end (10 s): the horizon reaches
    # 10 + 2 = 12 s, the failure; aided (from 10 s) it is the next fix + 2 s
    assert cons.tolist() == [True] * 2 + [False] * 11 + [True] * 7
    assert ver.all() and reason[5] == FilterReason.TEST_POSITION and reason[15] == FilterReason.OK
