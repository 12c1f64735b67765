"""The ``recording`` source: the real filter on ../shared/data/drive_0708 advanced by a caller's
clock on the recording's own GPS time (no epoch, no shift) stays on the RTK-fixed track; the
``[source]`` table is validated with the key named; the replay clock's leader/follower pair agrees
on time over a real zenoh link."""
from __future__ import annotations

import time

import numpy as np
import pytest

from v2xpos import geo
from v2xpos.ins.replay_engine import ReplayHook
from v2xpos.sources import SourceContext, SourceError, make_source
from v2xpos.sources.clock import ReplayClock
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA


def _drive():
    path = DATA / "drive_0708" / "dataset.toml"
    return require_shared(path)


@pytest.mark.slow
def test_recording_source_on_its_own_gps_time_and_on_track():
    path = _drive()
    src = make_source({"type": "recording", "dataset": str(path), "sync": "none"}, "[source]",
                      SourceContext(vehicle_id="car"))
    t0 = src.t_begin_gps_s
    assert abs(t0 - float(src.ds.imu.t_s[0])) < 1e-9
    states = []
    for k in range(1, 61):                       # 60 s of data in 1 s steps of the caller's clock
        new = src.advance(t0 + k)
        assert all(t0 - 0.5 <= s.t_s <= t0 + k + 0.5 for s in new)   # + the estimated IMU time offset
        states += new
    assert len(states) > 3000 and src.filter.initialized
    t = np.array([s.t_s for s in states])
    assert np.all(np.diff(t) > 0)
    g = src.ds.gnss
    fixed = (g.fix == FixStatus.FIXED) & (g.t_s > t[0] + 20) & (g.t_s < t[-1])
    lla = np.array([s.lla for s in states])
    errs = []
    for tg, llag in zip(g.t_s[fixed], g.lla[fixed]):
        i = int(np.argmin(np.abs(t - tg)))
        if abs(t[i] - tg) < 0.02:
            errs.append(np.linalg.norm(geo.lla_to_ned(lla[i], llag)[:2]))
    assert len(errs) > 50 and float(np.median(errs)) < 0.5
    assert not src.finished(t0 + 60) and src.status()["imu_done"] > 0


@pytest.mark.parametrize("table, where", [
    ({"type": "recording"}, "[source].dataset"),
    ({"type": "recording", "dataset": "x", "sped": 2.0}, "did you mean 'speed'"),
    ({"type": "recording", "dataset": "x", "speed": 0}, "[source].speed"),
    ({"type": "recording", "dataset": "x", "sync": "always"}, "[source].sync"),
    ({"type": "recording", "dataset": "/nonexistent/dataset.toml"}, "[source].dataset"),
    ({"type": "recordng", "dataset": "x"}, "did you mean 'recording'"),
])
def test_recording_table_errors_name_the_key(table, where):
    with pytest.raises(SourceError) as e:
        make_source(table, "[source]", SourceContext(vehicle_id="car"))
    assert where in str(e.value)


def test_replay_clock_follower_agrees_with_leader_over_zenoh():
    from v2xpos.launch import free_tcp_port
    from v2xpos.link import Link, LinkConfig
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = Link(LinkConfig(mode="router", listen=[ep]))
    client = Link(LinkConfig(mode="client", connect=[ep], connect_timeout_ms=5000))
    t_begin = 1.4e9 + 123.456
    try:
        leader = ReplayClock(t_begin, speed=2.0, mode="leader", link=router, fleet="f", vehicle_id="A",
                             wait_for=("B",), wait_timeout_s=10, say=lambda m: None)
        follower = ReplayClock(t_begin + 50.0, speed=1.0, mode="follower", link=client, fleet="f",
                               vehicle_id="B", wait_timeout_s=10, say=lambda m: None)
        import threading
        got = {}
        th = threading.Thread(target=lambda: got.update(ok=leader.start()))
        th.start()
        assert follower.start()            # announces ready; the leader starts; the follower anchors
        th.join(5)
        assert got["ok"] and follower.speed == 2.0      # the leader's speed wins
        time.sleep(0.5)                     # a few clock messages refine the anchor
        d = [follower.now_gps_s() - leader.now_gps_s() for _ in range(5)]
        assert all(-0.005 < x <= 0.001 for x in d), d   # the follower is never ahead, at most a few ms behind
        assert abs(leader.now_gps_s() - (t_begin + 2.0 * 0.5)) < 0.5
    finally:
        leader.close()
        follower.close()
        client.close()
        router.close()


def test_recording_source_applies_the_recordings_calibration_table():
    """A ``[calibration]`` table (from ``v2xpos calibrate --write-dataset``) reaches the filter of a
    recording source exactly as it reaches ``v2xpos replay``'s."""
    from v2xpos.datasets.calibration import parse_calibration
    from v2xpos.datasets.loader import load_dataset
    from v2xpos.ins.replay_engine import config_for
    from v2xpos.sources.recording import ins_config_for
    ds = load_dataset(_drive())
    plain = ins_config_for(ds)
    ds.calibration = parse_calibration({"gnss_lever_arm_m": {"value": [0.4, -0.2, 0.0], "sd": [0.01, 0.01, 0.02]},
                                        "imu_time_offset_s": {"value": -0.02, "sd": 0.001}}, "test: [calibration]")
    cal = ins_config_for(ds)
    assert np.allclose(cal.setup.lever_arm_m - plain.setup.lever_arm_m, [0.4, -0.2, 0.0])
    assert cal.effects.initial_time_offset_s == -0.02
    assert np.allclose(cal.setup.lever_arm_m, config_for(ds).setup.lever_arm_m)


class KeepStates(ReplayHook):
    """A replay hook keeping every state the replay emits (one per IMU sample)."""

    def __init__(self):
        self.states = []

    def on_state(self, f, nav):
        self.states.append(nav)


def _source_and_replay_states(path, span_s: float, step_s: float = 0.01):
    """The ``recording`` source advanced in ``step_s`` steps over ``span_s`` and ``run_replay`` of the
    same loaded recording (the services' profile, no outages) keeping every state."""
    from v2xpos.ins import InsFilter
    from v2xpos.ins.replay_engine import config_for, run_replay
    from v2xpos.sources.recording import RecordingSource
    src = RecordingSource(path, sync="none")
    t0, states, k = src.t_begin_gps_s, [], 0
    while t0 + k * step_s < t0 + span_s:
        k += 1
        states += src.advance(t0 + k * step_s)
    keep = KeepStates()
    run_replay(InsFilter(config_for(src.ds)), src.ds, [], [keep])
    return src, states, [s for s in keep.states if s.t_s <= states[-1].t_s]


def _assert_same_states(a, b):
    assert len(a) == len(b) > 1000
    for name in ("t_s", "lla", "v_ned_mps", "rpy_rad", "pos_sd_m", "att_sd_rad", "fix", "consistent", "verified"):
        np.testing.assert_array_equal(np.array([getattr(s, name) for s in a]), np.array([getattr(s, name) for s in b]),
                                      err_msg=name)


@pytest.mark.slow
def test_recording_source_and_replay_give_identical_states_with_wheel_speeds():
    """comma2k19 (a car with wheel speeds): the ``recording`` source and ``v2xpos replay``'s engine
    run the same driver, events, order and profile -- state for state identical, bit for bit."""
    seg = require_shared(DATA / "comma2k19_rav4_segment" / "processed_log")
    src, states, replayed = _source_and_replay_states(seg.parent, 30.0)
    assert src.status()["driver"]["wheel_pushed"] > 1000
    _assert_same_states(states, replayed)


@pytest.mark.slow
def test_recording_source_and_replay_agree_on_a_recording_with_malformed_lines(tmp_path):
    """A generated recording whose IMU csv has malformed lines besides its cut first one: both paths
    skip and count the same lines (``malformed_lines``) and give identical states; the source's
    advance step does not matter."""
    from sim.recordings import generate_convoy
    generate_convoy(tmp_path, seed=5, preset="dev_like", duration_s=60.0)
    csv = tmp_path / "A" / "imu.csv"
    lines = csv.read_text().splitlines(keepends=True)
    for k in (500, 1500, 2500):
        lines[k] = "0.01,abc,1.0,0.1,0.2\n"
    csv.write_text("".join(lines))
    src, states, replayed = _source_and_replay_states(tmp_path / "A" / "dataset.toml", 50.0)
    assert src.status()["malformed_lines"] == src.ds.malformed_lines == 4
    _assert_same_states(states, replayed)
    _, coarse, _ = _source_and_replay_states(tmp_path / "A" / "dataset.toml", 50.0, step_s=0.37)
    _assert_same_states(coarse[:len(states)], states[:len(coarse)])
