"""``v2xpos bench soak --slaves 32 --rate 100 --duration 60``: long run of the real master service
with many signing slaves, as separate OS processes on loopback.

Processes: one master (``master.service.MasterService`` with ``[record] mcap`` on, plus a
resident-memory sampler thread) embedding the zenoh router on ``tcp/127.0.0.1:PORT``;
``ceil(slaves / per_process)`` slave processes, each publishing ``per_process`` vehicles'
signed StateMessages at ``rate`` Hz with CongestionControl.BLOCK (a full queue blocks the
publisher instead of dropping). Every vehicle has its own Ed25519 key; the master holds the
trust list, so every message is verified.

Reported: ``sent`` (slaves' put calls), ``received`` (samples the master's subscriber got),
``recorded`` (received payloads written to MCAP), ``output`` (results the pipeline produced from
messages), ``lost = sent - received``, and ``rss_growth_pct``: master resident memory in the last quarter
of publishing versus the first quarter after ``warmup_fraction`` of the run (allocation warm-up),
each the median of its 0.5 s samples so that buffer churn (+-10 % from MCAP chunks and zenoh
queues) is not read as growth [%]. Also the achieved publish rate and the master's pipeline / end-to-end latency percentiles.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from tqdm import tqdm

from v2xpos.launch import free_tcp_port

SOAK_FLEET = "soak"


def rss_bytes() -> int:
    """Resident set size of this process [bytes] (Linux /proc/self/statm)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


# ----------------------------------------------------------------------------- master role

def _run_master(cfg_path: Path, start_file: Path, record: Path | None, stats_path: Path) -> int:
    import asyncio

    from master.config import MasterConfig
    from master.service import MasterService

    window = os.environ.get("V2XPOS_SOAK_LATENCY_WINDOW")
    if window:  # diagnosis only: size of the pipeline's latency percentile windows
        import master.pipeline
        master.pipeline.LATENCY_WINDOW = int(window)
    doc = json.loads(cfg_path.read_text())
    if record is not None:
        doc.setdefault("record", {}).update({"mcap": str(record), "mcap_max_mb": 64})
    doc["source"]["start_file"] = str(start_file)   # start stamp from the handshake (sim.source.ScenarioClock)
    cfg = MasterConfig.from_dict(doc, str(cfg_path))
    svc = MasterService(cfg)
    samples: list[tuple[float, int]] = []
    stop = threading.Event()

    progress = stats_path.with_suffix(".progress")

    trace = bool(os.environ.get("V2XPOS_SOAK_TRACEMALLOC"))
    snaps = []
    if trace:
        import tracemalloc
        tracemalloc.start()

    t_run0 = time.time()

    def sample() -> None:
        while not stop.wait(0.5):
            samples.append((time.time(), rss_bytes()))
            if trace and len(snaps) < 2 and svc.phase == "run" and time.time() > t_run0 + (5.0 if not snaps else 15.0):
                snaps.append(tracemalloc.take_snapshot())
            pipe = svc.pipeline
            if pipe is not None:
                handled = sum(t.accepted for t in list(pipe.tracks.values())) + sum(pipe.rejected.values())
                progress.write_text(f"{time.time()!r} {handled}")
    th = threading.Thread(target=sample, daemon=True)
    th.start()
    prof_path = os.environ.get("V2XPOS_SOAK_PROFILE")
    if prof_path:
        import cProfile
        prof = cProfile.Profile()
        final = prof.runcall(asyncio.run, svc.run())
        prof.dump_stats(prof_path)
    else:
        final = asyncio.run(svc.run())
    stop.set()
    th.join()
    final["recorded"] = dict(svc.recorder.recorded) if svc.recorder is not None else {}
    final["mcap_files"] = [str(p) for p in svc.recorder.files] if svc.recorder is not None else []
    final["rss_samples"] = samples
    final.setdefault("clock_skew", [])
    if len(snaps) == 2:
        final["tracemalloc_top"] = [str(d) for d in snaps[1].compare_to(snaps[0], "lineno")[:15]]
    stats_path.write_text(json.dumps(final))
    return 0


# ----------------------------------------------------------------------------- slave role

def _run_slaves(ids: list[str], keys_dir: Path | None, endpoint: str, start_file: Path, ready_id: str,
                duration: float, rate: float, out_path: Path, extra_json5: dict | None = None) -> int:
    import numpy as np

    from sim.scenarios import DEFAULT_EPOCH_GPS_S
    from v2xpos.link import Link, LinkConfig
    from v2xpos.security import MessageSigner
    from v2xpos.types import FixStatus
    from v2xpos.wire import Geometry, StateMessage, encode_state, state_key

    link = Link(LinkConfig(mode="peer", connect=[endpoint], extra_json5=extra_json5 or {}))
    signers = {vid: (MessageSigner.from_file(keys_dir / f"{vid}.key") if keys_dir is not None else None)
               for vid in ids}
    pubs = {vid: link.publisher(state_key(SOAK_FLEET, vid), block=True) for vid in ids}
    from sim.launcher import signal_ready_and_wait
    start = signal_ready_and_wait(start_file, ready_id)
    if start is None:
        link.close()
        print(f"no start stamp in {start_file}", file=sys.stderr)
        return 2
    geom = Geometry.box(3.8, 1.0, 0.9)
    sd = np.full(3, 0.01)
    sent = {vid: 0 for vid in ids}
    period = 1.0 / rate
    n_ticks = int(round(duration * rate))
    late = 0
    for k in range(n_ticks):
        t_wall = start + k * period
        delay = t_wall - time.time()
        if delay > 0:
            time.sleep(delay)
        else:
            late += 1
        for i, vid in enumerate(ids):
            now = time.time()
            t_gps = DEFAULT_EPOCH_GPS_S + (now - start) - 0.002
            along = 20.0 * (now - start)
            msg = StateMessage(
                fleet=SOAK_FLEET, vehicle_id=vid, seq=k, t_gps_s=t_gps, fix=FixStatus.FIXED,
                lat_rad=0.6981317 + (along / 6.4e6), lon_rad=-1.8325957 + 1e-6 * (hash(vid) % 100),
                height_m=1600.0, v_ned_mps=np.array([20.0, 0.0, 0.0]), acc_body_mps2=np.zeros(3),
                rate_body_rps=np.zeros(3), rpy_rad=np.zeros(3), pos_sd_m=sd, vel_sd_mps=sd,
                att_sd_rad=sd * 0.1, geometry=geom, t_sent_wall_s=now)
            pubs[vid].put(encode_state(msg, sign=signers[vid]))
            sent[vid] += 1
    end = time.time()
    out_path.write_text(json.dumps({"sent": sent, "late_ticks": late, "ticks": n_ticks, "end_unix_s": end}))
    # closing the session would drop what is still queued for sending: wait for the release file,
    # which the orchestrator writes once the master has received and worked off everything
    release = out_path.parent / "release"
    t_give_up = time.time() + 300.0
    while not release.exists() and time.time() < t_give_up:
        time.sleep(0.1)
    link.close()
    return 0


# ----------------------------------------------------------------------------- orchestration

def _wait_drained(progress: Path, quiet_s: float, max_wait_s: float) -> None:
    """Wait until the master's handled-message count has not changed for ``quiet_s`` (its
    backlog is processed), at most ``max_wait_s``."""
    t_end = time.time() + max_wait_s
    last, t_change = None, time.time()
    while time.time() < t_end:
        try:
            count = progress.read_text().split()[1]
        except (OSError, IndexError):
            count = None
        if count != last:
            last, t_change = count, time.time()
        elif time.time() - t_change >= quiet_s:
            return
        time.sleep(0.25)


def run_soak(slaves: int = 32, rate: float = 100.0, duration: float = 60.0, out_dir: str | Path = "out/soak",
             per_process: int = 8, warmup_fraction: float = 0.1, progress: bool = True,
             lead_s: float = 4.0, drain_s: float = 1.5, record: bool = True, signed: bool = True,
             block_wait_s: float | None = None) -> dict:
    """Run the soak (see module docstring) and return the report dict.

    ``block_wait_s``: zenoh ``congestion_control/block/wait_before_close`` for every session
    (default: zenoh's 5 s) -- how long a blocked send queue waits before the link is closed."""
    extra = {} if block_wait_s is None else {
        "transport/link/tx/queue/congestion_control/block/wait_before_close": int(block_wait_s * 1e6)}
    from v2xpos.security import TrustList, generate_vehicle_key, load_public_key_file

    out = Path(out_dir).resolve()    # absolute: the master resolves its config's paths against the config's directory
    out.mkdir(parents=True, exist_ok=True)
    keys = out / "keys"
    ids = [f"s{i:02d}" for i in range(slaves)]
    trust = TrustList()
    for vid in ids:
        files = generate_vehicle_key(vid, keys, overwrite=True)
        trust.add(*load_public_key_file(files.public_path))
    trust.save(out / "trust.json")
    for old in [*out.glob("session*.mcap"), *out.glob("slaves_*.json"), out / "release",
                out / "master_stats.json", out / "master_stats.progress"]:
        if old.exists():
            old.unlink()
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = {"service": {"fleet": SOAK_FLEET, "master_id": "ego", "duration_s": duration + 600.0, "status_hz": 1.0,
                       "tick_hz": 2.0},
           "link": {"mode": "router", "listen": [endpoint], "extra_json5": extra},
           "source": {"type": "sim", "factory": "sim.source:from_config", "model": "truth_noise", "scenario": "convoy",
                      "params": {"vehicles": 2, "duration_s": duration + 20.0}},
           "output": {"zenoh": {"enabled": True}},
           "security": {"trust_list": str(out / "trust.json")} if signed else {}}
    (out / "master.json").write_text(json.dumps(cfg))
    start_file = out / "start"
    for old in out.glob("start*"):
        old.unlink()
    py = [sys.executable, "-m", "bench.soak"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    repo = Path(__file__).resolve().parents[1]
    master = subprocess.Popen(py + ["--role", "master", "--config", str(out / "master.json"), "--start-file",
                                    str(start_file), "--stats", str(out / "master_stats.json")]
                              + (["--record", str(out / "session.mcap")] if record else []),
                              cwd=repo, env=env, stdout=subprocess.DEVNULL, stderr=open(out / "master.log", "w"))
    groups = [ids[i:i + per_process] for i in range(0, len(ids), per_process)]
    procs = []
    for g, group in enumerate(groups):
        procs.append(subprocess.Popen(py + ["--role", "slaves", "--ids", ",".join(group)]
                                      + (["--keys", str(keys)] if signed else []) + [
                                            "--endpoint", endpoint, "--start-file", str(start_file),
                                            "--ready-id", f"slaves_{g}", "--duration",
                                            repr(duration), "--rate", repr(rate), "--extra-json5", json.dumps(extra),
                                            "--out", str(out / f"slaves_{g}.json")],
                                      cwd=repo, env=env, stdout=subprocess.DEVNULL,
                                      stderr=open(out / f"slaves_{g}.log", "w")))
    # start handshake (sim.launcher): every process signals ready once its session is open, then
    # all get the same start stamp lead_s ahead (the master declares its subscriber meanwhile)
    from sim.launcher import release_when_ready
    start = release_when_ready(start_file, ["ego", *[f"slaves_{g}" for g in range(len(groups))]],
                               lead_s=lead_s, timeout_s=180.0)
    # the master runs until every slave has finished (publishers may be slowed down by BLOCK
    # back-pressure) and it has worked off its backlog, then gets SIGTERM
    total = lead_s + duration + 1.0
    with tqdm(total=int(total), disable=not progress, unit="s", desc="soak", file=sys.stderr) as bar:
        t0 = time.time()
        reports = [out / f"slaves_{g}.json" for g in range(len(groups))]
        while (not all(r.exists() or p.poll() is not None for r, p in zip(reports, procs))
               and master.poll() is None and time.time() - t0 < total + 300):
            time.sleep(0.5)
            bar.n = min(int(time.time() - t0), int(total))
            bar.refresh()
    _wait_drained(out / "master_stats.progress", drain_s, max_wait_s=300.0)
    (out / "release").write_text("done")
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
    if master.poll() is None:
        master.send_signal(signal.SIGTERM)
    try:
        master.wait(timeout=60)
    except subprocess.TimeoutExpired:
        master.kill()
    sent = {}
    late = 0
    publish_end = start + duration
    for g in range(len(groups)):
        f = out / f"slaves_{g}.json"
        if f.exists():
            d = json.loads(f.read_text())
            sent.update(d["sent"])
            late += d["late_ticks"]
            publish_end = max(publish_end, d.get("end_unix_s", publish_end))
    stats_file = out / "master_stats.json"
    if not stats_file.exists():
        raise RuntimeError(f"master wrote no stats; see {out / 'master.log'}")
    st = json.loads(stats_file.read_text())
    n_sent = sum(sent.values())
    received = int(st.get("link_received", 0))
    recorded = int(st["recorded"].get("/v2xpos/rx", 0)) if record else None
    samples = [(t, r) for t, r in st["rss_samples"] if start <= t <= publish_end]
    rss0 = rss1 = math.nan
    if samples:
        warm = start + warmup_fraction * duration
        after = [r for t, r in samples if t >= warm] or [samples[-1][1]]
        q = max(1, len(after) // 4)
        rss0, rss1 = statistics.median(after[:q]), statistics.median(after[-q:])
    results = st.get("targets", {})
    outputs_from_messages = sum(t.get("accepted", 0) for t in results.values())
    report = {
        "slaves": slaves, "rate_hz": rate, "duration_s": duration, "block_wait_s": block_wait_s,
        "sent": n_sent, "received": received, "recorded": recorded,
        "output": outputs_from_messages, "outputs_total": int(st.get("processed", 0)),
        "lost": n_sent - received, "lost_in_master": None if recorded is None else received - recorded,
        "signed": signed, "recorded_to_mcap": record,
        "rss_growth_pct": (rss1 - rss0) / rss0 * 100.0 if samples else None,
        "rss_start_mb": rss0 / 2 ** 20 if samples else None, "rss_end_mb": rss1 / 2 ** 20 if samples else None,
        "achieved_rate_hz": n_sent / max(1, slaves) / max(duration, publish_end - start),
        "publish_time_s": publish_end - start, "late_publish_ticks": late,
        "rejected": st.get("rejected", {}), "pipeline_ms_p50": st.get("pipeline_ms_p50"),
        "pipeline_ms_p99": st.get("pipeline_ms_p99"), "e2e_ms_p99": st.get("e2e_ms_p99"),
        "mcap_files": st.get("mcap_files", []),
        "skewed_senders": [s["vehicle_id"] for s in st.get("clock_skew", []) if s.get("skewed")],
    }
    (out / "soak_report.json").write_text(json.dumps(report, indent=1))
    return report


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--slaves", type=int, default=32)
    parser.add_argument("--rate", type=float, default=100.0, help="messages per second per slave")
    parser.add_argument("--duration", type=float, default=60.0, help="publishing time [s]")
    parser.add_argument("--per-process", type=int, default=8, help="slaves per OS process")
    parser.add_argument("--out", default="out/soak", help="directory for keys, recording, logs, report")
    parser.add_argument("--json", help="also write the report here")
    parser.add_argument("--block-wait-s", type=float, default=None,
                        help="zenoh block/wait_before_close for all sessions [s] (default zenoh's 5 s)")
    parser.add_argument("--no-record", action="store_true", help="diagnosis: master without the MCAP recorder")
    parser.add_argument("--unsigned", action="store_true", help="diagnosis: slaves do not sign, no trust list")
    parser.add_argument("--verify-replay", action="store_true",
                        help="afterwards replay the MCAP recording and check the outputs are identical")


def run_bench(args: argparse.Namespace) -> int:
    report = run_soak(args.slaves, args.rate, args.duration, args.out, args.per_process,
                      record=not args.no_record, signed=not args.unsigned, block_wait_s=args.block_wait_s)
    if args.verify_replay and not args.no_record:
        from master.replay_session import replay_session
        rep = replay_session(Path(args.out) / "session.mcap", progress=True)
        report["replay_identical"] = rep.identical
        report["replay_matched"] = rep.matched
    print(json.dumps(report, indent=1))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1))
    ok = report["lost"] == 0 and (args.no_record or report["sent"] == report["recorded"])
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    """Internal entry for the soak's child processes (``python -m bench.soak --role ...``)."""
    p = argparse.ArgumentParser(prog="python -m bench.soak")
    p.add_argument("--role", choices=("master", "slaves"), required=True)
    p.add_argument("--config")
    p.add_argument("--start-file", required=True)
    p.add_argument("--ready-id", default="slaves")
    p.add_argument("--record")
    p.add_argument("--stats")
    p.add_argument("--ids")
    p.add_argument("--keys")
    p.add_argument("--endpoint")
    p.add_argument("--duration", type=float)
    p.add_argument("--rate", type=float)
    p.add_argument("--out")
    p.add_argument("--extra-json5", default="{}")
    a = p.parse_args(argv)
    if a.role == "master":
        return _run_master(Path(a.config), Path(a.start_file), Path(a.record) if a.record else None,
                           Path(a.stats))
    return _run_slaves(a.ids.split(","), Path(a.keys) if a.keys else None, a.endpoint, Path(a.start_file),
                       a.ready_id, a.duration, a.rate, Path(a.out), json.loads(a.extra_json5))


if __name__ == "__main__":
    sys.exit(main())
