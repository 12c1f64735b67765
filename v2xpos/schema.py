"""Reading a TOML table against what it may hold: the one place where an unknown key or an unknown
choice is rejected, with a "did you mean" for a near miss.

Every reader of a configuration or descriptor (service configs, dataset descriptors, ``[source]``
tables, ``[calibration]``, ``[verification]``, stream and clock tables, field configs) calls
``check_keys`` with the table, the keys it allows and *where* the table is -- the file and the
table, e.g. ``"B/dataset.toml: [calibration]"`` -- and the exception class of its own layer, so the
message names what and where the same way everywhere::

    B/dataset.toml: [gnss]: unknown key 'lever_arm' (did you mean 'lever_arm_m'?); allowed [...]

``read_table`` goes one step further for flat tables of scalars: a list of ``Key`` (name, type,
range, default) is the whole schema, and the table is checked against it in one call.

"Did you mean" is the closest allowed name by ``difflib``'s Ratcliff/Obershelp similarity (at least
0.6, the ``difflib`` default), which catches a dropped, doubled or swapped letter in a key of
more than a few characters.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Sequence
from dataclasses import MISSING, dataclass
from typing import Any

REQUIRED = object()
"""``Key.default`` of a key that must be present."""


def did_you_mean(key: str, allowed: Iterable[Any]) -> str:
    """`` (did you mean 'x'?)`` for the closest allowed name, or an empty string."""
    close = difflib.get_close_matches(str(key), [str(a) for a in allowed], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _listed(allowed: Iterable[Any]) -> list:
    """The allowed names as the message lists them: in declared order, sorted if unordered."""
    return sorted(map(str, allowed)) if isinstance(allowed, (set, frozenset)) else list(allowed)


def check_keys(table: dict, allowed: Iterable[Any], where: str, error: type[Exception] = ValueError) -> None:
    """Raise ``error`` if ``table`` has a key outside ``allowed``: the message names ``where``, every
    unknown key (in the table's order) with a "did you mean" for a near miss, and the allowed keys."""
    allowed = tuple(allowed) if not isinstance(allowed, (set, frozenset, tuple, list)) else allowed
    unknown = [str(k) for k in table if k not in allowed]
    if unknown:
        named = ", ".join(f"{k!r}{did_you_mean(k, allowed)}" for k in unknown)
        noun = "key" if len(unknown) == 1 else "keys"
        raise error(f"{where}: unknown {noun} {named}; allowed {_listed(allowed)}")


def check_choice(value: Any, choices: Iterable[Any], where: str, error: type[Exception] = ValueError) -> None:
    """Raise ``error`` if ``value`` is not one of ``choices``, naming ``where`` and the near miss."""
    if value not in choices:
        raise error(f"{where}: {value!r} is not one of {_listed(choices)}{did_you_mean(str(value), choices)}")


@dataclass(frozen=True)
class Key:
    """One key of a flat table: its name, the type of its value (``float`` accepts integers; ``bool``
    is never a number), its default (``REQUIRED``: it must be present) and the range of a number:
    ``above`` (exclusive) or ``low`` (inclusive) below, ``high`` (inclusive) above."""
    name: str
    kind: type | tuple[type, ...]
    default: Any = REQUIRED
    above: float | None = None
    low: float | None = None
    high: float | None = None

    def range_text(self) -> str:
        lower = f"({self.above}" if self.above is not None else f"[{self.low}" if self.low is not None else "(-inf"
        return f"{lower}, {'inf)' if self.high is None else f'{self.high}]'}"


def _value(key: Key, v: Any, where: str, error: type[Exception]) -> Any:
    kinds = key.kind if isinstance(key.kind, tuple) else (key.kind,)
    if float in kinds and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, kinds) or (isinstance(v, bool) and bool not in kinds):
        names = "/".join(k.__name__ for k in kinds)
        raise error(f"{where}.{key.name}: expected {names}, got {type(v).__name__} {v!r}")
    if isinstance(v, float) and not math.isfinite(v):
        raise error(f"{where}.{key.name}: expected a finite number, got {v!r}")
    if ((key.above is not None and not v > key.above) or (key.low is not None and not v >= key.low)
            or (key.high is not None and not v <= key.high)):
        raise error(f"{where}.{key.name}: expected a number in {key.range_text()}, got {v!r}")
    return v


def field_key(cls: type, name: str, kind: type | tuple[type, ...], **bounds: float) -> Key:
    """The ``Key`` of the table key ``name`` read into the dataclass ``cls``'s field of the same name,
    with that field's default (one default for the file and for code) and ``bounds`` (``above``,
    ``low``, ``high``)."""
    f = cls.__dataclass_fields__[name]
    default = f.default if f.default_factory is MISSING else f.default_factory()
    return Key(name, kind, default, **bounds)


def read_table(table: Any, keys: Sequence[Key], where: str, error: type[Exception] = ValueError) -> dict[str, Any]:
    """``table`` checked against ``keys``: unknown keys rejected (``check_keys``), each value's type
    and range checked, absent keys given their default; a dict keyed by name. ``error`` names
    ``where`` and the key."""
    if not isinstance(table, dict):
        raise error(f"{where}: expected a table, got {type(table).__name__}")
    check_keys(table, tuple(k.name for k in keys), where, error)
    out = {}
    for key in keys:
        if key.name in table:
            out[key.name] = _value(key, table[key.name], where, error)
        elif key.default is REQUIRED:
            raise error(f"{where}.{key.name}: missing")
        else:
            out[key.name] = key.default
    return out
