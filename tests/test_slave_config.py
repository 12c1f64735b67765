"""Service configuration files: the shipped examples load; malformed files are rejected with a
message naming the file, the table and the key."""
from __future__ import annotations

from pathlib import Path

import pytest

from master.config import MasterConfig
from slave.config import ConfigError, SlaveConfig
from v2xpos.launch import to_toml

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_configs_load():
    m = MasterConfig.load(ROOT / "configs" / "master.toml")
    assert m.link.mode == "router" and m.link.listen == ["tcp/127.0.0.1:7447"] and m.service.timeout_ms == 200
    assert m.source.type == "recording" and m.source.table["wait_for"] == ["B"]
    assert MasterConfig.load(ROOT / "configs" / "master_mesh.toml").link.mode == "peer"
    assert MasterConfig.load(ROOT / "configs" / "master_sim.toml").source.type == "sim"
    s = SlaveConfig.load(ROOT / "configs" / "slave_t1.toml")
    assert s.service.vehicle_id == "B" and s.service.rate_hz == 100
    assert s.source.type == "recording" and s.link.mode == "client"
    assert not s.impairment.active
    p1 = SlaveConfig.load(ROOT / "configs" / "slave_p1.toml")
    assert p1.source.table["factory"] == "sim.source:from_config"


@pytest.mark.parametrize("text, where", [
    ("[service]\nrate_hz = 'fast'\n", "[service].rate_hz"),
    ("[service]\nrate_hz = 5000\n", "[service].rate_hz"),
    ("[service]\nrealtime_priority = 100\n", "[service].realtime_priority"),
    ("[service]\nvehicle = 't1'\n", "unknown key"),
    ("[link]\nmode = 'broker'\n", "[link]"),
    ("[source]\ntype = 'magic'\n", "[source].type"),
    ("[source]\ntype = 'recording'\ndataset = 'x'\n[impairment]\nlatency_ms = [1]\n", "[impairment].latency_ms"),
    ("[source]\ntype = 'recording'\ndataset = 'x'\n[impairment]\nspikes = [[1, 2]]\n", "[impairment].spikes[0]"),
    ("[source]\ntype = 'recording'\ndataset = 'x'\n[servise]\n", "did you mean 'service'"),
    ("[source]\n", "[source].type: required"),
    ("[source]\ntype = 'recording'\ndatset = 'x'\n", "did you mean 'dataset'"),
    ("[source]\ntype = 'sim'\nfactory = 'sim.source:from_config'\n[source.params]\nvehicels = 3\n",
     "did you mean 'vehicles'"),
    ("[service\n", "not valid TOML"),
])
def test_bad_slave_config_names_file_and_key(tmp_path, text, where):
    p = tmp_path / "bad_slave.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        SlaveConfig.load(p)
    assert str(p) in str(e.value) and where in str(e.value)


@pytest.mark.parametrize("table, where", [
    ({"service": {"timeout_ms": -1}}, "[service].timeout_ms"),
    ({"service": {"measurement_point_m": [1, 2]}}, "[service].measurement_point_m"),
    ({"service": {"dispatch": "threads"}}, "[service].dispatch"),
    ({"service": {"realtime_priority": 120}}, "[service].realtime_priority"),
    ({"output": {"udp": {"port": 70000}}}, "[output.udp].port"),
    ({"output": {"can": {"bitrat": 500000}}}, "[output.can]"),
        ({"output": {"can": {"bitrate": 5}}}, "[output.can].bitrate"),
        ({"output": {"udp": {"host": "239.0.0.1"}}}, "[output.udp].host"),
    ({"security": {"replay_window": 0}}, "[security].replay_window"),
    ({"scene": {"rate_hz": 0}}, "[scene].rate_hz"),
    ({"bogus": {}}, "unknown key"),
])
def test_bad_master_config_names_file_and_key(tmp_path, table, where):
    p = tmp_path / "bad_master.toml"
    p.write_text(to_toml(table) or "bogus = 1\n")
    with pytest.raises(ConfigError) as e:
        MasterConfig.load(p)
    assert str(p) in str(e.value) and where in str(e.value)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        SlaveConfig.load(tmp_path / "nope.toml")
