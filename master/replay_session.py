"""``v2xpos replay-session FILE``: re-run the master pipeline from an MCAP recording and check that
it reproduces the recorded outputs exactly.

The recording (``v2xpos.output.recorder``) holds the pipeline configuration, the admission
settings (trust list), every received payload (``/v2xpos/raw/rx``) with the master GPS time it was
processed at, the master filter state it was processed against, every silence tick and every
change of the degraded-vehicle set. Replaying these inputs in the recorded order through a fresh
``master.pipeline.MasterPipeline`` is deterministic -- nothing in it depends on set or dict
order or on the replaying computer's clock (the pipeline's wall clock is the recorded arrival
time of the message being replayed) -- so the ``encode_relative`` bytes of every result must equal
the recorded ones (``/v2xpos/raw/out/relative``), in order; any difference is reported with its
index.
"""
from __future__ import annotations

import argparse
import base64
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from master.pipeline import MasterPipeline, PipelineConfig
from v2xpos.output.recorder import read_recording, read_session, recording_files
from v2xpos.output.recording_schema import (TOPIC_DEGRADED, TOPIC_NAV, TOPIC_RAW_RELATIVE, TOPIC_RAW_RX, TOPIC_TICK,
                                            nav_from_dict)
from v2xpos.security import MessageAuthenticator, parse_trust_list
from v2xpos.wire import RelativeResult, encode_relative


class _Capture:
    def __init__(self):
        self.results: list[bytes] = []

    def write(self, result: RelativeResult) -> None:
        self.results.append(encode_relative(result))

    def close(self) -> None:
        pass


@dataclass
class ReplayReport:
    """Outcome of a replay: counts and the first mismatches (index, reason)."""
    files: int = 0
    received: int = 0
    ticks: int = 0
    recorded_outputs: int = 0
    replayed_outputs: int = 0
    matched: int = 0
    mismatches: list[tuple[int, str]] = field(default_factory=list)
    rejected: dict = field(default_factory=dict)
    damaged: list[str] = field(default_factory=list)

    @property
    def identical(self) -> bool:
        """Every recorded output reproduced; a recording cut short (``damaged``) may end with
        inputs whose outputs were not written any more -- only the recorded ones are compared."""
        if self.damaged:
            return not self.mismatches and self.matched == self.recorded_outputs
        return (not self.mismatches and self.recorded_outputs == self.replayed_outputs
                == self.matched)

    def as_dict(self) -> dict:
        return {"files": self.files, "received": self.received, "ticks": self.ticks,
                "recorded_outputs": self.recorded_outputs, "replayed_outputs": self.replayed_outputs,
                "matched": self.matched, "identical": self.identical,
                "mismatches": [{"index": i, "reason": r} for i, r in self.mismatches[:20]],
                "rejected": self.rejected, "damaged": self.damaged}


class _RecordedClock:
    """The pipeline's wall clock during a replay: the recorded time of the input being replayed."""

    def __init__(self):
        self.t_wall_s = 0.0

    def __call__(self) -> float:
        return self.t_wall_s


def pipeline_from_session(session: dict, sinks: list, clock_wall=None) -> MasterPipeline:
    """A fresh pipeline configured as the recorded one."""
    cfg = dict(session.get("pipeline_config") or {})
    for k in ("measurement_point_m", "known_vehicles"):
        if k in cfg and isinstance(cfg[k], list):
            cfg[k] = tuple(cfg[k])
    auth = None
    a = session.get("authenticator")
    if a:
        auth = MessageAuthenticator(parse_trust_list(a["trust_list"], "recording:trust_list"),
                                    require_signature=a["require_signature"], max_age_s=a["max_age_s"],
                                    future_tolerance_s=a["future_tolerance_s"],
                                    replay_window=a["replay_window"])
    kw = {} if clock_wall is None else {"clock_wall": clock_wall}
    return MasterPipeline(PipelineConfig(**cfg), sinks, authenticator=auth, **kw)


def replay_session(path: str | Path, progress: bool = False) -> ReplayReport:
    """Replay a recording and compare outputs (see the module docstring)."""
    session = read_session(path)
    capture = _Capture()
    clock = _RecordedClock()
    pipe = pipeline_from_session(session, [capture], clock)
    report = ReplayReport(files=len(recording_files(path)))
    recorded: list[bytes] = []
    navs: dict[int, object] = {}
    topics = (TOPIC_NAV, TOPIC_RAW_RX, TOPIC_TICK, TOPIC_DEGRADED, TOPIC_RAW_RELATIVE)
    for rec in tqdm(read_recording(path, topics=topics, errors=report.damaged), disable=not progress,
                    unit="msg", desc="replay"):
        d = rec.doc
        if rec.topic == TOPIC_NAV:
            navs = {d["index"]: nav_from_dict(d)}
        elif rec.topic == TOPIC_RAW_RX:
            report.received += 1
            nav = navs.get(d["nav_index"])
            if nav is None:
                report.mismatches.append((report.received, f"master state {d['nav_index']} missing"))
                continue
            clock.t_wall_s = d["t_arrival_wall_s"]
            pipe.handle(base64.b64decode(d["payload_b64"]), d["key"], nav, d["t_now_gps_s"],
                        d["t_arrival_wall_s"])
        elif rec.topic == TOPIC_TICK:
            report.ticks += 1
            clock.t_wall_s = rec.log_time_ns * 1e-9
            if d.get("master_fix") is None:
                pipe.tick(d["t_now_gps_s"], d["master_t_gps_s"])
            else:
                pipe.tick(d["t_now_gps_s"], d["master_t_gps_s"], d["master_fix"])
        elif rec.topic == TOPIC_DEGRADED:
            pipe.degraded_vehicles.clear()
            pipe.degraded_vehicles.update(d["vehicle_ids"])
        elif rec.topic == TOPIC_RAW_RELATIVE:
            recorded.append(base64.b64decode(d["payload_b64"]))
    report.recorded_outputs = len(recorded)
    report.replayed_outputs = len(capture.results)
    for i, (a, b) in enumerate(zip(recorded, capture.results)):
        if a == b:
            report.matched += 1
        elif len(report.mismatches) < 100:
            report.mismatches.append((i, "output bytes differ"))
    if report.recorded_outputs != report.replayed_outputs and not (
            report.damaged and report.replayed_outputs > report.recorded_outputs):
        report.mismatches.append((min(report.recorded_outputs, report.replayed_outputs),
                                  f"{report.recorded_outputs} outputs recorded, "
                                  f"{report.replayed_outputs} replayed"))
    report.rejected = dict(pipe.rejected)
    return report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="first .mcap file of the recording (rotated parts are found beside it)")
    parser.add_argument("--json", help="write the replay report here")


def run(args: argparse.Namespace) -> int:
    path = Path(args.file)
    if not path.exists():
        print(f"v2xpos replay-session: {path}: no such file", file=sys.stderr)
        return 2
    try:
        report = replay_session(path, progress=True)
    except Exception as exc:  # a damaged recording: say which file and why, do not trace back
        print(f"v2xpos replay-session: {path}: cannot replay ({type(exc).__name__}: {exc})", file=sys.stderr)
        return 2
    doc = report.as_dict()
    print(json.dumps(doc, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=1))
    return 0 if report.identical else 1
