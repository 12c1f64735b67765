"""Pieces shared by the service configurations (master and slave TOML files): loading, typed
fields, unknown-key rejection with "did you mean", the ``[source]`` table, ``[link]`` and the
``[impairment]`` table. Every error names the file, the table and the key.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Sequence
from typing import Any

from v2xpos.compat import tomllib
from v2xpos.link import LinkConfig, LinkImpairment
from v2xpos import schema
from v2xpos.schema import field_key  # noqa: F401  (the services' configs import it from here with the rest)


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names the file and the key."""


def load_toml(path: str | Path) -> dict:
    p = Path(path)
    try:
        with p.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{p}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # added by trust/resilience (fuzz finding): name the file
        raise ConfigError(f"{p}: not UTF-8 text: {exc}") from None


def take(table: dict, key: str, kind: type | tuple, default: Any, where: str) -> Any:
    """``table[key]`` checked against ``kind`` (ints are accepted for floats); default if absent."""
    if key not in table:
        return default
    v = table[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if float in kinds and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, kinds) or (isinstance(v, bool) and bool not in kinds):
        names = "/".join(k.__name__ for k in kinds)
        raise ConfigError(f"{where}.{key}: expected {names}, got {type(v).__name__} {v!r}")
    return v


def check_keys(table: dict, allowed: set, where: str) -> None:
    """``v2xpos.schema.check_keys`` raising ConfigError."""
    schema.check_keys(table, allowed, where, ConfigError)


def read_group(cls: type, table: Any, keys: Sequence[schema.Key], where: str, **extra: Any) -> Any:
    """``cls`` built from ``table`` read against ``keys`` (``v2xpos.schema.read_table``: unknown keys
    refused with a "did you mean", types and ranges checked, defaults filled), plus ``extra`` fields;
    ConfigError naming ``where`` and the key."""
    return cls(**schema.read_table(table, keys, where, ConfigError), **extra)


@dataclass
class SourceConfig:
    """Where the vehicle's states come from: the ``[source]`` table, handed as it is to
    ``v2xpos.sources.make_source`` (each source type validates its own keys when the service builds
    it). ``type`` is checked here: a built-in type (``recording``, ``device``), a registered one, or
    any name with a ``factory = "module:function"``."""
    table: dict = field(default_factory=lambda: {"type": "recording"})

    @property
    def type(self) -> str:
        return str(self.table.get("type"))

    @classmethod
    def from_table(cls, t: dict, where: str) -> "SourceConfig":
        from v2xpos.sources import SourceError, check_source_table
        try:
            check_source_table(t, where)
        except SourceError as exc:
            raise ConfigError(str(exc)) from None
        return cls(table=dict(t))


def impairment_from_table(t: dict, where: str) -> LinkImpairment:
    """``[impairment]``: injected link delay for tests and trials (see ``v2xpos.link.LinkImpairment``)."""
    v = schema.read_table(t, (schema.field_key(LinkImpairment, "latency_ms", float, low=0),
                              schema.field_key(LinkImpairment, "jitter_ms", float, low=0), schema.Key("spikes", list, []),
                              schema.field_key(LinkImpairment, "seed", int)), where, ConfigError)
    out = []
    for k, sp in enumerate(v["spikes"]):
        if (not isinstance(sp, list) or len(sp) != 3
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in sp)):
            raise ConfigError(f"{where}.spikes[{k}]: expected [t_start_gps_s, t_end_gps_s, extra_ms]")
        out.append((float(sp[0]), float(sp[1]), float(sp[2])))
    return LinkImpairment(v["latency_ms"], v["jitter_ms"], out, v["seed"])


def link_from_table(t: dict, where: str) -> LinkConfig:
    try:
        return LinkConfig.from_dict(t, where)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def config_dir(path: str) -> Path:
    """Directory against which a config's relative paths resolve: the file's own directory, or the
    working directory for a config built in memory (``path`` like ``"<dict>"``)."""
    return Path.cwd() if path.startswith("<") else Path(path).resolve().parent


def corrections_from_table(d: dict, path: str):
    """The ``[corrections]`` table of a service config (``v2xpos.sources.corrections``), or None."""
    if "corrections" not in d:
        return None
    from v2xpos.sources.corrections import parse_corrections
    try:
        return parse_corrections(d["corrections"], f"{path}: [corrections]")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


INTEGRITY_KEYS = (schema.Key("alert_limit_m", float, None), schema.Key("integrity_risk", float, None),
                  schema.Key("verification_file", str, None), schema.Key("write_verification", bool, False))
"""The ``[validity]`` keys that configure the vehicle's own filter (``InsConfig``): its horizontal
protection level is held against ``alert_limit_m`` at ``integrity_risk``; ``verification_file``
keeps the ``[verification]`` record of its set-up between sessions (read at the start: a verified
set-up starts with the prior of a change, not of a blunder; written at the end when
``write_verification``) -- docs/integrity.md."""


@dataclass
class FilterValidity:
    """What a service's ``[validity]`` sets for its own filter: ``filter_integrity``, fields of the
    filter's ``InsConfig.integrity`` (only what is given), and where the session's ``[verification]``
    record is written at the end (None: not asked)."""
    filter_integrity: dict = field(default_factory=dict)
    verification_out: Path | None = None


@dataclass(frozen=True)
class Validity:
    """A service's ``[validity]`` table, read once (``validity_from_table``)."""
    filter_integrity: dict           # overrides of the own filter's InsConfig.integrity group (only what is given)
    verification_out: Path | None    # where the session's [verification] record is written; None: not asked
    service: dict                    # the service's own [validity] keys by name, defaults filled in


def validity_from_table(table: Any, where: str, base_dir: Path | None = None,
                        service_keys: Sequence[schema.Key] = ()) -> Validity:
    """A service's ``[validity]`` table against ``INTEGRITY_KEYS`` and the service's own
    ``service_keys`` (``v2xpos.schema.read_table``: unknown keys refused with a "did you mean", types
    checked, defaults filled). The filter's overrides: ``alert_limit_m`` (0, 10] m,
    ``integrity_risk`` (0, 0.1], and ``setup_verified`` when ``verification_file`` (relative to
    ``base_dir``) holds a verified record; the record is written back at the end of the session
    when ``write_verification`` (which needs the file). ConfigError naming ``where`` and the key,
    or the file."""
    values = schema.read_table(table, (*service_keys, *INTEGRITY_KEYS), where, ConfigError)
    overrides = {}
    limit = values["alert_limit_m"]
    if limit is not None:
        if not 0 < limit <= 10.0:
            raise ConfigError(f"{where}.alert_limit_m: {limit} outside (0, 10] m")
        overrides["alert_limit_m"] = float(limit)
    risk = values["integrity_risk"]
    if risk is not None:
        if not 0 < risk <= 0.1:
            raise ConfigError(f"{where}.integrity_risk: {risk} outside (0, 0.1]")
        overrides["integrity_risk"] = float(risk)
    name = values["verification_file"]
    if values["write_verification"] and name is None:
        raise ConfigError(f"{where}.write_verification: needs verification_file (where to write the record)")
    path = None
    if name is not None:
        path = Path(name).expanduser()
        path = path if path.is_absolute() or base_dir is None else Path(base_dir) / path
        from v2xpos.datasets.verification import VerificationError, read_verification_file
        try:
            record = read_verification_file(path)
        except VerificationError as exc:
            raise ConfigError(f"{where}.verification_file: {exc}") from None
        if record is not None and record.verified:
            overrides["setup_verified"] = True
    return Validity(filter_integrity=overrides, verification_out=path if values["write_verification"] else None,
                    service={k.name: values[k.name] for k in service_keys})
