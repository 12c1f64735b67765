"""The precompiled CAN frame packer is bit-exact against cantools' encoder plus cantools' AUTOSAR E2E
profile-2 checksum, on every message layout of the shipped DBC (the reference is cantools alone: the
documented saturation rule, ``Message.encode`` and ``cantools.autosar.end_to_end.apply_profile2_crc``)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from cantools.autosar.end_to_end import apply_profile2_crc

from v2xpos.output.can import FramePacker
from v2xpos.output.can_dbc import (ID_ACC, ID_ATT, ID_GAP, ID_LANE, ID_MASTER, ID_MASTER_SIGMA, ID_OBJECT, ID_POS,
                                   ID_RANGE, ID_SIGMA, ID_STATUS, ID_VEL, load_dbc)


@pytest.fixture(scope="module")
def db():
    return load_dbc()


def _special(sig) -> int | None:
    for raw, label in (sig.choices or {}).items():
        if str(label) in ("none", "n/a"):
            return int(raw)
    return None


def _cantools_reference(message, values: dict) -> bytes:
    """Documented rule: None / NaN -> the signal's "none"/"n/a" code if it has one (else NaN -> 0),
    clip to the DBC range, cantools encode; then the E2E profile-2 CRC (data ID = frame id & 0xFF)."""
    phys = {}
    for s in message.signals:
        if s.name.endswith("_CRC"):
            phys[s.name] = 0
            continue
        v = values[s.name]
        code = _special(s)
        if v is None or v != v:
            if code is not None:
                phys[s.name] = code * s.scale + s.offset
                continue
            v = 0.0
        phys[s.name] = s.minimum if v < s.minimum else s.maximum if v > s.maximum else v
    data = bytes(message.encode(phys, strict=False))
    if any(s.name.endswith("_CRC") for s in message.signals):
        data = bytes(apply_profile2_crc(data, message.frame_id & 0xFF))
    return data


def _random_value(rng: np.random.Generator, sig) -> float | int | None:
    lo, hi = sig.minimum, sig.maximum
    pick = rng.integers(0, 11)
    if pick == 0:
        return math.nan
    if pick == 1:
        return lo - abs(rng.normal()) * (hi - lo + 1.0)
    if pick == 2:
        return hi + abs(rng.normal()) * (hi - lo + 1.0)
    if pick == 3:
        return float(rng.choice([lo, hi, 0.0, math.inf, -math.inf]))
    if pick == 4:   # exact raw grid points and half-way points (banker's rounding in both encoders)
        k = int(rng.integers(round((lo - sig.offset) / sig.scale), round((hi - sig.offset) / sig.scale) + 1))
        return sig.offset + (k + 0.5 * int(rng.integers(0, 2))) * sig.scale
    if pick == 5 and sig.scale == 1:
        return int(rng.integers(int(lo), int(hi) + 1))
    if pick == 6:
        return None
    return float(rng.uniform(lo, hi))


LAYOUTS = [ID_MASTER, ID_MASTER_SIGMA, ID_LANE, ID_OBJECT] + \
    [base + slot for base in (ID_STATUS, ID_POS, ID_RANGE, ID_VEL, ID_GAP, ID_ATT, ID_ACC, ID_SIGMA) for slot in (0, 17, 63)]


@pytest.mark.parametrize("frame_id", LAYOUTS)
def test_packer_bit_exact_against_cantools(db, frame_id):
    message = db.get_message_by_frame_id(frame_id)
    specials = {s.name: _special(s) for s in message.signals if _special(s) is not None}
    packer = FramePacker(message, specials=specials)
    rng = np.random.default_rng(frame_id)
    for _ in range(400):
        values = {s.name: _random_value(rng, s) for s in message.signals if not s.name.endswith("_CRC")}
        ref = _cantools_reference(message, values)
        assert packer.pack_mapping(values) == ref, values
        assert packer.pack_loop([values[n] for n in packer.names]) == ref


def test_packer_rejects_missing_signal(db):
    message = db.get_message_by_frame_id(ID_POS)
    packer = FramePacker(message)
    with pytest.raises(KeyError):
        packer.pack_mapping({"T00_PosX": 1.0})
