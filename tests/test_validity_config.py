"""Issue 27 item 1: the alert limit and the integrity risk are configuration. A service's
``[validity]`` ``alert_limit_m`` / ``integrity_risk`` reach the vehicle's own filter (the source it
builds), misspelt or out-of-range values are refused naming the table and key."""
from __future__ import annotations

from pathlib import Path

import pytest

from master.config import MasterConfig
from slave.config import SlaveConfig
from v2xpos.config import ConfigError
from v2xpos.ins.config import IntegrityModel
from tests.shared_data import SHARED_DATA, require_shared

DEV_A = SHARED_DATA / "convoy_dev" / "A" / "dataset.toml"
SOURCE = {"type": "recording", "dataset": str(DEV_A)}


@pytest.mark.parametrize("cls", [MasterConfig, SlaveConfig])
def test_validity_keys_configure_the_filter_and_are_checked(cls):
    cfg = cls.from_dict({"validity": {"alert_limit_m": 0.5, "integrity_risk": 1e-6}, "source": SOURCE}, "svc.toml")
    assert cfg.validity.filter_integrity == {"alert_limit_m": 0.5, "integrity_risk": 1e-6}
    assert cls.from_dict({"source": SOURCE}, "svc.toml").validity.filter_integrity == {}
    with pytest.raises(ConfigError, match=r"svc.toml: \[validity\].*'alert_limt_m'.*did you mean 'alert_limit_m'"):
        cls.from_dict({"validity": {"alert_limt_m": 0.5}, "source": SOURCE}, "svc.toml")
    with pytest.raises(ConfigError, match=r"\[validity\]\.integrity_risk: 2.0 outside"):
        cls.from_dict({"validity": {"integrity_risk": 2.0}, "source": SOURCE}, "svc.toml")
    with pytest.raises(ConfigError, match=r"\[validity\]\.alert_limit_m: 0.0 outside"):
        cls.from_dict({"validity": {"alert_limit_m": 0}, "source": SOURCE}, "svc.toml")


def test_the_recording_source_builds_its_filter_with_the_services_limits():
    require_shared(DEV_A)
    from v2xpos.sources import SourceContext, make_source
    ctx = SourceContext("A", config_dir=Path("."),
                        filter_overrides={"integrity": {"alert_limit_m": 0.55, "integrity_risk": 1e-7}})
    src = make_source(dict(SOURCE), "[source]", ctx)
    assert (src.filter.cfg.integrity.alert_limit_m, src.filter.cfg.integrity.integrity_risk) == (0.55, 1e-7)
    plain = make_source(dict(SOURCE), "[source]", SourceContext("A", config_dir=Path(".")))
    assert ((plain.filter.cfg.integrity.alert_limit_m, plain.filter.cfg.integrity.integrity_risk)
            == (IntegrityModel.alert_limit_m, IntegrityModel.integrity_risk))


def test_a_session_writes_its_verification_record_and_the_next_one_starts_from_it(tmp_path):
    """Issue 27 item 2: ``[validity] write_verification`` writes what the filter vouches for at the
    end of a session to ``verification_file``; the next session's filter reads it (a verified
    set-up starts with the prior of a change); a malformed file is refused naming it."""
    require_shared(DEV_A)
    from v2xpos.datasets.verification import read_verification_file, session_verification
    from v2xpos.sources import SourceContext, make_source
    table = {"verification_file": "B.verification.toml", "write_verification": True}
    cfg = SlaveConfig.from_dict({"validity": table, "source": SOURCE}, str(tmp_path / "slave.toml"))
    assert cfg.validity.verification_out == tmp_path / "B.verification.toml"
    assert "setup_verified" not in cfg.validity.filter_integrity            # no record yet: not verified
    with pytest.raises(ConfigError, match=r"write_verification: needs verification_file"):
        SlaveConfig.from_dict({"validity": {"write_verification": True}, "source": SOURCE}, "s.toml")
    src = make_source(dict(SOURCE), "[source]", SourceContext("B", config_dir=tmp_path))
    assert session_verification(src, cfg.validity.verification_out, "test") is None   # filter not started: nothing
    t0 = src.t_begin_gps_s
    src.advance(t0 + 150.0)                                        # through the first turns
    record = session_verification(src, cfg.validity.verification_out, "test drive")
    assert record is not None and record.verified, record
    assert record.protection_m <= record.alert_limit_m
    again = read_verification_file(cfg.validity.verification_out)
    assert again.verified and again.drive == "test drive" and again.protection_m == round(record.protection_m, 4)
    nxt = SlaveConfig.from_dict({"validity": table, "source": SOURCE}, str(tmp_path / "slave.toml"))
    assert nxt.validity.filter_integrity.get("setup_verified") is True
    verified = make_source(dict(SOURCE), "[source]", SourceContext("B", config_dir=tmp_path,
                                                                   filter_overrides={"integrity": nxt.validity.filter_integrity}))
    assert verified.filter.cfg.integrity.setup_verified
    (tmp_path / "B.verification.toml").write_text("[verification]\nverifed = true\n")
    with pytest.raises(ConfigError, match=r"B.verification.toml.*'verifed'.*did you mean 'verified'"):
        SlaveConfig.from_dict({"validity": table, "source": SOURCE}, str(tmp_path / "slave.toml"))


def test_a_services_end_of_session_record_is_reported_and_never_fatal(tmp_path):
    """Both services write their record through ``write_session_record``: the summary they report
    and a line saying what happened; a record that cannot be written, or a filter that never
    started, leaves nothing written and is said, not raised."""
    from types import SimpleNamespace
    from v2xpos.datasets.verification import read_verification_file, write_session_record
    flt = SimpleNamespace(initialized=True, separation=SimpleNamespace(protection_m=0.1, active=True, excluded=False),
                          cfg=SimpleNamespace(integrity=SimpleNamespace(alert_limit_m=0.3)),
                          consistency=SimpleNamespace(failed=False))
    source = SimpleNamespace(filter=flt)
    path = tmp_path / "A.verification.toml"
    summary, said = write_session_record(source, path, "session of A")
    assert summary == {"path": str(path), "verified": True, "protection_m": 0.1}
    assert said == f"verification record {path}: verified=True protection 0.100 m"
    assert read_verification_file(path).drive == "session of A"
    (tmp_path / "a_file").write_text("")
    blocked = tmp_path / "a_file" / "A.verification.toml"
    summary, said = write_session_record(source, blocked, "session of A")
    assert summary is None and said.startswith(f"[validity].verification_file {blocked}: not written: ")
    flt.initialized = False
    assert write_session_record(source, path, "s") == (
        None, f"[validity].verification_file {path}: not written: the filter never started")
