"""The one event loop (v2xpos.ins.driver.InsDriver) on a simulated drive: where each measurement
goes among the IMU samples (equal stamps, estimated delays, other sensors), late arrivals put in
their place or counted and rejected, bad input counted, and a live run that reorders giving
exactly the filter of the offline run."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from sim.trajectory import urban_drive
from v2xpos.ins import InsConfig, InsFilter
from v2xpos.ins.driver import DriverHook, InsDriver
from v2xpos.types import FixStatus

IMU_DT_S = 0.01


@pytest.fixture(scope="module")
def drive():
    tr = urban_drive(40.0, seed=5)
    imu = simulate_imu(tr, ImuErrorModel.preset("tactical", np.random.default_rng(1)), rng=np.random.default_rng(2))
    gn = simulate_gnss(tr, GnssErrorModel(rate_hz=4.0), rng=np.random.default_rng(3))
    return tr, imu, gn


def make_filter(tr, imu, **effects) -> tuple[InsFilter, dict]:
    """A car filter without timing states (the delays stay what the config says; ``effects``: fields
    of its ``effects`` group) and its start."""
    f = InsFilter(InsConfig(setup={"platform": "car"}, effects={"states": (), **effects}))
    t0 = float(imu.t_s[0])
    s = tr.sample(t0)
    return f, dict(t_s=t0, lla=s["lla"][0], v_ned_mps=s["v_ned_mps"][0], rpy_rad=s["rpy_rad"][0])


def push_gnss(drv: InsDriver, gn, k: int, t_s: float | None = None) -> bool:
    return drv.push_gnss(float(gn.t_s[k]) if t_s is None else t_s, gn.lla[k], gn.sd_ned_m[k], FixStatus(int(gn.fix[k])),
                         gn.vel_ned_mps[k], gn.vel_sd_ned_mps[k], index=k)


class Seen(DriverHook):
    """Where the filter stands at each GNSS epoch, the update kinds in order, the states emitted."""

    def __init__(self):
        self.at_epoch, self.kinds, self.states, self.after = [], [], [], {}

    def on_gnss_epoch(self, f, t_s, k, used):
        self.at_epoch.append((t_s, f.t_s, f.nav_state()))

    def after_gnss_epoch(self, f, t_s, k, used):
        self.after[t_s] = f.nav_state()

    def on_update(self, result, f):
        self.kinds.append((result.kind, result.t_s))

    def on_state(self, f, nav):
        self.states.append(nav)


def run_offline(tr, imu, gn, cfg=None, hooks=(), tags=None):
    f, start = make_filter(tr, imu, **(cfg or {}))
    drv = InsDriver(f, complete=True, hooks=hooks)
    drv.push_imu_block(imu.t_s, imu.acc_mps2, imu.gyro_rps)
    drv.initialize(**start)
    for k in range(1, len(gn.t_s)):
        push_gnss(drv, gn, k, None if tags is None else tags[k])
    drv.run()
    return f, drv


def test_gnss_at_an_imu_stamp_goes_after_that_sample_and_into_its_state(drive):
    """Equal times: the sample brings the state to the epoch (gap 0), the update follows, and the
    state reported for that sample includes it; one microsecond earlier, the epoch goes before the
    sample, at the previous sample's state, and that state is reported without it."""
    tr, imu, gn = drive
    t_imu = np.asarray(imu.t_s)
    on_grid = np.isin(gn.t_s, t_imu)
    assert on_grid[1:].all()                                  # the simulated epochs fall on IMU stamps
    seen = Seen()
    run_offline(tr, imu, gn, hooks=[seen])
    states = {s.t_s: s for s in seen.states}
    for t_tag, t_filter, _ in seen.at_epoch:
        assert t_filter == t_tag
        np.testing.assert_array_equal(states[t_tag].lla, seen.after[t_tag].lla)
    early = Seen()
    run_offline(tr, imu, gn, hooks=[early], tags=np.asarray(gn.t_s) - 1e-6)
    states = {s.t_s: s for s in early.states}
    for t_tag, t_filter, nav_before in early.at_epoch:
        k = int(np.searchsorted(t_imu, t_tag))            # the sample the epoch precedes
        assert t_filter == t_imu[k - 1]
        np.testing.assert_array_equal(states[t_imu[k - 1]].lla, nav_before.lla)   # reported without it


def test_estimated_delays_place_the_gnss_among_the_imu_samples(drive):
    """An IMU time offset dt (sample s valid at s + dt) and a GNSS latency L (tag t valid at t - L):
    the epoch goes after the last sample valid at or before t - L, whatever the two are."""
    tr, imu, gn = drive
    dt, lat = 0.013, 0.021
    seen = Seen()
    run_offline(tr, imu, gn, cfg=dict(initial_time_offset_s=dt, initial_effects={"gnss_latency_s": lat}),
                hooks=[seen])
    assert len(seen.at_epoch) == len(gn.t_s) - 1
    for t_tag, t_filter, _ in seen.at_epoch:
        valid = t_tag - lat
        assert t_filter <= valid + 1e-9 < t_filter + IMU_DT_S + 1e-6
        assert t_filter > valid - IMU_DT_S


def test_measurements_of_different_sensors_go_in_order_of_validity(drive):
    """A wheel speed 10 ms before a GNSS tag whose latency is 30 ms is valid after the epoch: the
    GNSS update comes first; without the latency the wheel speed does."""
    tr, imu, gn = drive
    k = 40
    t_g = float(gn.t_s[k])
    for lat, first in ((0.03, "gnss_pos"), (0.0, "odometer")):
        seen = Seen()
        f, start = make_filter(tr, imu, initial_effects={"gnss_latency_s": lat})
        drv = InsDriver(f, complete=True, hooks=[seen])
        drv.push_imu_block(imu.t_s, imu.acc_mps2, imu.gyro_rps)
        drv.initialize(**start)
        push_gnss(drv, gn, k)
        drv.push_wheel(t_g - 0.01, float(np.linalg.norm(tr.sample(t_g - 0.01)["v_ned_mps"][0])))
        drv.run()
        kinds = [kd for kd, _ in seen.kinds if kd in ("gnss_pos", "odometer")]
        assert kinds[0] == first and set(kinds) == {"gnss_pos", "odometer"}


def live_run(tr, imu, gn, gnss_lag_s: float, window_s: float | None, extra=(), skip=()):
    """Events pushed at their arrival: IMU samples 3 ms after their stamp, GNSS epochs ``gnss_lag_s``
    after their tag (except those in ``skip``); ``extra``: (arrival time, GNSS index) pushed besides."""
    f, start = make_filter(tr, imu)
    seen = Seen()
    drv = InsDriver(f, reorder_window_s=window_s, emit_states=True, hooks=[seen])
    drv.initialize(**start)
    events = [(float(t) + 0.003, 0, k) for k, t in enumerate(imu.t_s[1:], 1)]
    events += [(float(gn.t_s[k]) + gnss_lag_s, 1, k) for k in range(1, len(gn.t_s)) if k not in skip]
    events += [(t_arr, 1, k) for t_arr, k in extra]
    states, pushed = [], []
    for t_arr, kind, k in sorted(events):
        if kind == 0:
            drv.push_imu(imu.t_s[k], imu.acc_mps2[k], imu.gyro_rps[k])
        else:
            pushed.append(push_gnss(drv, gn, k))
        states += drv.run(now_s=t_arr)
    drv.end_of_input()
    states += drv.run()
    return f, drv, states, seen, pushed


def test_late_gnss_is_put_in_its_place_and_the_filter_is_the_offline_one(drive):
    """Live, each epoch arrives 60 ms after the IMU beyond it was processed: the driver restores its
    snapshot from before the epoch and processes the samples since again. The filter ends exactly
    as the offline run's (every update the same), states leave at once and only ever go forward."""
    tr, imu, gn = drive
    f_off, _ = run_offline(tr, imu, gn)
    f_live, drv, states, _, _ = live_run(tr, imu, gn, 0.06, 0.5)
    assert drv.counts["reordered"] == len(gn.t_s) - 1 and drv.counts["rejected_late"] == 0
    np.testing.assert_array_equal(f_live.nav, f_off.nav)
    np.testing.assert_array_equal(f_live.P, f_off.P)
    assert [r.t_s for r in f_live.residuals] == [r.t_s for r in f_off.residuals]
    np.testing.assert_array_equal(np.array([r.innovation for r in f_live.residuals]),
                                  np.array([r.innovation for r in f_off.residuals]))
    t = np.array([s.t_s for s in states])
    assert len(t) == len(imu.t_s) - 1 and np.all(np.diff(t) > 0)


def test_late_events_beyond_the_window_or_out_of_their_sensors_order_are_counted_and_rejected(drive):
    """After a gap in the GNSS stream, epoch k_late arrives 1 s after its time (the window is
    0.5 s): rejected, never applied; epoch k_old arrives a second time after k_old + 1: rejected as
    out of its sensor's order."""
    tr, imu, gn = drive
    k_late, k_old = 50, 30
    extra = [(float(gn.t_s[k_late]) + 1.0, k_late), (float(gn.t_s[k_old + 1]) + 0.07, k_old)]
    gap = range(k_late - 2, k_late + 5)
    f, drv, _, seen, pushed = live_run(tr, imu, gn, 0.06, 0.5, extra=extra, skip=gap)
    c = drv.counts
    assert c["rejected_late"] == 1 and c["rejected_out_of_order"] == 1 and pushed.count(False) == 2
    applied = [t for t, _, _ in seen.at_epoch]
    assert float(gn.t_s[k_late]) not in applied and applied.count(float(gn.t_s[k_old])) >= 1
    assert drv.status()["applied"]["gnss"] == len(gn.t_s) - 1 - len(gap)
    # without a window (offline, sources whose events come in order) a late event is rejected
    f3, start = make_filter(tr, imu)
    drv3 = InsDriver(f3)
    drv3.initialize(**start)
    drv3.push_imu_block(imu.t_s[1:200], imu.acc_mps2[1:200], imu.gyro_rps[1:200])
    drv3.run()
    assert not push_gnss(drv3, gn, 2) and drv3.counts["rejected_late"] == 1 and drv3.counts["reordered"] == 0


def test_bad_imu_stamps_are_counted_and_the_rest_processed(drive):
    tr, imu, gn = drive
    f, start = make_filter(tr, imu)
    drv = InsDriver(f, emit_states=True)
    drv.initialize(**start)
    t = np.array(imu.t_s[1:101], float)
    t[10] = math.nan                    # no time
    t[20] = t[19]                       # repeated
    t[30] = t[25]                       # back in time
    out = []
    for k in range(100):
        drv.push_imu(t[k], imu.acc_mps2[k + 1], imu.gyro_rps[k + 1])
        out += drv.run()
    assert drv.counts["rejected_malformed"] == 1 and drv.counts["imu_out_of_order"] == 2
    assert len(out) == 97 and np.all(np.diff([s.t_s for s in out]) > 0)
    assert not drv.push_gnss(math.inf, gn.lla[1], gn.sd_ned_m[1], FixStatus.FIXED)
    assert drv.counts["rejected_malformed"] == 2


def test_a_gnss_epoch_without_imu_waits_then_goes_at_the_state_it_has(drive):
    """Live, an epoch ahead of the IMU waits for the samples before it; with no sample for
    ``max_wait_s`` it is applied at the filter's state (an IMU stream that stopped must not hold the
    GNSS back), counted."""
    tr, imu, gn = drive
    f, start = make_filter(tr, imu)
    drv = InsDriver(f, reorder_window_s=0.5)
    drv.initialize(**start)
    drv.push_imu_block(imu.t_s[1:50], imu.acc_mps2[1:50], imu.gyro_rps[1:50])
    k = int(np.searchsorted(gn.t_s, imu.t_s[49])) + 1
    push_gnss(drv, gn, k)
    t_g = float(gn.t_s[k])
    drv.run(now_s=t_g + 0.5)
    assert drv.pending().get("gnss") == 1 and f.counts["gnss_pos_accepted"] == 0
    drv.run(now_s=t_g + 1.01)
    assert drv.counts["applied_without_imu"] == 1 and f.counts["gnss_pos_accepted"] == 1


FEEDS = {"process_imu", "process_imu_batch", "update_gnss", "update_heading", "update_wheel_speed",
         "apply_vehicle_constraints"}
FILTER_MODULES = {"v2xpos/ins/filter.py", "v2xpos/ins/imu_path.py", "v2xpos/ins/initialization.py",
                  "v2xpos/ins/driver.py"}


def test_no_other_loop_feeds_a_filter():
    """Only the driver calls the filter's input methods: no module of the library, the services,
    the simulation or the benches has a loop of its own (read with ``ast``)."""
    import ast
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    found = []
    for pkg in ("v2xpos", "master", "slave", "sim", "bench"):
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            if rel in FILTER_MODULES:
                continue
            for node in ast.walk(ast.parse(path.read_text(), rel)):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in FEEDS:
                    found.append(f"{rel}:{node.lineno} {node.func.attr}")
    assert found == []
