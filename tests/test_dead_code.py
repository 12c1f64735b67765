"""No dead code: vulture (static analysis) finds no unused function, method or class in the
project's packages, counting every use in the packages and in the tests.

Confidence: vulture reports an unused function, method or class at 60 % (it cannot see calls made
by name), so the test takes every such finding at 60 % and lists below, with the reason, each name
that is used only by name -- the whitelist. A finding outside it is either dead (delete it) or used
by name in a way this file should state (add it here, saying by whom).
"""
from __future__ import annotations

from pathlib import Path

import pytest

vulture = pytest.importorskip("vulture")

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("v2xpos", "master", "slave", "sim", "bench")
MIN_CONFIDENCE = 60
KINDS = ("function", "method", "class")

USED_BY_NAME = {
    # v2xpos.cli runs a command module's add_arguments/run and a bench's add_bench_arguments/run_bench by name
    "add_arguments": "v2xpos.cli (getattr on the command module)",
    "add_bench_arguments": "v2xpos.cli (getattr on bench/NAME.py)",
    "run_bench": "v2xpos.cli (getattr on bench/NAME.py)",
    # registries name their parts as "module:attribute" strings (v2xpos.plugins)
    "can_output": "master.outputs.BUILTIN_OUTPUTS", "udp_output": "master.outputs.BUILTIN_OUTPUTS",
    "zenoh_output": "master.outputs.BUILTIN_OUTPUTS", "results_csv_output": "master.outputs.BUILTIN_OUTPUTS",
    "UbxReceiver": "v2xpos.devices.stream.BUILTIN_DECODERS", "NmeaReceiver": "v2xpos.devices.stream.BUILTIN_DECODERS",
    "CsvImu": "v2xpos.devices.stream.BUILTIN_DECODERS",
    # replay hooks, called by name (v2xpos.ins.replay_engine._call_hooks)
    "on_output": "v2xpos.ins.replay_engine hooks", "on_outage_end": "v2xpos.ins.replay_engine hooks",
    # http.server.BaseHTTPRequestHandler calls these
    "do_GET": "http.server", "log_message": "http.server",
    # public API documented with an example in docs/quality.md
    "add_aligned": "docs/quality.md (ImuGrader.add_aligned)",
}


def test_no_unused_function_method_or_class():
    v = vulture.Vulture()
    v.scavenge([str(ROOT / p) for p in (*PACKAGES, "tests")])
    dead = [f"{Path(item.filename).relative_to(ROOT)}:{item.first_lineno}: unused {item.typ} {item.name!r}"
            for item in v.get_unused_code(min_confidence=MIN_CONFIDENCE)
            if item.typ in KINDS and item.name not in USED_BY_NAME
            and Path(item.filename).relative_to(ROOT).parts[0] in PACKAGES]
    assert not dead, "dead code (delete it, or whitelist a use by name in tests/test_dead_code.py):\n" + "\n".join(dead)


def test_every_whitelisted_name_is_still_defined():
    """A whitelist entry whose name is gone is itself dead."""
    text = "\n".join(p.read_text() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))
    gone = [name for name in USED_BY_NAME if f"def {name}(" not in text and f"class {name}" not in text]
    assert not gone, gone
