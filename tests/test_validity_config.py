"""Issue 27 item 1: the alert limit and the integrity risk are configuration. A service's
``[validity]`` ``alert_limit_m`` / ``integrity_risk`` reach the vehicle's own filter (the source it
builds), misspelt or out-of-range values are refused naming the table and key."""
from __future__ import annotations

from pathlib import Path

import pytest

from master.config import MasterConfig
from slave.config import SlaveConfig
from v2xpos.config import ConfigError
from v2xpos.ins.config import InsConfig
from tests.shared_data import SHARED_DATA, require_shared

DEV_A = SHARED_DATA / "convoy_dev" / "A" / "dataset.toml"
SOURCE = {"type": "recording", "dataset": str(DEV_A)}


@pytest.mark.parametrize("cls", [MasterConfig, SlaveConfig])
def test_validity_keys_configure_the_filter_and_are_checked(cls):
    cfg = cls.from_dict({"validity": {"alert_limit_m": 0.5, "integrity_risk": 1e-6}, "source": SOURCE}, "svc.toml")
    assert cfg.filter_integrity == {"alert_limit_m": 0.5, "integrity_risk": 1e-6}
    assert cls.from_dict({"source": SOURCE}, "svc.toml").filter_integrity == {}
    with pytest.raises(ConfigError, match=r"svc.toml: \[validity\].*'alert_limt_m'.*did you mean 'alert_limit_m'"):
        cls.from_dict({"validity": {"alert_limt_m": 0.5}, "source": SOURCE}, "svc.toml")
    with pytest.raises(ConfigError, match=r"\[validity\]\.integrity_risk: 2.0 outside"):
        cls.from_dict({"validity": {"integrity_risk": 2.0}, "source": SOURCE}, "svc.toml")
    with pytest.raises(ConfigError, match=r"\[validity\]\.alert_limit_m: 0.0 outside"):
        cls.from_dict({"validity": {"alert_limit_m": 0}, "source": SOURCE}, "svc.toml")


def test_the_recording_source_builds_its_filter_with_the_services_limits():
    require_shared(DEV_A)
    from v2xpos.sources import SourceContext, make_source
    ctx = SourceContext("A", config_dir=Path("."), filter_overrides={"alert_limit_m": 0.55, "integrity_risk": 1e-7})
    src = make_source(dict(SOURCE), "[source]", ctx)
    assert (src.filter.cfg.alert_limit_m, src.filter.cfg.integrity_risk) == (0.55, 1e-7)
    plain = make_source(dict(SOURCE), "[source]", SourceContext("A", config_dir=Path(".")))
    assert (plain.filter.cfg.alert_limit_m, plain.filter.cfg.integrity_risk) == (InsConfig.alert_limit_m,
                                                                                  InsConfig.integrity_risk)
