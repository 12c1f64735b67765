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

import importlib
from importlib import metadata
from typing import Callable

from .base import SessionClock, SourceContext, SourceError, Stopped, VehicleSource, run_until_stopped

ENTRY_POINT_GROUP = "v2xpos.sources"
BUILTIN: dict[str, str] = {
    "recording": "v2xpos.sources.recording:from_config",
    "device": "v2xpos.sources.device:from_config",
}


def _load(ref: str) -> Callable:
    module, _, attr = ref.partition(":")
    return getattr(importlib.import_module(module), attr)


def source_types() -> dict[str, str]:
    """Every known source type -> ``module:factory`` (built-in first, then entry points)."""
    out = dict(BUILTIN)
    try:
        eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
    except TypeError:  # Python < 3.10 API
        eps = metadata.entry_points().get(ENTRY_POINT_GROUP, [])
    for ep in eps:
        out.setdefault(ep.name, ep.value)
    return out


def make_source(table: dict, where: str, ctx: SourceContext) -> VehicleSource:
    """The source named by ``table["type"]``, built from the rest of the table."""
    if not isinstance(table, dict):
        raise SourceError(f"{where}: expected a table")
    kinds = source_types()
    kind = table.get("type")
    if kind is None:
        raise SourceError(f"{where}.type: missing; one of {sorted(kinds)}")
    factory_ref = table.get("factory")
    if factory_ref is not None:
        if not isinstance(factory_ref, str) or ":" not in factory_ref:
            raise SourceError(f"{where}.factory: expected 'module:function', got {factory_ref!r}")
        kinds = {**kinds, kind: factory_ref}
    elif kind not in kinds:
        from v2xpos.datasets.calibration import did_you_mean
        raise SourceError(f"{where}.type: {kind!r} is not one of {sorted(kinds)}{did_you_mean(str(kind), kinds)}")
    try:
        factory = _load(kinds[kind])
    except (ImportError, AttributeError) as exc:
        raise SourceError(f"{where}.type: source {kind!r} ({kinds[kind]}) cannot be loaded: {exc}") from None
    rest = {k: v for k, v in table.items() if k != "type"}
    return factory(rest, where, ctx)


__all__ = ["SessionClock", "SourceContext", "SourceError", "Stopped", "VehicleSource", "make_source",
           "run_until_stopped", "source_types",
           "ENTRY_POINT_GROUP"]
