"""`v2xpos demo` / `master` / `slave` / `bench fanin` command wiring (argument tables, defaults and
rejection of bad arguments; the runs themselves are in test_convoy_multiprocess.py)."""
from __future__ import annotations

import argparse

import pytest

from v2xpos import cli


def parse(module, argv, entry="add_arguments"):
    import importlib
    p = argparse.ArgumentParser()
    getattr(importlib.import_module(module), entry)(p)
    return p.parse_args(argv)


def test_demo_defaults_match_make_demo():
    a = parse("sim.demo", ["--out", "out/demo"])
    assert (a.vehicles, a.duration, a.latency_ms, a.source, a.out) == (4, 30.0, 100.0, "ins", "out/demo")
    assert not a.no_live and not a.no_pedestrian


def test_demo_rejects_too_few_vehicles(capsys):
    assert cli.main(["demo", "--vehicles", "1", "--out", "/nonexistent/never-written"]) == 2
    assert "--vehicles must be >= 2" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["-1", "nan", "inf"])
def test_demo_rejects_bad_rtk_vertical_factor(capsys, value):
    assert cli.main(["demo", "--rtk-vertical-factor", value, "--out", "/nonexistent/never-written"]) == 2
    assert "--rtk-vertical-factor must be a finite number >= 0" in capsys.readouterr().err


def test_convoy_receivers_have_the_requested_vertical_noise():
    from sim.scenarios import build
    sc = build("convoy", vehicles=3, duration_s=5.0, rtk_vertical_factor=1.0)
    assert {a.gnss_vertical_factor for a in sc.actors.values()} == {1.0}
    import numpy as np
    from sim.source import simulated_gnss
    for factor in (1.0, 1.5):
        s2 = build(**{**sc.params, "rtk_vertical_factor": factor})
        g = simulated_gnss(s2, s2.actors["t2"])
        assert np.allclose(g.sd_ned_m[:, 2], factor * g.sd_ned_m[:, 0])


def test_service_commands_report_config_errors(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[service]\nrate_hz = -1\n")
    assert cli.main(["slave", "--config", str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err
    bad.write_text("[service]\ntimeout_ms = 0\n")
    assert cli.main(["master", "--config", str(bad)]) == 2
    assert "timeout_ms" in capsys.readouterr().err


def test_bench_fanin_arguments():
    a = parse("bench.fanin", ["--slaves", "8,16"], "add_bench_arguments")
    assert a.slaves == "8,16" and a.rate_hz == 100.0 and a.p99_limit_ms == 10.0 and a.can_rate_hz == 25.0
    with pytest.raises(SystemExit):
        parse("bench.fanin", ["--dispatch", "threads"], "add_bench_arguments")
