"""Message authentication for V2V: Ed25519 vehicle keys, the master's trust list, replay and time
windows, and clock-skew detection (the ``v2xpos keys`` command is ``v2xpos.commands.keys``).

Signing (RFC 8032 Ed25519, via the ``cryptography`` package): each vehicle holds one private key;
the slave signs the msgpack *body* of every message (``v2xpos.wire`` carries ``[ver, body, sig,
key_id]``). ``key_id`` is the key's fingerprint: the first 16 hex digits of SHA-256 over the raw
32-byte public key. The master's trust list binds each key id to exactly one vehicle id, so a
valid signature from vehicle A's key on a message claiming to be vehicle B is rejected.

Admission checks, in this order, each rejection counted by reason (``REJECT_*``):
1. signature present, key id trusted, key bound to the claimed vehicle, signature valid;
2. time window: ``t_slave <= now + future_tolerance_s`` (else *future*) and
   ``t_slave >= now - max_age_s`` (else *too_old*: a replay of a captured message);
3. sequence window: the sliding anti-replay window of IPsec ESP (RFC 4303 sec. 3.4.3) per vehicle:
   a sequence number already seen, or older than the window, is a *replay*. A restarted sender
   (sequence far below the window) is accepted only when its time is after the time of the highest
   sequence accepted so far -- a replayed old message cannot satisfy that.
State is updated only after a message passed the signature check, so forged traffic cannot move
the windows.

Files (documented in docs/security.md):
* ``<vehicle>.key``: PKCS#8 PEM Ed25519 private key, file mode 0600.
* ``<vehicle>.pub``: one line ``v2xpos-ed25519 <vehicle_id> <base64 raw public key>``.
* trust list (JSON): ``{"format": "v2xpos-trust", "version": 1, "keys": [{"vehicle_id": ...,
  "key_id": ..., "public_key": <base64 raw 32 bytes>, "added_utc": ...}, ...]}``.
"""
from __future__ import annotations

import base64
import binascii
import datetime as _dt
import hashlib
import json
import math
import os
import re
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from v2xpos.wire import WireError, unpack_envelope

TRUST_FORMAT = "v2xpos-trust"
TRUST_VERSION = 1
PUB_PREFIX = "v2xpos-ed25519"
KEY_ID_HEX_CHARS = 16
_VEHICLE_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")

REJECT_UNSIGNED = "unsigned"
REJECT_UNKNOWN_KEY = "unknown_key"
REJECT_KEY_VEHICLE_MISMATCH = "key_vehicle_mismatch"
REJECT_BAD_SIGNATURE = "bad_signature"
REJECT_FUTURE = "future"
REJECT_TOO_OLD = "too_old"
REJECT_REPLAY = "replay"
REJECT_REASONS = (REJECT_UNSIGNED, REJECT_UNKNOWN_KEY, REJECT_KEY_VEHICLE_MISMATCH,
                  REJECT_BAD_SIGNATURE, REJECT_FUTURE, REJECT_TOO_OLD, REJECT_REPLAY)


class TrustFileError(ValueError):
    """A key or trust-list file that cannot be used; the message names the file and the field."""


# ----------------------------------------------------------------------------- keys

def raw_public_bytes(public_key: Ed25519PublicKey) -> bytes:
    """The 32-byte raw encoding of an Ed25519 public key (RFC 8032 sec. 5.1.5)."""
    return public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def key_id_of(public_key: Ed25519PublicKey) -> str:
    """Fingerprint: first 16 hex digits of SHA-256(raw public key)."""
    return hashlib.sha256(raw_public_bytes(public_key)).hexdigest()[:KEY_ID_HEX_CHARS]


def check_vehicle_id(vehicle_id: str, where: str = "vehicle_id") -> str:
    """Return ``vehicle_id`` if it is 1-64 chars of [A-Za-z0-9_.-] (the wire identifier rule)."""
    if not isinstance(vehicle_id, str) or not _VEHICLE_RE.match(vehicle_id):
        raise TrustFileError(f"{where}: vehicle id must be 1-64 chars of [A-Za-z0-9_.-], got {vehicle_id!r}")
    return vehicle_id


@dataclass
class VehicleKeyFiles:
    """Paths written by :func:`generate_vehicle_key`."""
    vehicle_id: str
    key_id: str
    private_path: Path
    public_path: Path


def generate_vehicle_key(vehicle_id: str, out_dir: str | Path, overwrite: bool = False) -> VehicleKeyFiles:
    """Make a new Ed25519 key pair for ``vehicle_id``: ``out_dir/<id>.key`` (PEM, 0600) and ``.pub``."""
    check_vehicle_id(vehicle_id, "--vehicle")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    priv_path, pub_path = out / f"{vehicle_id}.key", out / f"{vehicle_id}.pub"
    if not overwrite and (priv_path.exists() or pub_path.exists()):
        raise FileExistsError(f"{priv_path} or {pub_path} exists (use --force to replace)")
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    fd = os.open(priv_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(pem)
    os.chmod(priv_path, 0o600)
    pub = key.public_key()
    pub_path.write_text(public_key_line(vehicle_id, pub))
    return VehicleKeyFiles(vehicle_id, key_id_of(pub), priv_path, pub_path)


def public_key_line(vehicle_id: str, public_key: Ed25519PublicKey) -> str:
    """``v2xpos-ed25519 <vehicle_id> <base64 raw key>`` + newline (the .pub file content)."""
    return f"{PUB_PREFIX} {vehicle_id} {base64.b64encode(raw_public_bytes(public_key)).decode()}\n"


def _decode_raw_public(b64: object, where: str) -> Ed25519PublicKey:
    if not isinstance(b64, str):
        raise TrustFileError(f"{where}: public key must be a base64 string")
    try:
        raw = base64.b64decode(b64, validate=True)
    except (binascii.Error, ValueError):
        raise TrustFileError(f"{where}: public key is not valid base64") from None
    if len(raw) != 32:
        raise TrustFileError(f"{where}: public key must be 32 bytes, got {len(raw)}")
    return Ed25519PublicKey.from_public_bytes(raw)


def load_public_key_file(path: str | Path) -> tuple[str, Ed25519PublicKey]:
    """Read a ``.pub`` file -> (vehicle_id, public key); TrustFileError naming file and field."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise TrustFileError(f"{path}: cannot read public key file ({exc})") from None
    parts = text.split()
    if len(parts) != 3 or parts[0] != PUB_PREFIX:
        raise TrustFileError(f"{path}: line 1: expected '{PUB_PREFIX} <vehicle_id> <base64 key>'")
    vehicle_id = check_vehicle_id(parts[1], f"{path}: line 1: vehicle_id")
    return vehicle_id, _decode_raw_public(parts[2], f"{path}: line 1: public_key")


def load_private_key_file(path: str | Path) -> Ed25519PrivateKey:
    """Read a PEM PKCS#8 Ed25519 private key; TrustFileError if it is not one."""
    path = Path(path)
    try:
        data = path.read_bytes()
        key = serialization.load_pem_private_key(data, password=None)
    except (OSError, ValueError, TypeError) as exc:
        raise TrustFileError(f"{path}: not a readable unencrypted PEM private key ({exc})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise TrustFileError(f"{path}: key type {type(key).__name__} is not Ed25519")
    return key


class MessageSigner:
    """Signs message bodies with one vehicle's key: ``signer(body) -> (signature, key_id)``.

    This is the ``sign`` callable that ``v2xpos.wire.encode_state`` takes.
    """

    def __init__(self, private_key: Ed25519PrivateKey):
        self._key = private_key
        self.key_id = key_id_of(private_key.public_key())

    @classmethod
    def from_file(cls, path: str | Path) -> "MessageSigner":
        return cls(load_private_key_file(path))

    @property
    def public_key(self) -> Ed25519PublicKey:
        return self._key.public_key()

    def __call__(self, body: bytes) -> tuple[bytes, str]:
        return self._key.sign(body), self.key_id


# ----------------------------------------------------------------------------- trust list

@dataclass
class TrustEntry:
    """One trusted key, bound to one vehicle id."""
    vehicle_id: str
    key_id: str
    public_key: Ed25519PublicKey
    added_utc: str = ""

    def verifies(self, sig: bytes, body: bytes) -> bool:
        """True if ``sig`` is this key's Ed25519 signature of ``body`` (RFC 8032)."""
        try:
            self.public_key.verify(sig, body)
        except InvalidSignature:
            return False
        return True

    def as_dict(self) -> dict:
        return {"vehicle_id": self.vehicle_id, "key_id": self.key_id,
                "public_key": base64.b64encode(raw_public_bytes(self.public_key)).decode(),
                "added_utc": self.added_utc}


@dataclass
class TrustList:
    """Key id -> TrustEntry. ``issues``: entries of the file that were rejected (file: field: what)."""
    entries: dict[str, TrustEntry] = field(default_factory=dict)
    issues: list[str] = field(default_factory=list)
    source: Path | None = None

    def add(self, vehicle_id: str, public_key: Ed25519PublicKey) -> TrustEntry:
        entry = TrustEntry(check_vehicle_id(vehicle_id), key_id_of(public_key), public_key,
                           _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"))
        self.entries[entry.key_id] = entry
        return entry

    def remove(self, vehicle_id: str | None = None, key_id: str | None = None) -> int:
        """Remove entries matching the vehicle id or the key id; returns how many."""
        gone = [k for k, e in self.entries.items()
                if (vehicle_id is not None and e.vehicle_id == vehicle_id) or k == key_id]
        for k in gone:
            del self.entries[k]
        return len(gone)

    def get(self, key_id: str | None) -> TrustEntry | None:
        return self.entries.get(key_id) if key_id is not None else None

    def __len__(self) -> int:
        return len(self.entries)

    def to_json(self) -> str:
        doc = {"format": TRUST_FORMAT, "version": TRUST_VERSION,
               "keys": [e.as_dict() for e in sorted(self.entries.values(),
                                                     key=lambda e: (e.vehicle_id, e.key_id))]}
        return json.dumps(doc, indent=2) + "\n"

    def save(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(self.to_json())
        os.replace(tmp, path)


def load_trust_list(path: str | Path, missing_ok: bool = False) -> TrustList:
    """Read a trust-list JSON file.

    A file that is not a trust list raises TrustFileError; a bad entry is skipped and described in
    ``TrustList.issues`` as ``"<file>: keys[i].<field>: <what>"`` (the other entries are kept).
    """
    path = Path(path)
    if missing_ok and not path.exists():
        return TrustList(source=path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise TrustFileError(f"{path}: cannot read trust list ({exc})") from None
    except UnicodeDecodeError as exc:
        raise TrustFileError(f"{path}: not UTF-8 text ({exc})") from None
    return parse_trust_list(text, path)


def parse_trust_list(text: str, path: str | Path = "<trust list>") -> TrustList:
    """Trust list from its JSON text; ``path`` only names the source in messages."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TrustFileError(f"{path}: not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise TrustFileError(f"{path}: top level must be an object")
    if doc.get("format") != TRUST_FORMAT:
        raise TrustFileError(f"{path}: field 'format' must be {TRUST_FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != TRUST_VERSION:
        raise TrustFileError(f"{path}: field 'version' must be {TRUST_VERSION}, got {doc.get('version')!r}")
    keys = doc.get("keys")
    if not isinstance(keys, list):
        raise TrustFileError(f"{path}: field 'keys' must be a list")
    trust = TrustList(source=Path(path))
    for i, item in enumerate(keys):
        where = f"{path}: keys[{i}]"
        try:
            if not isinstance(item, dict):
                raise TrustFileError(f"{where}: entry must be an object")
            vehicle_id = check_vehicle_id(item.get("vehicle_id"), f"{where}.vehicle_id")
            public_key = _decode_raw_public(item.get("public_key"), f"{where}.public_key")
            kid = key_id_of(public_key)
            if item.get("key_id") not in (None, kid):
                raise TrustFileError(f"{where}.key_id: {item.get('key_id')!r} does not match the "
                                     f"public key (fingerprint {kid})")
            if kid in trust.entries and trust.entries[kid].vehicle_id != vehicle_id:
                raise TrustFileError(f"{where}.vehicle_id: key {kid} already bound to "
                                     f"{trust.entries[kid].vehicle_id!r}")
            trust.entries[kid] = TrustEntry(vehicle_id, kid, public_key, str(item.get("added_utc", "")))
        except TrustFileError as exc:
            trust.issues.append(str(exc))
    return trust


# ----------------------------------------------------------------------------- admission

class _SeqWindow:
    """Anti-replay sliding window (RFC 4303 sec. 3.4.3): highest seq + bitmap of the last N."""
    __slots__ = ("size", "highest", "bitmap", "t_highest_s")

    def __init__(self, size: int):
        self.size = size
        self.highest = -1
        self.bitmap = 0
        self.t_highest_s = -math.inf

    def check(self, seq: int, t_s: float) -> bool:
        """True if ``seq`` is new (not yet seen, not below the window or a sender restart)."""
        if seq > self.highest:
            return True
        offset = self.highest - seq
        if offset < self.size:
            return not (self.bitmap >> offset) & 1
        return t_s > self.t_highest_s

    def mark(self, seq: int, t_s: float) -> None:
        if seq > self.highest:
            shift = seq - self.highest
            self.bitmap = ((self.bitmap << shift) | 1) & ((1 << self.size) - 1) if shift < self.size else 1
            self.highest, self.t_highest_s = seq, t_s
            return
        offset = self.highest - seq
        if offset < self.size:
            self.bitmap |= 1 << offset
        else:  # restart of the sender: start a new window at this sequence
            self.highest, self.bitmap, self.t_highest_s = seq, 1, t_s


@dataclass
class AdmissionStats:
    """Counts of accepted messages and of rejections by reason (keys: REJECT_*)."""
    accepted: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: {r: 0 for r in REJECT_REASONS})

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def as_dict(self) -> dict:
        return {"accepted": self.accepted, "rejected": dict(self.rejected)}


class MessageAuthenticator:
    """Admission control for received StateMessages (see the module docstring for the rules).

    ``check(msg, now_gps_s)`` returns None when the message is accepted, else the rejection reason
    (one of REJECT_REASONS). ``msg`` needs ``vehicle_id``, ``seq``, ``t_gps_s``, ``sig``,
    ``key_id`` and ``signed_payload`` (as ``v2xpos.wire.decode_state`` fills them).
    ``require_signature=False`` admits unsigned messages (still time and replay checked); signed
    ones are always verified. Every authentic message also feeds ``clock`` (a ClockSkewMonitor,
    with ``now_gps_s`` as the arrival time), before the time checks, so a sender whose clock
    jumped ahead is both rejected as *future* and reported as skewed: ``skew_report()``.
    """

    def __init__(self, trust: TrustList, *, require_signature: bool = True, max_age_s: float = 5.0,
                 future_tolerance_s: float = 0.05, replay_window: int = 1024,
                 clock: "ClockSkewMonitor | None" = None):
        self.trust = trust
        self.clock = clock if clock is not None else ClockSkewMonitor()
        self.require_signature = require_signature
        self.max_age_s = float(max_age_s)
        self.future_tolerance_s = float(future_tolerance_s)
        self.replay_window = int(replay_window)
        self.stats = AdmissionStats()
        self._windows: dict[str, _SeqWindow] = {}

    def reset_replay_windows(self) -> None:
        """Forget every vehicle's sequence window (as after a master restart): the next message of
        each vehicle starts a new window. The trust list, the clock monitor and ``stats`` are kept."""
        self._windows.clear()

    def skew_report(self) -> list[dict]:
        """Clock status of every authentic sender seen (ClockSkewStatus.as_dict())."""
        return [st.as_dict() for st in self.clock.all_status()]

    def _reject(self, reason: str) -> str:
        self.stats.rejected[reason] += 1
        return reason

    def verify_envelope(self, payload: bytes) -> bool | None:
        """Ed25519 check of a received envelope's body against the trust list's key ``key_id``,
        without decoding the body or changing any state (the trust list is only read; the master
        runs it in ``v2xpos.verify_worker``). True / False: the signature is / is not valid for
        that key; None: not decided here (malformed envelope, unsigned, unknown key), ``check``
        decides."""
        try:
            env = unpack_envelope(payload)
        except WireError:
            return None
        entry = self.trust.get(env.key_id) if env.sig is not None else None
        return None if entry is None else entry.verifies(env.sig, env.body)

    def verify_signature(self, msg, signature_valid: bool | None = None) -> str | None:
        """Signature checks only (no state change): None if valid, else the reason.
        ``signature_valid``: the result of ``verify_envelope`` on the payload ``msg`` was decoded
        from, when already known (the Ed25519 verification is then not repeated)."""
        if msg.sig is None or msg.signed_payload is None:
            return None if not self.require_signature else REJECT_UNSIGNED
        entry = self.trust.get(msg.key_id)
        if entry is None:
            return REJECT_UNKNOWN_KEY
        if entry.vehicle_id != msg.vehicle_id:
            return REJECT_KEY_VEHICLE_MISMATCH
        if signature_valid is None:
            signature_valid = entry.verifies(msg.sig, msg.signed_payload)
        return None if signature_valid else REJECT_BAD_SIGNATURE

    def check(self, msg, now_gps_s: float, t_arrival_gps_s: float | None = None,
              signature_valid: bool | None = None) -> str | None:
        """Admit (None) or reject (reason) ``msg`` at receiver GPS time ``now_gps_s``.

        ``t_arrival_gps_s``: when the message arrived (receiver GPS time) if it waited in a queue
        before this call; the clock-skew monitor uses it so that the receiver's own queueing is
        not mistaken for sender clock skew (default: ``now_gps_s``). ``signature_valid``: see
        ``verify_signature``.
        """
        reason = self.verify_signature(msg, signature_valid)
        if reason is not None:
            return self._reject(reason)
        t = float(msg.t_gps_s)
        self.clock.update(msg.vehicle_id, int(msg.seq), t,
                          now_gps_s if t_arrival_gps_s is None else float(t_arrival_gps_s), snapshot=False)
        if t > now_gps_s + self.future_tolerance_s:
            return self._reject(REJECT_FUTURE)
        if t < now_gps_s - self.max_age_s:
            return self._reject(REJECT_TOO_OLD)
        window = self._windows.get(msg.vehicle_id)
        if window is None:
            window = self._windows[msg.vehicle_id] = _SeqWindow(self.replay_window)
        if not window.check(int(msg.seq), t):
            return self._reject(REJECT_REPLAY)
        window.mark(int(msg.seq), t)
        self.stats.accepted += 1
        return None


# ----------------------------------------------------------------------------- clock skew

@dataclass
class ClockSkewStatus:
    """Clock health of one sender as seen by the receiver.

    offset_change_s: change of the lower envelope of (arrival time - sender time) since the
    baseline; negative = the sender's clock moved ahead. drift_ppm: slope of that envelope
    [1e-6 s/s], positive = the sender's clock runs fast. jumps: step changes of the sender's
    time detected message-to-message. skewed: True while a jump or an offset/drift beyond the
    thresholds is present; ``reason`` says which.
    """
    vehicle_id: str
    offset_change_s: float = 0.0
    drift_ppm: float = 0.0
    jumps: int = 0
    last_jump_s: float = 0.0
    skewed: bool = False
    reason: str = ""

    def as_dict(self) -> dict:
        return {"vehicle_id": self.vehicle_id, "offset_change_s": self.offset_change_s,
                "drift_ppm": self.drift_ppm, "jumps": self.jumps, "last_jump_s": self.last_jump_s,
                "skewed": self.skewed, "reason": self.reason}


class _SkewTrack:
    __slots__ = ("period_samples", "period_s", "last", "block_start", "block_min", "blocks",
                 "baseline", "status", "jump_until")

    def __init__(self, vehicle_id: str):
        self.period_samples: deque = deque(maxlen=64)
        self.period_s = math.nan
        self.last: tuple[int, float, float] | None = None
        self.block_start = math.nan
        self.block_min = math.inf
        self.blocks: deque = deque(maxlen=30)
        self.baseline = math.nan
        self.status = ClockSkewStatus(vehicle_id)
        self.jump_until = -math.inf


class ClockSkewMonitor:
    """Detects a sender's clock jumping or drifting, apart from network delay.

    For each message the receiver knows the sender's time of validity ``t_tx`` (sender clock), the
    arrival time ``t_rx`` (receiver clock) and the sequence number. Two tests:

    * jump: between consecutive messages, the sender-time step ``d_tx`` disagrees both with the
      sequence step times the sender's nominal period (median of recent ``d_tx / d_seq``) and
      with the arrival step ``d_rx`` by more than ``jump_threshold_s``. A network delay spike
      changes ``d_rx`` only, a pause of the sender changes ``d_tx`` and ``d_rx`` together; only a
      clock step changes ``d_tx`` alone.
    * offset / drift: the minimum of ``t_rx - t_tx`` over blocks of ``block_s`` (the NTP
      minimum-delay filter, Mills, RFC 5905 sec. 10) removes queueing delay; its change from the
      first blocks (baseline) is the sender's clock offset change, and a line fitted through the
      block minima (once they span ``drift_min_span_s``) gives the drift rate. Flagged when ``|offset change| > offset_threshold_s``
      or ``|drift| > drift_threshold_ppm``.
    A sustained rise of the network's minimum delay itself is indistinguishable from the sender
    clock falling behind and is reported as negative skew.
    """

    def __init__(self, jump_threshold_s: float = 0.02, offset_threshold_s: float = 0.02,
                 drift_threshold_ppm: float = 1000.0, block_s: float = 0.5, baseline_blocks: int = 3,
                 jump_hold_s: float = 2.0, drift_min_span_s: float = 4.0):
        self.jump_threshold_s = jump_threshold_s
        self.offset_threshold_s = offset_threshold_s
        self.drift_threshold_ppm = drift_threshold_ppm
        self.block_s = block_s
        self.baseline_blocks = baseline_blocks
        self.jump_hold_s = jump_hold_s
        self.drift_min_span_s = drift_min_span_s
        self._tracks: dict[str, _SkewTrack] = {}

    def status(self, vehicle_id: str) -> ClockSkewStatus:
        """Snapshot of one sender's clock status."""
        track = self._tracks.get(vehicle_id)
        return replace(track.status) if track is not None else ClockSkewStatus(vehicle_id)

    def all_status(self) -> list[ClockSkewStatus]:
        return [replace(t.status) for t in self._tracks.values()]

    def update(self, vehicle_id: str, seq: int, t_tx_s: float, t_rx_s: float,
               snapshot: bool = True) -> ClockSkewStatus | None:
        """Feed one received message; returns a snapshot of the sender's current status
        (None with ``snapshot=False``: the per-message admission path does not need the copy)."""
        tr = self._tracks.get(vehicle_id)
        if tr is None:
            tr = self._tracks[vehicle_id] = _SkewTrack(vehicle_id)
        st = tr.status
        if tr.last is not None:
            seq0, tx0, rx0 = tr.last
            d_seq = seq - seq0
            if d_seq > 0:
                d_tx, d_rx = t_tx_s - tx0, t_rx_s - rx0
                expected = d_seq * tr.period_s if len(tr.period_samples) >= 8 else math.nan
                off_seq = abs(d_tx - expected) if math.isfinite(expected) else 0.0
                if off_seq > self.jump_threshold_s and abs(d_tx - d_rx) > self.jump_threshold_s:
                    st.jumps += 1
                    st.last_jump_s = d_tx - expected
                    tr.jump_until = t_rx_s + self.jump_hold_s
                elif d_seq <= 4:
                    tr.period_samples.append(d_tx / d_seq)
                    s = sorted(tr.period_samples)
                    tr.period_s = s[len(s) // 2]
        if tr.last is None or seq > tr.last[0]:
            tr.last = (seq, t_tx_s, t_rx_s)
        self._block(tr, t_tx_s, t_rx_s)
        jumping = t_rx_s < tr.jump_until
        reasons = []
        if jumping:
            reasons.append(f"clock jump {st.last_jump_s * 1e3:+.1f} ms")
        if abs(st.offset_change_s) > self.offset_threshold_s:
            reasons.append(f"offset {-st.offset_change_s * 1e3:+.1f} ms")
        if abs(st.drift_ppm) > self.drift_threshold_ppm:
            reasons.append(f"drift {st.drift_ppm:+.0f} ppm")
        st.skewed = bool(reasons)
        st.reason = "; ".join(reasons)
        return replace(st) if snapshot else None

    def _block(self, tr: _SkewTrack, t_tx_s: float, t_rx_s: float) -> None:
        delay = t_rx_s - t_tx_s
        if not math.isfinite(tr.block_start):
            tr.block_start = t_rx_s
        if t_rx_s - tr.block_start < self.block_s:
            tr.block_min = min(tr.block_min, delay)
            return
        if math.isfinite(tr.block_min):
            tr.blocks.append((tr.block_start, tr.block_min))
        tr.block_start, tr.block_min = t_rx_s, delay
        st = tr.status
        if len(tr.blocks) == self.baseline_blocks and not math.isfinite(tr.baseline):
            tr.baseline = sorted(b for _, b in tr.blocks)[len(tr.blocks) // 2]
        if math.isfinite(tr.baseline):
            st.offset_change_s = tr.blocks[-1][1] - tr.baseline
        if len(tr.blocks) >= 4 and tr.blocks[-1][0] - tr.blocks[0][0] >= self.drift_min_span_s:
            n = len(tr.blocks)
            t0 = tr.blocks[0][0]
            xs = [b[0] - t0 for b in tr.blocks]
            ys = [b[1] for b in tr.blocks]
            mx, my = sum(xs) / n, sum(ys) / n
            sxx = sum((x - mx) ** 2 for x in xs)
            if sxx > 0:
                slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx
                st.drift_ppm = -slope * 1e6
