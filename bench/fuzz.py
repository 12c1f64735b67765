"""``v2xpos bench fuzz``: mutation fuzzing of the message decoder, the master pipeline, the dataset
readers and the file loaders. Every input must be decoded or rejected with a reason; anything
else (another exception type) is a crash and is saved for reproduction.

Mutator (coverage-free, in the spirit of AFL's deterministic + havoc stages, Zalewski 2014):
inputs start from valid encodings ("seeds") and get 1-4 operations drawn at random --

* bytes: flip a bit, set an "interesting" byte (msgpack type markers 0xc0-0xdf, 0x00/0x7f/0x80/
  0xff), overwrite 2/4/8 bytes with a boundary integer or a NaN/inf float64, insert random bytes,
  delete / duplicate a range, truncate, splice with another seed;
* structure (msgpack messages): replace one field of the body map with an interesting value
  (nil, bools, +-2^63, 2^64-1, +-1e308, NaN, +-inf, empty / 70-char / non-ASCII strings, bin,
  arrays of wrong length, maps, ext types, deep nesting), delete or add a field, or break the
  envelope (version, body/sig/key_id types, length);
* text (line formats, TOML, JSON): delete / duplicate / swap lines, replace a token with
  "nan", "1e999", "-", "", a huge integer, a separator.

Targets and what counts as "rejected with a reason":

* ``wire.state`` / ``wire.relative``: ``decode_state`` / ``decode_relative`` raise only
  ``WireError`` (its ``reason`` is tallied);
* ``master.pipeline``: ``MasterPipeline.handle`` with an authenticator never raises; the
  rejection reason is read from its counters;
* readers (``rtklib_pos``, ``timetag``, ``imu_csv``, ``ubx``) and loaders (``geojson`` scene,
  ``master_config`` TOML, ``trust_list`` JSON, ``dataset_toml`` descriptors over small data
  files): return normally (malformed records skipped and
  counted) or raise ``ValueError`` (incl. its subclasses SceneError, ConfigError, ...) or
  ``OSError`` with a message.
Seeds for the readers are the first records of the shared recordings (read, never copied into
the repository) or small synthetic files when the data are missing.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import random
import re
import shutil
import struct
import sys
import tempfile
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import msgpack
import numpy as np
from tqdm import tqdm

from v2xpos.types import FixStatus, NavState
from v2xpos.wire import (FixSide, Geometry, RelativeResult, StateMessage, TargetStatus, WireError,
                         decode_relative, decode_state, encode_relative, encode_state, state_key)

DATA_DIR = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"

_INTERESTING_BYTES = bytes([0x00, 0x01, 0x7f, 0x80, 0xff, 0xc0, 0xc1, 0xc2, 0xc3, 0xc4, 0xc7, 0xca,
                            0xcb, 0xcc, 0xcf, 0xd0, 0xd3, 0xd4, 0xd8, 0xd9, 0xdb, 0xdc, 0xdd, 0xde,
                            0xdf, 0x90, 0x9f, 0x8f, 0xa0, 0xbf, 0xe0])
_BOUNDARY = [struct.pack(">d", math.nan), struct.pack(">d", math.inf), struct.pack(">d", -math.inf),
             struct.pack(">d", 1e308), struct.pack(">Q", 2 ** 64 - 1), struct.pack(">q", -2 ** 63),
             struct.pack(">I", 2 ** 32 - 1), struct.pack(">i", -1), struct.pack(">H", 0xffff),
             struct.pack("<I", 2 ** 31), struct.pack("<I", 0), b"\x00\x00"]


def _nested(depth: int) -> list:
    out: list = [1]
    for _ in range(depth):
        out = [out]
    return out


_DEEP = _nested(40)
_INTERESTING_VALUES = [None, True, False, 0, -1, 2 ** 63 - 1, -2 ** 63, 2 ** 64 - 1, 1e308, -1e308,
                       math.nan, math.inf, -math.inf, 5e-324, "", "x" * 70, "ü\u202e", "a/b",
                       b"", b"\x00" * 9, [], [1.0, 2.0], [math.nan, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0],
                       ["1", "2", "3"], {}, {"k": 1}, {1: 2}, msgpack.ExtType(5, b"ab"), _DEEP,
                       list(range(200))]
_TEXT_TOKENS = ["nan", "inf", "-inf", "1e999", "-", "", "99999999999999999999", "/", ":", "0x1f",
                "\x00", "é", "=", "[", "]", "{", "}", '"', ",", "-0", "1e-400", "true"]


def mutate_bytes(rng: random.Random, data: bytes, seeds: list[bytes]) -> bytes:
    """1-4 byte-level operations (see the module docstring)."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(9)
        n = len(b)
        if n == 0:
            b += bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
            continue
        i = rng.randrange(n)
        if op == 0:
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1:
            b[i] = rng.choice(_INTERESTING_BYTES)
        elif op == 2:
            v = rng.choice(_BOUNDARY)
            b[i:i + len(v)] = v
        elif op == 3:
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        elif op == 4:
            del b[i:i + rng.randint(1, 32)]
        elif op == 5:
            j = min(n, i + rng.randint(1, 64))
            b[j:j] = b[i:j]
        elif op == 6:
            del b[rng.randrange(n):]
        elif op == 7:
            other = rng.choice(seeds)
            k = rng.randrange(len(other) + 1)
            b = b[:i] + bytearray(other[k:])
        else:
            b[i] = rng.randrange(256)
    return bytes(b)


def _mutate_value(rng: random.Random, obj):
    if isinstance(obj, dict) and obj:
        d = dict(obj)
        key = rng.choice(list(d))
        op = rng.randrange(5)
        if op == 0:
            del d[key]
        elif op == 1:
            d[rng.choice(["zz", "", "T", "ver", 7])] = rng.choice(_INTERESTING_VALUES)
        elif op == 2 and isinstance(d[key], (dict, list)):
            d[key] = _mutate_value(rng, d[key])
        else:
            d[key] = rng.choice(_INTERESTING_VALUES)
        return d
    if isinstance(obj, list) and obj:
        out = list(obj)
        i = rng.randrange(len(out))
        op = rng.randrange(3)
        if op == 0:
            del out[i]
        elif op == 1:
            out.append(rng.choice(_INTERESTING_VALUES))
        else:
            out[i] = rng.choice(_INTERESTING_VALUES)
        return out
    return rng.choice(_INTERESTING_VALUES)


def mutate_message(rng: random.Random, data: bytes, seeds: list[bytes]) -> bytes:
    """A structural mutation of a wire envelope (body field / envelope), else a byte mutation."""
    op = rng.randrange(10)
    if op >= 6:
        return mutate_bytes(rng, data, seeds)
    env = msgpack.unpackb(data, raw=False)
    if op >= 4:
        env = _mutate_value(rng, env)
        return msgpack.packb(env, use_bin_type=True)
    body = msgpack.unpackb(env[1], raw=False, strict_map_key=False)
    for _ in range(rng.randint(1, 2)):
        body = _mutate_value(rng, body)
    try:
        env[1] = msgpack.packb(body, use_bin_type=True)
    except (TypeError, ValueError, OverflowError):
        return mutate_bytes(rng, data, seeds)
    return msgpack.packb(env, use_bin_type=True)


def mutate_text(rng: random.Random, data: bytes, seeds: list[bytes]) -> bytes:
    """Line / token operations on a text file, else a byte mutation."""
    if rng.random() < 0.35:
        return mutate_bytes(rng, data, seeds)
    lines = data.decode("utf-8", errors="replace").split("\n")
    for _ in range(rng.randint(1, 3)):
        if not lines:
            break
        i = rng.randrange(len(lines))
        op = rng.randrange(5)
        if op == 0:
            del lines[i]
        elif op == 1:
            lines.insert(i, lines[i])
        elif op == 2:
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        else:
            tokens = re.split(r"(\s+|,|=|:)", lines[i])
            if tokens:
                k = rng.randrange(len(tokens))
                tokens[k] = rng.choice(_TEXT_TOKENS)
            lines[i] = "".join(tokens)
    return "\n".join(lines).encode("utf-8", errors="replace")


# ----------------------------------------------------------------------------- seeds

T_SEED = 1.4e9


def seed_state_messages(n: int = 6) -> list[StateMessage]:
    """Valid StateMessages of both kinds and all geometry types."""
    rng = np.random.default_rng(7)
    out = []
    for k in range(n):
        geom = [Geometry.box(3.8, 1.0, 0.9), Geometry(kind="circle", radius_m=0.4),
                Geometry(kind="points", points_body_m=rng.normal(size=(4, 3)))][k % 3]
        out.append(StateMessage(
            fleet="demo", vehicle_id=f"car{k}", seq=k * 100 + 1, t_gps_s=T_SEED + k, fix=FixStatus(k % 6),
            lat_rad=0.7, lon_rad=-1.8, height_m=1600.0, v_ned_mps=rng.normal(size=3) * 10,
            acc_body_mps2=rng.normal(size=3), rate_body_rps=rng.normal(size=3) * 0.1,
            rpy_rad=np.array([0.01, -0.02, 1.5]), pos_sd_m=np.full(3, 0.01), vel_sd_mps=np.full(3, 0.02),
            att_sd_rad=np.full(3, 1e-3), geometry=geom, kind="pedestrian" if k == 4 else "vehicle",
            t_sent_wall_s=1.7e9 if k % 2 else None, imu_quality={"grade": "B"} if k == 3 else None))
    return out


def seed_state_payloads():
    """(payloads, trust list): the odd ones signed by car1's key, which the trust list holds."""
    from v2xpos.security import Ed25519PrivateKey, MessageSigner, TrustList
    signer = MessageSigner(Ed25519PrivateKey.generate())
    trust = TrustList()
    trust.add("car1", signer.public_key)
    msgs = seed_state_messages()
    return [encode_state(m, sign=signer if i % 2 else None) for i, m in enumerate(msgs)], trust


def seed_relative_payloads() -> list[bytes]:
    valid = RelativeResult(target_id="car1", status=TargetStatus.VALID, fleet="demo", master_id="ego",
                           seq=3, source_seq=9, t_gps_s=T_SEED, latency_s=0.01,
                           rel_pos_body_m=np.array([10.0, 1.0, 0.0]), rel_pos_sd_m=np.full(3, 0.02),
                           rel_vel_body_mps=np.zeros(3), rel_acc_body_mps2=np.zeros(3),
                           rel_rpy_rad=np.zeros(3), range_m=10.05, range_sd_m=0.02, bearing_rad=0.1,
                           elevation_rad=0.0, longitudinal_m=6.0, lateral_m=1.0, gap_m=6.1,
                           closing_speed_mps=1.0, ttc_s=6.1)
    timeout = RelativeResult(target_id="p1", target_kind="pedestrian", status=TargetStatus.FIX_INVALID,
                             fix_side=FixSide.SLAVE, fleet="demo", master_id="ego", seq=4, t_gps_s=T_SEED)
    return [encode_relative(valid), encode_relative(timeout)]


def _head_lines(path: Path, n: int, header_prefix: str | None = None) -> bytes | None:
    if not path.exists():
        return None
    out, body = [], 0
    with open(path, "rb") as fh:
        for line in fh:
            out.append(line)
            if header_prefix is None or not line.startswith(header_prefix.encode()):
                body += 1
            if body >= n:
                break
    return b"".join(out)


def _synthetic_pos() -> bytes:
    lines = ["% program   : synthetic", "%  GPST          latitude(deg) longitude(deg)  height(m)   Q  ns   "
             "sdn(m)   sde(m)   sdu(m)  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio"]
    for k in range(20):
        lines.append(f"2025/07/08 19:34:{10 + k * 0.25:06.3f}   39.123456780 -105.123456780  1650.1234   1   "
                     f"12   0.0100   0.0100   0.0200   0.0000   0.0000   0.0000   0.00    9.9")
    return ("\n".join(lines) + "\n").encode()


def _synthetic_timetag() -> bytes:
    head = b"TIMETAG RTKLIB demo5".ljust(60, b"\0") + struct.pack("<IId", 1000, 1_751_000_000, 0.25)
    return head + b"".join(struct.pack("<II", 16 * k, 40 * k) for k in range(40))


def _synthetic_imu_csv() -> bytes:
    return b"".join(f"-0.012,0.034,-1.001,0.120,-0.340,0.560,{1000 + 10 * k}\r\n".encode() for k in range(40))


def _synthetic_ubx() -> bytes:
    def frame(cls, mid, payload):
        body = bytes([cls, mid]) + struct.pack("<H", len(payload)) + payload
        a = b = 0
        for x in body:
            a = (a + x) & 0xff
            b = (b + a) & 0xff
        return b"\xb5\x62" + body + bytes([a, b])
    return frame(0x01, 0x07, bytes(92)) * 3 + frame(0x0a, 0x04, bytes(40))


GEOJSON_SEED = json.dumps({"type": "FeatureCollection", "features": [
    {"type": "Feature", "properties": {"id": "lane1", "kind": "lane"},
     "geometry": {"type": "LineString", "coordinates": [[-105.1, 39.1], [-105.0999, 39.1001, 1650.0]]}},
    {"type": "Feature", "properties": {"id": "cone"}, "geometry": {"type": "Point", "coordinates": [-105.1, 39.1]}},
    {"type": "Feature", "properties": {"name": "box"}, "geometry": {"type": "Polygon", "coordinates": [
        [[-105.1, 39.1], [-105.1, 39.1001], [-105.0999, 39.1001], [-105.1, 39.1]]]}}]}, indent=1).encode()

MASTER_TOML_SEED = b"""[service]
fleet = "demo"
master_id = "ego"
timeout_ms = 200
measurement_point_m = [3.8, 0, 0]
known_vehicles = ["car1", "car2"]
duration_s = 40

[link]
mode = "router"
listen = ["tcp/127.0.0.1:17650"]

[output.udp]
enabled = true
host = "127.0.0.1"
port = 47001

[security]
trust_list = "keys/trust.json"
"""


def _dataset_toml_seed(workdir: Path, imu_csv: bytes, pos: bytes) -> bytes:
    """A dataset.toml over small IMU / GNSS files written into ``workdir``."""
    (workdir / "seed_imu.csv").write_bytes(imu_csv)
    (workdir / "seed_gnss.pos").write_bytes(pos)
    return b"""name = "fuzz"
platform = "car"

[imu]
file = "seed_imu.csv"
format = "csv_g_dps_ms"
imu_to_body = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]

[gnss]
file = "seed_gnss.pos"
format = "rtklib_pos"
lever_arm_m = [0.0, 0.0, 0.0]
lever_arm_sd_m = 0.1
"""


def _trust_seed() -> bytes:
    from v2xpos.security import Ed25519PrivateKey, TrustList
    t = TrustList()
    for vid in ("car1", "car2"):
        t.add(vid, Ed25519PrivateKey.generate().public_key())
    return t.to_json().encode()


# ----------------------------------------------------------------------------- targets

@dataclass
class TargetStats:
    """Outcome counts of one fuzz target."""
    name: str
    inputs: int = 0
    decoded: int = 0
    rejected: int = 0
    crashes: int = 0
    seconds: float = 0.0
    reasons: Counter = field(default_factory=Counter)
    crash_examples: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"inputs": self.inputs, "decoded": self.decoded, "rejected": self.rejected,
                "crashes": self.crashes, "seconds": round(self.seconds, 3),
                "inputs_per_s": round(self.inputs / self.seconds, 1) if self.seconds > 0 else None,
                "top_reasons": dict(self.reasons.most_common(12)), "crash_examples": self.crash_examples[:5]}


_NUM_RE = re.compile(r"[-+]?\d[\d.e+-]*|'[^']*'|\"[^\"]*\"|/[^\s:]+")


def _reason_class(text: str) -> str:
    """A reason with numbers, quoted values and paths removed (for tallying)."""
    return _NUM_RE.sub("#", text.split("\n")[0])[:90]


@dataclass
class Target:
    """One fuzz target: seeds, a mutator and a function that consumes one input.

    ``consume(data)`` returns the rejection reason (str) or None when decoded; it raises only on a
    crash (an exception type outside ``expected``).
    """
    name: str
    seeds: list[bytes]
    mutate: Callable[[random.Random, bytes, list[bytes]], bytes]
    consume: Callable[[bytes], str | None]
    expected: tuple[type, ...]
    weight: float = 1.0


def _wire_target(name: str, decoder: Callable, seeds: list[bytes]) -> Target:
    def consume(data: bytes) -> str | None:
        try:
            decoder(data)
        except WireError as exc:
            return f"{exc.field}: {_reason_class(exc.reason)}"
        return None
    return Target(name, seeds, mutate_message, consume, (WireError,))


def _pipeline_target(seeds: list[bytes], trust) -> Target:
    """The master's whole admission + evaluation path; its tracks are cleared before each input so
    sequence checks do not hide the deeper stages."""
    from master.pipeline import MasterPipeline, PipelineConfig
    from v2xpos.security import MessageAuthenticator

    auth = MessageAuthenticator(trust, require_signature=False, max_age_s=1e12, future_tolerance_s=1e12)
    pipe = MasterPipeline(PipelineConfig(fleet="demo", master_id="ego", measurement_point_m=(3.8, 0.0, 0.0)),
                          authenticator=auth)
    nav = NavState(t_s=T_SEED + 3, lla=np.array([0.7, -1.8, 1600.0]), v_ned_mps=np.array([10.0, 0, 0]),
                   acc_body_mps2=np.zeros(3), rate_body_rps=np.zeros(3), rpy_rad=np.zeros(3),
                   pos_sd_m=np.full(3, 0.01), vel_sd_mps=np.full(3, 0.01), att_sd_rad=np.full(3, 1e-3),
                   fix=FixStatus.FIXED)
    keys = [state_key("demo", "car1"), "v2xpos/demo/vehicle/x/state", "bad/key", None, None, None]
    counter = {"i": 0}

    def consume(data: bytes) -> str | None:
        counter["i"] += 1
        pipe.tracks.clear()
        auth.reset_replay_windows()
        before = Counter(pipe.rejected)
        res = pipe.handle(data, keys[counter["i"] % len(keys)], nav, T_SEED + 3.01, 1.7e9)
        if res is not None:
            return None
        diff = Counter(pipe.rejected) - before
        return next(iter(diff), "rejected (uncounted)")
    return Target("master.pipeline", seeds, mutate_message, consume, ())


UNNAMED = "error message does not name the file"


def _file_target(name: str, seeds: list[bytes], mutate, reader: Callable[[Path], object],
                 workdir: Path, suffix: str, weight: float) -> Target:
    """A reader/loader fed through a file; its error messages must name that file (else the
    rejection is tallied under UNNAMED)."""
    path = workdir / f"fuzz_{name}{suffix}"

    def consume(data: bytes) -> str | None:
        path.write_bytes(data)
        try:
            reader(path)
        except (ValueError, OSError) as exc:
            text = str(exc)
            if path.name not in text:
                return f"{UNNAMED}: {type(exc).__name__}: {_reason_class(text)}"
            return f"{type(exc).__name__}: {_reason_class(text.replace(str(path), '<file>'))}"
        return None
    return Target(name, seeds, mutate, consume, (ValueError, OSError), weight)


def build_targets(workdir: Path, data_dir: Path = DATA_DIR) -> list[Target]:
    """Every fuzz target with its seeds."""
    from master.config import MasterConfig
    from v2xpos.datasets.imu_csv import read_imu_csv
    from v2xpos.datasets.rtklib_pos import read_rtklib_pos
    from v2xpos.datasets.timetag import read_timetag
    from v2xpos.datasets.ubx import read_ubx
    from v2xpos.scene import Scene
    from v2xpos.security import load_trust_list

    from v2xpos.datasets.loader import load_dataset

    state, trust = seed_state_payloads()
    drive, walk = data_dir / "drive_0708", data_dir / "walk_0827"
    pos = [s for s in (_head_lines(drive / "gnss_1934.pos", 20, "%"), _head_lines(walk / "gnss_1730.pos", 20, "%"))
           if s] or [_synthetic_pos()]
    tag = [(drive / "imu_1934.csv.tag").read_bytes()[:76 + 8 * 60]] if (drive / "imu_1934.csv.tag").exists() \
        else [_synthetic_timetag()]
    csv = [s for s in (_head_lines(drive / "imu_1934.csv", 40), _head_lines(walk / "imu_1730.csv", 40)) if s] \
        or [_synthetic_imu_csv()]
    ubx = [(walk / "gnss_1730.ubx").read_bytes()[:6000]] if (walk / "gnss_1730.ubx").exists() else [_synthetic_ubx()]
    return [
        _wire_target("wire.state", decode_state, state),
        _wire_target("wire.relative", decode_relative, seed_relative_payloads()),
        _pipeline_target(state, trust),
        _file_target("rtklib_pos", pos, mutate_text, read_rtklib_pos, workdir, ".pos", 1.0),
        _file_target("timetag", tag, mutate_bytes, read_timetag, workdir, ".tag", 1.0),
        _file_target("imu_csv", csv, mutate_text, read_imu_csv, workdir, ".csv", 1.0),
        _file_target("ubx", ubx, mutate_bytes, read_ubx, workdir, ".ubx", 1.0),
        _file_target("geojson", [GEOJSON_SEED], mutate_text, Scene.load, workdir, ".geojson", 1.0),
        _file_target("master_config", [MASTER_TOML_SEED], mutate_text, MasterConfig.load, workdir, ".toml", 1.0),
        _file_target("trust_list", [_trust_seed()], mutate_text, load_trust_list, workdir, ".json", 1.0),
        _file_target("dataset_toml", [_dataset_toml_seed(workdir, csv[0], pos[0])], mutate_text, load_dataset,
                     workdir, ".toml", 0.3),
    ]


def run_target(target: Target, n: int, rng: random.Random, crash_dir: Path | None = None,
               progress: tqdm | None = None) -> TargetStats:
    """Feed ``n`` mutated inputs (plus the seeds themselves first) to one target."""
    stats = TargetStats(target.name)
    t0 = time.perf_counter()
    for i in range(n):
        base = rng.choice(target.seeds)
        data = base if i < len(target.seeds) else target.mutate(rng, base, target.seeds)
        stats.inputs += 1
        try:
            reason = target.consume(data)
        except Exception as exc:  # a crash: anything consume() did not turn into a reason
            stats.crashes += 1
            tb = traceback.format_exception(type(exc), exc, exc.__traceback__)
            example = {"error": f"{type(exc).__name__}: {exc}"[:300], "where": tb[-2].strip()[:300] if len(tb) > 1 else "",
                       "input_hex": data[:256].hex()}
            if len(stats.crash_examples) < 20:
                stats.crash_examples.append(example)
            if crash_dir is not None:
                crash_dir.mkdir(parents=True, exist_ok=True)
                (crash_dir / f"{target.name}_{stats.crashes:04d}.bin").write_bytes(data)
            reason = None
        else:
            if reason is None:
                stats.decoded += 1
            else:
                stats.rejected += 1
                stats.reasons[reason] += 1
        if progress is not None:
            progress.update(1)
    stats.seconds = time.perf_counter() - t0
    return stats


def plan_counts(total: int, targets: list[Target], decoder_share: float = 0.6) -> dict[str, int]:
    """Inputs per target: ``decoder_share`` of ``total`` to wire.state, the rest in proportion to
    the targets' weights (rounded up, so the sum is at least ``total``)."""
    counts = {}
    rest = [t for t in targets if t.name != "wire.state"]
    counts["wire.state"] = int(round(total * decoder_share))
    weight = sum(t.weight for t in rest) or 1.0
    for t in rest:
        counts[t.name] = max(1, math.ceil((total - counts["wire.state"]) * t.weight / weight))
    return counts


def run_fuzz(total: int = 100_000, seed: int = 1, crash_dir: Path | None = None, progress: bool = True,
             only: list[str] | None = None, data_dir: Path = DATA_DIR) -> dict:
    """Run every target; returns the report dict (``fuzz_inputs``, ``fuzz_crashes``, per target)."""
    rng = random.Random(seed)
    logging.disable(logging.WARNING)  # readers log each skipped record; the counts are in the report
    base = Path("/dev/shm") if Path("/dev/shm").is_dir() and os.access("/dev/shm", os.W_OK) else None
    workdir = Path(tempfile.mkdtemp(prefix="v2xpos_fuzz_", dir=base))
    try:
        targets = build_targets(workdir, data_dir)
        if only:
            targets = [t for t in targets if t.name in only]
        counts = plan_counts(total, targets)
        per: dict[str, TargetStats] = {}
        with tqdm(total=sum(counts.values()), disable=not progress, unit="in", desc="fuzz",
                  file=sys.stderr, mininterval=0.5) as bar:
            for t in targets:
                per[t.name] = run_target(t, counts[t.name], rng, crash_dir, bar)
    finally:
        logging.disable(logging.NOTSET)
        shutil.rmtree(workdir, ignore_errors=True)
    unnamed = {k: sum(n for r, n in v.reasons.items() if r.startswith(UNNAMED)) for k, v in per.items()}
    return {"fuzz_inputs": sum(s.inputs for s in per.values()),
            "fuzz_unnamed_errors": {k: n for k, n in unnamed.items() if n},
            "fuzz_crashes": sum(s.crashes for s in per.values()),
            "fuzz_decoded": sum(s.decoded for s in per.values()),
            "fuzz_rejected": sum(s.rejected for s in per.values()),
            "seed": seed, "targets": {k: v.as_dict() for k, v in per.items()}}


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--inputs", type=int, default=100_000, help="malformed inputs in total (default 100000)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (a run is reproducible)")
    parser.add_argument("--only", nargs="*", help="target names (default all)")
    parser.add_argument("--crash-dir", help="save crashing inputs here")
    parser.add_argument("--json", help="write the report here")


def run_bench(args: argparse.Namespace) -> int:
    report = run_fuzz(args.inputs, args.seed, Path(args.crash_dir) if args.crash_dir else None,
                      only=args.only)
    for name, t in report["targets"].items():
        print(f"{name:<16} {t['inputs']:>7} inputs  {t['decoded']:>6} decoded  {t['rejected']:>7} rejected  "
              f"{t['crashes']:>3} crashes  {t['inputs_per_s'] or 0:>9.0f} /s")
    print(f"total {report['fuzz_inputs']} inputs, {report['fuzz_crashes']} crashes")
    for name, n in report["fuzz_unnamed_errors"].items():
        print(f"warning: {name}: {n} error message(s) without the file name", file=sys.stderr)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0 if report["fuzz_crashes"] == 0 else 1
