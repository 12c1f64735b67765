"""The replay engine (v2xpos.ins.replay_engine.run_replay) on a simulated drive: what each hook sees, and
that v2xpos replay and calibrate's fit replays are the same loop."""
from __future__ import annotations

import numpy as np
import pytest

from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from sim.trajectory import urban_drive
from v2xpos.diagnose import runner
from v2xpos.ins import InsConfig, InsFilter
from v2xpos.ins.replay import replay
from v2xpos.ins.replay_engine import OutageSchedule, ReplayHook, outage_windows, run_replay
from v2xpos.types import Dataset

CAR_MOUNT = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
SCHEDULE = OutageSchedule(length_s=6.0, every_s=20.0, first_s=15.0)


@pytest.fixture(scope="module")
def dataset() -> Dataset:
    tr = urban_drive(80.0, seed=3)
    imu = simulate_imu(tr, ImuErrorModel.preset("automotive", np.random.default_rng(4)), imu_to_body=CAR_MOUNT,
                       rng=np.random.default_rng(5))
    gn = simulate_gnss(tr, GnssErrorModel(rate_hz=4.0), rng=np.random.default_rng(6))
    return Dataset(name="sim", platform="car", imu=imu, gnss=gn, imu_to_body=CAR_MOUNT)


class Recorder(ReplayHook):
    def __init__(self):
        self.epochs, self.after, self.ends, self.updates = [], [], [], []

    def on_gnss_epoch(self, f, t_s, k, used):
        self.epochs.append((t_s, k, used, f.t_s if f.initialized else np.nan))

    def after_gnss_epoch(self, f, t_s, k, used):
        self.after.append((t_s, k))

    def on_outage_end(self, f, t_s, i):
        self.ends.append((t_s, i))

    def on_update(self, result, f):
        self.updates.append(result)


def test_hooks_see_every_epoch_in_order_and_no_gnss_inside_outages(dataset):
    outages, n_scheduled = outage_windows(SCHEDULE, dataset)
    assert len(outages) == n_scheduled >= 2
    f = InsFilter(InsConfig(setup={"platform": "car", "imu_to_body": CAR_MOUNT}))
    rec = Recorder()
    run_replay(f, dataset, outages, [rec])
    t_gnss = np.asarray(dataset.gnss.t_s)
    assert [k for _, k, _, _ in rec.epochs] == list(range(len(t_gnss)))
    assert [k for _, k in rec.after] == list(range(len(t_gnss)))
    inside = np.array([any(a <= t < b for a, b in outages) for t in t_gnss])
    assert np.array_equal([u for _, _, u, _ in rec.epochs], ~inside)
    assert [i for _, i in rec.ends] == list(range(len(outages)))
    assert np.allclose([t for t, _ in rec.ends], [b for _, b in outages])
    # the state reaches each epoch (to within one IMU interval) before the hook sees it; its label,
    # stamp + time-offset estimate, may pass the epoch by what that estimate moved while the batch
    # up to it was integrated (updates at its chunk ends: tens of microseconds as the offset
    # becomes observable when the car drives off)
    lag = np.array([t - tf for t, _, _, tf in rec.epochs if np.isfinite(tf)])
    assert len(lag) > 0.9 * len(t_gnss) and np.all(lag > -1e-3) and np.all(lag < 0.02)
    # no GNSS update inside an outage; the per-update hook sees every update (the filter keeps GNSS's)
    t_gnss_updates = np.array([r.t_s for r in rec.updates if r.kind == "gnss_pos"])
    assert len(t_gnss_updates) > 0
    assert not np.any([any(a <= t < b for a, b in outages) for t in t_gnss_updates])
    assert [id(r) for r in rec.updates if r.kind.startswith("gnss")] == [id(r) for r in f.residuals]
    assert {"nhc", "zupt"} & {r.kind for r in rec.updates}


def test_exact_epochs_puts_the_state_at_each_epoch_and_constraints_between(dataset):
    f = InsFilter(InsConfig(setup={"platform": "car", "imu_to_body": CAR_MOUNT}, effects={"states": ()},
                            constraints={"constraints_on_request": True}))
    rec = Recorder()
    run_replay(f, dataset, [], [rec], wheel=False, outage_end_events=False, exact_epochs=True)
    lag = np.array([t - tf for t, _, _, tf in rec.epochs if np.isfinite(tf)])
    assert np.all(np.abs(lag) < 1e-9)
    t_gnss = np.asarray(dataset.gnss.t_s)
    t_nhc = np.array([r.t_s for r in rec.updates if r.kind in ("nhc", "zupt")])
    assert len(t_nhc) > 0
    # each constraint mid-way between two GNSS epochs, never at one
    gap = np.min(np.abs(t_nhc[:, None] - t_gnss[None, :]), axis=1)
    assert np.all(gap > 0.05)
    with pytest.raises(ValueError):
        run_replay(InsFilter(InsConfig(setup={"platform": "car", "imu_to_body": CAR_MOUNT})), dataset, [],
                   exact_epochs=True)


@pytest.mark.slow
def test_replay_and_fit_replay_are_the_same_loop(dataset):
    """The declared model through ``v2xpos replay`` and through calibrate's fit replay (no
    odometer, outages not thinned) gives the same innovations, update for update."""
    setup = dict(platform="car", imu_to_body=CAR_MOUNT, lever_arm_m=np.zeros(3), lever_arm_sd_m=0.1)
    res = replay(dataset, SCHEDULE, cfg=InsConfig(setup=setup, effects={"states": ()}), progress=False,
                 keep_series=False)
    fit = runner.replay(dataset, SCHEDULE, config={"setup": setup})
    pos = [r for r in res.filter.residuals if r.kind == "gnss_pos"]
    g = fit.log["gnss_pos"]
    assert len(pos) == len(g) > 100
    assert np.allclose([r.t_s for r in pos], g.t_s, rtol=0, atol=0)
    assert np.allclose(np.array([r.innovation for r in pos]), g.innovation, rtol=0, atol=1e-9)
    assert res.summary["outage_count"] == fit.metrics["outage_count"]
