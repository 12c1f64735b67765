"""The outer frame of every datagram and the signing hook.

Every datagram is a msgpack array ``[ENVELOPE_VERSION, body, sig, key_id]``: ``body`` is the
msgpack-encoded message map as a *bin* value -- exactly the byte string that is signed (Ed25519
over ``body``); ``sig`` is bin or nil, ``key_id`` str or nil. ``sign`` arguments are callables
``body -> (sig_bytes, key_id)`` (``Signer``). A malformed frame raises ``WireError``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import msgpack

from .fields import MAX_ID_CHARS, WireError

ENVELOPE_VERSION = 1
MAX_MESSAGE_BYTES = 8192
Signer = Callable[[bytes], tuple[bytes, str]]
"""Signs a message body: ``body -> (signature, key id)``."""


@dataclass
class Envelope:
    """Outer frame: ``body`` (the signed bytes), optional ``sig`` and ``key_id``."""
    body: bytes
    sig: bytes | None = None
    key_id: str | None = None


def pack_envelope(body: bytes, sig: bytes | None = None, key_id: str | None = None) -> bytes:
    """``[ENVELOPE_VERSION, body, sig, key_id]`` as msgpack."""
    return msgpack.packb([ENVELOPE_VERSION, body, sig, key_id], use_bin_type=True)


def seal(body: bytes, sign: Signer | None) -> bytes:
    if sign is None:
        return pack_envelope(body)
    sig, key_id = sign(body)
    return pack_envelope(body, sig, key_id)


def unpack_envelope(data: bytes) -> Envelope:
    """Envelope bytes -> Envelope; WireError if malformed or oversize."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError("not bytes", None)
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"oversize ({len(data)} > {MAX_MESSAGE_BYTES} bytes)", None)
    try:
        env = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES,
                              max_str_len=MAX_MESSAGE_BYTES, max_array_len=1024, max_map_len=256)
    except Exception as exc:  # msgpack raises many types; all mean "not a valid frame"
        raise WireError(f"not msgpack ({type(exc).__name__})", "envelope") from None
    if type(env) is not list or len(env) != 4:
        raise WireError("envelope is not a 4-element array", "envelope")
    ver, body, sig, key_id = env
    if type(ver) is not int:
        raise WireError("envelope version not an integer", "envelope.version")
    if ver != ENVELOPE_VERSION:
        raise WireError(f"unknown envelope version {ver}", "envelope.version")
    if type(body) is not bytes:
        raise WireError("body is not bin", "envelope.body")
    if sig is not None and type(sig) is not bytes:
        raise WireError("signature is not bin", "envelope.sig")
    if key_id is not None and (type(key_id) is not str or not key_id or len(key_id) > MAX_ID_CHARS):
        raise WireError("key id is not a short string", "envelope.key_id")
    return Envelope(body, sig, key_id)
