"""The integrity model of issue 27 (docs/integrity.md): the set-up hypothesis's record that lasts
across drives, the reason a solution is not verified, and the heading noise taken at standstill.
Each test builds its input from a known law or a known state and checks what must follow."""
from __future__ import annotations

import math

import numpy as np
import pytest

from v2xpos.types import FilterReason


def test_verification_record_round_trip_and_bad_keys():
    from v2xpos.compat import tomllib
    from v2xpos.datasets.verification import VerificationError, VerificationRecord, parse_verification
    rec = VerificationRecord(verified=True, drive="B/dataset.toml", date="2026-11-27", protection_m=0.113,
                             alert_limit_m=0.3, software="v2xpos test")
    back = parse_verification(tomllib.loads(rec.to_toml())["verification"], "x.toml: [verification]")
    assert back == VerificationRecord(True, "B/dataset.toml", "2026-11-27", 0.113, 0.3, "v2xpos test")
    with pytest.raises(VerificationError, match=r"x.toml: \[verification\]: unknown key 'verifed' \(did you mean 'verified'\?\)"):
        parse_verification({"verifed": True}, "x.toml: [verification]")
    with pytest.raises(VerificationError, match="verified: required"):
        parse_verification({"drive": "a"}, "w")
    with pytest.raises(VerificationError, match="protection_m"):
        parse_verification({"verified": True, "protection_m": -1.0}, "w")


def test_a_verified_setup_starts_with_the_prior_of_a_change(tmp_path):
    """The loader reads ``[verification]`` and ``ins_config`` turns it into the set-up prior."""
    from v2xpos.ins.calibrated import ins_config
    from v2xpos.datasets.verification import VerificationRecord
    from v2xpos.ins import InsFilter
    plain = ins_config("car", np.eye(3), np.zeros(3), 0.02, service=True)
    verified = ins_config("car", np.eye(3), np.zeros(3), 0.02, service=True,
                          verification=VerificationRecord(verified=True))
    unverified = ins_config("car", np.eye(3), np.zeros(3), 0.02, service=True,
                            verification=VerificationRecord(verified=False))
    assert (not plain.integrity.setup_verified and verified.integrity.setup_verified
            and not unverified.integrity.setup_verified)
    assert InsFilter(verified).separation.prior == verified.integrity.setup_change_prior
    assert InsFilter(plain).separation.prior == plain.integrity.setup_fault_prior
    assert verified.integrity.setup_change_prior < plain.integrity.setup_fault_prior


def test_the_loader_reads_the_verification_table(tmp_path):
    from v2xpos.datasets.loader import read_descriptor
    from v2xpos.datasets.verification import parse_verification
    from tests.shared_data import SHARED_DATA, require_shared
    src = require_shared(SHARED_DATA / "convoy_dev" / "B" / "dataset.toml")
    text = src.read_text().replace('imu.csv"', f'{src.parent / "imu.csv"}"', 1)
    text = text.replace('"imu.csv.tag"', f'"{src.parent / "imu.csv.tag"}"').replace('"gnss.pos"', f'"{src.parent / "gnss.pos"}"')
    out = tmp_path / "dataset.toml"
    out.write_text(text + '\n[verification]\nverified = true\ndrive = "earlier"\nprotection_m = 0.12\n')
    desc = read_descriptor(out)
    assert parse_verification(desc["verification"], "w").verified
    out.write_text(text + '\n[verification]\nverified = true\nprotecton_m = 0.12\n')
    from v2xpos.datasets.loader import load_dataset
    with pytest.raises(ValueError, match="did you mean 'protection_m'"):
        load_dataset(out)


def test_reasons_follow_the_filter_state():
    """``nav_state().reason``: ALIGNING before the start, HEADING_PENDING at a standstill start,
    TIME_OFFSET_CONVERGING while the IMU time offset's prior dominates the position sd at speed,
    SETUP_UNVERIFIED before a turn with the set-up hypothesis running, OK once verified."""
    from v2xpos.ins import InsConfig, InsFilter
    timing = InsFilter(InsConfig(setup={"platform": "car", "lever_arm_sd_m": 0.02},
                                 integrity={"fault_tolerant_solution": True}))
    timing.initialize(100.0, np.array([0.7, 0.2, 300.0]), np.array([10.0, 0.0, 0.0]), np.zeros(3))
    timing.consistency.t_settled_s = -math.inf
    timing._test_separation(100.0)
    assert timing.integrity_reason() == FilterReason.TIME_OFFSET_CONVERGING    # 10 m/s x 0.3 s prior
    flt = InsFilter(InsConfig(setup={"platform": "car", "lever_arm_sd_m": 0.02}, integrity={"fault_tolerant_solution": True},
                              effects={"effect_initial_sd": {"imu_time_offset": 1e-3}}))
    assert flt.integrity_reason() == FilterReason.ALIGNING
    flt.initialize(100.0, np.array([0.7, 0.2, 300.0]), np.array([10.0, 0.0, 0.0]), np.zeros(3))
    flt.heading_known = False
    assert flt.integrity_reason() == FilterReason.HEADING_PENDING
    flt.heading_known = True
    flt.last_gnss_t_s = 100.0                                        # a fix just used: not coasting
    flt.consistency.t_settled_s = -math.inf
    flt._test_separation(100.0)
    assert flt.consistency.protection_m > flt.cfg.integrity.alert_limit_m     # the lever arm is open before a turn
    assert flt.integrity_reason() == FilterReason.SETUP_UNVERIFIED
    nav = flt.nav_state()
    assert nav.reason == FilterReason.SETUP_UNVERIFIED and not nav.verified
    assert nav.protection_m == pytest.approx(flt.consistency.protection_m)
    flt.consistency.fail(101.0, "gnss_vel")
    assert flt.integrity_reason() == FilterReason.TEST_VELOCITY
    flt.consistency.failed = False
    flt.consistency.set_protection(0.1, flt.cfg.integrity.alert_limit_m)
    assert flt.integrity_reason() == FilterReason.OK and flt.nav_state().verified


def test_the_heading_noise_is_the_one_measured_at_standstill():
    """Vibration while driving raises the second differences of every gyro axis; the heading axis's
    process noise takes the density of the stops (the sensor's own noise), the others the running
    one. A white sensor with no vibration gives the same figure both ways."""
    from v2xpos.ins.noise import ImuNoiseMeter
    rng = np.random.default_rng(7)
    dt, n_white = 0.01, 1.5e-4
    meter = ImuNoiseMeter(window_s=10.0)
    t = np.arange(2000) * dt
    meter.feed(t, rng.normal(0.0, n_white / math.sqrt(dt), (2000, 3)), np.zeros((2000, 3)), static=True)
    vib = 8.0 * n_white
    t2 = t[-1] + dt + np.arange(3000) * dt
    meter.feed(t2, rng.normal(0.0, vib / math.sqrt(dt), (3000, 3)), np.zeros((3000, 3)), static=False)
    g_running, _ = meter.densities()
    np.testing.assert_allclose(g_running, vib, rtol=0.1)
    np.testing.assert_allclose(meter.static_gyro_density(), n_white, rtol=0.1)
    q = np.zeros(15)
    meter.apply(q, np.eye(3))
    np.testing.assert_allclose(np.sqrt(q[6:9]), [vib, vib, n_white], rtol=0.1)
    fresh = ImuNoiseMeter(window_s=10.0)                          # no stop yet: the running figure
    fresh.feed(t2, rng.normal(0.0, vib / math.sqrt(dt), (3000, 3)), np.zeros((3000, 3)))
    q = np.zeros(15)
    fresh.apply(q, np.eye(3))
    assert math.sqrt(q[8]) == pytest.approx(vib, rel=0.1)
