"""Vehicle state sources and session clocks (see ``v2xpos.sources.base``).

``make_source(table, where, ctx)`` builds the source a ``[source]`` table names by its ``type``:
the library's own types (``recording``, ``device``) or any registered under the entry-point group
``v2xpos.sources`` (the simulator registers ``sim``), or the one a ``factory = "module:function"`` key
names (a plugin that is not installed as a package, e.g. the simulator run from a checkout; the key
stays in the table so that the factory can accept it). A factory is a callable
``factory(table: dict, where: str, ctx: SourceContext) -> VehicleSource`` that validates its table
and raises ``SourceError`` naming ``where`` and the key.
"""
from __future__ import annotations

from typing import Callable

from v2xpos import plugins

from .base import SessionClock, SourceContext, SourceError, Stopped, VehicleSource, run_until_stopped

ENTRY_POINT_GROUP = "v2xpos.sources"
BUILTIN: dict[str, str] = {
    "recording": "v2xpos.sources.recording:from_config",
    "device": "v2xpos.sources.device:from_config",
}


def source_types() -> dict[str, str]:
    """Every known source type -> ``module:factory`` (built-in first, then entry points)."""
    return plugins.registered(ENTRY_POINT_GROUP, BUILTIN)


def _factory_ref(table: dict, where: str) -> str:
    """``module:function`` of the factory that builds ``table``'s type (SourceError if none)."""
    if not isinstance(table, dict):
        raise SourceError(f"{where}: expected a table")
    kinds = source_types()
    kind = table.get("type")
    if kind is None:
        raise SourceError(f"{where}.type: required: one of {sorted(kinds)}")
    if not isinstance(kind, str):
        raise SourceError(f"{where}.type: expected a string (one of {sorted(kinds)}), got {kind!r}")
    factory_ref = table.get("factory")
    if factory_ref is not None:
        if not isinstance(factory_ref, str) or ":" not in factory_ref:
            raise SourceError(f"{where}.factory: expected 'module:function', got {factory_ref!r}")
        kinds = {**kinds, kind: factory_ref}
    elif kind not in kinds:
        from v2xpos.schema import check_choice
        check_choice(kind, sorted(kinds), f"{where}.type", SourceError)
    return kinds[kind]


def _module_attr(ref: str, where: str, kind: str, attr: str | None = None) -> Callable | None:
    """The factory ``ref`` names; with ``attr``: that attribute of the factory's module, or None."""
    what = f"{where}.type: source {kind!r}"
    if attr is not None:
        return plugins.load(f"{ref.partition(':')[0]}:{attr}", what, SourceError, missing=None)
    return plugins.load(ref, what, SourceError)


def make_source(table: dict, where: str, ctx: SourceContext) -> VehicleSource:
    """The source named by ``table["type"]``, built from the rest of the table."""
    ref = _factory_ref(table, where)
    factory = _module_attr(ref, where, table["type"])
    rest = {k: v for k, v in table.items() if k != "type"}
    return factory(rest, where, ctx)


def check_source_table(table: dict, where: str) -> None:
    """Validate a ``[source]`` table without building the source (no file loaded, no port opened):
    the type, and the keys through the factory module's ``check_table(table, where)`` when it has
    one. SourceError naming ``where`` and the key. Service configs call it when they load."""
    ref = _factory_ref(table, where)
    check = _module_attr(ref, where, table["type"], attr="check_table")
    if check is not None:
        check({k: v for k, v in table.items() if k != "type"}, where)


__all__ = ["SessionClock", "SourceContext", "SourceError", "Stopped", "VehicleSource", "make_source",
           "run_until_stopped", "source_types", "check_source_table",
           "ENTRY_POINT_GROUP"]
