"""Limits of the message fields and their validated readers, shared by the message codecs.

The readers (``num``, ``uint``, ``ident``, ``vec3``, ...) take a decoded map and a key and return
the value or raise ``WireError(reason, key)``: type, finiteness and range are checked for every
field, so that a decoder raises ``WireError`` and nothing else on any input.
"""
from __future__ import annotations

import math
import re
from typing import Any

import msgpack
import numpy as np

from v2xpos.types import FixStatus

MAX_GEOMETRY_POINTS = 64
MAX_ID_CHARS = 32

MAX_SPEED_MPS = 150.0
MAX_ACC_MPS2 = 100.0
MAX_RATE_RPS = 50.0
MAX_HEIGHT_M = 20000.0
MIN_HEIGHT_M = -1000.0
MAX_SD = 1.0e6
MAX_GEOMETRY_M = 100.0
MAX_T_GPS_S = 1.0e11
MAX_UINT64 = 2 ** 64 - 1

KINDS = ("vehicle", "pedestrian")
ID_RE = re.compile(r"[A-Za-z0-9_.\-]+")


class WireError(ValueError):
    """A message that cannot be accepted: ``reason`` (short, stable text) and ``field`` (or None)."""

    def __init__(self, reason: str, field: str | None = None):
        self.reason = reason
        self.field = field
        super().__init__(f"{reason} (field {field!r})" if field else reason)


def unpack_body(body: bytes, expect_type: str, versions: tuple) -> dict:
    """The message map of ``body``, of type ``expect_type`` and a schema version in ``versions``."""
    try:
        m = msgpack.unpackb(body, raw=False, strict_map_key=True, max_array_len=1024, max_map_len=256)
    except Exception as exc:
        raise WireError(f"body not msgpack ({type(exc).__name__})", "body") from None
    if type(m) is not dict:
        raise WireError("body is not a map", "body")
    t = m.get("T")
    if t != expect_type:
        raise WireError(f"message type {t!r} is not {expect_type!r}", "T")
    ver = m.get("ver")
    if type(ver) is not int:
        raise WireError("missing or non-integer schema version", "ver")
    if ver not in versions:
        raise WireError(f"unknown schema version {ver}", "ver")
    return m


def get_field(m: dict, key: str) -> Any:
    try:
        return m[key]
    except KeyError:
        raise WireError("missing field", key) from None


def num(m: dict, key: str, lo: float, hi: float) -> float:
    x = get_field(m, key)
    tx = type(x)
    if tx is not float and tx is not int:
        raise WireError(f"not a number ({tx.__name__})", key)
    x = float(x)
    if not math.isfinite(x):
        raise WireError("non-finite number", key)
    if x < lo or x > hi:
        raise WireError(f"out of range [{lo:g}, {hi:g}]: {x:g}", key)
    return x


def opt_num(m: dict, key: str, lo: float, hi: float) -> float | None:
    return None if m.get(key) is None else num(m, key, lo, hi)


def uint(m: dict, key: str, hi: int = MAX_UINT64) -> int:
    x = get_field(m, key)
    if type(x) is not int:
        raise WireError(f"not an integer ({type(x).__name__})", key)
    if x < 0 or x > hi:
        raise WireError(f"out of range [0, {hi}]: {x}", key)
    return x


_VALID_IDENTS: set = set()
_IDENT_CACHE_MAX = 4096


def ident(m: dict, key: str) -> str:
    s = get_field(m, key)
    if type(s) is str and s in _VALID_IDENTS:
        return s
    s = _check_ident(s, key)
    if len(_VALID_IDENTS) >= _IDENT_CACHE_MAX:
        _VALID_IDENTS.clear()
    _VALID_IDENTS.add(s)
    return s


def _check_ident(s: Any, key: str) -> str:
    if type(s) is not str:
        raise WireError(f"not a string ({type(s).__name__})", key)
    if not s or len(s) > MAX_ID_CHARS or not ID_RE.fullmatch(s):
        raise WireError(f"identifier must be 1-{MAX_ID_CHARS} chars of [A-Za-z0-9_.-]", key)
    return s


def vec3(m: dict, key: str, bound: float, nonneg: bool = False) -> np.ndarray:
    return np.array(vec3_list(m, key, bound, nonneg), dtype=float)


def vec3_list(m: dict, key: str, bound: float, nonneg: bool = False) -> list:
    """The validated 3-number list of ``key``."""
    try:
        v = m[key]
    except KeyError:
        raise WireError("missing field", key) from None
    if type(v) is not list or len(v) != 3:
        raise WireError("not an array of 3 numbers", key)
    a, b, c = v
    ta, tb, tc = type(a), type(b), type(c)
    if not ((ta is float or ta is int) and (tb is float or tb is int) and (tc is float or tc is int)):
        raise WireError("not a number", key)
    lo = 0.0 if nonneg else -bound
    # chained comparisons are False for NaN, so this also rejects non-finite values
    if lo <= a <= bound and lo <= b <= bound and lo <= c <= bound:
        return v
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
        raise WireError("non-finite number", key)
    if nonneg and (a < 0 or b < 0 or c < 0):
        raise WireError("negative standard deviation", key)
    raise WireError(f"out of range (|x| <= {bound:g})", key)


def f3(a: np.ndarray) -> list:
    if type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (3,):
        return a.tolist()
    return [float(a[0]), float(a[1]), float(a[2])]


FIX_BY_CODE = {int(f): f for f in FixStatus}


def fix_field(m: dict, key: str) -> FixStatus:
    code = uint(m, key, 255)
    fix = FIX_BY_CODE.get(code)
    if fix is None:
        raise WireError(f"unknown fix status {code}", key)
    return fix
