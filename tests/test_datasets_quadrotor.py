"""quadrotor_mimu path folders -> MultiImuRecording."""
from pathlib import Path

import numpy as np
import pytest

from v2xpos.datasets import load_dataset, load_multi_imu
from v2xpos.datasets.quadrotor import read_quadrotor_path
from tests.shared_data import SHARED_DATA, require_shared

ROOT = Path(__file__).resolve().parents[1]
DATA = SHARED_DATA


def _require(path: Path) -> Path:
    return require_shared(path)


def _data_rows(path: Path) -> int:
    return sum(1 for ln in path.read_text().splitlines()[1:] if ln.strip())


@pytest.mark.parametrize("k", [1, 2, 3])
def test_quadrotor_paths(k):
    folder = _require(DATA / "quadrotor_mimu" / f"path_{k}")
    rec = load_multi_imu(folder)
    assert sorted(rec.units) == ["IMU_1", "IMU_2", "IMU_3", "IMU_4"]
    for name, imu in rec.units.items():
        bad = rec.notes["malformed"][f"{name}.csv"]["count"]
        assert len(imu) + bad == _data_rows(folder / f"{name}.csv")
        assert bad <= 2
        assert np.all(np.diff(imu.t_s) > 0)
        assert rec.unit_euler_rad[name].shape == (len(imu), 3)
        assert rec.notes["rate_hz"][name] == pytest.approx(120.0, rel=0.01)
        # flying: mean specific force ~ g (hover) in m/s^2, rates in rad/s (< 10 rad/s)
        assert 8.0 < np.linalg.norm(imu.acc_mps2, axis=1).mean() < 13.0
        assert np.abs(imu.gyro_rps).max() < 10.0
    ref = rec.reference
    assert len(ref.t_s) == _data_rows(folder / "GT.csv")
    assert np.median(np.diff(ref.t_s)) == pytest.approx(0.1, abs=1e-3)
    np.testing.assert_allclose(ref.pos_ned_m[0], 0.0, atol=1e-6)   # NED about take-off
    assert np.all(np.abs(ref.rpy_rad[:, :2]) < np.radians(45))
    assert rec.malformed_lines == sum(m["count"] for m in rec.notes["malformed"].values())


def test_quadrotor_descriptor_and_dataset_view():
    _require(DATA / "quadrotor_mimu" / "path_1")
    rec = load_multi_imu(ROOT / "datasets" / "quadrotor_path_1.toml")
    assert rec.name.endswith("path_1")
    ds = load_dataset(ROOT / "datasets" / "quadrotor_path_1.toml")
    assert ds.platform == "quadrotor" and len(ds.gnss) == 0
    assert len(ds.imu) == len(rec.units["IMU_1"])


def test_quadrotor_malformed_rows_counted(tmp_path):
    src = _require(DATA / "quadrotor_mimu" / "path_1")
    for f in ("IMU_1.csv", "GT.csv"):
        (tmp_path / f).write_text((src / f).read_text())
    lines = (src / "IMU_1.csv").read_text().splitlines()
    lines[5] = "1.0,2.0"
    lines[9] = lines[9].replace(",", ",x", 1)
    (tmp_path / "IMU_1.csv").write_text("\n".join(lines) + "\n")
    rec = read_quadrotor_path(tmp_path)
    assert rec.malformed_lines == 2
    assert len(rec.units["IMU_1"]) == len(lines) - 1 - 2
    assert [e["line"] for e in rec.notes["malformed"]["IMU_1.csv"]["examples"]] == [6, 10]
