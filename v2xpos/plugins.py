"""Plug-in points: a kind of part (vehicle sources, receiver decoders, output sinks) is a registry
mapping a name to a ``"module:attribute"`` reference -- the library's own parts, then every entry
point of the kind's group, which an installed package declares in its ``pyproject.toml``::

    [project.entry-points."v2xpos.outputs"]
    mysink = "mypackage.mysink:from_table"

A program that embeds v2xpos (or a test) registers a part at run time with ``register(group, name,
ref)``. The reference is imported only when the part is used, so a part never loads another's
dependencies. Used by ``v2xpos.sources`` (group ``v2xpos.sources``), ``v2xpos.devices.stream``
(``v2xpos.decoders``) and ``master.outputs`` (``v2xpos.outputs``); docs/extending.md walks
through adding one.
"""
from __future__ import annotations

import importlib
from importlib import metadata
from typing import Any


_REGISTERED: dict[str, dict[str, str]] = {}
"""Parts registered at run time (``register``), by group."""


def register(group: str, name: str, ref: str) -> None:
    """Make ``ref`` (``"module:attribute"``) the part ``name`` of ``group`` in this process -- for a
    program that embeds v2xpos, or a test; an installed package declares an entry point instead."""
    _REGISTERED.setdefault(group, {})[name] = ref


def unregister(group: str, name: str) -> None:
    """Undo ``register``."""
    _REGISTERED.get(group, {}).pop(name, None)


def registered(group: str, builtin: dict[str, str]) -> dict[str, str]:
    """Every known name of ``group`` -> ``module:attribute``: the built-in ones first, then those
    registered at run time, then the entry points (neither replaces a name already known)."""
    out = dict(builtin)
    for name, ref in _REGISTERED.get(group, {}).items():
        out.setdefault(name, ref)
    for ep in metadata.entry_points(group=group):
        out.setdefault(ep.name, ep.value)
    return out


_RAISE = object()


def load(ref: str, what: str, error: type[Exception] = ValueError, missing: Any = _RAISE) -> Any:
    """The object ``ref`` (``"module:attribute"``, the attribute possibly dotted) names; ``error``
    naming ``what`` when the module cannot be imported, or when it has no such attribute and no
    ``missing`` value is given."""
    module, _, attr = ref.partition(":")
    if not module or not attr:
        raise error(f"{what}: expected 'module:attribute', got {ref!r}")
    try:
        obj: Any = importlib.import_module(module)
    except ImportError as exc:
        raise error(f"{what} ({ref}) cannot be loaded: {exc}") from None
    for name in attr.split("."):
        try:
            obj = getattr(obj, name)
        except AttributeError:
            if missing is not _RAISE:
                return missing
            raise error(f"{what}: {module} has no {attr!r}") from None
    return obj
