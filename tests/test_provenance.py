"""Provenance of reports: software version and git revision, config hashes that change with the
configs, seeds, start time; and the reports that carry it."""
from __future__ import annotations

import json
import re
from datetime import datetime, timedelta, timezone

import pytest

from v2xpos import __version__
from v2xpos.provenance import config_digest, process_start_utc, provenance, software, utc_iso


def test_layout_and_software(tmp_path):
    cfg = tmp_path / "master.toml"
    cfg.write_text("[service]\nfleet = 'a'\n")
    p = provenance("test", {"master": cfg, "args": {"seed": 3, "n": [1, 2]}}, seeds={"scenario": 3},
                   started_utc=1_700_000_000.0, argv=["v2xpos", "test"])
    assert set(p) == {"command", "software", "python", "configs", "configs_sha256", "seeds", "started_utc",
                      "written_utc", "argv"}
    assert p["software"]["version"] == __version__ and p["software"] == software()
    rev = p["software"]["git_revision"]
    assert rev is None or re.fullmatch(r"[0-9a-f]{40}", rev)
    assert p["started_utc"] == "2023-11-14T22:13:20.000Z" and p["seeds"] == {"scenario": 3}
    names = [c["name"] for c in p["configs"]]
    assert names == ["args", "master"] and p["configs"][0]["value"] == {"n": [1, 2], "seed": 3}
    assert p["configs"][1]["path"] == str(cfg) and re.fullmatch(r"[0-9a-f]{64}", p["configs"][1]["sha256"])
    json.dumps(p)                                   # plain JSON


def test_config_hash_follows_the_content_not_the_order(tmp_path):
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text("x = 1\n")
    b.write_text("y = 2\n")
    _, h1 = config_digest({"a": a, "b": b})
    _, h2 = config_digest({"b": b, "a": a})
    assert h1 == h2
    a.write_text("x = 2\n")
    _, h3 = config_digest({"a": a, "b": b})
    assert h3 != h1
    assert config_digest({"o": {"k": 1, "j": 2}})[1] == config_digest({"o": {"j": 2, "k": 1}})[1]
    entries, _ = config_digest({"gone": tmp_path / "missing.toml"})
    assert entries[0]["sha256"] is None
    assert config_digest(None) == ([], None)
    with pytest.raises(TypeError):
        config_digest({"bad": 3.0})


def test_start_time_is_this_process_and_iso_utc():
    start = process_start_utc()
    now = datetime.now(timezone.utc)
    assert now - timedelta(hours=2) < start <= now + timedelta(seconds=1)
    assert provenance("x")["started_utc"].endswith("Z")
    assert utc_iso(None) is None and provenance("x", seeds=5)["seeds"] == {"seed": 5}
