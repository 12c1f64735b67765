"""docs/configuration.md names every key the service configs accept.

The accepted keys are taken from the parsers themselves: every call of ``v2xpos.schema.check_keys``
(the one unknown-key check every config table goes through) is observed with ``sys.setprofile``
while the example configs in ``configs/`` and the field examples of docs/field.md are loaded. A
key added to a parser without a line in the doc fails here."""
from __future__ import annotations

import re
import sys
from pathlib import Path

from v2xpos import schema
from v2xpos.compat import tomllib

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "configuration.md"
DOCUMENTED_ELSEWHERE = (".calibration", "InsConfig.")
"""Tables documented on another page (the ``[calibration]`` table: docs/calibration.md; the
filter's ``InsConfig`` groups, given in Python by a source: v2xpos/ins/config.py, docs/ins.md)."""


def _documented() -> set[str]:
    """Names the doc gives in code spans: a key (`fleet`) or a table (`[output.can]`: output, can)."""
    names = set()
    for span in re.findall(r"`([^`\n]+)`", DOC.read_text()):
        if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", span):
            names.add(span)
        elif re.fullmatch(r"\[[A-Za-z_][A-Za-z0-9_.]*\]", span):
            names.update(span[1:-1].split("."))
    return names


def _accepted_keys(load) -> dict[str, set[str]]:
    """{where: allowed keys} of every ``check_keys`` call made by ``load()``."""
    seen: dict[str, set[str]] = {}
    code = schema.check_keys.__code__

    def profile(frame, event, arg):
        if event == "call" and frame.f_code is code:
            loc = frame.f_locals
            seen.setdefault(str(loc["where"]), set()).update(map(str, loc["allowed"]))

    old = sys.getprofile()
    sys.setprofile(profile)
    try:
        load()
    finally:
        sys.setprofile(old)
    return seen


def _load_all() -> None:
    from master.config import MasterConfig
    from slave.config import SlaveConfig
    from v2xpos.sources import SourceContext, make_source
    from v2xpos.sources.corrections import parse_corrections
    for p in sorted((ROOT / "configs").glob("master*.toml")):
        MasterConfig.load(p)
    for p in sorted((ROOT / "configs").glob("slave*.toml")):
        SlaveConfig.load(p)
    text = (ROOT / "docs" / "field.md").read_text()
    for block in re.findall(r"```toml\n(.*?)```", text, re.S):
        cfg = tomllib.loads(block)
        make_source(cfg["source"], "[source]", SourceContext("v", config_dir=Path("/nonexistent"))).close()
        parse_corrections(cfg["corrections"])


def test_every_accepted_key_is_documented():
    accepted = _accepted_keys(_load_all)
    assert len(accepted) >= 20, sorted(accepted)             # the observation itself works
    documented = _documented()
    missing = {where: sorted(keys - documented) for where, keys in accepted.items()
               if not any(part in where for part in DOCUMENTED_ELSEWHERE) and keys - documented}
    assert not missing, f"keys accepted but not in docs/configuration.md: {missing}"


def test_the_observation_sees_a_new_key():
    """The check fails for a key the doc does not have (the test can fail)."""
    def load():
        schema.check_keys({"fleet": "x"}, ("fleet", "a_key_nobody_documented_s"), "[service]", ValueError)
    accepted = _accepted_keys(load)
    documented = _documented()
    assert accepted == {"[service]": {"fleet", "a_key_nobody_documented_s"}}
    assert accepted["[service]"] - documented == {"a_key_nobody_documented_s"}
