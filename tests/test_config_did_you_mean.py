"""Every key of every master and slave table refuses a misspelling with a "did you mean" naming it:
each table is read against its schema (``v2xpos.schema.read_table``), so a key added to a schema is
covered here without a line of its own."""
from __future__ import annotations

import pytest

from master import config as master_config
from slave import config as slave_config
from v2xpos.config import INTEGRITY_KEYS, ConfigError
from v2xpos.link import LinkConfig, LinkImpairment

SOURCE = {"type": "sim", "model": "truth_noise"}
MASTER_TABLES = {("service",): master_config.SERVICE_KEYS, ("output", "can"): master_config.CAN_KEYS,
                 ("output", "udp"): master_config.UDP_KEYS, ("scene",): master_config.SCENE_KEYS,
                 ("record",): master_config.RECORD_KEYS, ("security",): master_config.SECURITY_KEYS,
                 ("grading",): master_config.GRADING_KEYS,
                 ("validity",): (*master_config.VALIDITY_KEYS, *INTEGRITY_KEYS),
                 ("link",): tuple(LinkConfig.__dataclass_fields__)}
SLAVE_TABLES = {("service",): slave_config.SERVICE_KEYS, ("validity",): INTEGRITY_KEYS,
                ("link",): tuple(LinkConfig.__dataclass_fields__),
                ("impairment",): tuple(LinkImpairment.__dataclass_fields__)}


def _misspelt(name: str) -> str:
    """``name`` with its middle letter doubled (a typing slip)."""
    k = len(name) // 2
    return name[:k] + name[k] + name[k:]


def _cases(tables):
    return [(path, getattr(key, "name", key)) for path, keys in tables.items() for key in keys]


def _nested(path: tuple, key: str) -> dict:
    table: dict = {key: None}
    for name in reversed(path):
        table = {name: table}
    return table


@pytest.mark.parametrize("cls, path, key", [(master_config.MasterConfig, p, k) for p, k in _cases(MASTER_TABLES)]
                         + [(slave_config.SlaveConfig, p, k) for p, k in _cases(SLAVE_TABLES)])
def test_every_key_refuses_a_misspelling_with_did_you_mean(cls, path, key):
    bad = _misspelt(key)
    with pytest.raises(ConfigError) as e:
        cls.from_dict({"source": SOURCE, **_nested(path, bad)}, "x.toml")
    text = str(e.value)
    assert f"x.toml: [{'.'.join(path)}]" in text and f"{bad!r} (did you mean {key!r}?)" in text, text
