"""The MCAP session recorder in a child process, so that recording never sits on the master's
real-time path.

Writing one message with the ``mcap`` package (JSON text, base64, record framing, chunk
compression) costs ~30-40 us of Python; the master records two per received message (the
payload and the output), which doubled its per-message cost. ``RecorderProcess`` has the
``McapRecorder`` interface; it packs each call (msgpack, ~2 us) into a buffer written to the
child's stdin, and the child (``python -m v2xpos.output.recorder_process``) replays the calls on
a ``McapRecorder`` in the same order. Log times are taken in the master when the call is made.

Frames: ``uint32 little-endian length, msgpack array [op, ...]``; ops: ``open`` (path,
max_bytes, chunk_size, compression), ``s`` (session), ``n`` (nav doc, log time), ``r``
(payload, key, arrival, now, nav index), ``t`` (now, master time, log time), ``o`` (raw result
bytes, log time), ``d`` (degraded vehicle ids, log time), ``g`` (the site's lanes and objects).
Decoding the messages to JSON and drawing them for Foxglove happen in the child. On end of input the child closes the recorder and prints
``{"recorded": {...}, "files": [...]}`` as one JSON line. The buffer is written when it holds
``FLUSH_BYTES`` or is ``FLUSH_INTERVAL_S`` old (checked at every call) and on ``flush``/``close``.
If the child fails, the error is printed once, further records are counted in ``dropped`` and
the master keeps running.
"""
from __future__ import annotations

import json
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, BinaryIO

import msgpack

from v2xpos.output.recorder import McapRecorder
from v2xpos.output.recording_schema import FOXGLOVE_TOPICS, SCHEMAS, nav_to_dict
from v2xpos.wire import RelativeResult, encode_relative

_U32 = struct.Struct("<I")
FLUSH_BYTES = 64 * 1024
FLUSH_INTERVAL_S = 0.05
MAX_FRAME_BYTES = 64 * 2 ** 20
CLOSE_TIMEOUT_S = 120.0
"""How long ``close`` waits for the child to write what is queued and finish the file."""


class RecorderProcess:
    """``McapRecorder`` interface backed by a child process (see the module docstring).
    ``recorded`` / ``files`` are the child's figures once ``close`` returned."""

    def __init__(self, path: str | Path, max_bytes: int = 256 * 2 ** 20, chunk_size: int = 256 * 1024,
                 compression: str = "zstd"):
        self.path = Path(path)
        self.proc = subprocess.Popen([sys.executable, "-m", "v2xpos.output.recorder_process"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0)
        self.recorded: dict[str, int] = {t: 0 for t in [*SCHEMAS, *FOXGLOVE_TOPICS]}
        self.files: list[Path] = []
        self.dropped = 0
        self.failure = ""
        self._lock = threading.Lock()
        self._buf: list[bytes] = []
        self._buf_bytes = 0
        self._t_flush = time.monotonic()
        self._closed = False
        self._frame(["open", str(self.path), int(max_bytes), int(chunk_size), compression])
        self.flush()

    @property
    def total_recorded(self) -> int:
        return sum(self.recorded.values())

    def _frame(self, op: list) -> None:
        data = msgpack.packb(op, use_bin_type=True)
        with self._lock:
            if self._closed or self.failure:
                self.dropped += 1
                return
            self._buf.append(_U32.pack(len(data)))
            self._buf.append(data)
            self._buf_bytes += len(data) + 4
            if self._buf_bytes >= FLUSH_BYTES or time.monotonic() - self._t_flush >= FLUSH_INTERVAL_S:
                self._flush_locked()

    def _flush_locked(self) -> None:
        self._t_flush = time.monotonic()
        if not self._buf or self.failure:
            return
        data = b"".join(self._buf)
        self._buf.clear()
        self._buf_bytes = 0
        try:
            self.proc.stdin.write(data)
        except (OSError, ValueError) as exc:
            self.failure = f"recorder process gone ({exc})"
            print(f"v2xpos recorder: {self.failure}; {self.path}: records from now on are dropped",
                  file=sys.stderr)

    def flush(self) -> None:
        with self._lock:
            self._flush_locked()

    def write_session(self, session: dict[str, Any]) -> None:
        self._frame(["s", {k: v if isinstance(v, str) else json.dumps(v) for k, v in session.items()}])

    def record_nav(self, nav: Any, index: int) -> None:
        self._frame(["n", nav_to_dict(nav, index), time.time_ns()])

    def record_received(self, payload: bytes, key: str | None, t_arrival_wall_s: float,
                        t_now_gps_s: float, nav_index: int) -> None:
        self._frame(["r", bytes(payload), key, float(t_arrival_wall_s), float(t_now_gps_s), int(nav_index)])

    def record_tick(self, t_now_gps_s: float, master_t_gps_s: float | None, master_fix: int | None = None) -> None:
        self._frame(["t", float(t_now_gps_s), None if master_t_gps_s is None else float(master_t_gps_s),
                     time.time_ns(), None if master_fix is None else int(master_fix)])

    def record_result(self, res: RelativeResult) -> None:
        self._frame(["o", encode_relative(res), time.time_ns()])

    def record_degraded(self, vehicle_ids: list[str]) -> None:
        self._frame(["d", list(vehicle_ids), time.time_ns()])

    def write_scene_features(self, features: list[dict]) -> None:
        self._frame(["g", features])

    def close(self) -> None:
        """Flush, end the child's input and take its figures (waits for it to finish writing)."""
        with self._lock:
            if self._closed:
                return
            self._flush_locked()
            self._closed = True
        try:
            out, _ = self.proc.communicate(timeout=CLOSE_TIMEOUT_S)   # closes stdin: the child finishes
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        except (OSError, ValueError):
            out = b""
        try:
            doc = json.loads(out.decode().strip().splitlines()[-1])
            self.recorded = {k: int(v) for k, v in doc["recorded"].items()}
            self.files = [Path(f) for f in doc["files"]]
        except (ValueError, IndexError, KeyError, UnicodeDecodeError):
            self.failure = self.failure or f"recorder process exited {self.proc.returncode} without its figures"
            print(f"v2xpos recorder: {self.failure}", file=sys.stderr)

    def __enter__(self) -> "RecorderProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve(inp: BinaryIO, out: BinaryIO) -> int:
    """Child loop (see the module docstring)."""
    rec: McapRecorder | None = None
    n_frame = 0
    try:
        while True:
            head = inp.read(4)
            if len(head) < 4:
                break
            n = _U32.unpack(head)[0]
            if n > MAX_FRAME_BYTES:
                raise ValueError(f"frame {n_frame}: {n} bytes")
            data = inp.read(n)
            if len(data) < n:
                raise ValueError(f"frame {n_frame}: cut short ({len(data)} of {n} bytes)")
            op = msgpack.unpackb(data, raw=False)
            kind = op[0]
            if kind == "open":
                rec = McapRecorder(op[1], max_bytes=op[2], chunk_size=op[3], compression=op[4])
            elif rec is None:
                raise ValueError(f"frame {n_frame}: {kind!r} before 'open'")
            elif kind == "r":
                rec.record_received(op[1], op[2], op[3], op[4], op[5])
            elif kind == "o":
                rec.record_result_bytes(op[1], log_time_ns=op[2])
            elif kind == "d":
                rec.record_degraded(op[1], op[2])
            elif kind == "g":
                rec.write_scene_features(op[1])
            elif kind == "n":
                rec.record_nav_doc(op[1], op[2])
            elif kind == "t":
                rec.record_tick(op[1], op[2], op[3], op[4] if len(op) > 4 else None)
            elif kind == "s":
                rec.write_session(op[1])
            else:
                raise ValueError(f"frame {n_frame}: unknown op {kind!r}")
            n_frame += 1
    except Exception as exc:  # keep what was written: the recorder is closed below either way
        print(f"v2xpos recorder process: {type(exc).__name__}: {exc}", file=sys.stderr)
    if rec is None:
        return 2
    rec.close()
    out.write((json.dumps({"recorded": rec.recorded, "files": [str(f) for f in rec.files]}) + "\n").encode())
    out.flush()
    return 0


if __name__ == "__main__":
    sys.exit(serve(sys.stdin.buffer, sys.stdout.buffer))
