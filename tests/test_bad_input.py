"""Issue 17, case by case: every input a new user broke by hand ends in exit code 2 with a message
naming the file and the key or line, or in a result whose warnings the report states -- and never
in a traceback. The commands run as a user runs them (``python -m v2xpos ...`` in a subprocess,
so the real stderr is checked); broken copies of the shared recordings are made in tmp dirs."""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from tests.shared_data import SHARED_DATA, require_shared

ROOT = Path(__file__).resolve().parents[1]
DATA = SHARED_DATA
DRIVE = DATA / "drive_0708"
QUAD = DATA / "quadrotor_mimu" / "path_1"


def _require(p: Path) -> Path:
    return require_shared(p)


def v2xpos(*args: str, env: dict | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "v2xpos", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env={**os.environ, **(env or {})})


def _no_traceback(r: subprocess.CompletedProcess) -> None:
    assert "Traceback" not in r.stderr and "Traceback" not in r.stdout, r.stderr


def _error_line(r: subprocess.CompletedProcess, *needles: str) -> str:
    """The exit code is 2, there is no traceback and one stderr line carries every needle."""
    _no_traceback(r)
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if all(n in ln for n in needles)]
    assert lines, (needles, r.stderr)
    return lines[0]


def _drive_copy(tmp_path: Path, toml_edit=None, files: dict | None = None) -> Path:
    """A drive_0708 descriptor in tmp_path; data files linked unless ``files`` gives new content."""
    _require(DRIVE / "dataset.toml")
    for name in ("imu_1934.csv", "imu_1934.csv.tag", "gnss_1934.pos"):
        if files and name in files:
            (tmp_path / name).write_bytes(files[name])
        else:
            (tmp_path / name).symlink_to((DRIVE / name).resolve())
    text = (DRIVE / "dataset.toml").read_text()
    (tmp_path / "dataset.toml").write_text(toml_edit(text) if toml_edit else text)
    return tmp_path / "dataset.toml"


# ---------------------------------------------------------------------------------- descriptor keys
@pytest.mark.parametrize("command", ["replay", "calibrate"])
def test_misspelt_imu_to_body_is_exit_2_naming_file_table_key(tmp_path, command):
    toml = _drive_copy(tmp_path, lambda s: s.replace("imu_to_body =", "imu_2_body ="))
    r = v2xpos(command, toml, "--no-progress")
    line = _error_line(r, str(toml), "[imu]", "'imu_2_body'")
    assert "did you mean 'imu_to_body'" in line


def test_misspelt_lever_arm_is_exit_2(tmp_path):
    toml = _drive_copy(tmp_path, lambda s: s.replace("lever_arm_m =", "lever_arm_mm ="))
    line = _error_line(v2xpos("replay", toml, "--no-progress"), str(toml), "[gnss]", "'lever_arm_mm'")
    assert "did you mean 'lever_arm_m'" in line


def test_missing_imu_to_body_is_caught_by_gravity(tmp_path):
    """Without the matrix the z-up IMU is taken as z-down: the measured down direction is ~180 deg
    from body +z; the error names the key and the direction."""
    toml = _drive_copy(tmp_path, lambda s: re.sub(r"^imu_to_body.*\n", "", s, flags=re.M))
    line = _error_line(v2xpos("replay", toml, "--check"), str(toml), "imu_to_body", "down direction")
    deg = float(re.search(r"(\d+) deg from body \+z", line).group(1))
    assert deg > 150


def test_declared_mounting_passes_gravity_check(tmp_path):
    from v2xpos.datasets import load_dataset
    from v2xpos.datasets.checks import check_dataset
    for name in ("drive_0708", "walk_0827"):
        chk = check_dataset(load_dataset(_require(DATA / name / "dataset.toml")))
        assert not chk.errors, chk.errors
        assert chk.details["mounting"]["angle_from_body_z_deg"] < 20.0


# ---------------------------------------------------------------------------------- IMU csv cut in half
@pytest.mark.slow
def test_imu_csv_cut_in_half_scores_only_the_common_span(tmp_path):
    """Exit 0 with the cut stated (stderr and JSON), GNSS epochs after the IMU ends not used, and
    the outages scored are exactly the full run's outages inside the IMU's span, with the same errors
    (before: 120 m outage RMS, every outage after the IMU's end scored)."""
    raw = _require(DRIVE / "imu_1934.csv").read_bytes()
    half = _drive_copy(tmp_path, files={"imu_1934.csv": raw[:len(raw) // 2]})
    full_json, half_json = tmp_path / "full.json", tmp_path / "half.json"
    r_full = v2xpos("replay", DRIVE / "dataset.toml", "--no-progress", "--json", full_json)
    r_half = v2xpos("replay", half, "--no-progress", "--json", half_json)
    _no_traceback(r_half)
    assert r_full.returncode == 0 and r_half.returncode == 0, r_half.stderr
    assert "truncated last line" in r_half.stderr and "imu_1934.csv" in r_half.stderr
    assert "GNSS without IMU" in r_half.stderr
    full, cut = json.loads(full_json.read_text()), json.loads(half_json.read_text())
    warnings = cut["input_checks"]["warnings"]
    assert cut["warnings"] == len(warnings) >= 2
    assert any("common span" in w for w in warnings)
    ov = cut["input_checks"]["overlap"]
    imu_end = ov["imu_span_s"][1]
    assert 0.4 < ov["share"] < 0.6
    n = cut["outage_count"]
    assert 0 < n < full["outage_count"]
    first = ov["gnss_span_s"][0]
    schedule_ends = [first + 40 + 15 + 45 * k for k in range(full["outage_count"])]
    assert n == sum(e <= imu_end for e in schedule_ends)
    # the same outages with the same errors, up to the IMU clock fit over half the lines (mm)
    np.testing.assert_allclose(cut["outage_h_m"], full["outage_h_m"][:n], atol=0.05)


def test_imu_csv_cut_short_is_exit_2_below_the_configured_share(tmp_path):
    raw = _require(DRIVE / "imu_1934.csv").read_bytes()
    toml = _drive_copy(tmp_path, files={"imu_1934.csv": raw[:len(raw) // 10]})
    line = _error_line(v2xpos("replay", toml, "--check"), str(toml), "in common", "imu_1934.csv")
    assert "minimum 25 %" in line
    # the share is configurable: with a lower minimum the same file is a stated warning
    r = v2xpos("replay", toml, "--check", "--min-overlap", "0.05")
    _no_traceback(r)
    assert r.returncode == 0 and "warning" in r.stderr and "GNSS without IMU" in r.stderr


def test_imu_without_timetag_has_no_common_time(tmp_path):
    toml = _drive_copy(tmp_path, lambda s: re.sub(r"^timetag.*\n", "", s, flags=re.M))
    _error_line(v2xpos("replay", toml, "--check"), str(toml), "in common", "declare [imu] timetag")


# ---------------------------------------------------------------------------------- .pos header only
@pytest.mark.parametrize("command", ["replay", "calibrate"])
def test_pos_with_headers_only_is_exit_2_naming_the_file(tmp_path, command):
    pos = _require(DRIVE / "gnss_1934.pos").read_text()
    header = "".join(ln for ln in pos.splitlines(keepends=True) if ln.startswith("%"))
    toml = _drive_copy(tmp_path, files={"gnss_1934.pos": header.encode()})
    line = _error_line(v2xpos(command, toml, "--no-progress"), str(tmp_path / "gnss_1934.pos"), "GNSS epochs")
    assert "header" in line and "[gnss] file" in line


@pytest.mark.parametrize("content, words", [(b"", "empty"), (b"ax,ay,az,gx,gy,gz,counter\r\n", "malformed"),
                                            (b"\xff\xfe garbage \x00\r\n" * 50, "malformed")])
def test_empty_or_header_only_imu_csv_is_exit_2(tmp_path, content, words):
    toml = _drive_copy(tmp_path, files={"imu_1934.csv": content})
    line = _error_line(v2xpos("replay", toml, "--check"), str(tmp_path / "imu_1934.csv"), "IMU samples")
    assert words in line


def test_replay_json_carries_warnings(tmp_path):
    """Records skipped by a reader are warnings in the JSON, not only in the log."""
    raw = _require(DRIVE / "imu_1934.csv").read_bytes().split(b"\n")
    raw[1000:1000] = [b"garbage line\r", b"1,2,3\r"]
    toml = _drive_copy(tmp_path, files={"imu_1934.csv": b"\n".join(raw)})
    js = tmp_path / "c.json"
    r = v2xpos("replay", toml, "--check", "--json", js)
    assert r.returncode == 0
    w = json.loads(js.read_text())["input_checks"]["warnings"]
    assert any("2 malformed record(s)" in x and "line 1001" in x for x in w)


# ---------------------------------------------------------------------------------- grade
def test_grade_with_one_unit_truncated_states_the_cut(tmp_path):
    _require(QUAD / "IMU_1.csv")
    for f in QUAD.glob("*.csv"):
        (tmp_path / f.name).symlink_to(f.resolve())
    raw = (QUAD / "IMU_3.csv").read_bytes()
    (tmp_path / "IMU_3.csv").unlink()
    (tmp_path / "IMU_3.csv").write_bytes(raw[:len(raw) // 3])
    js = tmp_path / "g.json"
    r = v2xpos("grade", tmp_path, "--json", js)
    _no_traceback(r)
    assert r.returncode == 1                        # a unit fails: the truncated one at least
    assert "graded on the span all units share" in r.stderr and "IMU_3.csv" in r.stderr
    rep = json.loads(js.read_text())
    cov = rep["coverage"]
    assert cov["common_s"] < 0.5 * cov["recording_s"]
    assert rep["duration_s"] == pytest.approx(cov["common_s"], abs=0.1)
    units = {u["id"]: u for u in rep["units"]}
    c3 = next(c for c in units["IMU_3"]["checks"] if c["name"] == "coverage")
    assert c3["grade"] == "fail" and c3["value"] < 0.5
    for uid in ("IMU_1", "IMU_2", "IMU_4"):
        assert next(c for c in units[uid]["checks"] if c["name"] == "coverage")["grade"] == "pass"
    assert rep["warnings"]


def test_grade_too_short_common_span_is_exit_2_naming_the_unit_file(tmp_path):
    _require(QUAD / "IMU_1.csv")
    for f in QUAD.glob("*.csv"):
        if f.name != "IMU_2.csv":
            (tmp_path / f.name).symlink_to(f.resolve())
    raw = (QUAD / "IMU_2.csv").read_bytes()
    (tmp_path / "IMU_2.csv").write_bytes(raw[:len(raw) // 20])
    _error_line(v2xpos("grade", tmp_path), str(tmp_path / "IMU_2.csv"), "share only")


def test_grade_implausible_absolute_figures_are_not_a_pass():
    """Every unit equally bad: the consensus ratios are ~1, the absolute checks still fail."""
    from v2xpos.quality.verdict import Thresholds, accel_pcc_check, fused_checks
    th = Thresholds()
    bad = {u: {"att_deg": {"p90": 60.0}, "pos_m": {"p90": 25.0}} for u in ("a", "b", "c")}
    checks = {c["name"]: c["grade"] for c in fused_checks("a", bad, th)}
    assert checks["fused_attitude"] == "pass" and checks["fused_position"] == "pass"   # ratio 1
    assert checks["fused_attitude_plausible"] == "fail" and checks["fused_position_plausible"] == "fail"
    assert accel_pcc_check([0.1, -0.2, 0.05], th)["grade"] == "fail"
    assert accel_pcc_check([0.2, 0.9, -0.4], th)["grade"] == "pass"


# ---------------------------------------------------------------------------------- services
def test_port_in_use_is_one_line_naming_the_endpoint(tmp_path):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    cfg = tmp_path / "master.toml"
    cfg.write_text(f'[service]\nfleet = "t"\nduration_s = 1\n[link]\nmode = "router"\n'
                   f'listen = ["tcp/127.0.0.1:{port}"]\n[source]\ntype = "sim"\nfactory = "sim.source:from_config"\nmodel = "truth_noise"\n[source.params]\nvehicles = 2\n')
    try:
        r = v2xpos("master", "--config", cfg, timeout=120)
    finally:
        busy.close()
    line = _error_line(r, f"tcp/127.0.0.1:{port}", "already in use")
    assert ".rs:" not in line                       # zenoh's source locations are cut


@pytest.mark.parametrize("service, config", [("slave", "slave_p1.toml"), ("master", "master_sim.toml")])
def test_misspelt_scenario_parameter_names_file_and_key(tmp_path, service, config):
    text = (ROOT / "configs" / config).read_text()
    bad = tmp_path / config
    bad.write_text(re.sub(r"^vehicles = ", "vehicels = ", text, flags=re.M).replace("7447", "1"))
    line = _error_line(v2xpos(service, "--config", bad, timeout=120), str(bad), "[source.params]", "'vehicels'")
    assert "did you mean 'vehicles'" in line


def test_config_unknown_key_says_did_you_mean(tmp_path):
    from slave.config import ConfigError, SlaveConfig
    with pytest.raises(ConfigError, match=r"x.toml: \[service\].*'fleeet'.*did you mean 'fleet'"):
        SlaveConfig.from_dict({"service": {"fleeet": "a"}}, "x.toml")
    with pytest.raises(ConfigError, match=r"connect_timeout_ms"):
        SlaveConfig.from_dict({"link": {"mode": "client", "connect_timeout_ms": "fast"}}, "x.toml")


@pytest.mark.slow
def test_stop_signals_interrupt_the_block_even_when_sigint_was_inherited_ignored():
    from v2xpos.stop_signals import interrupt_on_stop_signals
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            term_before = signal.getsignal(signal.SIGTERM)
            with pytest.raises(KeyboardInterrupt):
                with interrupt_on_stop_signals():
                    os.kill(os.getpid(), sig)
                    time.sleep(1.0)          # the handler runs at the next bytecode; never reached
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) is term_before
    finally:
        signal.signal(signal.SIGINT, before)


@pytest.mark.slow
def test_demo_ctrl_c_writes_a_partial_report(tmp_path):
    """The demo is started as a script's background job would be, with SIGINT ignored (what a
    non-interactive shell gives an asynchronous command): a SIGINT to its process group must still
    stop it with a partial report, not let it report a cut-short run as complete."""
    out = tmp_path / "demo"
    # a relative --out from another working directory, as `make demo` gives it (the services
    # resolve their config paths against the config's directory: a relative out once broke them)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    p = subprocess.Popen([sys.executable, "-m", "v2xpos", "demo", "--vehicles", "2", "--duration", "20",
                          "--no-live", "--no-pedestrian", "--out", "demo"], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    seen = ""
    t_end = time.time() + 180
    while time.time() < t_end:
        line = p.stderr.readline()
        seen += line
        if "all processes ready" in line or not line:
            break
    time.sleep(3.0)
    os.killpg(p.pid, signal.SIGINT)
    t_signal = time.time()
    stdout, stderr = p.communicate(timeout=120)
    stderr = seen + stderr
    logs = "".join(f"\n--- {f.name}\n" + "\n".join(f.read_text(errors="replace").splitlines()[-15:])
                   for f in sorted((out / "logs").glob("*.log")))
    why = f"{stderr}\nstdout:\n{stdout}\nended {time.time() - t_signal:.1f} s after the signal{logs}"
    assert "Traceback" not in stderr and "Traceback" not in stdout, why
    assert p.returncode == 130, why
    assert "partial report" in stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["partial"] is True and rep["interrupted_after_s"] > 0
    assert [t["id"] for t in rep["targets"]] == ["t1"]


# ---------------------------------------------------------------------------------- entry points
def test_python_dash_m_and_version():
    from importlib import metadata
    r = v2xpos("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"v2xpos {metadata.version('v2xpos')}"
    r = v2xpos()
    assert r.returncode == 2 and "usage: v2xpos COMMAND" in r.stdout and "--version" in r.stdout
    exe = Path(sys.executable).with_name("v2xpos")
    if exe.exists():
        assert subprocess.run([exe, "--version"], capture_output=True, text=True).stdout == r"v2xpos " + \
            metadata.version("v2xpos") + "\n"


def test_unexpected_error_is_one_line_and_debug_shows_the_traceback(monkeypatch, capsys):
    from v2xpos import cli

    def boom(*_a, **_k):
        raise IndexError("list index out of range")
    monkeypatch.setattr(cli, "_dispatch", boom)
    monkeypatch.delenv("V2XPOS_DEBUG", raising=False)
    assert cli.main(["replay", "x.toml"]) == cli.EXIT_INTERNAL
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "internal error: IndexError" in err and "Traceback" not in err
    assert "V2XPOS_DEBUG=1" in err
    monkeypatch.setenv("V2XPOS_DEBUG", "1")
    assert cli.main(["replay", "x.toml"]) == cli.EXIT_INTERNAL
    assert "Traceback" in capsys.readouterr().err

    def gone(*_a, **_k):
        raise FileNotFoundError(2, "No such file or directory", "/no/such")
    monkeypatch.setattr(cli, "_dispatch", gone)
    monkeypatch.delenv("V2XPOS_DEBUG")
    assert cli.main(["grade", "x"]) == cli.EXIT_INPUT
    err = capsys.readouterr().err
    assert err.startswith("v2xpos grade: error:") and "/no/such" in err and "Traceback" not in err

    def interrupted(*_a, **_k):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli, "_dispatch", interrupted)
    assert cli.main(["demo"]) == cli.EXIT_INTERRUPTED
    assert capsys.readouterr().err.strip() == "v2xpos demo: interrupted"


def test_tomllib_only_through_the_compat_import_and_python_310_declared():
    """Python 3.10 has no tomllib: every reader goes through v2xpos.compat (tomli there), which
    pyproject installs for 3.10; README and pyproject state the same minimum."""
    offenders = []
    for p in [*ROOT.glob("v2xpos/**/*.py"), *ROOT.glob("master/*.py"), *ROOT.glob("slave/*.py"),
              *ROOT.glob("sim/*.py")]:
        if p.name == "compat.py":
            continue
        if re.search(r"^\s*(import tomllib|from tomllib|import tomli\b)", p.read_text(), flags=re.M):
            offenders.append(str(p.relative_to(ROOT)))
    assert offenders == []
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'requires-python = ">=3.10"' in pyproject
    assert re.search(r'"tomli[^"]*;\s*python_version\s*<\s*\\"3\.11\\""', pyproject)
    assert "Python ≥ 3.10" in (ROOT / "README.md").read_text()
    from v2xpos.compat import tomllib
    assert tomllib.loads("a = 1") == {"a": 1}
