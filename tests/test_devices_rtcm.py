"""RTCM3 corrections: frame checks, the NTRIP client against a stand-in caster on 127.0.0.1 (v1 and
v2, chunked), and the relay over zenoh into two slaves' pseudo-terminal receivers -- every RTCM byte
that goes in arrives, in order; a corrupted frame is counted and never relayed."""
from __future__ import annotations

import base64
import os
import select
import socket
import threading
import time

import numpy as np
import pytest
from pyrtcm import RTCMReader
from pyrtcm.rtcmhelpers import calc_crc24q

from v2xpos.devices.rtcm import NtripClient, RtcmChecker, rtcm_message_type
from v2xpos.launch import free_tcp_port
from v2xpos.sources.corrections import CorrectionRelay, CorrectionSink, parse_corrections
from v2xpos.wire import corrections_key


# ------------------------------------------------------------------ RTCM3 frames built by hand
class BitWriter:
    def __init__(self):
        self.bits: list[int] = []

    def u(self, value: int, n: int) -> "BitWriter":
        value &= (1 << n) - 1
        self.bits += [(value >> (n - 1 - k)) & 1 for k in range(n)]
        return self

    def s(self, value: int, n: int) -> "BitWriter":
        return self.u(value if value >= 0 else (1 << n) + value, n)

    def bytes(self) -> bytes:
        bits = self.bits + [0] * (-len(self.bits) % 8)
        return bytes(int("".join(map(str, bits[k:k + 8])), 2) for k in range(0, len(bits), 8))


def frame(payload: bytes) -> bytes:
    """0xD3, 6 zero bits + 10-bit length, payload, CRC-24Q (RTCM 10403.3 sec. 4)."""
    head = bytes([0xD3, (len(payload) >> 8) & 0x03, len(payload) & 0xFF]) + payload
    return head + calc_crc24q(head).to_bytes(3, "big")


def msg_1005(station: int, ecef_m: tuple) -> bytes:
    w = BitWriter().u(1005, 12).u(station, 12).u(0, 6).u(1, 1).u(1, 1).u(1, 1).u(0, 1)
    w.s(round(ecef_m[0] / 1e-4), 38).u(0, 1).u(0, 1).s(round(ecef_m[1] / 1e-4), 38).u(0, 2)
    w.s(round(ecef_m[2] / 1e-4), 38)
    return frame(w.bytes())


def msg_1077(station: int, tow_ms: int, rng: np.random.Generator, nsat: int = 3) -> bytes:
    """GPS MSM7 with ``nsat`` satellites on one signal (L1C); field values random but in range."""
    sats = sorted(rng.choice(np.arange(1, 33), nsat, replace=False))
    w = BitWriter().u(1077, 12).u(station, 12).u(tow_ms, 30).u(0, 1).u(0, 3).u(0, 7).u(0, 2).u(0, 2)
    w.u(0, 1).u(0, 3)
    for k in range(1, 65):
        w.u(1 if k in sats else 0, 1)
    for k in range(1, 33):
        w.u(1 if k == 2 else 0, 1)                 # signal 2 = L1 C/A
    for _ in sats:
        w.u(1, 1)                                   # cell mask: every satellite has the signal
    for _ in sats:
        w.u(int(rng.integers(60, 90)), 8)
    for _ in sats:
        w.u(0, 4)
    for _ in sats:
        w.u(int(rng.integers(0, 1024)), 10)
    for _ in sats:
        w.s(int(rng.integers(-800, 800)), 14)
    for _ in sats:
        w.s(int(rng.integers(-1000, 1000)), 20)
    for _ in sats:
        w.s(int(rng.integers(-1000, 1000)), 24)
    for _ in sats:
        w.u(int(rng.integers(0, 1000)), 10)
    for _ in sats:
        w.u(0, 1)
    for _ in sats:
        w.u(int(rng.integers(300, 800)), 10)
    for _ in sats:
        w.s(int(rng.integers(-1000, 1000)), 15)
    return frame(w.bytes())


def correction_stream(seconds: int = 6, seed: int = 3) -> list[bytes]:
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(seconds):
        frames.append(msg_1005(7, (-1288398.123, -4721696.456, 4078625.789)))
        frames.append(msg_1077(7, 345_600_000 + 1000 * k, rng, nsat=int(rng.integers(3, 9))))
    return frames


def test_hand_built_frames_parse_with_pyrtcm_and_check():
    frames = correction_stream(2)
    for f in frames:
        msg = RTCMReader.parse(f)                   # CRC validated by pyrtcm
        assert int(msg.identity) == rtcm_message_type(f)
    m = RTCMReader.parse(frames[0])
    assert m.DF025 == pytest.approx(-1288398.123, abs=1e-4)
    chk = RtcmChecker()
    bad = bytearray(frames[1])
    bad[10] ^= 0x40
    out = chk.feed(b"noise" + frames[0] + bytes(bad) + frames[2], 0.0)
    assert [f for f, _ in out] == [frames[0], frames[2]]
    assert chk.stats()["malformed"] == 1 and chk.stats()["by_type"] == {"1005": 2}


# ------------------------------------------------------------------ stand-in caster
class StandInCaster:
    """NTRIP caster on 127.0.0.1 (port from the OS) serving ``payload`` on one mountpoint.

    v2 requests (``Ntrip-Version: Ntrip/2.0``) get ``HTTP/1.1 200 OK`` and a chunked body; v1
    requests get ``ICY 200 OK``. The first data goes out in the same send as the header; the rest
    in pieces of random size (frames split across sends). Wrong mountpoint: the sourcetable;
    wrong credentials: 401."""

    def __init__(self, payload: bytes, mountpoint: str = "MOUNT", user: str = "u", password: str = "p",
                 piece_s: float = 0.01):
        self.payload = payload
        self.mountpoint = mountpoint
        self.auth = base64.b64encode(f"{user}:{password}".encode()).decode()
        self.piece_s = piece_s
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.port = self.sock.getsockname()[1]
        self.requests: list[str] = []
        self.go = threading.Event()
        self._t = threading.Thread(target=self._serve, daemon=True)
        self._t.start()

    def _serve(self) -> None:
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._handle, args=(c,), daemon=True).start()

    def _handle(self, c: socket.socket) -> None:
        with c:
            req = b""
            while b"\r\n\r\n" not in req:
                part = c.recv(4096)
                if not part:
                    return
                req += part
            text = req.decode()
            self.requests.append(text)
            first = text.split("\r\n")[0]
            v2 = "Ntrip-Version: Ntrip/2.0" in text
            if first.split(" ")[1] != "/" + self.mountpoint:
                body = b"STR;MOUNT;x;RTCM 3.2;;;;;;;;;;\r\nENDSOURCETABLE\r\n"
                c.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: gnss/sourcetable\r\n\r\n" + body if v2
                          else b"SOURCETABLE 200 OK\r\n\r\n" + body)
                return
            if f"Authorization: Basic {self.auth}" not in text:
                c.sendall(b"HTTP/1.1 401 Unauthorized\r\n\r\n")
                return
            self.go.wait(10)
            rng = np.random.default_rng(len(self.requests))
            pieces, k = [], 0
            while k < len(self.payload):
                n = int(rng.integers(1, 300))
                pieces.append(self.payload[k:k + n])
                k += n

            def wrap(b: bytes) -> bytes:
                return (f"{len(b):x}\r\n".encode() + b + b"\r\n") if v2 else b
            head = (b"HTTP/1.1 200 OK\r\nNtrip-Version: Ntrip/2.0\r\nContent-Type: gnss/data\r\n"
                    b"Transfer-Encoding: chunked\r\n\r\n") if v2 else b"ICY 200 OK\r\n"
            c.sendall(head + wrap(pieces[0]))
            for p in pieces[1:]:
                time.sleep(self.piece_s)
                c.sendall(wrap(p))
            time.sleep(0.5)
            if v2:
                c.sendall(b"0\r\n\r\n")

    def close(self) -> None:
        self.sock.close()


def _collect(client_factory, payload_frames, version: int) -> tuple[bytes, RtcmChecker, NtripClient]:
    caster = StandInCaster(b"".join(payload_frames))
    chk = RtcmChecker()
    got = bytearray()
    lock = threading.Lock()

    def on_chunk(b: bytes, t: float) -> None:
        with lock:
            for f, _ in chk.feed(b, t):
                got.extend(f)
    cli = client_factory(caster, on_chunk, version)
    cli.start()
    caster.go.set()
    want = sum(len(f) for f in payload_frames)
    deadline = time.time() + 15
    while len(got) < want and time.time() < deadline:
        time.sleep(0.05)
    cli.stop()
    caster.close()
    return bytes(got), chk, cli


@pytest.mark.parametrize("version", [1, 2])
def test_ntrip_client_keeps_every_byte(version):
    frames = correction_stream(5, seed=version)
    got, chk, cli = _collect(lambda c, cb, v: NtripClient("127.0.0.1", c.port, "MOUNT", cb, user="u", password="p",
                                                          version=v, retry_s=0.2), frames, version)
    assert got == b"".join(frames)
    assert chk.stats()["malformed"] == 0 and chk.stats()["skipped_bytes"] == 0
    assert cli.stats()["status_line"].startswith("ICY 200" if version == 1 else "HTTP/1.1 200")


def test_ntrip_client_reports_wrong_mountpoint_and_credentials():
    caster = StandInCaster(b"")
    for mount, pw, expect in (("NOPE", "p", "sourcetable"), ("MOUNT", "x", "401")):
        cli = NtripClient("127.0.0.1", caster.port, mount, lambda b, t: None, user="u", password=pw, retry_s=5)
        cli.start()
        deadline = time.time() + 5
        while not cli.last_error and time.time() < deadline:
            time.sleep(0.02)
        cli.stop()
        assert expect in cli.last_error and cli.bytes_in == 0
    caster.close()


def test_corrections_config_is_strict():
    c = parse_corrections({"source": "ntrip", "caster": "127.0.0.1:2101", "mountpoint": "M", "ntrip_version": 1})
    assert c.caster == ("127.0.0.1", 2101) and c.ntrip_version == 1
    assert parse_corrections({"receive": True}).receive
    with pytest.raises(ValueError, match="mountpoint"):
        parse_corrections({"source": "ntrip", "caster": "127.0.0.1:2101"})
    with pytest.raises(ValueError, match="did you mean 'mountpoint'"):
        parse_corrections({"source": "ntrip", "caster": "h:1", "mountpoint": "M", "mountpont": "M"})
    with pytest.raises(ValueError, match="only with source = 'serial'"):
        parse_corrections({"source": "tcp", "tcp": "127.0.0.1:5000", "baud": 9600})
    with pytest.raises(ValueError, match="receive = true"):
        parse_corrections({})


# ------------------------------------------------------------------ relay to two slaves' receivers
def _pty_receiver():
    """A pseudo-terminal standing in for a receiver: the device source opens ``path``; the test
    reads what was written to the receiver from ``master``."""
    import tty
    m, s = os.openpty()
    tty.setraw(s)
    path = os.ttyname(s)
    os.close(s)
    os.set_blocking(m, False)
    return m, path


def _read_all(fd: int, into: bytearray) -> None:
    while select.select([fd], [], [], 0)[0]:
        try:
            b = os.read(fd, 65536)
        except OSError:
            return
        if not b:
            return
        into += b


def test_relay_from_stand_in_caster_to_two_slave_receivers():
    from v2xpos.link import Link, LinkConfig, loopback_endpoint
    from v2xpos.sources import SourceContext, make_source
    frames = correction_stream(8, seed=11)
    bad = bytearray(frames[3])
    bad[-1] ^= 0xFF                                   # a corrupted frame in the caster's stream
    stream = b"".join(frames[:3]) + bytes(bad) + b"\x00junk" + b"".join(frames[3:])
    good = b"".join(frames)
    caster = StandInCaster(stream, piece_s=0.005)
    port = free_tcp_port()
    master = Link(LinkConfig(mode="router", listen=[loopback_endpoint(port)]))
    slaves, sources, sinks, ptys = [], [], [], []
    try:
        for k in range(2):
            m, path = _pty_receiver()
            ptys.append(m)
            src = make_source({"type": "device", "gnss": {"format": "ubx", "port": path}, "imu": "receiver", "platform": "car",
                               "imu_to_body": "identity", "lever_arm_m": [0.0, 0.0, 0.0]},
                              f"slave{k}.[source]", SourceContext(f"s{k}"))
            sources.append(src)
            link = Link(LinkConfig(mode="client", connect=[loopback_endpoint(port)]))
            slaves.append(link)
            sinks.append(CorrectionSink(link, "test", src.write_corrections))
        deadline = time.time() + 5
        while not all(s.gnss_stream.transport.connected for s in sources) and time.time() < deadline:
            time.sleep(0.02)
        # wait until the routes to both subscribers exist (probe on the same key, not RTCM: dropped)
        probe = master.publisher(corrections_key("test"))
        deadline = time.time() + 10
        while not all(s.bad_attachment or s.frames for s in sinks) and time.time() < deadline:
            probe.put(b"probe")
            time.sleep(0.05)
        assert all(s.checker.stats()["skipped_bytes"] for s in sinks), "subscribers not reached"
        cfg = parse_corrections({"source": "ntrip", "caster": f"127.0.0.1:{caster.port}", "mountpoint": "MOUNT",
                                 "user": "u", "password": "p"})
        local = bytearray()
        relay = CorrectionRelay(cfg, master, "test", local_write=lambda b: local.extend(b) or len(b)).start()
        caster.go.set()
        received = [bytearray(), bytearray()]
        deadline = time.time() + 20
        while time.time() < deadline and not all(len(r) >= len(good) for r in received):
            for m, r in zip(ptys, received):
                _read_all(m, r)
            time.sleep(0.02)
        st = relay.stats()
        relay.close()
        assert bytes(local) == good
        for r, sink in zip(received, sinks):
            assert bytes(r) == good                    # every byte, in order, nothing else
            s = sink.stats()
            assert s["frames_written"] == len(frames) and s["gaps"] == 0 and s["malformed"] == 0
            assert s["age_s"] is not None and s["throughput_bps"] > 0
        assert st["frames_sent"] == len(frames) and st["malformed"] == 1
        assert st["by_type"] == {"1005": 8, "1077": 8} and st["throughput_bps"] > 0
        assert sources[0].status()["streams"]["gnss"]["transport"]["bytes_out"] == len(good)
    finally:
        for s in sinks:
            s.close()
        for s in sources:
            s.close()
        for link in slaves:
            link.close()
        master.close()
        caster.close()
        for m in ptys:
            os.close(m)
