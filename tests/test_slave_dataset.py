"""Slave state source from a recorded drive: the real filter on ../shared/data/drive_0708, with the
recording's times shifted onto a scenario epoch, stays on the RTK-fixed track."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slave.source import DatasetSource
from v2xpos import geo
from v2xpos.types import FixStatus

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def test_dataset_source_paced_and_on_track():
    path = DATA / "drive_0708"
    if not (path / "dataset.toml").exists():
        pytest.skip(f"dataset missing: {path}")
    epoch = 1.4e9
    src = DatasetSource(str(path), epoch_gps_s=epoch)
    states = []
    for k in range(1, 61):                       # 60 s of data in 1 s steps of the caller's clock
        new = src.advance(epoch + k)
        assert all(epoch - 0.05 <= s.t_s <= epoch + k + 0.05 for s in new)   # + estimated IMU time offset
        states += new
    assert len(states) > 3000 and src.filter.initialized
    t = np.array([s.t_s for s in states])
    assert np.all(np.diff(t) > 0)
    g = src.ds.gnss
    fixed = (g.fix == FixStatus.FIXED) & (g.t_s + src.time_shift_s > t[0] + 20) & (g.t_s + src.time_shift_s < t[-1])
    lla = np.array([s.lla for s in states])
    errs = []
    for tg, llag in zip(g.t_s[fixed] + src.time_shift_s, g.lla[fixed]):
        i = int(np.argmin(np.abs(t - tg)))
        if abs(t[i] - tg) < 0.02:
            errs.append(np.linalg.norm(geo.lla_to_ned(lla[i], llag)[:2]))
    assert len(errs) > 50 and float(np.median(errs)) < 0.5
