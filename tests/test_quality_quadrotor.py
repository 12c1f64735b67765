"""Real multi-IMU data (quadrotor_mimu, four Xsens DOT units, mounting not declared): the four
healthy units pass on every path, their relative rotation and per-axis gyro PCC after alignment are
reported, the second parameter is computed against the RTK reference; the command writes the JSON
and the figures."""
import json
from pathlib import Path

import pytest

from v2xpos.cli import main
from v2xpos.quality.recording import grade_recording
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA / "quadrotor_mimu"


def _path(name: str) -> Path:
    return require_shared(DATA / name / "IMU_1.csv").parent


@pytest.mark.slow
@pytest.mark.parametrize("name", ["path_2", "path_3"])
def test_quadrotor_units_all_pass_with_estimated_rotation_and_pcc(name):
    rep = grade_recording(_path(name))
    assert rep["n_units"] == 4
    assert [u["grade"] for u in rep["units"]] == ["pass"] * 4, [(u["id"], u["checks"]) for u in rep["units"]]
    for u in rep["units"]:
        pcc = u["pcc"]["gyro"]
        assert len(pcc) == 3 and min(pcc) > 0.8          # similar after alignment, every axis
        assert pcc[0] > 0.99                              # the axis with most motion
        rr = u["relative_rotation"]
        if not u["reference"]:
            assert rr["source"] == "estimated"
            assert 0.1 < rr["angle_deg"] < 10.0           # nearly co-aligned, but not identical
            assert "fused_diff" in u
            assert set(u["fused_diff"]["att_deg"]) == {"p50", "p90", "p99"}
            assert u["fused_diff"]["pos_m"]["p90"] < 1.0
        assert abs(u["time_offset_ms"]) < 10.0
        # pose-aided check with the reference attitude as pose source: no anomaly on healthy units
        assert u["rate_check"]["anomaly"] is False and abs(u["rate_check"]["relative_diff"]) < 0.01


@pytest.mark.slow
def test_grade_command_writes_json_and_plots(tmp_path):
    out = tmp_path / "grade.json"
    plots = tmp_path / "plots"
    rc = main(["grade", str(_path("path_1")), "--json", str(out), "--plots", str(plots)])
    assert rc == 0
    rep = json.loads(out.read_text())
    assert len(rep["units"]) == 4
    for u in rep["units"]:
        assert {"id", "grade", "rmse", "pcc", "relative_rotation", "rmse_stats", "pcc_stats"} <= set(u)
        assert u["grade"] == "pass"
        assert set(u["rmse"]) == {"gyro", "accel"}
        stats = u["rmse_stats"]["gyro"]["x"]
        assert stats["lower_whisker"] <= stats["lower_quartile"] <= stats["median"] <= stats["upper_quartile"] <= stats["upper_whisker"]
        assert len(u["pcc_stats"]["gyro"]["covariance"]) == 3
    for name in ("rmse_boxplot_gyro.png", "rmse_boxplot_accel.png", "pcc_hist_gyro.png", "pcc_hist_accel.png"):
        assert (plots / name).stat().st_size > 5000


def test_reference_option_and_bad_inputs(tmp_path, capsys):
    rep = grade_recording(_path("path_2"), reference="IMU_1", fusion=False)
    assert rep["reference"] == "IMU_1" and rep["reference_chosen"] == "given"
    assert next(u for u in rep["units"] if u["id"] == "IMU_1")["relative_rotation"]["angle_deg"] == 0.0
    assert main(["grade", str(_path("path_2")), "--reference", "IMU_9", "--no-fusion"]) == 2
    assert "IMU_9" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text(f'layout = "quadrotor_mimu"\npath = "{_path("path_1")}"\n[grade]\nmounting_xyz_deg = 3\n')
    assert main(["grade", str(bad)]) == 2
    assert "mounting_xyz_deg" in capsys.readouterr().err
    bad.write_text(f'layout = "quadrotor_mimu"\npath = "{_path("path_1")}"\n[grade.mounting_xyz_deg]\nIMU_1 = [1, "x"]\n')
    assert main(["grade", str(bad), "--no-fusion"]) == 2
    assert "IMU_1" in capsys.readouterr().err
    good = tmp_path / "good.toml"
    good.write_text(f'layout = "quadrotor_mimu"\npath = "{_path("path_1")}"\n[grade]\nreference = "IMU_2"\n')
    assert main(["grade", str(good), "--no-fusion"]) == 0
    assert "reference: IMU_2 (given)" in capsys.readouterr().out
    assert main(["grade", str(tmp_path)]) == 2
