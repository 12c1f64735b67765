"""`v2xpos bench trust --json FILE` writes the report's keys, and its exit code says whether the
link held: 0 when nothing forged or replayed got through and every fault scenario passed, 1 when a
scenario failed."""
from __future__ import annotations

import json

import pytest

from bench import trust_faults
from v2xpos.cli import main as cli_main

pytestmark = pytest.mark.slow


def test_bench_trust_json_keys(tmp_path):
    soak = {"sent": 10, "received": 10, "recorded": 10, "lost": 0, "rss_growth_pct": 1.0}
    (tmp_path / "soak.json").write_text(json.dumps(soak))
    out = tmp_path / "trust.json"
    rc = cli_main(["bench", "trust", "--json", str(out), "--fuzz-inputs", "3000", "--soak-json",
                   str(tmp_path / "soak.json"), "--faults", "reordering_and_duplicates"])
    report = json.loads(out.read_text())
    for key in ("forged_sent", "forged_accepted", "replayed_sent", "replayed_accepted", "fuzz_inputs",
                "fuzz_crashes", "faults", "sent", "received", "recorded", "lost", "rss_growth_pct"):
        assert key in report, key
    assert report["forged_sent"] > 0 and report["forged_accepted"] == 0
    assert report["replayed_sent"] > 0 and report["replayed_accepted"] == 0
    assert report["fuzz_inputs"] >= 3000 and report["fuzz_crashes"] == 0
    assert [f["name"] for f in report["faults"]] == ["reordering_and_duplicates"]
    assert set(report["faults"][0]) == {"name", "passed", "detail"}
    assert report["faults"][0]["passed"], report["faults"][0]["detail"]   # as in test_faults_live
    assert report["sent"] == 10 and report["lost"] == 0
    assert rc == 0


def test_bench_trust_exits_1_when_a_fault_scenario_fails(tmp_path, monkeypatch):
    failing = trust_faults.FaultResult("link_cut", False, "target stayed VALID after the cut")
    monkeypatch.setattr(trust_faults, "FAULTS", {"link_cut": lambda: failing})
    out = tmp_path / "trust.json"
    rc = cli_main(["bench", "trust", "--json", str(out), "--fuzz-inputs", "200", "--skip-soak"])
    report = json.loads(out.read_text())
    assert report["forged_accepted"] == 0 and report["fuzz_crashes"] == 0
    assert report["faults"] == [failing.as_dict()]
    assert rc == 1
