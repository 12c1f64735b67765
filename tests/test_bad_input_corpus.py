"""The bad-input corpus (``bench.corpus``, also ``v2xpos bench corpus``): >= 500 deliberately broken
inputs -- mutated ``dataset.toml`` (misspelt, missing, mistyped, misplaced keys; wrong matrices and
vectors; unknown formats; missing files; broken TOML; a bad ``[calibration]``), IMU csv (truncated,
cut in half, garbage lines, empty, header only, non-UTF-8, gaps, wrong units), ``.pos`` (headers
only, bad columns, empty, truncated, garbage), TIMETAG (truncated, wrong header, corrupt times),
multi-IMU folders and ``[grade]`` tables, master and slave configs (every key misspelt and
mistyped, scenario parameters, broken TOML).

What is covered how:

* every case, in process (``test_corpus_...``, ~30 s): dataset cases through ``v2xpos replay --check``
  and ``v2xpos calibrate --check`` (the commands' whole input path: loader, plausibility checks,
  exit code, message, JSON), grade cases through ``v2xpos grade --check``, configs through
  ``MasterConfig.load`` / ``SlaveConfig.load`` and the scenario check the services run. Commands are
  called without the CLI's top-level guard, so any exception counts as a traceback. Each must end
  in exit 2 with the damaged file named, or exit 0/1 with the damage in the report's warnings.
* a sample, as a user runs it (``@slow``): one case of each family through the full commands in a
  subprocess (``python -m v2xpos replay`` with the filter, ``grade`` with the grading, one
  ``calibrate``), checking exit codes, stderr without "Traceback" and the warnings in the JSON.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench import corpus as corpus_mod
from tests.shared_data import SHARED_DATA, require_shared

ROOT = Path(__file__).resolve().parents[1]
DATA = SHARED_DATA


def _require_data() -> None:
    for p in (DATA / "drive_0708" / "imu_1934.csv", DATA / "quadrotor_mimu" / "path_1" / "IMU_1.csv"):
        require_shared(p)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    _require_data()
    work = tmp_path_factory.mktemp("corpus")
    return corpus_mod.build_corpus(work / "cases"), work


def test_corpus_bases_are_clean(built):
    """The undamaged bases give no error and no warning, so every warning below is the damage's."""
    corpus, work = built
    from v2xpos.datasets import load_dataset
    from v2xpos.datasets.checks import check_dataset
    from v2xpos.quality.recording import prepare_recording
    chk = check_dataset(load_dataset(corpus.base["dataset"]))
    assert chk.findings == [], chk.findings
    assert prepare_recording(corpus.base["grade"])["coverage"]["warnings"] == []
    base = corpus_mod.Case("base", "dataset", corpus.base["dataset"], corpus.base["dataset"])
    outs = corpus_mod.run_case(base, work / "base_out")
    assert [o.status for o in outs] == ["silent", "silent"]       # clean input: exit 0, nothing to state
    for kind in ("master_config", "slave_config"):
        case = corpus_mod.Case("base", kind, corpus.base[kind], corpus.base[kind])
        assert corpus_mod.run_case(case, work)[0].status == "silent"


@pytest.mark.slow
def test_corpus_zero_tracebacks_zero_silent_exits(built):
    corpus, work = built
    res = corpus_mod.run_corpus(corpus, work / "out")
    assert res["cases"] >= 500
    kinds = {c.kind for c in corpus.cases}
    assert kinds == {"dataset", "grade", "master_config", "slave_config"}
    damaged = {c.damaged.suffix or c.damaged.name for c in corpus.cases}
    assert {".toml", ".csv", ".pos", ".tag"} <= damaged
    assert res["tracebacks"] == 0, res["failures"]
    assert res["silent"] == 0, res["failures"]
    assert res["unnamed"] == 0 and res["wrong_code"] == 0, res["failures"]
    # both outcomes occur: damage that leaves a usable result is stated, not refused
    assert res["by_status"]["error"] > 300 and res["by_status"]["warning"] > 30
    # replay and calibrate read a dataset the same way
    assert res["by_kind"]["dataset/replay"] == res["by_kind"]["dataset/calibrate"]


def test_corpus_harness_catches_what_it_must(built, monkeypatch):
    """An exception a command lets out is a traceback; exit 2 without the file named is 'unnamed'."""
    corpus, work = built
    case = next(c for c in corpus.cases if c.name.startswith("csv 1 garbage"))
    from v2xpos.commands import replay

    def broken_check(*_a, **_k):
        raise IndexError("boom")
    monkeypatch.setattr(replay, "check_only", broken_check)
    assert corpus_mod.run_case(case, work / "h")[0].status == "traceback"
    monkeypatch.undo()
    outcome = corpus_mod._classify(case, 2, "v2xpos replay: something is wrong", None, [])
    assert outcome.status == "unnamed"


def _families(corpus) -> dict[str, corpus_mod.Case]:
    """One case per family: the damaged file type and the first words of the case name."""
    out = {}
    for c in corpus.cases:
        if c.kind != "dataset" and c.kind != "grade":
            continue
        family = (c.damaged.name, " ".join(c.name.split()[:2]))
        out.setdefault(family, c)
    return out


@pytest.mark.slow
def test_corpus_sample_through_the_full_commands(built):
    """One case per family as a user runs it: the full replay (filter included) or grade in a
    subprocess; the exit code and the outcome match the --check path, stderr has no traceback."""
    corpus, work = built
    fam = _families(corpus)
    assert len(fam) >= 25
    ran = 0
    for case in fam.values():
        checked = corpus_mod.run_case(case, work / "sample")[0]
        js = work / "sample" / "full.json"
        js.unlink(missing_ok=True)
        argv = (["replay", case.target, "--no-progress"] if case.kind == "dataset" else
                ["grade", case.target, "--no-fusion"]) + ["--json", js]
        r = subprocess.run([sys.executable, "-m", "v2xpos", *map(str, argv)], capture_output=True, text=True,
                           timeout=300, cwd=ROOT)
        assert "Traceback" not in r.stderr, (case.name, r.stderr)
        if checked.status == "error":
            assert r.returncode == 2 and case.damaged.name in r.stderr, (case.name, r.stderr)
        else:
            assert r.returncode in (0, 1), (case.name, r.returncode, r.stderr)
            rep = json.loads(js.read_text())
            warnings = rep["input_checks"]["warnings"] if case.kind == "dataset" else rep["warnings"]
            assert warnings, case.name
            assert "warning:" in r.stderr
        ran += 1
    assert ran == len(fam)


@pytest.mark.slow
def test_corpus_calibrate_on_a_damaged_recording(built):
    """The full calibrate on a csv with garbage lines: exit 0, the skipped lines in its JSON."""
    corpus, work = built
    case = next(c for c in corpus.cases if c.name.startswith("csv 5 garbage"))
    js = work / "cal.json"
    r = subprocess.run([sys.executable, "-m", "v2xpos", "calibrate", str(case.target), "--no-progress",
                        "--json", str(js)], capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    out = json.loads(js.read_text())
    assert out["warnings"] >= 1 and any("5 malformed record(s)" in w for w in out["input_checks"]["warnings"])
