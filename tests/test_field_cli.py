"""Small things a user trips on (issue 29 items 7 and 8) and output directories: every command that
writes service configs makes its output directory absolute (the services resolve the paths of a
config against the config file's own directory, as ``configs/master.toml`` says)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from v2xpos import cli
from v2xpos.compat import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "v2xpos.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_help_lists_bench(capsys):
    assert cli.main(["--help"]) == 0
    assert "\n  bench " in capsys.readouterr().out


@pytest.mark.parametrize("argv,hint", [(["raplay"], "did you mean 'replay'?"),
                                       (["bench", "fanim"], "did you mean 'fanin'?")])
def test_a_misspelt_command_gets_a_did_you_mean(capsys, argv, hint):
    assert cli.main(argv) == 2
    assert hint in capsys.readouterr().err


def test_a_misspelt_option_gets_a_did_you_mean(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["replay", "x.toml", "--outage-lenght", "3"])
    assert info.value.code == 2
    assert "did you mean --outage-length?" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["-5", "0", "nan", "inf"])
def test_demo_refuses_a_duration_that_is_not_positive(capsys, tmp_path, value):
    assert cli.main(["demo", "--duration", value, "--out", str(tmp_path / "never")]) == 2
    assert "--duration must be > 0" in capsys.readouterr().err
    assert not (tmp_path / "never").exists()


def _paths(doc: dict) -> list[str]:
    """Every value of a config that names a file."""
    out = []
    for table in ("record", "scene", "security"):
        out += [v for v in (doc.get(table) or {}).values() if isinstance(v, str)]
    src = doc.get("source") or {}
    out += [src[k] for k in ("dataset", "start_file") if isinstance(src.get(k), str)]
    return out


def test_demo_configs_from_a_relative_out_are_absolute(tmp_path, monkeypatch):
    from sim.launcher import FleetPlan, write_configs
    from sim.scenarios import build
    monkeypatch.chdir(tmp_path)
    sc = build("convoy", vehicles=2, duration_s=5.0, pedestrian=False)
    plan = FleetPlan(out_dir=Path("rel/demo"), router_port=1, udp_port=2, start_file=Path("rel/demo/start"))
    write_configs(sc, plan, 5.0)
    for path in plan.configs.values():
        doc = tomllib.loads(path.read_text())
        assert _paths(doc) and all(Path(p).is_absolute() for p in _paths(doc)), (path, _paths(doc))
    assert all(p.is_absolute() for p in plan.configs.values())


def test_convoy_configs_from_a_relative_out_are_absolute(tmp_path, monkeypatch):
    from master.convoy import write_configs
    monkeypatch.chdir(tmp_path)
    paths = write_configs(Path("rel/convoy"), (tmp_path / "A.toml", "A", "car"), [(tmp_path / "B.toml", "B", "car")],
                          1.0)
    for path in paths.values():
        doc = tomllib.loads(path.read_text())
        assert _paths(doc) and all(Path(p).is_absolute() for p in _paths(doc)), _paths(doc)


def test_emulate_configs_from_a_relative_dir_are_absolute_and_complete(tmp_path, monkeypatch):
    """The master and slave configs emulate writes load as they are (the [source] table complete:
    platform, mounting, lever arm, streams, clock) with absolute record paths."""
    from master.config import MasterConfig
    from slave.config import SlaveConfig
    from v2xpos.commands.emulate import service_configs
    from v2xpos.devices.emulate import Emulator
    monkeypatch.chdir(tmp_path)
    assert _run(["simulate", "convoy", "--out", "rec", "--duration", "60", "--seed", "3"], tmp_path).returncode == 0
    emu = Emulator(["rec/A/dataset.toml", "rec/B/dataset.toml"], tcp=True)
    try:
        written = service_configs(emu, Path("rel/bench"), "tcp/127.0.0.1:7447", "bench", {})
    finally:
        emu.close()
    m = MasterConfig.load(written["A"])
    s = SlaveConfig.load(written["B"])
    assert Path(m.record.results_csv).is_absolute() and Path(m.record.results_csv).parent == (tmp_path / "rel/bench")
    assert m.source.table["clock"]["host_time_offset_s"] == s.source.table["clock"]["host_time_offset_s"]
    for table in (m.source.table, s.source.table):
        assert {"platform", "imu_to_body", "lever_arm_m", "gnss", "imu"} <= set(table)
    desc_b = tomllib.loads((tmp_path / "rec/B/dataset.toml").read_text())
    assert s.source.table["lever_arm_m"] == desc_b["gnss"]["lever_arm_m"]


def test_emulate_refuses_a_recording_it_cannot_serve_fully(tmp_path):
    from tests.shared_data import SHARED_DATA
    toml = SHARED_DATA / "convoy_dev" / "A" / "dataset.toml"
    if not toml.is_file():
        pytest.skip("shared data not present")
    p = _run(["emulate", str(toml)], tmp_path, timeout=60)
    assert p.returncode == 2 and "no GNSS byte stream" in p.stderr and "Traceback" not in p.stderr


def test_record_paths_are_relative_to_the_config_file(tmp_path, monkeypatch):
    from master.config import MasterConfig
    cfg_dir = tmp_path / "cfg"
    cfg_dir.mkdir()
    (cfg_dir / "master.toml").write_text('[source]\ntype = "recording"\ndataset = "x/dataset.toml"\n'
                                         '[record]\nresults_csv = "out/results.csv"\nmcap = "/abs/s.mcap"\n')
    monkeypatch.chdir(tmp_path)
    cfg = MasterConfig.load("cfg/master.toml")
    assert Path(cfg.record.results_csv) == cfg_dir / "out/results.csv"
    assert cfg.record.mcap == "/abs/s.mcap"


@pytest.mark.slow
def test_bench_trust_from_a_checkout_with_its_default_out(tmp_path):
    """`v2xpos bench trust` run from a directory with a relative default out/soak: its soak's
    services found out/soak/out/soak/... (a traceback, exit 3) before the soak made it absolute."""
    p = _run(["bench", "trust", "--fuzz-inputs", "200", "--soak-slaves", "2", "--soak-duration", "3",
              "--faults", "none"], tmp_path, timeout=600)
    assert "Traceback" not in p.stderr and p.returncode != 3, p.stderr[-3000:]
    report = json.loads(p.stdout[p.stdout.index("{"):])
    assert report["sent"] and report["lost"] == 0, report
    assert (tmp_path / "out" / "soak" / "master.json").is_file()


@pytest.mark.slow
def test_bench_fanin_from_a_relative_out(tmp_path):
    p = _run(["bench", "fanin", "--slaves", "1", "--step-s", "2", "--out", "rel/fanin", "--no-can"], tmp_path)
    assert "Traceback" not in p.stderr and p.returncode in (0, 1), p.stderr[-3000:]
    cfg = tomllib.loads((tmp_path / "rel/fanin/master.toml").read_text())
    assert all(Path(x).is_absolute() for x in _paths(cfg))
    assert (tmp_path / "rel/fanin/master_summary.json").is_file()
