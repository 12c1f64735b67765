"""``v2xpos master --config FILE``: the hunter vehicle. Runs its own navigation filter, receives every
slave's StateMessage over zenoh and runs ``master.pipeline.MasterPipeline`` on each, writing CAN,
UDP and zenoh outputs.

Threads: the zenoh callback threads (messages, with ``dispatch = "inline"``) and one asyncio loop
with these tasks; shared state is guarded by ``MasterService.lock``:

* ``nav``: every 10 ms advance the own source (``[source]``: a recording, live devices, or the
  simulator's plugin, built by ``v2xpos.sources.make_source``) to the session time of its clock
  (``source.make_clock``: a recording's own GPS time, GPS time from the host clock, or a
  scenario clock) and keep the latest NavState (time t_m);
* ``consume`` (``dispatch = "asyncio"``): await the next sample, then drain the queue, running the
  pipeline on each; with ``dispatch = "inline"`` (default) a dispatch thread runs the pipeline on
  batches instead (``master.dispatch``), under a lock shared with ``tick`` and ``status``;
* ``tick``: ``tick_hz`` status-only results for silent targets (NO_DATA / TIMEOUT);
* scene: at ``scene_hz`` the nav task evaluates the GeoJSON scene (V2L lane lines, points,
  polygons) for the master state and sends it (``MasterPipeline.process_scene``);
* IMU grading (``[grading] enabled``): a worker process (``master/grading.py``) grades every
  vehicle's IMU units from their ``.../imu`` streams and publishes grades; a vehicle with a failing
  unit gets ``degraded`` results; ``imu_grades`` appear in the status;
* ``status``: ``status_hz`` JSON summary on ``v2xpos/<fleet>/master/<id>/status`` for monitors.

Start-up phases: build the source, warm it up (in a thread), open the zenoh link (the master
embeds the router), start the session clock (a recording master waits for the slaves named in
``wait_for`` and then leads the session clock), run. SIGTERM/SIGINT end any phase within about
half a second. On exit (clock start + ``duration_s``, the end of the source, or a signal) it
writes the summary JSON, the per-result rows (npz, ``master.pipeline.RECORD_FIELDS``) and closes
``results.csv`` when configured, closes outputs, then the zenoh session.
"""
from __future__ import annotations

import argparse
import asyncio
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
from master.dispatch import InlineDispatch, StartupHold
from master.outputs import OutputContext, make_output, master_status, summary_provenance
from master.pipeline import RECORD_FIELDS, MasterPipeline, PipelineConfig
from v2xpos.config import ConfigError, config_dir
from v2xpos.launch import apply_realtime_priority, freeze_setup_heap
from v2xpos.link import Link, LinkUnavailable
from v2xpos.sources import SourceContext, SourceError, make_source
from v2xpos.wire import STATE_KEY_ALL, alive_key, grades_key, status_key

GRADING_NICE = 10
"""CPU priority offset of the IMU grading worker: grading is background analysis (windows of
seconds); it must not preempt the master's real-time pipeline on a shared core."""
FINAL_GRADES_TIMEOUT_S = 10.0
"""Longest wait at shutdown for the grading worker's final grades (a starved, niced worker may need
seconds to finish the regrade in hand)."""
NAV_TICK_S = 0.01
EXIT_INTERRUPTED = 130
"""Exit code of a service stopped by a signal (README: exit codes)."""
"""The own source is advanced every 10 ms of session time."""


def _background_priority() -> None:
    """preexec_fn of background workers (IMU grading): normal scheduling, nice GRADING_NICE."""
    if hasattr(os, "sched_setscheduler") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.nice(GRADING_NICE)


class MasterService:
    """Composition of source, link, pipeline and sinks (constructed from a MasterConfig)."""

    def __init__(self, cfg: MasterConfig):
        self.cfg = cfg
        self.ctx = SourceContext(vehicle_id=cfg.service.master_id, fleet=cfg.service.fleet, role="master",
                                 config_dir=config_dir(cfg.path), stop=self._stopping,
                                 filter_overrides={"integrity": dict(cfg.validity.filter_integrity)})
        self.source = None
        from v2xpos.security import TrustList, load_trust_list
        try:
            self.trust = load_trust_list(cfg.security.trust_list) if cfg.security.trust_list else TrustList()
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{cfg.path}: [security].trust_list: {exc}") from None
        self.scene = None
        if cfg.scene.geojson:
            from v2xpos.scene import Scene, SceneError
            try:
                self.scene = Scene.load(cfg.scene.geojson)
            except (SceneError, OSError) as exc:
                raise ConfigError(f"{cfg.path}: [scene].geojson: {exc}") from None
        self.clock = None
        self.t_start_gps_s = math.nan
        self.end_gps = math.inf
        self.nav = None
        self.startup = StartupHold()
        self.nav_steps = 0
        self.nav_ms: list[float] = []
        self.stop_event: asyncio.Event | None = None
        self.link: Link | None = None
        self.relay = None
        self.sinks: list = []
        self.pipeline: MasterPipeline | None = None
        self.grading_proc = None
        self.recorder = None
        self.lock = threading.Lock()
        self.closing = False
        self._next_scene_t = -math.inf
        self.realtime = False
        self.phase = "init"
        self._closed = False
        self.signalled = False
        self.quiet = False
        from v2xpos.sources.status import VehicleStatus
        self.vehicle_status = VehicleStatus("master", cfg.service.master_id, cfg.service.fleet)

    def _on_signal(self) -> None:
        self.signalled = True
        self.stop_event.set()

    def _stopping(self) -> bool:
        return self.stop_event is not None and self.stop_event.is_set()

    def gps_now(self) -> float:
        return self.clock.now_gps_s()

    def _open(self) -> None:
        cfg = self.cfg
        try:
            self.link = Link(cfg.link)
        except LinkUnavailable as exc:
            raise ConfigError(f"{cfg.path}: [link]: {exc}") from None
        self.ctx.link = self.link
        octx = OutputContext(cfg, self.link)
        for name, table in cfg.enabled_outputs():
            sink = make_output(name, table, f"{cfg.path}: [output.{name}]", octx)
            self.sinks.append(sink)
            if name == "can":
                self.can = sink
            elif name == "udp":
                self.udp = sink
        from v2xpos.security import MessageAuthenticator
        sec, svc, val = cfg.security, cfg.service, cfg.validity
        auth = MessageAuthenticator(self.trust, require_signature=sec.require_signature and bool(sec.trust_list),
                                    max_age_s=sec.max_age_s, future_tolerance_s=sec.future_tolerance_s,
                                    replay_window=sec.replay_window)
        self.authenticator = auth
        pcfg = PipelineConfig(fleet=svc.fleet, master_id=svc.master_id, timeout_s=svc.timeout_ms / 1e3,
                              measurement_point_m=svc.measurement_point_m, known_vehicles=svc.known_vehicles,
                              evaluate_uncompensated=cfg.record.evaluate_uncompensated,
                              record=cfg.record.results_npz is not None, max_sigma_h_m=val.max_sigma_h_m,
                              max_sigma_yaw_deg=val.max_sigma_yaw_deg, require_consistency=val.require_consistency,
                              max_clock_disagreement_s=val.max_clock_disagreement_s)
        self.pipeline = MasterPipeline(pcfg, self.sinks, authenticator=auth)
        self.pipeline.warm_up()
        if cfg.record.mcap:
            from v2xpos.output.recorder import RecordingPipeline
            from v2xpos.output.recorder_process import RecorderProcess
            Path(cfg.record.mcap).parent.mkdir(parents=True, exist_ok=True)
            self.recorder = RecorderProcess(cfg.record.mcap, max_bytes=int(cfg.record.mcap_max_mb * 2 ** 20))
            self.pipeline = RecordingPipeline(self.pipeline, self.recorder)
        self.status_pub = self.link.publisher(status_key(cfg.service.fleet, cfg.service.master_id), express=False)
        self.link.declare_alive(alive_key(cfg.service.fleet, "master", cfg.service.master_id))
        self.imu_grades: dict = {}
        self.imu_grading_counters: dict = {}     # the worker's malformed payloads and failed regrades
        self._final_grades = threading.Event()
        if cfg.grading.enabled:
            self.link.subscribe(grades_key(cfg.service.fleet, cfg.service.master_id), self._on_grades)

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
            [sys.executable, "-m", "master.grading", "--endpoint", endpoint, "--fleet", cfg.service.fleet,
             "--master-id", cfg.service.master_id], env=env, cwd=root, preexec_fn=_background_priority)

    def _on_grades(self, payload: bytes, key: str, att, t_arr: float) -> None:
        try:
            doc = json.loads(payload)
            vehicles = doc["vehicles"]
        except (ValueError, KeyError, TypeError):
            return
        with self.lock:
            self.imu_grades = vehicles
            self.imu_grading_counters = {k: doc.get(k) for k in ("malformed", "grading_errors")}
            if doc.get("final") is True:
                self._final_grades.set()
            for vid, g in vehicles.items():
                units = g.get("units") or {}
                if any(v == "fail" for v in units.values()):
                    self.pipeline.degraded_vehicles.add(vid)
                else:
                    self.pipeline.degraded_vehicles.discard(vid)

    async def _nav_task(self) -> None:
        clock = self.clock
        while not self.stop_event.is_set():
            t = self.gps_now()
            if t > self.end_gps or self.source.finished(t):
                self.stop_event.set()
                return
            t0 = time.perf_counter()
            states = self.source.advance(t)
            if states:
                with self.lock:
                    self.nav = states[-1]
                    self.pipeline.master_time_ok = clock.synchronised()
                self.nav_steps += len(states)
                self.nav_ms.append((time.perf_counter() - t0) * 1e3 / len(states))
                if self.scene is not None and self.nav.t_s >= self._next_scene_t:
                    self._next_scene_t = self.nav.t_s + 1.0 / self.cfg.scene.rate_hz
                    with self.lock:
                        self.pipeline.process_scene(self.scene, self.nav)
            t_next = (math.floor(self.gps_now() / NAV_TICK_S) + 1) * NAV_TICK_S
            await asyncio.sleep(min(max(0.0, clock.wall_of(t_next) - time.time()), 0.25))

    async def _consume_task(self, sub) -> None:
        pipe = self.pipeline
        while not self.stop_event.is_set():
            first = await sub.get()
            for item in [first, *sub.drain()]:
                if self.nav is None:
                    self.startup.hold(pipe, (item.payload, item.key, item.t_arrival_wall_s, None))
                    continue
                for held in self.startup.release():
                    pipe.handle(held[0], held[1], self.nav, self.gps_now(), held[2])
                pipe.handle(item.payload, item.key, self.nav, self.gps_now(), item.t_arrival_wall_s)

    async def _tick_task(self) -> None:
        period = 1.0 / self.cfg.service.tick_hz
        while not self.stop_event.is_set():
            await asyncio.sleep(period)
            if self.nav is not None:
                with self.lock:
                    self.pipeline.tick(self.gps_now(), float(self.nav.t_s), self.nav.fix)

    def status(self, window: int | None = 2000) -> dict:
        """Summary for monitors; percentiles over the last ``window`` messages (None = all). Before
        the session clock runs (a master waiting for its slaves) it says which phase it is in."""
        s = self.pipeline.summary(window)
        clock = self.clock if self.phase == "run" else None
        t_now = self.gps_now() if clock is not None else None
        s.update({"master_id": self.cfg.service.master_id, "t_gps_s": t_now,
                  "t_rel_s": None if t_now is None else t_now - self.t_start_gps_s, "phase": self.phase,
                  "waiting_for": self._waiting_for(), "timeout_s": self.cfg.service.timeout_ms / 1e3,
                  "status_period_s": 1.0 / self.cfg.service.status_hz, "t_wall_s": time.time(),
                  "vehicle": self.vehicle_status.snapshot(
                      self.source, clock, self.nav, None if self.relay is None else {"corrections": self.relay.stats()}),
                  "clock": None if clock is None else clock.status(),
                  "time_synchronised": None if clock is None else clock.synchronised(),
                  "source_status": None if self.source is None else self.source.status(),
                  "corrections": None if self.relay is None else self.relay.stats(),
                  "master_fix": None if self.nav is None else int(self.nav.fix), "nav_steps": self.nav_steps,
                  "nav_ms_p50": float(np.percentile(self.nav_ms, 50)) if self.nav_ms else None,
                  "can_frames": self.can.frames if self.cfg.output.can.enabled else 0,
                  "udp_datagrams": self.udp.datagrams if self.cfg.output.udp.enabled else 0,
                  "source": getattr(self.source, "name", None), "imu_grades": self.imu_grades,
                  "imu_grading": self.imu_grading_counters,
                  "degraded_vehicles": sorted(self.pipeline.degraded_vehicles),
                  "clock_skew": self.authenticator.skew_report(),
                  "admission": self.authenticator.stats.as_dict()})
        return s

    def _waiting_for(self) -> list | None:
        """Vehicles a recording master still waits for before its session clock starts."""
        if self.phase != "clock" or self.clock is None:
            return None
        missing = getattr(self.clock, "missing", None)
        return sorted(missing()) if callable(missing) else None

    async def _can_status_task(self) -> None:
        """MASTER_STATUS / MASTER_SIGMA frames at ``[output.can] status_hz``: the master's own time,
        fix, sigmas, whether its heading is determined and its clock synchronised, its filter's
        reason."""
        period = 1.0 / self.cfg.output.can.status_hz
        clock = self.clock
        while not self.stop_event.is_set():
            await asyncio.sleep(period)
            nav = self.nav
            with self.lock:
                st = master_status(nav, t_gps_s=self.gps_now(),
                                   heading_valid=None if nav is None else bool(nav.attitude_ok),
                                   clock_synced=clock.synchronised(), clock_offset_s=clock.status().get("offset_s"))
                self.can.write_master_status(st)

    async def _udp_heartbeat_task(self) -> None:
        """The UDP heartbeat at ``[output.udp] status_hz`` (``v2xpos.output.udp.heartbeat``): a
        consumer tells a master that is gone from one with nothing to report."""
        period = 1.0 / self.cfg.output.udp.status_hz
        while not self.stop_event.is_set():
            await asyncio.sleep(period)
            with self.lock:
                self.udp.write_heartbeat(self.pipeline.seq, self.gps_now())

    async def _status_task(self) -> None:
        """The status JSON at ``status_hz`` from the moment the link is open (a master still
        waiting for its slaves says so), and a one-line status every few seconds on stderr."""
        from v2xpos.sources.status import STATUS_LINE_PERIOD_S
        period = 1.0 / self.cfg.service.status_hz
        next_line = time.time() + STATUS_LINE_PERIOD_S
        while not self.stop_event.is_set():
            await asyncio.sleep(period)
            with self.lock:
                st = self.status()
            self.status_pub.put(json.dumps(st).encode())
            if not self.quiet and time.time() >= next_line:
                next_line = time.time() + STATUS_LINE_PERIOD_S
                print(master_line(st), file=sys.stderr, flush=True)

    async def _in_thread(self, fn, *args):
        """Run a blocking start-up step on a daemon thread so that a signal can end the wait (the
        thread is abandoned then; a daemon thread does not hold the process at exit)."""
        loop = asyncio.get_running_loop()
        fut = loop.create_future()

        def work() -> None:
            try:
                res = fn(*args)
            except BaseException as exc:  # noqa: BLE001 -- handed to the awaiting task
                loop.call_soon_threadsafe(lambda e=exc: fut.done() or fut.set_exception(e))
            else:
                loop.call_soon_threadsafe(lambda: fut.done() or fut.set_result(res))

        threading.Thread(target=work, name="v2xpos-master-startup", daemon=True).start()
        stop = asyncio.ensure_future(self.stop_event.wait())
        done, _ = await asyncio.wait({fut, stop}, return_when=asyncio.FIRST_COMPLETED)
        if fut in done:
            stop.cancel()
            return fut.result()
        return None

    async def run(self) -> dict:
        self.stop_event = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                loop.add_signal_handler(sig, self._on_signal)
            except (NotImplementedError, RuntimeError):  # not the main thread (tests)
                pass
        self.realtime = apply_realtime_priority(self.cfg.service.realtime_priority, "master")
        if self.cfg.grading.enabled:
            self._start_grading()
        self.phase = "source"
        try:
            self.source = await self._in_thread(make_source, self.cfg.source.table, f"{self.cfg.path}: [source]",
                                                self.ctx)
        except SourceError as exc:
            self._close()
            raise ConfigError(str(exc)) from None
        if self._stopping():
            return self._early_exit()
        self.phase = "warm_up"
        await self._in_thread(self.source.warm_up)
        if self._stopping():
            return self._early_exit()
        self.phase = "link"
        try:
            self._open()
        except ConfigError:
            self._close()
            raise
        status_task = asyncio.create_task(self._status_task())
        if self.cfg.corrections is not None and self.cfg.corrections.source is not None:
            from v2xpos.sources.corrections import CorrectionRelay
            try:
                self.relay = CorrectionRelay(self.cfg.corrections, self.link, self.cfg.service.fleet,
                                             local_write=self.source.write_corrections).start()
            except (OSError, ValueError) as exc:
                self._close()
                raise ConfigError(f"{self.cfg.path}: [corrections]: {exc}") from None
        self.clock = self.source.make_clock(self.ctx)
        self.phase = "clock"
        try:
            started = await self._in_thread(self.clock.start, self._stopping)
        except TimeoutError as exc:
            raise ConfigError(f"{self.cfg.path}: [source]: {exc}") from None
        if not started:
            status_task.cancel()
            return self._early_exit()
        self.phase = "run"
        self.t_start_gps_s = self.clock.session_start_gps_s()
        if self.cfg.service.duration_s is not None:
            self.end_gps = self.t_start_gps_s + self.cfg.service.duration_s
        primed = self.source.prime(self.clock.now_gps_s())
        if primed is not None:
            self.nav = primed
        if self.cfg.service.dispatch == "inline":
            verifier = None
            if len(self.trust) > 0:
                from v2xpos.verify_worker import VerifierProcess
                verifier = VerifierProcess(self.trust.to_json())
            sub = InlineDispatch(self, verifier)
            sub.subscribe(self.link, STATE_KEY_ALL(self.cfg.service.fleet))
        else:
            sub = self.link.subscribe_async(STATE_KEY_ALL(self.cfg.service.fleet), loop)
        freeze_setup_heap()
        coros = [self._nav_task(), self._tick_task()]
        if self.cfg.output.can.enabled and self.cfg.output.can.status_hz > 0:
            coros.append(self._can_status_task())
        if self.cfg.output.udp.enabled and self.cfg.output.udp.status_hz > 0:
            coros.append(self._udp_heartbeat_task())
        if self.cfg.service.dispatch != "inline":
            coros.append(self._consume_task(sub))
        tasks = [status_task] + [asyncio.create_task(c) for c in coros]
        try:
            await self.stop_event.wait()
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            if self.cfg.service.dispatch != "inline" and self.nav is not None:
                for item in sub.drain():          # nothing received is left unprocessed
                    self.pipeline.handle(item.payload, item.key, self.nav, self.gps_now(), item.t_arrival_wall_s)
            grades_final = await asyncio.to_thread(self._collect_final_grades) if self.cfg.grading.enabled else None
            with self.lock:
                self.closing = True
                final = self.status(window=None)
            final["link_received"] = sub.received
            if isinstance(sub, InlineDispatch) and sub.received:
                final["handler_cpu_ms_per_message"] = sub.cpu_s / sub.received * 1e3
                final["dispatch_batches"] = sub.batches
            final["dispatch"] = self.cfg.service.dispatch
            final["imu_grades_final"] = grades_final
            final["realtime_priority"] = self.cfg.service.realtime_priority if self.realtime else 0
            if self.cfg.validity.verification_out is not None and self.source is not None:
                from v2xpos.datasets.verification import write_session_record
                final["verification"], said = write_session_record(self.source, self.cfg.validity.verification_out,
                                                                   f"session of {self.cfg.service.master_id}")
                print(f"master: {said}", file=sys.stderr, flush=True)
            self._write_outputs(final)
            self._close()
            if isinstance(sub, InlineDispatch):
                sub.close_verifier()
        return final

    def _collect_final_grades(self, timeout_s: float = FINAL_GRADES_TIMEOUT_S) -> bool:
        """Stop the grading worker and wait for its final grades (master/grading.py: it publishes
        them once more on SIGTERM), so the report holds the last regrade of the data received. False
        when there is no worker or it did not answer within ``timeout_s`` (the last periodic grades
        then stand, and the report says so with ``imu_grades_final`` false)."""
        proc = self.grading_proc
        if proc is None or proc.poll() is not None:
            return False
        proc.terminate()
        got = self._final_grades.wait(timeout_s)
        if not got:
            print(f"v2xpos master: no final IMU grades from the grading worker within {timeout_s:.0f} s; "
                  "the report keeps its last periodic grades", file=sys.stderr)
        return got

    def _early_exit(self) -> dict:
        """Stopped before the session started: close what is open, report the phase."""
        self._close()
        return {"phase": self.phase, "stopped_early": True, "processed": 0, "rejected": {},
                "pipeline_ms_p99": None, "e2e_ms_p99": None, "can_frames": 0, "udp_datagrams": 0}

    def _close(self) -> None:
        """Close outputs, recorder, grading worker, clock, source and link (once)."""
        if self._closed:
            return
        self._closed = True
        if self.relay is not None:
            self.relay.close()
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
            self.grading_proc = None
        if self.clock is not None:
            self.clock.close()
        if self.source is not None:
            self.source.close()
        if self.link is not None:
            self.link.close()

    def _write_outputs(self, final: dict) -> None:
        cfg = self.cfg
        if cfg.record.results_npz:
            Path(cfg.record.results_npz).parent.mkdir(parents=True, exist_ok=True)
            arrays = {f"target_{vid}": a for vid, a in self.pipeline.records_arrays().items()}
            if self.pipeline.scene_records and len({len(r) for r in self.pipeline.scene_records}) == 1:
                arrays["scene"] = np.asarray(self.pipeline.scene_records, dtype=float)
            np.savez_compressed(cfg.record.results_npz, fields=np.array(RECORD_FIELDS), **arrays)
        if cfg.record.summary_json:
            Path(cfg.record.summary_json).parent.mkdir(parents=True, exist_ok=True)
            final["provenance"] = summary_provenance(cfg)
            Path(cfg.record.summary_json).write_text(json.dumps(final, indent=1))


def master_line(st: dict) -> str:
    """The master's one-line status: its vehicle line, then its targets and their statuses."""
    from v2xpos.sources.status import status_line
    if st.get("phase") != "run":
        waiting = st.get("waiting_for")
        return (f"master {st.get('master_id')}: {st.get('phase')}"
                + (f", waiting for {', '.join(waiting)}" if waiting else ""))
    targets = st.get("targets") or {}
    rows = ", ".join(f"{tid} {t['status'].upper()}" + (f" ({t['reason']})" if t.get("reason") and t["status"] != "valid"
                                                        else "") for tid, t in targets.items())
    return f"{status_line(st['vehicle'])}  processed {st.get('processed', 0)}  targets: {rows or 'none yet'}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="master TOML file (see configs/master.toml)")
    parser.add_argument("--quiet", action="store_true", help="no one-line status every 5 s on stderr")


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:   # not already handled (v2xpos.stop_signals)
        signal.signal(signal.SIGTERM, _interrupt)   # until the service installs its own handlers
    try:
        cfg = MasterConfig.load(args.config)
        svc = MasterService(cfg)
        svc.quiet = bool(getattr(args, "quiet", False))
        final = asyncio.run(svc.run())
    except ConfigError as exc:
        print(f"v2xpos master: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("v2xpos master: stopped before the service started", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)   # asked again while finishing: finish anyway
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    print(json.dumps({k: final[k] for k in ("processed", "rejected", "pipeline_ms_p99", "e2e_ms_p99",
                                             "can_frames", "udp_datagrams")}), flush=True)
    return EXIT_INTERRUPTED if svc.signalled else 0
