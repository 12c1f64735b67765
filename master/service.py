"""``v2xpos master --config FILE``: the hunter vehicle. Runs its own navigation filter, receives every
slave's StateMessage over zenoh and runs ``master.pipeline.MasterPipeline`` on each, writing CAN,
UDP and zenoh outputs.

Threads: the zenoh callback threads (messages, with ``dispatch = "inline"``) and one asyncio loop
with these tasks; shared state is guarded by ``MasterService.lock``:

* ``nav``: every 10 ms advance the own source to the current scenario GPS time
  (``epoch + wall - start``) and keep the latest NavState (time t_m);
* ``consume`` (``dispatch = "asyncio"``): await the next sample, then drain the queue, running the
  pipeline on each; with ``dispatch = "inline"`` (default) the pipeline runs on the zenoh callback
  thread instead, under a lock shared with ``tick`` and ``status``;
* ``tick``: ``tick_hz`` status-only results for silent targets (NO_DATA / TIMEOUT);
* scene: at ``scene_hz`` the nav task evaluates the GeoJSON scene (V2L lane lines, points,
  polygons) for the master state and sends it (``MasterPipeline.process_scene``);
* IMU grading (``[grading] enabled``): a worker process (``master/grading.py``) grades every
  vehicle's IMU units from their ``.../imu`` streams and publishes grades; a vehicle with a failing
  unit gets ``degraded`` results; ``imu_grades`` appear in the status;
* ``status``: ``status_hz`` JSON summary on ``v2xpos/<fleet>/master/<id>/status`` for monitors.

On exit (epoch + duration or SIGTERM/SIGINT) it writes the summary JSON and the per-result rows
(npz, ``master.pipeline.RECORD_FIELDS``) when configured, closes outputs, then the zenoh session.
"""
from __future__ import annotations

import argparse
import asyncio
import gc
import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from master.config import MasterConfig
from master.outputs import CanSink, UdpSink, ZenohSink, summary_provenance
from master.pipeline import RECORD_FIELDS, MasterPipeline, PipelineConfig
from sim.scenarios import build
from slave.config import ConfigError
from slave.source import make_source
from v2xpos.link import Link, grades_key, status_key
from v2xpos.wire import STATE_KEY_ALL, relative_key

WARMUP_S = 1.0
GRADING_NICE = 10
"""CPU priority offset of the IMU grading worker: grading is background analysis (windows of
seconds); it must not preempt the master's real-time pipeline on a shared core."""
REJECT_MASTER_NOT_READY = "master_not_ready"


def apply_realtime_priority(priority: int) -> bool:
    """Put the calling thread under SCHED_RR at ``priority`` (1-99) before the service creates its
    threads and worker processes, which inherit it (Linux sched(7)): other processes on the same
    computer -- in the demo, the simulated vehicles -- can then not preempt the pipeline. Needs
    CAP_SYS_NICE or an rtprio limit; if not granted the master runs at normal priority and says
    so. The kernel keeps 5 % of each period for normal tasks (sched_rt_runtime_us)."""
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
        return True
    except (AttributeError, OSError) as exc:
        print(f"master: realtime_priority {priority} not granted ({exc}); running at normal priority",
              file=sys.stderr)
        return False


def _background_priority() -> None:
    """preexec_fn of background workers (IMU grading): normal scheduling, nice GRADING_NICE."""
    if hasattr(os, "sched_setscheduler") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.nice(GRADING_NICE)


class MasterService:
    """Composition of source, link, pipeline and sinks (constructed from a MasterConfig)."""

    def __init__(self, cfg: MasterConfig, start_unix_s: float | None = None, start_file: str | None = None):
        self.cfg = cfg
        self.start_file = start_file
        start = float(cfg.source.start_unix_s if start_unix_s is None else start_unix_s)
        self.start = start if start > 0 else time.time() + WARMUP_S
        try:
            self.sc = build(cfg.source.scenario, **cfg.source.params)
        except ValueError as exc:  # unknown scenario or parameter (did you mean)
            raise ConfigError(f"{cfg.path}: [source.params]: {exc}") from None
        actor_id = cfg.source.actor or cfg.master_id
        if actor_id not in self.sc.actors:
            raise ConfigError(f"{cfg.path}: [source].actor {actor_id!r} not in scenario actors {sorted(self.sc.actors)}")
        self.actor = self.sc.actors[actor_id]
        try:
            self.source = make_source(cfg.source.type, self.sc, self.actor, cfg.source.dataset,
                                      cfg.source.align_to_epoch)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{cfg.path}: [source]: {exc}") from None
        from v2xpos.security import TrustList, load_trust_list
        try:
            self.trust = load_trust_list(cfg.trust_list) if cfg.trust_list else TrustList()
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{cfg.path}: [security].trust_list: {exc}") from None
        self.epoch = self.sc.epoch_gps_s
        self.scene = None
        if cfg.geojson:
            from v2xpos.scene import Scene, SceneError
            try:
                self.scene = Scene.load(cfg.geojson)
            except (SceneError, OSError) as exc:
                raise ConfigError(f"{cfg.path}: [scene].geojson: {exc}") from None
        self.end_gps = self.epoch + cfg.duration_s if cfg.duration_s is not None else math.inf
        self.nav = None
        self.nav_steps = 0
        self.nav_ms: list[float] = []
        self.stop_event: asyncio.Event | None = None
        self.link: Link | None = None
        self.sinks: list = []
        self.pipeline: MasterPipeline | None = None
        self.grading_proc = None
        self.lock = threading.Lock()
        self.closing = False
        self._next_scene_t = -math.inf
        self.realtime = False

    def gps_now(self) -> float:
        return self.epoch + (time.time() - self.start)

    def _open(self) -> None:
        cfg = self.cfg
        self.link = Link(cfg.link)
        if cfg.can_enabled:
            self.can = CanSink.from_config(cfg)
            self.sinks.append(self.can)
        if cfg.udp_enabled:
            self.udp = UdpSink.from_config(cfg)
            self.sinks.append(self.udp)
        if cfg.zenoh_enabled:
            self.sinks.append(ZenohSink(self.link.publisher(relative_key(cfg.fleet, cfg.master_id), express=False)))
        from v2xpos.security import MessageAuthenticator
        auth = MessageAuthenticator(self.trust, require_signature=cfg.require_signature and bool(cfg.trust_list),
                                    max_age_s=cfg.max_age_s, future_tolerance_s=cfg.future_tolerance_s,
                                    replay_window=cfg.replay_window)
        self.authenticator = auth
        pcfg = PipelineConfig(fleet=cfg.fleet, master_id=cfg.master_id, timeout_s=cfg.timeout_ms / 1e3,
                              measurement_point_m=cfg.measurement_point_m, known_vehicles=cfg.known_vehicles,
                              evaluate_uncompensated=cfg.evaluate_uncompensated,
                              record=cfg.results_npz is not None)
        self.pipeline = MasterPipeline(pcfg, self.sinks, authenticator=auth)
        self.pipeline.warm_up()
        self.recorder = None
        if cfg.mcap:
            from v2xpos.output.recorder import RecordingPipeline
            from v2xpos.output.recorder_process import RecorderProcess
            Path(cfg.mcap).parent.mkdir(parents=True, exist_ok=True)
            self.recorder = RecorderProcess(cfg.mcap, max_bytes=int(cfg.mcap_max_mb * 2 ** 20))
            self.pipeline = RecordingPipeline(self.pipeline, self.recorder)
        self.status_pub = self.link.publisher(status_key(cfg.fleet, cfg.master_id), express=False)
        self.imu_grades: dict = {}
        if cfg.grading:
            self.link.subscribe(grades_key(cfg.fleet, cfg.master_id), self._on_grades)

    def _start_grading(self) -> None:
        """Start the IMU grading worker process (master/grading.py, a zenoh client of this master's
        network; it waits for the router) -- early, so its imports overlap the preparation. The
        master follows its grades (``_on_grades``): a vehicle with a failing unit gets ``degraded``."""
        import os
        import subprocess
        cfg = self.cfg
        endpoint = (cfg.link.listen or cfg.link.connect)[0]
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.grading_proc = subprocess.Popen(
            [sys.executable, "-m", "master.grading", "--endpoint", endpoint, "--fleet", cfg.fleet,
             "--master-id", cfg.master_id], env=env, cwd=root, preexec_fn=_background_priority)

    def _on_grades(self, payload: bytes, key: str, att, t_arr: float) -> None:
        try:
            doc = json.loads(payload)
            vehicles = doc["vehicles"]
        except (ValueError, KeyError, TypeError):
            return
        with self.lock:
            self.imu_grades = vehicles
            for vid, g in vehicles.items():
                units = g.get("units") or {}
                if any(v == "fail" for v in units.values()):
                    self.pipeline.degraded_vehicles.add(vid)
                else:
                    self.pipeline.degraded_vehicles.discard(vid)

    async def _nav_task(self) -> None:
        while not self.stop_event.is_set():
            t = self.gps_now()
            if t >= self.epoch - WARMUP_S:
                t0 = time.perf_counter()
                states = self.source.advance(t)
                if states:
                    self.nav = states[-1]
                    self.nav_steps += len(states)
                    self.nav_ms.append((time.perf_counter() - t0) * 1e3 / len(states))
                    if self.scene is not None and self.nav.t_s >= self._next_scene_t:
                        self._next_scene_t = self.nav.t_s + 1.0 / self.cfg.scene_hz
                        with self.lock:
                            self.pipeline.process_scene(self.scene, self.nav)
            if t > self.end_gps:
                self.stop_event.set()
                return
            await asyncio.sleep(max(0.0, 0.01 - (self.gps_now() % 0.01)))

    async def _consume_task(self, sub) -> None:
        pipe = self.pipeline
        while not self.stop_event.is_set():
            first = await sub.get()
            for item in [first, *sub.drain()]:
                if self.nav is None:
                    pipe.rejected[REJECT_MASTER_NOT_READY] += 1
                    continue
                pipe.handle(item.payload, item.key, self.nav, self.gps_now(), item.t_arrival_wall_s)

    async def _tick_task(self) -> None:
        period = 1.0 / self.cfg.tick_hz
        while not self.stop_event.is_set():
            await asyncio.sleep(period)
            if self.nav is not None:
                with self.lock:
                    self.pipeline.tick(self.gps_now(), float(self.nav.t_s))

    def status(self, window: int | None = 2000) -> dict:
        """Summary for monitors; percentiles over the last ``window`` messages (None = all)."""
        s = self.pipeline.summary(window)
        s.update({"master_id": self.cfg.master_id, "t_gps_s": self.gps_now(), "t_rel_s": self.gps_now() - self.epoch,
                  "master_fix": None if self.nav is None else int(self.nav.fix), "nav_steps": self.nav_steps,
                  "nav_ms_p50": float(np.percentile(self.nav_ms, 50)) if self.nav_ms else None,
                  "can_frames": self.can.frames if self.cfg.can_enabled else 0,
                  "udp_datagrams": self.udp.datagrams if self.cfg.udp_enabled else 0,
                  "source": self.source.name, "imu_grades": self.imu_grades,
                  "degraded_vehicles": sorted(self.pipeline.degraded_vehicles),
                  "clock_skew": self.authenticator.skew_report(),
                  "admission": self.authenticator.stats.as_dict()})
        return s

    async def _status_task(self) -> None:
        period = 1.0 / self.cfg.status_hz
        while not self.stop_event.is_set():
            await asyncio.sleep(period)
            with self.lock:
                st = self.status()
            self.status_pub.put(json.dumps(st).encode())

    async def run(self) -> dict:
        self.stop_event = asyncio.Event()
        self.realtime = apply_realtime_priority(self.cfg.realtime_priority)
        if self.cfg.grading:
            self._start_grading()
        self.source.warm_up()
        history = self.source.advance(self.epoch - WARMUP_S - 0.5)   # driving history before the run
        if history:
            self.nav = history[-1]
        self._open()
        if self.start_file is not None:
            from sim.launcher import signal_ready_and_wait
            got = await asyncio.to_thread(signal_ready_and_wait, self.start_file, self.cfg.master_id)
            if got is None:
                self.link.close()
                raise ConfigError(f"no start stamp in {self.start_file} (timeout)")
            self.start = got
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                loop.add_signal_handler(sig, self.stop_event.set)
            except (NotImplementedError, RuntimeError):  # not the main thread (tests)
                pass
        if self.cfg.dispatch == "inline":
            verifier = None
            if len(self.trust) > 0:
                from v2xpos.verify_worker import VerifierProcess
                verifier = VerifierProcess(self.trust.to_json())
            sub = _InlineDispatch(self, verifier)
            sub.subscribe(self.link, STATE_KEY_ALL(self.cfg.fleet))
        else:
            sub = self.link.subscribe_async(STATE_KEY_ALL(self.cfg.fleet), loop)
        gc.collect()
        gc.freeze()                       # long-lived setup objects leave the collector's scans
        gc.set_threshold(50_000, 50, 100)  # fewer young-generation pauses in the message path
        coros = [self._nav_task(), self._tick_task(), self._status_task()]
        if self.cfg.dispatch != "inline":
            coros.append(self._consume_task(sub))
        tasks = [asyncio.create_task(c) for c in coros]
        try:
            await self.stop_event.wait()
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            if self.cfg.dispatch != "inline" and self.nav is not None:
                for item in sub.drain():          # nothing received is left unprocessed
                    self.pipeline.handle(item.payload, item.key, self.nav, self.gps_now(), item.t_arrival_wall_s)
            with self.lock:
                self.closing = True
                final = self.status(window=None)
            final["link_received"] = sub.received
            if isinstance(sub, _InlineDispatch) and sub.received:
                final["handler_cpu_ms_per_message"] = sub.cpu_s / sub.received * 1e3
                final["dispatch_batches"] = sub.batches
            final["dispatch"] = self.cfg.dispatch
            final["realtime_priority"] = self.cfg.realtime_priority if self.realtime else 0
            self._write_outputs(final)
            for s in self.sinks:
                s.close()
            if self.recorder is not None:
                self.recorder.close()
            if self.grading_proc is not None:
                self.grading_proc.terminate()
                try:
                    self.grading_proc.wait(timeout=5)
                except Exception:
                    self.grading_proc.kill()
            self.link.close()
            if isinstance(sub, _InlineDispatch):
                sub.close_verifier()
        return final

    def _write_outputs(self, final: dict) -> None:
        cfg = self.cfg
        if cfg.results_npz:
            Path(cfg.results_npz).parent.mkdir(parents=True, exist_ok=True)
            arrays = {f"target_{vid}": a for vid, a in self.pipeline.records_arrays().items()}
            if self.pipeline.scene_records and len({len(r) for r in self.pipeline.scene_records}) == 1:
                arrays["scene"] = np.asarray(self.pipeline.scene_records, dtype=float)
            np.savez_compressed(cfg.results_npz, fields=np.array(RECORD_FIELDS), **arrays)
        if cfg.summary_json:
            Path(cfg.summary_json).parent.mkdir(parents=True, exist_ok=True)
            final["provenance"] = summary_provenance(cfg)
            Path(cfg.summary_json).write_text(json.dumps(final, indent=1))


BATCH_WINDOW_MAX_S = float(os.environ.get("V2XPOS_BATCH_WINDOW_MAX_S", "0"))
BATCH_WINDOW_MIN_S = min(0.00025, BATCH_WINDOW_MAX_S)
BATCH_WINDOW_PER_MSG_PER_S = BATCH_WINDOW_MAX_S / 6400.0
"""Optional batching wait: after the first sample of a batch arrives the dispatch thread waits a
window growing with the received rate (BATCH_WINDOW_MIN_S .. BATCH_WINDOW_MAX_S at 6,400
messages/s), then takes everything queued (up to MAX_BATCH). Default 0: no wait, a batch is what
queued while the previous one was processed. Bigger batches cost less CPU per message (a message
handled alone after a pause costs ~0.29 ms of CPU on the shared 2-core machine, one right after
another ~0.08 ms), but in `v2xpos bench fanin` every waiting window (0.5 / 2 ms) gave worse e2e
p99 than none: each wait is one more chance to lose the core. V2XPOS_BATCH_WINDOW_MAX_S sets it
for such comparisons."""
RATE_WINDOW_S = 0.5
MAX_BATCH = 128
"""Most messages per lock hold (~10 ms of work); a full batch means a backlog: the next batch is
taken at once, without the window."""
FIFO_CAPACITY = 65536


class _InlineDispatch:
    """Pipeline on a dedicated dispatch thread that drains the zenoh subscriber's FIFO channel in
    batches (everything queued, up to MAX_BATCH; optional wait ``BATCH_WINDOW_MAX_S``): no
    per-sample zenoh-python callback thread hand-over, no asyncio hop; ``MasterService.lock``
    serialises it with the loop's tick and status tasks. Every sample of a batch is stamped with
    the batch's wake-up time as its arrival, so the reported pipeline time includes any wait
    behind earlier samples of the same batch (not the time queued before the wake-up).

    With a trust list (signed slaves) the Ed25519 verification of each envelope, about half of a
    message's cost, runs in a worker process (``v2xpos.verify_worker``): the thread sends batch k
    to the worker, then handles batch k-1 with its verdicts while the worker verifies batch k; when
    nothing else is queued it waits for batch k's verdicts at once (no added latency at low rates)."""

    def __init__(self, svc: MasterService, verifier=None):
        self.svc = svc
        self.verifier = verifier
        self.received = 0
        self.batches = 0
        self.cpu_s = 0.0
        self._sub = None
        self._thread: threading.Thread | None = None
        self._window_s = BATCH_WINDOW_MIN_S      # batching wait, follows the received rate
        self._t_rate0, self._n_rate = time.time(), 0
        self._backlog = False                    # the last batch was full

    def subscribe(self, link: Link, key: str):
        """Declare the state subscriber on ``link`` and start the dispatch thread (it ends when the
        link's session closes)."""
        import zenoh
        self._sub = link.session.declare_subscriber(key, zenoh.handlers.FifoChannel(FIFO_CAPACITY))
        self._thread = threading.Thread(target=self._run, name="v2xpos-dispatch", daemon=True)
        self._thread.start()
        return self._sub

    def close_verifier(self, timeout_s: float = 2.0) -> None:
        """After the link closed: let the dispatch thread finish its last batch, then end the
        verify worker (closing it under a thread still reading its verdicts would be reported
        as a worker failure)."""
        if self._thread is not None:
            self._thread.join(timeout_s)
        if self.verifier is not None:
            self.verifier.close()

    def _next_batch(self, block: bool) -> tuple[list, float] | None:
        """([(payload, key), ...], wake-up wall time [s]) of everything queued (up to MAX_BATCH);
        None when not ``block`` and nothing is queued. Raises EOFError when the session closed."""
        sub = self._sub
        try:
            first = sub.recv() if block else sub.try_recv()
        except Exception:   # the session closed (zenoh raises its own error type)
            raise EOFError from None
        if first is None:
            return None
        t_arr = time.time()
        if t_arr - self._t_rate0 >= RATE_WINDOW_S:
            rate = self._n_rate / (t_arr - self._t_rate0)
            self._window_s = min(BATCH_WINDOW_MAX_S, max(BATCH_WINDOW_MIN_S, rate * BATCH_WINDOW_PER_MSG_PER_S))
            self._t_rate0, self._n_rate = t_arr, 0
        if self._window_s > 0.0 and not self._backlog:
            time.sleep(self._window_s)
        batch = [first]
        while len(batch) < MAX_BATCH:
            try:
                sample = sub.try_recv()
            except Exception:
                break
            if sample is None:
                break
            batch.append(sample)
        self._n_rate += len(batch)
        self._backlog = len(batch) >= MAX_BATCH
        return [(s.payload.to_bytes(), str(s.key_expr)) for s in batch], t_arr

    def _run(self) -> None:
        verifier = self.verifier
        pending = None          # batch sent to the verifier, verdicts not read yet
        while True:
            try:
                batch = self._next_batch(block=pending is None)
            except EOFError:
                batch = None
                if pending is None:
                    return
            if verifier is None:
                items, t_arr = batch
                self.on_batch([(payload, key, None) for payload, key in items], t_arr)
                continue
            if batch is not None:
                verifier.submit([payload for payload, _ in batch[0]])
            if pending is not None:
                items, t_arr = pending
                self.on_batch([(payload, key, ok) for (payload, key), ok in zip(items, verifier.collect())], t_arr)
            pending = batch

    def on_batch(self, items: list, t_arrival_wall_s: float) -> None:
        """Run (payload, key, signature_valid) triples through the pipeline under the service lock."""
        svc = self.svc
        c0 = time.thread_time()
        with svc.lock:
            self.received += len(items)
            self.batches += 1
            if svc.closing:
                return
            pipe = svc.pipeline
            with pipe.batch():
                for payload, key, signature_valid in items:
                    if svc.nav is None:
                        pipe.rejected[REJECT_MASTER_NOT_READY] += 1
                        continue
                    pipe.handle(payload, key, svc.nav, svc.gps_now(), t_arrival_wall_s, signature_valid)
        self.cpu_s += time.thread_time() - c0

    def on_sample(self, payload: bytes, key: str, attachment: bytes | None, t_arrival_wall_s: float) -> None:
        """One sample (``Link.subscribe`` callback signature)."""
        self.on_batch([(payload, key, None)], t_arrival_wall_s)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="master TOML file (see configs/master.toml)")
    parser.add_argument("--start", type=float, default=None,
                        help="wall time (Unix s) of the scenario epoch, shared by all processes")
    parser.add_argument("--start-file", default=None,
                        help="start handshake: signal <file>.ready.<id>, then read the start stamp from <file>")


def run(args: argparse.Namespace) -> int:
    try:
        cfg = MasterConfig.load(args.config)
        svc = MasterService(cfg, args.start, args.start_file)
        final = asyncio.run(svc.run())
    except ConfigError as exc:
        print(f"v2xpos master: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: final[k] for k in ("processed", "rejected", "pipeline_ms_p99", "e2e_ms_p99",
                                             "can_frames", "udp_datagrams")}), flush=True)
    return 0
