"""UBX NAV-PVT reader on walk_0827: epochs, fix status, times against the .pos, latency, damage."""
from pathlib import Path

import numpy as np
import pytest

from v2xpos.datasets import load_dataset
from v2xpos.datasets.rtklib_pos import read_rtklib_pos
from v2xpos.datasets.ubx import fix_status_from_nav_pvt, read_ubx
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA
WALK = DATA / "walk_0827"


def _require(path: Path) -> Path:
    return require_shared(path)


@pytest.fixture(scope="module")
def walk_ubx():
    return read_ubx(_require(WALK / "gnss_1730.ubx"), WALK / "gnss_1730.ubx.tag")


def test_nav_pvt_epochs_and_times(walk_ubx):
    raw = (WALK / "gnss_1730.ubx").read_bytes()
    # NAV-PVT frames have a 92-byte payload: header b5 62 01 07 5c 00
    assert len(walk_ubx.gnss) == raw.count(b"\xb5\x62\x01\x07\x5c\x00")
    assert walk_ubx.issues.count == 0
    assert np.all(np.diff(walk_ubx.gnss.t_s) > 0)
    assert np.median(np.diff(walk_ubx.gnss.t_s)) == pytest.approx(0.25, abs=1e-3)
    # the .pos of this walk holds the receiver's own solution: same epochs, same fix status
    pos, _ = read_rtklib_pos(WALK / "gnss_1730.pos")
    idx = np.searchsorted(walk_ubx.gnss.t_s, pos.t_s - 0.01)
    idx = np.clip(idx, 0, len(walk_ubx.gnss) - 1)
    dt = np.abs(walk_ubx.gnss.t_s[idx] - pos.t_s)
    assert np.mean(dt < 0.005) > 0.95
    both = dt < 0.005
    assert np.mean(walk_ubx.gnss.fix[idx][both] == pos.fix[both]) > 0.95
    assert np.sum(walk_ubx.gnss.fix == FixStatus.FLOAT) > 0 and np.sum(walk_ubx.gnss.fix == FixStatus.FIXED) > 0
    # the .pos height is above MSL; the NAV-PVT MSL height agrees with it
    np.testing.assert_allclose(walk_ubx.height_msl_m[idx][both], pos.lla[both, 2], atol=0.01)
    assert walk_ubx.gnss.height_datum == "ellipsoidal"


def test_latency_is_positive_and_small(walk_ubx):
    lat = walk_ubx.latency_s
    assert np.all(np.isfinite(lat))
    assert lat.min() > 0.0 and np.median(lat) < 0.5
    s = walk_ubx.summary()
    assert s["latency_s"]["median"] == pytest.approx(np.median(lat))
    assert s["message_counts"]["NAV-PVT"] == len(walk_ubx.gnss)


def test_damaged_stream_counts_bad_frames(tmp_path):
    raw = bytearray(_require(WALK / "gnss_1730.ubx").read_bytes())
    pvt = [raw.find(b"\xb5\x62\x01\x07\x5c\x00")]
    for _ in range(2):
        pvt.append(raw.find(b"\xb5\x62\x01\x07\x5c\x00", pvt[-1] + 1))
    raw[pvt[1] + 20] ^= 0xFF                      # corrupt one NAV-PVT payload byte
    cut = bytes(raw[: pvt[2] + 30])                # stream cut inside the third NAV-PVT
    path = tmp_path / "cut.ubx"
    path.write_bytes(cut)
    res = read_ubx(path)
    assert len(res.gnss) == 1
    reasons = [r for _, r in res.issues.examples]
    assert any("checksum" in r for r in reasons) and any("cut" in r for r in reasons)
    assert np.all(np.isnan(res.latency_s))


def test_fix_mapping():
    assert fix_status_from_nav_pvt(3, 1, 1, 2) == FixStatus.FIXED
    assert fix_status_from_nav_pvt(3, 1, 1, 1) == FixStatus.FLOAT
    assert fix_status_from_nav_pvt(3, 1, 0, 0) == FixStatus.SINGLE
    assert fix_status_from_nav_pvt(3, 1, 1, 0) == FixStatus.DGPS
    assert fix_status_from_nav_pvt(3, 0, 1, 2) == FixStatus.NONE
    assert fix_status_from_nav_pvt(1, 1, 0, 0) == FixStatus.DEAD_RECKONING


def test_walk_descriptor_reads_raw_stream():
    ds = load_dataset(_require(WALK / "dataset.toml"), read_raw=True)
    assert ds.notes["ubx"]["nav_pvt_epochs"] == len(ds.gnss)
    assert ds.notes["ubx"]["latency_s"]["median"] > 0


def test_every_bad_timetag_record_is_counted(tmp_path):
    """A timetag with more damaged records than the examples kept: all of them are counted."""
    tag = bytearray(_require(WALK / "gnss_1730.ubx.tag").read_bytes())
    header, record = 76, 8
    n_records = (len(tag) - header) // record
    damaged = list(range(10, min(n_records, 400), 40))
    for k in damaged:   # each of these records goes back in time
        tag[header + k * record:header + k * record + 4] = (0).to_bytes(4, "little")
    path = tmp_path / "damaged.tag"
    path.write_bytes(bytes(tag))
    res = read_ubx(WALK / "gnss_1730.ubx", path)
    assert len(damaged) > res.issues.max_examples
    assert res.issues.count == len(damaged)
    assert all(r.startswith("timetag: ") for _, r in res.issues.examples)
