"""Integrity on generated two-car recordings with truth (issue 15 "Numbers it must reach",
docs/integrity.md): the master pipeline in one process (``v2xpos convoy --in-process``) on a pair
with nothing undeclared and on the same pair with an undeclared 0.8 m antenna lever arm on the
follower, scored against the recordings' truth. The seed is not one of the Monte-Carlo seeds the
defaults were checked on. A third case is ``dev_like`` seed 5 of the Monte-Carlo (undeclared
misalignment, late IMU stamps, gyro scale and a 0.64 m lever-arm error on the follower): before the
protection level its follower was VALID while 0.5-0.6 m wrong, after passing a turn-count check."""
from __future__ import annotations

import csv
import io
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow

SEED = 11
DEV_SEED = 5


def _case(tmp: Path, name: str, effects: list[str], seed: int = SEED, preset: str = "clean") -> dict:
    from sim.recordings import apply_overrides, draw_params, simulate, write
    from master.convoy import dataset_identity, run_in_process
    from v2xpos.diagnose.truth import score_results_csv
    rec = tmp / name
    p = draw_params(seed, preset)
    apply_overrides(p, [], effects, [])
    write(simulate(p), rec)
    a, b = dataset_identity(rec / "A"), dataset_identity(rec / "B")
    out = tmp / f"{name}_out"
    out.mkdir()
    run_in_process(out, a, [b], log=io.StringIO())
    score = score_results_csv(out / "results.csv", rec / "truth_rel.csv",
                              {a[1]: rec / "A" / "truth.csv", b[1]: rec / "B" / "truth.csv"}, a[1])
    with open(out / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    reasons = Counter(part for row in rows for part in row["reason"].split(";") if part)
    first_valid_gps_s = next((float(r["t_gps_s"]) for r in rows if r["target"] == b[1] and r["status"] == "VALID"), None)
    return {**score["targets"][b[1]], "reasons": dict(reasons), "first_valid_gps_s": first_valid_gps_s,
            "first_turn_end_gps_s": _first_turn_end_gps_s(rec / "B" / "truth.csv", rows[0]["t_gps_s"])}


def _first_turn_end_gps_s(truth_csv: Path, any_result_gps_s: str, turn_deg: float = 45.0) -> float:
    """GPS time [s] at which the follower has completed its first turn: the first instant, after it
    starts moving, at which its true heading differs from the heading it drove off with by
    ``turn_deg`` (lane changes of a few degrees are not turns). The truth is in time of week; the
    week is that of the results."""
    tr = np.genfromtxt(truth_csv, delimiter=",", skip_header=1)
    tow, yaw = tr[:, 0], np.unwrap(np.radians(tr[:, 9]))
    k0 = int(np.argmax(np.hypot(tr[:, 4], tr[:, 5]) > 1.0))
    k1 = k0 + int(np.argmax(np.degrees(np.abs(yaw[k0:] - yaw[k0])) > turn_deg))
    week_start = float(any_result_gps_s) - float(any_result_gps_s) % 604800.0
    return week_start + float(tow[k1])


@pytest.fixture(scope="module")
def scores(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("integrity")
    return {"clean": _case(tmp, "clean", []), "lever": _case(tmp, "lever", ["B.lever_arm_error_m=0.8,0,0"]),
            "dev_like": _case(tmp, "dev_like", [], DEV_SEED, "dev_like")}


def test_clean_pair_sigma_is_honest_and_not_inflated(scores):
    s = scores["clean"]
    assert s["valid_fraction"] > 0.4, s["status_counts"]
    assert s["violations"] == 0, s["violation_examples"]
    assert s["within_3sd_x"] >= 0.98 and s["within_3sd_y"] >= 0.98, s
    assert s["moving"]["h_rms_m"] <= 0.03, s["moving"]
    assert s["median_sigma_h_over_h_rms"] <= 3.0, s
    # verified within the first turn: the first VALID row no later than the follower's first 45 deg
    # of heading change (issue 27; from a parked start the lever arm needs a turn unless verified)
    assert s["first_valid_gps_s"] is not None and s["first_valid_gps_s"] <= s["first_turn_end_gps_s"], s
    # and not before: a set-up never verified is not vouched for before both vehicles have turned
    # (no data depends on a lever arm before a heading change; diagnose.truth.HEADING_CHANGE_DEG)
    assert s["moving_valid_fraction"] <= s["moving_after_turn_fraction"], s
    # nothing undeclared: neither filter's consistency or separation test fires
    assert not [r for r in s["reasons"] if ":TEST_" in r], s["reasons"]


@pytest.mark.parametrize("case", ["lever", "dev_like"])
def test_undeclared_effects_are_never_valid_and_wrong(scores, case):
    s = scores[case]
    assert s.get("violations", 0) == 0, s.get("violation_examples")
    # the follower's own solution-separation test found it (its declaration excluded, the rows
    # meanwhile UNVERIFIED, reason target:TEST_SEPARATION) before any VALID row could be wrong;
    # on the clean pair the test never fires (test_clean_pair_sigma_is_honest_and_not_inflated)
    assert s["reasons"].get("target:TEST_SEPARATION", 0) > 0, s["reasons"]
    if s["status_counts"].get("VALID", 0):
        # after the exclusion the sigma is that of an estimate that never relied on the declaration
        assert s["within_3sd_x"] >= 0.98 and s["within_3sd_y"] >= 0.98, s


EVIDENCE_CASES = tuple((seed, preset) for seed in (11, 12, 13) for preset in ("clean", "dev_like")) + ((9, "clean"),)
"""Seeds not in the Monte-Carlo (0-9), and the Monte-Carlo's clean seed 9, whose follower raised
P(H1) to 0.5 on a straight road before the first-estimates lever-arm columns."""


def _replayed(dataset_toml: Path):
    """One vehicle's recording through the services' filter (``v2xpos.ins.profiles.dataset_config``):
    the filter at its end, its set-up hypothesis in ``separation``."""
    from v2xpos.datasets.loader import load_dataset
    from v2xpos.ins import InsFilter
    from v2xpos.ins.profiles import dataset_config
    from v2xpos.ins.replay_engine import run_replay
    ds = load_dataset(dataset_toml)
    flt = InsFilter(dataset_config(ds))
    run_replay(flt, ds, [], wheel=True)
    return flt


def test_the_set_up_hypothesis_rises_for_a_fault_and_only_then(tmp_path):
    """The twin's evidence (docs/integrity.md, "The twin sees the lever arm only through rotation
    the IMU measured"): on generated drives that start parked and accelerate straight before their
    first turn, a vehicle as declared never makes P(H1) rise to 10 times its prior, and a
    follower with undeclared effects (dev_like: an antenna 0.2-0.6 m off among them) makes it
    likely. Before the twin took its lever-arm columns at the first-estimates attitude, the clean
    follower of seed 9 reached P(H1) = 0.5 (a likelihood ratio of 1100) on a straight road."""
    from sim.recordings import draw_params, simulate, write
    for seed, preset in EVIDENCE_CASES:
        rec = tmp_path / f"{preset}_{seed}"
        write(simulate(draw_params(seed, preset)), rec)
        for vehicle in ("A", "B"):
            sep = _replayed(rec / vehicle / "dataset.toml").separation
            peak, prior = sep.peak_fault_probability, sep.prior
            if preset == "dev_like" and vehicle == "B":
                assert peak > 0.5, (preset, seed, vehicle, peak)
            else:
                assert peak < 10 * prior, (preset, seed, vehicle, peak, prior)


def test_a_real_pedestrian_as_declared_keeps_its_set_up():
    """The real walk_0827 (handheld receiver and IMU, tight turns; its declared set-up taken as
    right): the twin never excludes the declaration and P(H1) stays below 10 times its prior.
    An anchor that ignored the corrections of the heading's convergence from the walking course,
    or a pedestrian start at 20 deg sd (the course start was about 60 deg off), excluded it."""
    from tests.shared_data import SHARED_DATA, require_shared
    flt = _replayed(require_shared(SHARED_DATA) / "walk_0827" / "dataset.toml")
    assert flt.cfg.setup.platform == "pedestrian"
    assert flt.counts.get("lever_arm_excluded", 0) == 0
    assert flt.separation.peak_fault_probability < 10 * flt.separation.prior
