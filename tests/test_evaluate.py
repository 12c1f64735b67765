"""``v2xpos evaluate`` (issue 28): effects recovered from simulated sensors over seeds and error
models, absent effects not significant, the same log as csv / ASC / BLF / MDF4 giving the same
metrics, bad input rejected with nothing written, the reference read by column name (extra and
``smoothed`` columns), an MCAP reference, and what the HTML report shows."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bench.evaluate import MC_MODELS, TOLERANCE, run_case, synthetic_truths
from sim.object_sensor import (MODELS, DeclaredSensor, SensorErrorModel, convoy_truth, rear_sensor, simulate_objects,
                               truth_results_csv, write_sensor)
from tests.shared_data import SHARED_DATA, require_shared
from v2xpos.cli import main

CONVOY = SHARED_DATA / "convoy_dev"
FRONT = DeclaredSensor(name="front_radar", mount_m=(3.7, 0.0, -0.5))


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """Three targets ahead of a front radar for 240 s, and their truth as a results.csv."""
    work = tmp_path_factory.mktemp("synthetic")
    truths = synthetic_truths(240.0, seed=3)
    truth_results_csv(truths, work / "reference.csv")
    return truths, work / "reference.csv"


@pytest.fixture(scope="module")
def convoy(tmp_path_factory):
    require_shared(CONVOY)
    work = tmp_path_factory.mktemp("convoy")
    names = convoy_truth(CONVOY, {})
    truths = convoy_truth(CONVOY, {k: np.array([1.8, 0.0, 0.0]) for k in names})
    truth_results_csv(truths, work / "reference.csv")
    return truths, work / "reference.csv"


def _check(res: dict, where: str) -> None:
    outside = {k: res["error"][k] for k, ok in res["within"].items() if not ok}
    assert not outside, f"{where}: outside tolerance {TOLERANCE}: {outside} (got {res['got']}, want {res['want']})"
    assert not res["false_significant"], f"{where}: absent effects reported significant: {res['false_significant']}"
    assert not res["present_not_significant"], f"{where}: present effects not found: {res['present_not_significant']}"


@pytest.mark.slow
def test_effects_recovered_over_seeds_and_models(convoy, synthetic, tmp_path):
    """10 seeds on convoy_dev (a rear radar watching the follower) cycling through every error model,
    and 4 on three synthetic targets ahead of a front radar with other models."""
    truths, ref = convoy
    for seed in range(10):
        name = MC_MODELS[seed % len(MC_MODELS)]
        _check(run_case(truths, rear_sensor(), MODELS[name], seed, ref, tmp_path / f"c{seed}"), f"convoy {name} seed {seed}")
    truths, ref = synthetic
    models = [MODELS["radar_biased"], MODELS["camera"],
              SensorErrorModel(latency_s=0.2, range_bias_m=-0.15, mount_yaw_error_deg=-0.7, azimuth_bias_deg=0.3,
                               range_sd_m=0.3, detection_probability=0.7, ghosts_per_min=20.0, track_loss_cycles=2),
              SensorErrorModel(latency_s=0.0, range_sd_m=0.05, azimuth_sd_deg=0.5, ghosts_per_min=0.0)]
    for seed, model in enumerate(models):
        _check(run_case(truths, FRONT, model, 100 + seed, ref, tmp_path / f"s{seed}"), f"synthetic model {seed}")


def test_id_switches_counted(convoy, tmp_path):
    truths, ref = convoy
    model = SensorErrorModel(detection_probability=0.6, track_loss_cycles=2, ghosts_per_min=0.0)
    res = run_case(truths, rear_sensor(), model, 7, ref, tmp_path)
    assert res["want"]["B.id_switches"] > 5
    assert res["got"]["B.id_switches"] == res["want"]["B.id_switches"]


def _evaluate(ref, objs, cfg, out, *extra) -> int:
    return main(["evaluate", "--reference", str(ref), "--sensor", str(objs), "--sensor-config", str(cfg),
                 "--out", str(out), *extra])


def _metrics(out: Path) -> dict:
    m = json.loads((out / "metrics.json").read_text())
    m.pop("inputs")
    m.pop("provenance")
    return m


@pytest.mark.slow
def test_same_log_as_csv_asc_blf_mf4_same_metrics(convoy, tmp_path):
    truths, ref = convoy
    points = {k: t.reference_point_m for k, t in truths.items()}
    objs = simulate_objects(truths, rear_sensor(), MODELS["radar_biased"], seed=4)
    write_sensor(objs, tmp_path, rear_sensor(), points, formats=("csv", "asc", "blf", "mf4"))
    got = {}
    for fmt in ("csv", "asc", "blf", "mf4"):
        assert _evaluate(ref, tmp_path / f"objects.{fmt}", tmp_path / "sensor.toml", tmp_path / f"out_{fmt}",
                         "--no-plots") == 0
        got[fmt] = _metrics(tmp_path / f"out_{fmt}")
    assert got["csv"]["latency_ms"]["significant"]
    for fmt in ("asc", "blf", "mf4"):
        assert got[fmt] == got["csv"], fmt


def _sensor_dir(convoy, tmp_path, formats=("csv",)) -> Path:
    truths, ref = convoy
    points = {k: t.reference_point_m for k, t in truths.items()}
    objs = simulate_objects(truths, rear_sensor(), MODELS["radar"], seed=2)
    write_sensor(objs, tmp_path, rear_sensor(), points, formats=formats)
    shutil.copy(ref, tmp_path / "reference.csv")
    return tmp_path


def test_bad_input_exit_2_names_file_and_key_writes_nothing(convoy, tmp_path, capsys):
    d = _sensor_dir(convoy, tmp_path / "in", ("csv", "asc"))
    out = tmp_path / "out"
    good = (d / "sensor.toml").read_text()
    # a misspelt key: file, table, key and the suggestion
    (d / "bad.toml").write_text(good.replace("mount_yaw_deg", "mount_yaw_dge"))
    assert _evaluate(d / "reference.csv", d / "objects.csv", d / "bad.toml", out) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "[sensor]" in err and "mount_yaw_dge" in err and "did you mean 'mount_yaw_deg'" in err
    assert not out.exists()
    # a DBC without the mapped signal
    (d / "bad.toml").write_text(good.replace('"ObjectList.DistLong"', '"ObjectList.DistLongitude"'))
    assert _evaluate(d / "reference.csv", d / "objects.asc", d / "bad.toml", out) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "x_m" in err and "DistLongitude" in err and "sensor.dbc" in err
    assert not out.exists()
    # no overlap in time: both files named
    rows = (d / "objects.csv").read_text().splitlines()
    shifted = [rows[0]] + [f"{float(r.split(',')[0]) + 86400.0:.4f}," + r.split(",", 1)[1] for r in rows[1:]]
    (d / "late.csv").write_text("\n".join(shifted) + "\n")
    assert _evaluate(d / "reference.csv", d / "late.csv", d / "sensor.toml", out) == 2
    err = capsys.readouterr().err
    assert "late.csv" in err and "reference.csv" in err and "no overlap" in err
    assert not out.exists()
    # a failed run leaves an earlier result untouched
    assert _evaluate(d / "reference.csv", d / "objects.csv", d / "sensor.toml", out, "--no-plots") == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert _evaluate(d / "reference.csv", d / "late.csv", d / "sensor.toml", out, "--no-plots") == 2
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".out.")]


@pytest.mark.slow
def test_reference_by_column_name_extra_columns_and_smoothed(convoy, tmp_path):
    d = _sensor_dir(convoy, tmp_path)
    lines = (d / "reference.csv").read_text().splitlines()
    header = lines[0].split(",")
    order = list(reversed(range(len(header))))            # every column moved
    def remap(line, extra):
        cells = line.split(",")
        return ",".join(cells[j] for j in order) + "," + extra
    (d / "ref_extra.csv").write_text("\n".join([remap(lines[0], "reason,protection_m,smoothed")]
                                               + [remap(x, "none,0.12,1") for x in lines[1:]]) + "\n")
    assert _evaluate(d / "reference.csv", d / "objects.csv", d / "sensor.toml", tmp_path / "a", "--no-plots") == 0
    assert _evaluate(d / "ref_extra.csv", d / "objects.csv", d / "sensor.toml", tmp_path / "b", "--no-plots") == 0
    a, b = _metrics(tmp_path / "a"), _metrics(tmp_path / "b")
    assert a["reference_smoothed"] is False and b["reference_smoothed"] is True
    b["reference_smoothed"] = False
    assert a == b


@pytest.mark.slow
def test_mcap_reference_same_effects(convoy, tmp_path):
    from v2xpos.evaluate.reference import read_results_csv_reference
    from v2xpos.output.recorder import McapRecorder
    from v2xpos.wire import RelativeResult, TargetStatus
    d = _sensor_dir(convoy, tmp_path)
    ref = read_results_csv_reference(d / "reference.csv")
    with McapRecorder(d / "session.mcap") as rec:
        for tid, tr in ref.tracks.items():
            for k in range(0, len(tr.t_s)):
                rec.record_result(RelativeResult(target_id=tid, fleet="test", master_id="A", status=TargetStatus.VALID, t_gps_s=float(tr.t_s[k]),
                                                 rel_acc_body_mps2=np.zeros(3), rel_pos_body_m=tr.pos_m[k], rel_pos_sd_m=tr.sd_m[k],
                                                 rel_vel_body_mps=tr.vel_mps[k], rel_rpy_rad=tr.rpy_rad[k],
                                                 range_m=float(np.linalg.norm(tr.pos_m[k])), range_sd_m=0.01,
                                                 bearing_rad=0.0, elevation_rad=0.0, longitudinal_m=0.0, lateral_m=0.0,
                                                 gap_m=0.0, closing_speed_mps=0.0, rel_yaw_sd_rad=0.001))
            rec.record_result(RelativeResult(target_id=tid, fleet="test", master_id="A", status=TargetStatus.TIMEOUT, t_gps_s=float(tr.t_s[-1]) + 1))
    assert _evaluate(d / "reference.csv", d / "objects.csv", d / "sensor.toml", tmp_path / "a", "--no-plots") == 0
    assert _evaluate(d / "session.mcap", d / "objects.csv", d / "sensor.toml", tmp_path / "b", "--no-plots") == 0
    a, b = _metrics(tmp_path / "a"), _metrics(tmp_path / "b")
    assert b["reference"]["kind"] == "mcap"
    assert b["targets"]["B"]["reference_gaps"]["rows_by_status"] == {"TIMEOUT": 1}
    for key in ("latency_ms", "range_bias_m", "mount_yaw_deg"):
        assert abs(a[key]["value"] - b[key]["value"]) < 0.1 * a[key]["sd"] + 1e-9, key
    assert a["targets"]["B"]["detection_rate"] == b["targets"]["B"]["detection_rate"]


@pytest.mark.slow
def test_report_shows_what_a_test_record_needs(convoy, tmp_path):
    d = _sensor_dir(convoy, tmp_path / "in")
    out = tmp_path / "out"
    assert _evaluate(d / "reference.csv", d / "objects.csv", d / "sensor.toml", out) == 0
    m = json.loads((out / "metrics.json").read_text())
    for key in ("sensor", "latency_ms", "mount_yaw_deg", "false_objects_per_min", "targets", "reference_smoothed"):
        assert key in m
    t = m["targets"]["B"]
    for key in ("span_s", "reference_rows", "detection_rate", "id_switches"):
        assert key in t
    for q in ("range_error_m", "azimuth_error_deg", "longitudinal_error_m", "lateral_error_m", "range_rate_error_mps"):
        assert set(t[q]) >= {"bias", "sd", "rms", "p50", "p90", "p99"}
    assert {"value", "sd"} <= set(m["latency_ms"]) and {"value", "sd"} <= set(m["mount_yaw_deg"])
    assert m["inputs"]["sensor"]["sha256"] and m["provenance"]["software"]["name"] == "v2xpos"
    header = (out / "matches.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["t_gps_s", "cycle", "target", "object_id"] and "range_error_m" in header
    page = (out / "report.html").read_text()
    for text in (m["sensor"], "Latency", "Mounting yaw", "Range bias", "significant", m["inputs"]["sensor"]["sha256"],
                 "detection rate", "id switches", "False objects", "p99"):
        assert text in page, text
    assert page.count("data:image/png;base64,") == 5
