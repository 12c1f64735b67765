"""Ed25519 envelope verification in a worker process, beside the master's pipeline thread.

Verifying one signature costs ~0.1-0.2 ms here, as much as the rest of a message's handling. A
thread cannot take it off the pipeline's core: ``cryptography`` releases the GIL only inside the
verification, and every re-acquisition waits behind the pipeline thread (CPython's switch interval,
5 ms), so the two threads convoy. A process has its own interpreter: the master sends a batch of
received envelopes, handles the previous batch while the worker verifies, then reads the verdicts.

Protocol on the worker's stdin / stdout (all integers little-endian uint32):
* first frame from the master: ``len, trust-list JSON`` (``TrustList.to_json``);
* request: ``n, (len, envelope bytes) * n``; reply: ``n, verdict byte * n`` in the same order,
  verdict 1 = signature valid for the trust list's key ``key_id``, 0 = invalid, 2 = not decided
  (``MessageAuthenticator.verify_envelope`` returned None: the pipeline decides).
A worker that dies or answers garbage is abandoned: its outstanding batches get undecided verdicts
and the pipeline verifies in its own thread from then on, so no message goes unverified.
"""
from __future__ import annotations

import struct
import subprocess
import sys
from collections import deque
from typing import BinaryIO

_U32 = struct.Struct("<I")
VERDICTS = {1: True, 0: False, 2: None}
MAX_BATCH = 4096
MAX_FRAME_BYTES = 64 * 2 ** 20


def _read_exact(fh: BinaryIO, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = fh.read(n - len(buf))
        if not chunk:
            raise EOFError(f"pipe closed after {len(buf)} of {n} bytes")
        buf += chunk
    return bytes(buf)


def _read_u32(fh: BinaryIO) -> int:
    return _U32.unpack(_read_exact(fh, 4))[0]


def encode_batch(payloads: list[bytes]) -> bytes:
    """Request frame for ``payloads``."""
    parts = [_U32.pack(len(payloads))]
    for p in payloads:
        parts.append(_U32.pack(len(p)))
        parts.append(p)
    return b"".join(parts)


class VerifierProcess:
    """Master side: ``submit`` a batch of envelopes, ``collect`` the verdicts of the oldest
    submitted batch (FIFO). ``alive`` is False once the worker failed; then every verdict is
    None (undecided) and the caller's pipeline verifies itself."""

    def __init__(self, trust_json: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "v2xpos.verify_worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, bufsize=0)
        self._pending: deque[int] = deque()
        self.alive = True
        self.failure = ""
        self._write(_U32.pack(len(trust_json.encode())) + trust_json.encode())

    def _fail(self, why: str) -> None:
        if self.alive:
            self.alive = False
            self.failure = why
            print(f"v2xpos verify worker abandoned ({why}); verifying in the pipeline thread", file=sys.stderr)
            self.close()

    def _write(self, data: bytes) -> None:
        try:
            self.proc.stdin.write(data)
        except (OSError, ValueError) as exc:
            self._fail(f"write: {exc}")

    def submit(self, payloads: list[bytes]) -> None:
        self._pending.append(len(payloads))
        if self.alive:
            self._write(encode_batch(payloads))

    def collect(self) -> list[bool | None]:
        n = self._pending.popleft()
        if not self.alive:
            return [None] * n
        try:
            m = _read_u32(self.proc.stdout)
            codes = _read_exact(self.proc.stdout, m)
            if m != n:
                raise ValueError(f"reply for {m} envelopes, expected {n}")
            return [VERDICTS[c] for c in codes]
        except (OSError, EOFError, ValueError, KeyError) as exc:
            self._fail(f"read: {exc}")
            return [None] * n

    @property
    def outstanding(self) -> int:
        return len(self._pending)

    def close(self) -> None:
        for fh in (self.proc.stdin, self.proc.stdout):
            try:
                fh.close()
            except OSError:
                pass
        try:
            self.proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def serve(inp: BinaryIO, out: BinaryIO) -> int:
    """Worker loop: read the trust list, then answer requests until stdin closes."""
    from v2xpos.security import MessageAuthenticator, parse_trust_list
    n_trust = _read_u32(inp)
    if n_trust > MAX_FRAME_BYTES:
        print(f"verify worker: trust frame of {n_trust} bytes", file=sys.stderr)
        return 2
    verify = MessageAuthenticator(parse_trust_list(_read_exact(inp, n_trust).decode(), "<master>")).verify_envelope
    codes = {True: 1, False: 0, None: 2}
    while True:
        try:
            n = _read_u32(inp)
        except EOFError:
            return 0
        if n > MAX_BATCH:
            print(f"verify worker: batch of {n} envelopes (max {MAX_BATCH})", file=sys.stderr)
            return 2
        verdicts = bytearray()
        for _ in range(n):
            size = _read_u32(inp)
            if size > MAX_FRAME_BYTES:
                print(f"verify worker: envelope of {size} bytes", file=sys.stderr)
                return 2
            verdicts.append(codes[verify(_read_exact(inp, size))])
        out.write(_U32.pack(n) + bytes(verdicts))
        out.flush()


if __name__ == "__main__":
    sys.exit(serve(sys.stdin.buffer, sys.stdout.buffer))
