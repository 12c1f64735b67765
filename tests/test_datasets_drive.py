"""drive_0708 / walk_0827 through load_dataset: counts against the files, time mapping, damage."""
import datetime
from pathlib import Path

import numpy as np
import pytest

from v2xpos.datasets import load_dataset
from v2xpos.datasets.imu_csv import read_imu_csv
from v2xpos.datasets.rtklib_pos import read_rtklib_pos
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA


def _require(path: Path) -> Path:
    return require_shared(path)


def _pos_rows(path: Path) -> list[list[str]]:
    return [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("%")]


@pytest.fixture(scope="module")
def drive():
    return load_dataset(_require(DATA / "drive_0708" / "dataset.toml"))


def test_drive_descriptor_fields(drive):
    assert drive.name == "drive_0708" and drive.platform == "car"
    np.testing.assert_array_equal(drive.imu_to_body, [[-1, 0, 0], [0, 1, 0], [0, 0, -1]])
    assert drive.lever_arm_m.shape == (3,)
    assert drive.gnss.height_datum == "msl"


def test_drive_sample_counts_match_files(drive):
    csv = DATA / "drive_0708" / "imu_1934.csv"
    n_lines = sum(1 for ln in csv.read_bytes().split(b"\n") if ln.strip())
    assert len(drive.imu) + drive.notes["imu"]["malformed_lines"] == n_lines
    assert len(drive.imu) > 0.99 * n_lines
    rows = _pos_rows(DATA / "drive_0708" / "gnss_1934.pos")
    assert len(drive.gnss) == len(rows)
    q = np.array([int(float(r[5])) for r in rows])
    assert np.sum(drive.gnss.fix == FixStatus.FIXED) == np.sum(q == 1)
    assert np.sum(drive.gnss.fix == FixStatus.FLOAT) == np.sum(q == 2)
    assert np.sum(q == 2) > 0


def test_drive_units_and_frames(drive):
    rows = _pos_rows(DATA / "drive_0708" / "gnss_1934.pos")
    lat0, lon0, h0 = (float(v) for v in rows[0][2:5])
    np.testing.assert_allclose(drive.gnss.lla[0], [np.radians(lat0), np.radians(lon0), h0])
    vu0 = float(rows[0][17])
    assert drive.gnss.vel_ned_mps[0, 2] == pytest.approx(-vu0)
    # at rest at the start: |f| ~ g in m/s^2, body z (down) reads -g after the nominal mounting
    f_imu = drive.imu.acc_mps2[:200].mean(axis=0)
    assert np.linalg.norm(f_imu) == pytest.approx(9.8, abs=0.3)
    assert (drive.imu_to_body @ f_imu)[2] == pytest.approx(-9.8, abs=0.4)
    assert np.abs(drive.imu.gyro_rps[:200]).max() < np.radians(10)


def test_drive_time_mapping(drive):
    t_imu, t_gnss = drive.imu.t_s, drive.gnss.t_s
    assert np.all(np.diff(t_imu) > 0) and np.all(np.diff(t_gnss) > 0)
    # first epoch from the file's own GPST calendar stamp (no leap seconds in GPST)
    date_s, time_s = _pos_rows(DATA / "drive_0708" / "gnss_1934.pos")[0][:2]
    stamp = datetime.datetime.strptime(f"{date_s} {time_s}", "%Y/%m/%d %H:%M:%S.%f")
    assert drive.gnss.t_s[0] == pytest.approx((stamp - datetime.datetime(1980, 1, 6)).total_seconds(), abs=1e-6)
    # the IMU log starts inside the GNSS solution and ends within a few seconds of its end
    assert t_gnss[0] <= t_imu[0] < t_gnss[-1]
    assert t_imu[-1] < t_gnss[-1] + 5.0
    overlap = min(t_imu[-1], t_gnss[-1]) - max(t_imu[0], t_gnss[0])
    assert overlap > 0.98 * (t_gnss[-1] - t_gnss[0])
    clock = drive.notes["imu"]["clock"]
    assert abs(clock["drift_ppm"]) < 200.0           # a crystal, not a unit error
    assert clock["residual_min_s"] == pytest.approx(0.0, abs=1e-6)
    assert 0.0 < clock["residual_median_s"] < 0.05
    assert drive.notes["imu"]["rate_hz"] == pytest.approx(1000.0 / np.mean(np.diff(drive.imu.counter_ms)), rel=0.02)


def test_walk_rate_from_counter_and_cut_first_line():
    res = read_imu_csv(_require(DATA / "walk_0827" / "imu_1730.csv"), DATA / "walk_0827" / "imu_1730.csv.tag")
    first_line = (DATA / "walk_0827" / "imu_1730.csv").read_bytes().split(b"\n")[0]
    if first_line.count(b",") != 6:
        assert res.issues.count >= 1 and res.issues.examples[0][0] == 1
    # the rate comes from the counter (samples per counter span of the file's 7-field lines)
    counters = [int(ln.split(b",")[-1]) for ln in (DATA / "walk_0827" / "imu_1730.csv").read_bytes().split(b"\n")
                if ln.count(b",") == 6]
    assert res.rate_hz == pytest.approx(1000.0 * (len(counters) - 1) / (counters[-1] - counters[0]), rel=0.01)
    gnss, issues = read_rtklib_pos(DATA / "walk_0827" / "gnss_1730.pos")
    q = np.array([int(float(r[5])) for r in _pos_rows(DATA / "walk_0827" / "gnss_1730.pos")])
    assert issues.count == 0 and len(gnss) == q.size
    assert np.sum(gnss.fix == FixStatus.FLOAT) == np.sum(q == 2) > 0


def test_malformed_imu_lines_are_counted_not_fatal(tmp_path):
    src = _require(DATA / "drive_0708" / "imu_1934.csv")
    lines = src.read_bytes().split(b"\r\n")[:3000]
    good_total = len(lines)
    damaged = list(lines)
    damaged[10] = b"garbage,line"                       # wrong field count
    damaged[20] = damaged[20][3:]                       # cut at its start
    damaged[30] = b"0.1,0.2,abc,0.1,0.2,0.3,262000"     # non-number
    parts = damaged[40].split(b",")
    damaged[40] = b",".join(parts[:6] + [b"999999999"])  # counter out of sequence
    body = b"\r\n".join(damaged) + b"\r\n" + lines[100][:12]  # truncated last line
    path = tmp_path / "imu.csv"
    path.write_bytes(body)
    res = read_imu_csv(path, DATA / "drive_0708" / "imu_1934.csv.tag")
    assert res.issues.count == 5
    assert [n for n, _ in res.issues.examples] == [11, 21, 31, 41, good_total + 1]
    assert len(res.imu) == good_total - 4
    assert np.all(np.diff(res.imu.t_s) > 0)


def test_truncated_pos_is_counted_not_fatal(tmp_path):
    src = _require(DATA / "drive_0708" / "gnss_1934.pos")
    text = src.read_text()
    n_rows = len(_pos_rows(src))
    lines = text.splitlines(keepends=True)
    lines.insert(len(lines) // 2, "2025/07/08 19:40:00.000 not a number\n")
    cut = "".join(lines)
    cut = cut[: len(cut) - len(lines[-1]) // 2]        # last line cut in the middle
    path = tmp_path / "cut.pos"
    path.write_text(cut)
    gnss, issues = read_rtklib_pos(path)
    assert issues.count == 2
    assert len(gnss) == n_rows - 1
    assert "truncated" in issues.examples[-1][1]


def _write_toml(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "dataset.toml"
    path.write_text(body)
    return path


GOOD_TOML = """name = "t"
platform = "car"
[imu]
file = "{imu}"
format = "csv_g_dps_ms"
timetag = "{tag}"
[gnss]
file = "{pos}"
format = "rtklib_pos"
"""


@pytest.mark.parametrize("damage, field", [
    (lambda s: s.replace('format = "csv_g_dps_ms"\n', ""), "[imu] format"),
    (lambda s: s.replace('"csv_g_dps_ms"', '"csv_unknown"'), "[imu] format"),
    (lambda s: s.replace('format = "rtklib_pos"', 'format = "nmea"'), "[gnss] format"),
    (lambda s: s.replace('platform = "car"\n', ""), "platform"),
    (lambda s: s + "lever_arm_m = [1.0, 2.0]\n", "[gnss] lever_arm_m"),
    (lambda s: s.replace("[imu]\n", "[imu]\nimu_to_body = [[1,0,0],[0,1,0],[0,0,2]]\n"), "[imu] imu_to_body"),
    (lambda s: s.replace("[imu]\n", "[imu]\nimu_to_body = [[1,0,0],[0,1,0],[0,0,-1]]\n"), "[imu] imu_to_body"),
    (lambda s: s.replace('[gnss]', '[gnss'), "TOML"),
])
def test_bad_toml_names_the_field(tmp_path, damage, field):
    d = _require(DATA / "drive_0708")
    body = GOOD_TOML.format(imu=(d / "imu_1934.csv").as_posix(), tag=(d / "imu_1934.csv.tag").as_posix(),
                            pos=(d / "gnss_1934.pos").as_posix())
    path = _write_toml(tmp_path, damage(body))
    with pytest.raises(ValueError) as err:
        load_dataset(path)
    assert str(path) in str(err.value) and field in str(err.value)


def test_deeply_nested_toml_is_a_value_error(tmp_path):
    path = _write_toml(tmp_path, "name = " + "[" * 100000 + "]" * 100000 + "\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_dataset(path)


def test_missing_file_named(tmp_path):
    path = _write_toml(tmp_path, GOOD_TOML.format(imu="nope.csv", tag="nope.tag", pos="nope.pos"))
    with pytest.raises(ValueError, match=r"\[imu\] file"):
        load_dataset(path)


@pytest.mark.parametrize("folder, stem", [("drive_0708", "imu_1934"), ("walk_0827", "imu_1730")])
def test_affine_clock_holds_over_the_whole_recording(folder, stem):
    """With the right drift the envelope touches every part of the recording: each tenth of the
    lines comes within a few ms of it and the median delay does not trend."""
    d = _require(DATA / folder)
    res = read_imu_csv(d / f"{stem}.csv", d / f"{stem}.csv.tag")
    delay = res.arrival_delay_s
    assert np.nanmin(delay) == pytest.approx(0.0, abs=1e-6)
    parts = np.array_split(delay, 10)
    assert max(np.nanmin(p) for p in parts) < 0.004
    medians = [np.nanmedian(p) for p in parts]
    assert max(medians) - min(medians) < 0.004
    # a fit without drift would leave a trend of drift * span in the delays
    span_s = (res.imu.counter_ms[-1] - res.imu.counter_ms[0]) * 1e-3
    assert abs(res.clock.drift_ppm) * 1e-6 * span_s > 0.001
