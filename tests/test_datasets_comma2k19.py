"""comma2k19 segment -> Dataset: time mapping, frames and units against the reference pose."""
from pathlib import Path

import numpy as np
import pytest

from v2xpos import geo
from v2xpos.datasets import load_dataset
from v2xpos.datasets.comma2k19 import load_comma2k19
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, require_shared

ROOT = Path(__file__).resolve().parents[1]
SEGMENT = SHARED_DATA / "comma2k19_rav4_segment"


@pytest.fixture(scope="module")
def seg():
    require_shared(SEGMENT)
    return load_dataset(ROOT / "datasets" / "comma2k19.toml")


def test_counts_and_monotonic_times(seg):
    n_imu = np.load(SEGMENT / "processed_log/IMU/accelerometer/t").size
    n_gnss = np.load(SEGMENT / "processed_log/GNSS/live_gnss_ublox/t").size
    assert len(seg.imu) + seg.malformed_lines >= n_imu and len(seg.imu) > 0.99 * n_imu
    assert len(seg.gnss) > 0.99 * n_gnss
    for t in (seg.imu.t_s, seg.gnss.t_s, seg.wheel.t_s, seg.reference.t_s):
        assert np.all(np.diff(t) > 0)
    assert np.all(seg.gnss.fix == FixStatus.SINGLE)
    assert seg.name == "comma2k19_rav4_segment" and seg.platform == "car"


def test_boot_clock_mapped_to_gps(seg):
    week_tow = np.load(SEGMENT / "global_pose/frame_gps_times")
    np.testing.assert_allclose(seg.reference.t_s, week_tow[:, 0] * 604800 + week_tow[:, 1], rtol=0, atol=1e-6)
    # IMU and reference cover the same minute on the GPS axis
    assert abs(seg.imu.t_s[0] - seg.reference.t_s[0]) < 0.5
    assert abs(seg.imu.t_s[-1] - seg.reference.t_s[-1]) < 0.5
    lat = seg.notes["gnss_latency_s"]
    assert 0.0 < lat["min"] <= lat["median"] < 1.0


def test_reference_frames_and_gnss_agree(seg):
    ref = seg.reference
    eye = np.einsum("nji,njk->nik", ref.C_nb, ref.C_nb)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(3), eye.shape), atol=1e-9)
    vel_ecef = np.load(SEGMENT / "global_pose/frame_velocities")
    np.testing.assert_allclose(np.linalg.norm(ref.v_ned_mps, axis=1), np.linalg.norm(vel_ecef, axis=1), rtol=1e-9)
    # the device x axis points along the velocity (highway driving, no reversing)
    v_body = np.einsum("nji,nj->ni", ref.C_nb, ref.v_ned_mps)
    moving = np.linalg.norm(v_body, axis=1) > 3.0
    angle = np.degrees(np.arctan2(np.linalg.norm(v_body[moving, 1:], axis=1), v_body[moving, 0]))
    assert np.median(angle) < 10.0
    # GNSS altitude is ellipsoidal like the reference; horizontal within metres
    h_ref = np.interp(seg.gnss.t_s, ref.t_s, ref.lla[:, 2])
    assert np.median(np.abs(seg.gnss.lla[:, 2] - h_ref)) < 5.0
    ned_ref = geo.lla_to_ned(ref.lla, ref.lla[0])
    ned_ref_at_gnss = np.column_stack([np.interp(seg.gnss.t_s, ref.t_s, ned_ref[:, k]) for k in range(2)])
    err_h = np.linalg.norm(geo.lla_to_ned(seg.gnss.lla, ref.lla[0])[:, :2] - ned_ref_at_gnss, axis=1)
    assert np.median(err_h) < 10.0


def test_imu_wheel_units(seg):
    f = seg.imu.acc_mps2
    assert np.median(f[:, 2]) == pytest.approx(-9.8, abs=0.6)      # z down: specific force -g
    assert np.abs(seg.imu.gyro_rps).max() < 2.0                      # rad/s on a highway
    v_ref = np.linalg.norm(seg.reference.v_ned_mps, axis=1)
    wheel = np.interp(seg.reference.t_s, seg.wheel.t_s, seg.wheel.speed_mps)
    assert np.median(wheel / v_ref) == pytest.approx(1.0, abs=0.03)
    rear = load_comma2k19(SEGMENT, wheel_mode="rear")
    assert rear.wheel.speed_mps.shape == seg.wheel.speed_mps.shape
    with pytest.raises(ValueError, match="wheel_mode"):
        load_comma2k19(SEGMENT, wheel_mode="front")


def test_folder_autodetect(seg):
    ds = load_dataset(SEGMENT)
    assert len(ds.imu) == len(seg.imu)


def test_gnss_stamp_jumping_ahead_drops_the_rows_behind_it(tmp_path):
    """One UTC stamp jumps ahead of the next rows: those rows are dropped and counted, and the GNSS
    times stay strictly increasing."""
    require_shared(SEGMENT)
    import shutil
    copy = tmp_path / "segment"
    shutil.copytree(SEGMENT, copy)
    value_file = copy / "processed_log/GNSS/live_gnss_ublox/value"
    value = np.load(value_file)
    value[3, 3] = value[10, 3]          # rows 4..10 are now not after row 3
    with open(value_file, "wb") as fh:
        np.save(fh, value)
    clean = load_comma2k19(SEGMENT)
    damaged = load_comma2k19(copy)
    assert np.all(np.diff(damaged.gnss.t_s) > 0)
    assert len(damaged.gnss) == len(clean.gnss) - 7
    assert damaged.malformed_lines == clean.malformed_lines + 7
