"""Output sinks of the master pipeline: each has ``write(result)`` and counts what it sent.

* ``CanSink`` -- ``v2xpos.output.can.CanOutput`` (DBC frames; python-can ``virtual`` or socketcan);
  scene results as LANE / OBJECT frames (``write_scene``);
* ``UdpSink`` -- ``v2xpos.output.udp.UdpOutput``, one datagram per flush: the results of one message
  or of one dispatch batch (layout in docs/protocol.md)
  and one datagram of lane / object records per scene update;
* ``ZenohSink`` -- ``encode_relative`` republished on ``v2xpos/<fleet>/master/<id>/relative``.
"""
from __future__ import annotations


from v2xpos.link import Publisher
from v2xpos.wire import RelativeResult, encode_relative


class CanSink:
    """Target results as CAN frames (slots assigned per target id by the CanOutput).

    ``rate_hz``: at most this many updates per target per second (None = every result); a change of
    status is always sent at once. A 1 Mbit/s bus carries about 8,000 8-byte frames per second, i.e.
    5-frame target updates for 64 targets at 25 Hz; UDP and zenoh carry every result regardless.
    """

    def __init__(self, channel: str = "v2xpos", interface: str = "virtual", dbc_path: str | None = None,
                 rate_hz: float | None = None, **bus_kwargs):
        from v2xpos.output.can import CanOutput
        self.out = CanOutput(channel=channel, interface=interface, dbc_path=dbc_path, **bus_kwargs)
        self.min_period_s = 0.0 if not rate_hz else 1.0 / rate_hz
        self._last: dict[str, tuple[float, int]] = {}
        self.skipped = 0

    @property
    def frames(self) -> int:
        return self.out.frames_sent

    def write(self, result: RelativeResult) -> None:
        if self.min_period_s > 0.0:
            last = self._last.get(result.target_id)
            if (last is not None and last[1] == int(result.status)
                    and result.t_gps_s - last[0] < self.min_period_s - 1e-4):
                self.skipped += 1
                return
            self._last[result.target_id] = (result.t_gps_s, int(result.status))
        self.out.send_result(result)

    def write_scene(self, scene_result, t_gps_s: float, seq: int) -> None:
        """LANE / OBJECT frames numbered as in docs/protocol.md §5 (``CanOutput.send_scene``)."""
        self.out.send_scene(scene_result)

    def close(self) -> None:
        self.out.close()


class UdpSink:
    """UDP datagrams to a loopback address by default: ``write`` queues a result, ``flush`` sends the
    queued results as one datagram (the pipeline flushes after every message, or once per dispatch
    batch); the header's sequence number is the last result's. Scene updates go out at once."""

    def __init__(self, host: str = "127.0.0.1", port: int = 47001, allow_remote: bool = False):
        from v2xpos.output.udp import MAX_DATAGRAM_BYTES, TARGET, UdpOutput
        self.out = UdpOutput(host=host, port=port, allow_remote=allow_remote)
        self.max_targets = (MAX_DATAGRAM_BYTES - 64) // TARGET.size
        self._queued: list[RelativeResult] = []

    @property
    def datagrams(self) -> int:
        return self.out.datagrams_sent

    def write(self, result: RelativeResult) -> None:
        self._queued.append(result)
        if len(self._queued) >= self.max_targets:
            self.flush()

    def flush(self) -> None:
        """Send the queued results (if any) as one datagram."""
        q = self._queued
        if q:
            self.out.send(q, q[-1].seq, q[-1].t_gps_s)
            q.clear()

    def write_scene(self, scene_result, t_gps_s: float, seq: int) -> None:
        """One datagram with no targets and the lane / object records."""
        from v2xpos.output.udp import records_from_scene
        lanes, objects = records_from_scene(scene_result)
        self.out.send([], seq, t_gps_s, lanes, objects)

    def close(self) -> None:
        self.flush()
        self.out.close()


class ZenohSink:
    """Republish results for monitors (msgpack envelope, ``v2xpos.wire.encode_relative``)."""

    def __init__(self, publisher: Publisher, sign=None):
        self.pub = publisher
        self.sign = sign

    @property
    def sent(self) -> int:
        return self.pub.sent

    def write(self, result: RelativeResult) -> None:
        self.pub.put(encode_relative(result, self.sign))

    def close(self) -> None:
        pass
