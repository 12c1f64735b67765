"""A short soak: separate master and slave processes, signed messages, BLOCK congestion control;
nothing lost, everything recorded, the recording replays to identical outputs."""
from __future__ import annotations

import pytest

from bench.soak import run_soak
from master.replay_session import replay_session

pytestmark = pytest.mark.slow


def test_short_soak_loses_nothing_and_replays_exactly(tmp_path):
    report = run_soak(slaves=4, rate=50.0, duration=6.0, out_dir=tmp_path, per_process=2, progress=False,
                      lead_s=3.0)
    assert report["sent"] == 4 * 50 * 6
    assert report["lost"] == 0 and report["received"] == report["sent"]
    assert report["recorded"] == report["received"]
    assert report["output"] == report["received"]
    assert report["rejected"] == {}
    assert report["rss_growth_pct"] is not None and report["rss_growth_pct"] < 20.0
    rep = replay_session(tmp_path / "session.mcap")
    assert rep.identical and rep.matched >= report["output"]
