"""Ed25519 signing, trust list, replay/time windows, clock-skew detection, `v2xpos keys`."""
from __future__ import annotations

import json
import random

import numpy as np
import pytest

from v2xpos import security as sec
from v2xpos.cli import main as cli_main
from v2xpos.types import FixStatus
from v2xpos.wire import Geometry, StateMessage, decode_state, encode_state, pack_envelope, unpack_envelope

T0 = 1.4e9


def _msg(vehicle: str, seq: int, t: float) -> StateMessage:
    z = np.zeros(3)
    return StateMessage(fleet="f", vehicle_id=vehicle, seq=seq, t_gps_s=t, fix=FixStatus.FIXED,
                        lat_rad=0.7, lon_rad=-1.8, height_m=1600.0, v_ned_mps=np.array([10.0, 1, 0]),
                        acc_body_mps2=z, rate_body_rps=z, rpy_rad=z, pos_sd_m=z + 0.01,
                        vel_sd_mps=z + 0.01, att_sd_rad=z + 0.001, geometry=Geometry.box(4, 1, 1))


@pytest.fixture
def fleet(tmp_path):
    trust_path = tmp_path / "trust.json"
    signers = {}
    for vid in ("car1", "car2"):
        assert cli_main(["keys", "gen", "--vehicle", vid, "--out", str(tmp_path / "keys"),
                         "--trust", str(trust_path)]) == 0
        signers[vid] = sec.MessageSigner.from_file(tmp_path / "keys" / f"{vid}.key")
    return sec.load_trust_list(trust_path), signers, trust_path


def test_signed_message_accepted_and_forgeries_rejected(fleet):
    trust, signers, _ = fleet
    auth = sec.MessageAuthenticator(trust)
    good = decode_state(encode_state(_msg("car1", 1, T0), sign=signers["car1"]))
    assert auth.check(good, T0 + 0.01) is None

    outsider = sec.MessageSigner(sec.Ed25519PrivateKey.generate())
    forged_unknown = decode_state(encode_state(_msg("car1", 2, T0), sign=outsider))
    assert auth.check(forged_unknown, T0 + 0.01) == sec.REJECT_UNKNOWN_KEY

    impersonation = decode_state(encode_state(_msg("car1", 3, T0), sign=signers["car2"]))
    assert auth.check(impersonation, T0 + 0.01) == sec.REJECT_KEY_VEHICLE_MISMATCH

    env = unpack_envelope(encode_state(_msg("car1", 4, T0), sign=signers["car1"]))
    tampered_body = env.body.replace(b"car1", b"car1", 1)[:-1] + bytes([env.body[-1] ^ 0x01])
    try:
        tampered = decode_state(pack_envelope(tampered_body, env.sig, env.key_id))
    except Exception:
        tampered = None
    if tampered is not None:
        assert auth.check(tampered, T0 + 0.01) == sec.REJECT_BAD_SIGNATURE
    # a signature copied onto a different (valid) body
    other = encode_state(_msg("car1", 5, T0 + 0.02))
    swapped = decode_state(pack_envelope(unpack_envelope(other).body, env.sig, env.key_id))
    assert auth.check(swapped, T0 + 0.03) == sec.REJECT_BAD_SIGNATURE

    unsigned = decode_state(encode_state(_msg("car1", 6, T0)))
    assert auth.check(unsigned, T0 + 0.01) == sec.REJECT_UNSIGNED
    assert auth.stats.accepted == 1
    assert auth.stats.rejected[sec.REJECT_BAD_SIGNATURE] >= 1
    # the forged traffic did not move car1's sequence window: seq 2..6 are still acceptable
    ok = decode_state(encode_state(_msg("car1", 2, T0 + 0.04), sign=signers["car1"]))
    assert auth.check(ok, T0 + 0.05) is None


def test_envelope_verified_ahead_gives_the_same_verdicts(fleet):
    """``verify_envelope`` (run on the master's receive thread) decides exactly what ``check``
    would: a verdict passed on is used, not re-derived, and undecided cases fall back to check."""
    trust, signers, _ = fleet
    auth = sec.MessageAuthenticator(trust)
    good = encode_state(_msg("car1", 1, T0), sign=signers["car1"])
    env = unpack_envelope(good)
    swapped = pack_envelope(unpack_envelope(encode_state(_msg("car1", 2, T0))).body, env.sig, env.key_id)
    outsider = encode_state(_msg("car1", 3, T0), sign=sec.MessageSigner(sec.Ed25519PrivateKey.generate()))
    impersonation = encode_state(_msg("car1", 4, T0), sign=signers["car2"])
    unsigned = encode_state(_msg("car1", 5, T0))
    assert auth.verify_envelope(good) is True
    assert auth.verify_envelope(swapped) is False
    assert auth.verify_envelope(impersonation) is True   # valid for car2's key; check sees the mismatch
    for undecided in (outsider, unsigned, b"\x93\x01", b""):
        assert auth.verify_envelope(undecided) is None
    expected = {good: None, swapped: sec.REJECT_BAD_SIGNATURE, outsider: sec.REJECT_UNKNOWN_KEY,
                impersonation: sec.REJECT_KEY_VEHICLE_MISMATCH, unsigned: sec.REJECT_UNSIGNED}
    for payload, reason in expected.items():
        msg = decode_state(payload)
        assert auth.verify_signature(msg, auth.verify_envelope(payload)) == reason
        assert auth.verify_signature(msg) == reason
    # a negative verdict from the receive thread is final even for a body that would verify
    assert auth.check(decode_state(good), T0 + 0.01, signature_valid=False) == sec.REJECT_BAD_SIGNATURE
    assert auth.check(decode_state(good), T0 + 0.01, signature_valid=True) is None


def test_replay_duplicate_reorder_restart_and_time_windows(fleet):
    trust, signers, _ = fleet
    auth = sec.MessageAuthenticator(trust, max_age_s=2.0, replay_window=64)
    s = signers["car2"]
    wire = {k: encode_state(_msg("car2", k, T0 + 0.01 * k), sign=s) for k in range(0, 300)}
    now = lambda k: T0 + 0.01 * k + 0.002  # noqa: E731
    order = [0, 1, 2, 4, 3, 5, 5, 2]   # reordering inside the window is fine, repeats are not
    verdicts = [auth.check(decode_state(wire[k]), now(5)) for k in order]
    assert verdicts == [None, None, None, None, None, None, sec.REJECT_REPLAY, sec.REJECT_REPLAY]
    for k in range(6, 200):
        assert auth.check(decode_state(wire[k]), now(k)) is None
    # a message captured 1 s ago, replayed now: time still in the age window, seq in the window
    assert auth.check(decode_state(wire[100]), now(199)) == sec.REJECT_REPLAY
    # older than the age window
    assert auth.check(decode_state(wire[10]), now(299)) == sec.REJECT_TOO_OLD
    # below the sequence window with an old time: replay
    auth2 = sec.MessageAuthenticator(trust, max_age_s=100.0, replay_window=64)
    for k in range(0, 200):
        assert auth2.check(decode_state(wire[k]), now(k)) is None
    assert auth2.check(decode_state(wire[20]), now(200)) == sec.REJECT_REPLAY
    # the sender restarts (sequence from 0) with a current time: accepted, then its window is new
    restarted = decode_state(encode_state(_msg("car2", 0, T0 + 2.5), sign=s))
    assert auth2.check(restarted, T0 + 2.51) is None
    assert auth2.check(restarted, T0 + 2.52) == sec.REJECT_REPLAY
    # a message from the future
    future = decode_state(encode_state(_msg("car2", 1, T0 + 3.0), sign=s))
    assert auth2.check(future, T0 + 2.6) == sec.REJECT_FUTURE
    assert auth2.stats.rejected[sec.REJECT_FUTURE] == 1


def test_trust_list_cli_and_malformed_entries_named(tmp_path, fleet, capsys):
    _, _, trust_path = fleet
    assert cli_main(["keys", "trust", "list", "--trust", str(trust_path)]) == 0
    out = capsys.readouterr().out
    assert "car1" in out and "car2" in out
    assert cli_main(["keys", "trust", "remove", "--trust", str(trust_path), "--vehicle", "car2"]) == 0
    assert [e.vehicle_id for e in sec.load_trust_list(trust_path).entries.values()] == ["car1"]
    assert cli_main(["keys", "trust", "add", "--trust", str(trust_path),
                     str(tmp_path / "keys" / "car2.pub")]) == 0
    assert len(sec.load_trust_list(trust_path)) == 2

    doc = json.loads(trust_path.read_text())
    doc["keys"].append({"vehicle_id": "car3", "public_key": "not*base64"})
    doc["keys"].append({"vehicle_id": "bad id!", "public_key": doc["keys"][0]["public_key"]})
    doc["keys"].append({"vehicle_id": "car4", "public_key": "AAAA"})
    trust_path.write_text(json.dumps(doc))
    trust = sec.load_trust_list(trust_path)
    assert len(trust) == 2
    assert len(trust.issues) == 3
    assert all(str(trust_path) in i for i in trust.issues)
    assert "keys[2].public_key" in trust.issues[0]
    assert "keys[3].vehicle_id" in trust.issues[1]
    assert "32 bytes" in trust.issues[2]

    trust_path.write_text('{"format": "v2xpos-trust", "version": 1, "keys": {}}')
    with pytest.raises(sec.TrustFileError, match="'keys'"):
        sec.load_trust_list(trust_path)
    trust_path.write_text("{not json")
    with pytest.raises(sec.TrustFileError, match="trust.json"):
        sec.load_trust_list(trust_path)
    bad_pub = tmp_path / "x.pub"
    bad_pub.write_text("ssh-ed25519 AAAA\n")
    with pytest.raises(sec.TrustFileError, match="x.pub: line 1"):
        sec.load_public_key_file(bad_pub)
    assert (tmp_path / "keys" / "car1.key").stat().st_mode & 0o077 == 0


def _feed(monitor, vid, n, period, tx_of, delay_of, start_seq=0):
    st = None
    for k in range(start_seq, start_seq + n):
        t_true = T0 + k * period
        st = monitor.update(vid, k, tx_of(k, t_true), t_true + delay_of(k))
    return st


def test_clock_jump_and_drift_reported_but_delay_spikes_are_not():
    rng = random.Random(1)
    jitter = lambda k: 0.001 + 0.002 * rng.random()  # noqa: E731
    mon = sec.ClockSkewMonitor()
    # delay spikes (300 ms for 20 messages) and jitter: not a clock problem
    spike = lambda k: jitter(k) + (0.3 if 500 <= k < 520 else 0.0)  # noqa: E731
    st = _feed(mon, "a", 1500, 0.01, lambda k, t: t, spike)
    assert not st.skewed and st.jumps == 0
    assert abs(st.drift_ppm) < 500 and abs(st.offset_change_s) < 0.005

    # the slave clock steps back by 150 ms at message 600
    mon = sec.ClockSkewMonitor()
    reports = []
    for k in range(1500):
        t = T0 + k * 0.01
        tx = t - (0.15 if k >= 600 else 0.0)
        reports.append(mon.update("b", k, tx, t + jitter(k)))
    assert not any(r.skewed for r in reports[:590])
    st = reports[-1]
    assert st.jumps == 1 and abs(st.last_jump_s + 0.15) < 0.01
    assert st.skewed and abs(st.offset_change_s - 0.15) < 0.01

    # the slave clock drifts 3000 ppm (3 ms/s): flagged within 10 s, estimate within 20 %
    mon = sec.ClockSkewMonitor()
    st = _feed(mon, "c", 1000, 0.01, lambda k, t: T0 + (t - T0) * (1 + 3e-3), jitter)
    assert st.skewed and st.jumps == 0
    assert 2400 < st.drift_ppm < 3600


def test_verifier_process_matches_in_process_verdicts_and_survives_its_death(fleet, capsys):
    """The master's verify worker answers batches in order with the verdicts verify_envelope
    gives in process; once it is gone every verdict is undecided (the pipeline verifies itself)."""
    from v2xpos.verify_worker import VerifierProcess
    trust, signers, _ = fleet
    auth = sec.MessageAuthenticator(trust)
    good = encode_state(_msg("car1", 1, T0), sign=signers["car1"])
    env = unpack_envelope(good)
    swapped = pack_envelope(unpack_envelope(encode_state(_msg("car1", 2, T0))).body, env.sig, env.key_id)
    batches = [[good, swapped], [b"", encode_state(_msg("car2", 3, T0), sign=signers["car2"])], [good] * 5]
    worker = VerifierProcess(trust.to_json())
    try:
        for b in batches:
            worker.submit(b)
        for b in batches:
            assert worker.collect() == [auth.verify_envelope(p) for p in b]
        assert worker.alive
        worker.proc.kill()
        worker.proc.wait()
        worker.submit([good] * 3)
        assert worker.collect() == [None, None, None]
        assert not worker.alive
        assert "verify worker abandoned" in capsys.readouterr().err
    finally:
        worker.close()
