"""Plug-in points (``v2xpos.plugins``, docs/extending.md): an output sink and a receiver decoder
defined in this test module and registered by name are configured, built and run exactly as the
built-in ones -- the master's ``[output.NAME]`` table, a device stream's ``format``."""
from __future__ import annotations

import pytest

from master.config import MasterConfig
from master.outputs import OUTPUT_GROUP, OutputContext, make_output
from v2xpos import plugins
from v2xpos.config import ConfigError
from v2xpos.datasets.issues import ParseIssues
from v2xpos.devices.framing import LineFramer
from v2xpos.devices.stream import DECODER_GROUP, DeviceStream, open_stream
from v2xpos.wire import RelativeResult


class ToySink:
    """Keeps every result's target and range (a stand-in for a new output format)."""

    def __init__(self, prefix: str):
        self.prefix = prefix
        self.rows: list[str] = []
        self.closed = False

    def write(self, result: RelativeResult) -> None:
        self.rows.append(f"{self.prefix}{result.target_id}:{result.range_m:.2f}")

    def close(self) -> None:
        self.closed = True


def check_table(table: dict, where: str) -> None:
    """The toy output's table: one key, ``prefix``."""
    from v2xpos.schema import check_keys
    check_keys(table, ("prefix",), where, ConfigError)


def toy_output(table: dict, where: str, ctx: OutputContext) -> ToySink:
    return ToySink(table.get("prefix", ""))


class ToyDecoder:
    """``t,value`` lines -> (t, value) records; anything else is malformed (a stand-in for a new
    receiver's protocol)."""

    def __init__(self, name: str, options):
        self.framer = LineFramer(name)
        self.lines = ParseIssues(f"{name} (toy)")
        self.parts = {"toy": self}
        self.issues = self.lines

    def decode(self, frame) -> list:
        try:
            t, value = frame.raw.decode().strip().split(",")
            return [(float(t), float(value))]
        except ValueError:
            self.issues.add(frame.end_offset, "not 't,value'")
            return []


SOURCE = {"source": {"type": "recording", "dataset": "A/dataset.toml"}}


@pytest.fixture
def toy_parts():
    plugins.register(OUTPUT_GROUP, "toy", f"{__name__}:toy_output")
    plugins.register(DECODER_GROUP, "toy_lines", f"{__name__}:ToyDecoder")
    yield
    plugins.unregister(OUTPUT_GROUP, "toy")
    plugins.unregister(DECODER_GROUP, "toy_lines")


def test_a_registered_output_is_configured_and_built_like_a_builtin(toy_parts):
    cfg = MasterConfig.from_dict({**SOURCE, "output": {"zenoh": {"enabled": False}, "toy": {"prefix": "T-"}}}, "m.toml")
    assert cfg.enabled_outputs() == [("toy", {"prefix": "T-"})]
    sink = make_output("toy", {"prefix": "T-"}, "m.toml: [output.toy]", OutputContext(cfg))
    sink.write(RelativeResult(target_id="B", range_m=12.345))
    sink.close()
    assert sink.rows == ["T-B:12.35"] and sink.closed


def test_a_registered_output_checks_its_table_and_a_misspelt_output_is_named(toy_parts):
    with pytest.raises(ConfigError, match=r"m.toml: \[output.toy\]: unknown key 'prefx' \(did you mean 'prefix'\?\)"):
        MasterConfig.from_dict({**SOURCE, "output": {"toy": {"prefx": "T-"}}}, "m.toml")
    with pytest.raises(ConfigError, match=r"m.toml: \[output\]: unknown key 'toyy' \(did you mean 'toy'\?\)"):
        MasterConfig.from_dict({**SOURCE, "output": {"toyy": {}}}, "m.toml")
    off = MasterConfig.from_dict({**SOURCE, "output": {"toy": {"enabled": False}}}, "m.toml")
    assert ("toy", {"enabled": False}) not in off.enabled_outputs()


def test_an_unregistered_output_can_name_its_factory():
    cfg = MasterConfig.from_dict({**SOURCE, "output": {"mine": {"factory": f"{__name__}:toy_output"}}}, "m.toml")
    assert [n for n, _ in cfg.enabled_outputs()][-1] == "mine"
    assert isinstance(make_output("mine", cfg.output.plugins["mine"], "w", OutputContext(cfg)), ToySink)


def test_a_registered_decoder_is_a_stream_format(toy_parts):
    got = []
    stream = open_stream({"format": "toy_lines", "tcp": "127.0.0.1:9"}, "dev", "s.toml: [source].gnss",
                         lambda: 0.0, got.append)
    stream.feed(b"1.0,2.5\ngarbage\n2.0,", 10.0)
    stream.feed(b"3.5\n", 10.1)
    assert got == [(1.0, 2.5), (2.0, 3.5)]
    stats = stream.stats()
    assert stats["format"] == "toy_lines" and stats["records"] == 2 and stats["toy"]["malformed"] == 1
    assert stats["malformed"] == 1
    with pytest.raises(ValueError, match=r"s.toml: \[source\].gnss.format: 'toy_line' is not one of .* \(did you mean 'toy_lines'\?\)"):
        open_stream({"format": "toy_line", "tcp": "127.0.0.1:9"}, "dev", "s.toml: [source].gnss", lambda: 0.0, got.append)


def test_the_builtin_formats_and_outputs_stay_registered():
    from master.outputs import output_kinds
    from v2xpos.devices.stream import decoder_formats
    assert list(decoder_formats())[:3] == ["ubx", "nmea", "csv_g_dps_ms"]
    assert list(output_kinds())[:4] == ["can", "udp", "zenoh", "results_csv"]
    with pytest.raises(ValueError, match="unknown stream format 'toy_lines'"):
        DeviceStream("x", "toy_lines", None, print)
