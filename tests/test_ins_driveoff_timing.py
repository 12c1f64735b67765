"""The IMU time offset after a drive-off (docs/integrity.md, What is short): a generated follower
starts from a stop, its heading is set from the GNSS course, and it accelerates straight. At a
constant acceleration the time offset is nearly collinear with the reset velocity's error, so the
drive-off teaches little about it: its estimate a few seconds after the heading reset must be
within 3 sd of the truth whether the IMU stamps are late or not. Before the position model carried
the quadratic term of the epoch shift (``updates.gnss_position``) and the heading reset turned the
models' accelerations (``Initialization._turn_about_down``), the estimate came out the same for
6 ms and 34 ms late stamps with a sd of ~10 ms (4.9 sd off with the stamps late on this route).
Seed 16 is not one of the Monte-Carlo seeds of docs/figures.md."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

SEED = 16
SECONDS_AFTER_RESET = 5.0


def _time_offset_after_drive_off(rec: Path) -> tuple[float, float, float]:
    """(truth, estimate, sd) of the follower's IMU time offset [s] 5 s after its heading reset."""
    from v2xpos.datasets.loader import load_dataset
    from v2xpos.ins.filter import InsFilter
    from v2xpos.ins.replay_engine import ReplayHook, config_for, run_replay
    truth = -json.loads((rec / "truth_effects.json").read_text())["vehicles"]["B"]["imu_time_late_s"]
    ds = load_dataset(rec / "B" / "dataset.toml")
    f = InsFilter(config_for(ds, "service"))
    i = f.layout.at("imu_time_offset")
    seen: dict = {}

    class At(ReplayHook):
        def on_update(self, r, flt):
            if "reset" not in seen:
                if flt.heading_known:
                    seen["reset"] = r.t_s
            elif "dt" not in seen and r.t_s - seen["reset"] >= SECONDS_AFTER_RESET:
                seen["dt"] = (flt.fx.imu_time_offset_s, math.sqrt(flt.P[i, i]))

    run_replay(f, ds, [], [At()])
    return truth, *seen["dt"]


@pytest.mark.parametrize("extra_delay_s", [0.0, 0.028])
def test_the_drive_off_does_not_pin_the_imu_time_offset(tmp_path, extra_delay_s):
    from sim.recordings import apply_overrides, draw_params, simulate, write
    p = draw_params(SEED, "clean")
    apply_overrides(p, [], [f"B.imu_stamp_extra_delay_s={extra_delay_s}"], [])
    write(simulate(p), tmp_path)
    truth, est, sd = _time_offset_after_drive_off(tmp_path)
    assert abs(est - truth) <= 3.0 * sd, (truth, est, sd)
