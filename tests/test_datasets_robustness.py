"""Readers on damaged input: only ValueError (with the file named) or a result, never a crash;
counter wrap; TIMETAG layout."""
import random
from pathlib import Path

import numpy as np
import pytest

from v2xpos.datasets.imu_csv import COUNTER_MODULUS_MS, read_imu_csv
from v2xpos.datasets.rtklib_pos import read_rtklib_pos
from v2xpos.datasets.timetag import read_timetag
from v2xpos.datasets.ubx import read_ubx
from v2xpos import timebase
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA


def _require(path: Path) -> Path:
    return require_shared(path)


def _mutate(rng: random.Random, b: bytes) -> bytes:
    b = bytearray(b)
    for _ in range(rng.randint(0, 40)):
        op, i = rng.random(), rng.randrange(len(b) + 1)
        if op < 0.4 and i < len(b):
            b[i] = rng.randrange(256)
        elif op < 0.7:
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
        else:
            del b[i:i + rng.randint(1, 20)]
    if rng.random() < 0.2:
        b = b[:rng.randrange(len(b) + 1)]
    return bytes(b)


@pytest.mark.parametrize("name", ["imu_csv", "rtklib_pos", "timetag", "ubx"])
def test_mutated_inputs_never_crash(tmp_path, name):
    drive, walk = _require(DATA / "drive_0708"), _require(DATA / "walk_0827")
    src, reader = {
        "imu_csv": ((drive / "imu_1934.csv").read_bytes()[:4000],
                    lambda p: read_imu_csv(p, drive / "imu_1934.csv.tag")),
        "rtklib_pos": ((drive / "gnss_1934.pos").read_bytes()[:4000], read_rtklib_pos),
        "timetag": ((drive / "imu_1934.csv.tag").read_bytes()[:1500], read_timetag),
        "ubx": ((walk / "gnss_1730.ubx").read_bytes()[:15000], read_ubx),
    }[name]
    rng = random.Random(name)
    for k in range(60):
        path = tmp_path / f"case{k}"
        path.write_bytes(_mutate(rng, src) if k else b"")
        try:
            result = reader(path)
        except ValueError as exc:
            assert str(path) in str(exc)
            continue
        _assert_well_formed(name, result, path)


def _assert_well_formed(name: str, result, path: Path) -> None:
    """What a reader returns from damaged input is still a valid result: one entry per record in
    every array, finite times, no more records than the file could hold, skips counted as issues."""
    n_lines = path.read_bytes().count(b"\n") + 1
    if name == "timetag":
        tag, issues = result
        assert len(tag.t_s) == len(tag.byte_offset) and np.all(np.isfinite(tag.t_s))
        assert np.all(np.diff(tag.byte_offset) >= 0)          # bytes received never decrease
        assert issues.count >= 0
        return
    if name == "imu_csv":
        imu, issues = result.imu, result.issues
        n = len(imu.t_s)
        assert imu.acc_mps2.shape == (n, 3) and imu.gyro_rps.shape == (n, 3)
        assert np.all(np.isfinite(imu.t_s))
        assert n + issues.count <= n_lines
        return
    gnss, issues = (result.gnss, result.issues) if name == "ubx" else result
    n = len(gnss.t_s)
    assert gnss.lla.shape == (n, 3) and len(gnss.fix) == n and gnss.sd_ned_m.shape == (n, 3)
    assert np.all(np.isfinite(gnss.t_s)) and np.all(np.isfinite(gnss.lla))
    if name == "rtklib_pos":
        assert n + issues.count <= n_lines


def test_counter_wrap_is_unwrapped(tmp_path):
    counter = (COUNTER_MODULUS_MS - 50 + 10 * np.arange(12)) % COUNTER_MODULUS_MS
    lines = [f"0.000,0.000,1.000,0.100,0.200,0.300,{c}" for c in counter]
    path = tmp_path / "wrap.csv"
    path.write_text("\r\n".join(lines) + "\r\n")
    res = read_imu_csv(path)
    assert res.counter_wraps == 1 and res.issues.count == 0
    assert np.all(np.diff(res.imu.counter_ms) == 10)
    assert res.rate_hz == pytest.approx(100.0)
    np.testing.assert_allclose(res.imu.acc_mps2[0], [0.0, 0.0, 9.80665])
    np.testing.assert_allclose(res.imu.gyro_rps[0], np.radians([0.1, 0.2, 0.3]))


def test_counter_beyond_uint32_is_a_counted_line_issue(tmp_path):
    """A counter no uint32 logger can print (fuzzing found one) is rejected with its line number,
    not cast to a wrapped int64; the other lines are kept."""
    lines = [f"0.000,0.000,1.000,0.100,0.200,0.300,{1000 + 10 * i}" for i in range(12)]
    lines[4] = "0.000,0.000,1.000,0.100,0.200,0.300,99999999999999999999999"
    path = tmp_path / "big.csv"
    path.write_text("\r\n".join(lines) + "\r\n")
    res = read_imu_csv(path)
    assert res.issues.count == 1 and res.issues.examples[0][0] == 5
    assert "out of range" in res.issues.examples[0][1]
    assert len(res.imu.t_s) == 11 and np.all(np.diff(res.imu.counter_ms) > 0)


def test_timetag_layout():
    tag, issues = read_timetag(_require(DATA / "drive_0708" / "imu_1934.csv.tag"))
    assert issues.count == 0 and tag.header.startswith("TIMETAG RTKLIB")
    # the IMU log and the GNSS solution of the session start together: within seconds, so an error
    # of the leap seconds (18 s) or of the epoch (GPST vs Unix) would show
    first = next(ln for ln in (DATA / "drive_0708" / "gnss_1934.pos").read_text().splitlines()
                 if ln.strip() and not ln.startswith("%"))
    y, mo, d = (int(v) for v in first.split()[0].split("/"))
    hh, mm, ss = first.split()[1].split(":")
    t_first = timebase.gpst_calendar_to_gps_seconds(y, mo, d, int(hh), int(mm), float(ss))
    assert abs(t_first - tag.open_gps_s) < 10.0
    assert tag.byte_offset[-1] == (DATA / "drive_0708" / "imu_1934.csv").stat().st_size
    assert np.all(np.diff(tag.t_s) >= 0) and np.all(np.diff(tag.byte_offset) >= 0)
    assert np.median(np.diff(tag.t_s)) == pytest.approx(0.016, abs=0.002)
    # arrival of byte k is the first record that reached k
    k = int(tag.byte_offset[10]) - 1
    assert tag.arrival_gps_s(np.array([k]))[0] == tag.t_s[10]
    assert np.isnan(tag.arrival_gps_s(np.array([tag.byte_offset[-1] + 1]))[0])
