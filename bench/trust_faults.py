"""Fault scenarios of the trust bench over a live loopback rig (``bench.live_rig``): slave dropout and
return, slave restart, delay spikes and jitter, reordering and duplicates, clock jump and drift,
GNSS outage and fix downgrades, and the router killed (SIGKILL) and restarted on the same port by a
standalone router process. Each scenario returns a ``FaultResult``: the master keeps running and
every target's status agrees with what it was sent."""
from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from bench.live_rig import DEFAULT_TIMEOUT_S, Delivered, LiveRig, fresh_rig, paced, wait_connected
from v2xpos.launch import free_tcp_port
from v2xpos.types import FixStatus
from v2xpos.wire import TargetStatus


@dataclass
class FaultResult:
    """One fault scenario's verdict."""
    name: str
    passed: bool
    detail: str

    def as_dict(self) -> dict:
        return {"name": self.name, "passed": bool(self.passed), "detail": self.detail}



def _statuses(items: list[Delivered]) -> Counter:
    return Counter(d.result.status.name.lower() for d in items)


def _inconsistent(items: list[Delivered], timeout_s: float = DEFAULT_TIMEOUT_S) -> list[Delivered]:
    """Message results whose status disagrees with their own latency: TIMEOUT exactly when the
    message was older than the timeout on evaluation (a loaded machine may legitimately delay a
    message past the timeout; then TIMEOUT is the correct answer, a VALID output would be stale)."""
    return [d for d in items if d.payload is not None
            and (d.result.status == TargetStatus.TIMEOUT) != (d.result.latency_s > timeout_s)]


def fault_dropout_and_return() -> FaultResult:
    """car2 silent for 1 s (link drop; sequence continues), then back; car1 unaffected."""
    rig = fresh_rig()
    try:
        gap = range(100, 200)
        t_return = None
        for k in paced(300):
            now = rig.now()
            rig.put("car1", rig.encode("car1", k, now - 0.003))
            if k not in gap:
                if k == gap.stop:
                    t_return = now
                rig.put("car2", rig.encode("car2", k, now - 0.003))
            if k % 5 == 0 and k >= 10:
                rig.tick()
        rig.settle()
        with rig.lock:
            c2 = rig.results("car2")
            c1 = rig.results("car1")
            t_first_timeout = next((d.t_now_gps_s for d in c2 if d.result.status == TargetStatus.TIMEOUT), None)
            back = [d for d in c2 if t_return is not None and d.t_now_gps_s >= t_return]
            valid_back = next((d.t_now_gps_s for d in back if d.result.status == TargetStatus.VALID), None)
            c1_bad = [d for d in c1 if d.result.status not in (TargetStatus.VALID, TargetStatus.TIMEOUT)]
            c1_bad += _inconsistent(c1)
    finally:
        rig.close()
    ok = (t_first_timeout is not None and valid_back is not None and valid_back - t_return < 0.5
          and not c1_bad)
    det = (f"car2 TIMEOUT reported {'yes' if t_first_timeout else 'no'}; VALID again "
           f"{(valid_back - t_return) * 1e3:.0f} ms after return" if valid_back and t_return else "car2 never valid again")
    return FaultResult("slave_dropout_and_return", ok,
                       f"{det}; car1 wrong results: {len(c1_bad)} {dict(_statuses(c1_bad))}")


def fault_slave_restart() -> FaultResult:
    """car2's process restarts after a 0.2 s gap: its sequence starts again at 0 (it was at
    about 5000, i.e. it had run for a minute); time keeps increasing."""
    rig = fresh_rig()
    try:
        for k in paced(200):
            now = rig.now()
            rig.put("car1", rig.encode("car1", k, now - 0.003))
            if k < 80:
                rig.put("car2", rig.encode("car2", k + 5000, now - 0.003))
            elif k >= 100:
                rig.put("car2", rig.encode("car2", k - 100, now - 0.003))
            if k % 5 == 0:
                rig.tick()
        rig.settle()
        with rig.lock:
            after = [d for d in rig.results("car2") if d.payload is not None and d.result.source_seq < 5000]
            rejected = dict(rig.pipe.rejected)
    finally:
        rig.close()
    valid_after = sum(1 for d in after if d.result.status == TargetStatus.VALID)
    return FaultResult("slave_restart_sequence_reset", valid_after >= 90,
                       f"{valid_after}/100 messages after the restart gave VALID results; rejected {rejected}")


def fault_delay_spikes_and_jitter(spike_s: float = 0.3) -> FaultResult:
    """car1's link: 5-10 ms jitter throughout and a 300 ms stall at message 100 (FIFO: the
    messages behind it queue up, as on a TCP link); car2 clean. Every message older than the
    timeout on arrival must give TIMEOUT, no VALID result may be older than the timeout, and the
    spike must not be mistaken for clock skew."""
    rng = np.random.default_rng(3)
    rig = fresh_rig()
    held: list[tuple[float, bytes]] = []
    spiked: set[bytes] = set()
    last_release = 0.0
    try:
        for k in paced(300):
            now_wall = time.time()
            now = rig.now()
            p = rig.encode("car1", k, now - 0.003)
            d = 0.005 + 0.005 * rng.random() + (spike_s if k == 100 else 0.0)
            release = max(now_wall + d, last_release)
            last_release = release
            if release - now_wall > DEFAULT_TIMEOUT_S + 0.02:
                spiked.add(p)
            held.append((release, p))
            rig.put("car2", rig.encode("car2", k, now - 0.003))
            due = [x for x in held if x[0] <= now_wall]
            held = [x for x in held if x[0] > now_wall]
            for _, q in sorted(due):
                rig.put("car1", q)
        time.sleep(spike_s + 0.05)
        for _, q in sorted(held):
            rig.put("car1", q)
        rig.settle()
        with rig.lock:
            c1 = [d for d in rig.results("car1") if d.payload is not None]
            stale_valid = [d for d in rig.delivered if d.result.status == TargetStatus.VALID
                           and d.result.latency_s > DEFAULT_TIMEOUT_S]
            spiked_res = [d for d in c1 if d.payload in spiked]
            spiked_timeout = sum(1 for d in spiked_res if d.result.status == TargetStatus.TIMEOUT)
            c2_bad = _inconsistent(rig.results("car2")) + _inconsistent(c1)
            lat = [d.result.latency_s for d in c1 if d.result.status == TargetStatus.VALID]
            skew = rig.auth.clock.status("car1")
    finally:
        rig.close()
    ok = not stale_valid and spiked_timeout == len(spiked_res) and len(spiked_res) >= 5 and not c2_bad \
        and not skew.skewed
    return FaultResult("delay_spikes_and_jitter", ok,
                       f"{spiked_timeout}/{len(spiked_res)} spiked messages -> TIMEOUT; stale VALID outputs: "
                       f"{len(stale_valid)}; car1 VALID latency p99 {np.percentile(lat, 99) * 1e3:.1f} ms; "
                       f"status/latency mismatches: {len(c2_bad)}; clock skew flagged: {skew.skewed} {skew.reason}")


def fault_reorder_and_duplicates() -> FaultResult:
    """car1: every 10th pair of messages swapped, every 7th message sent twice; car2 clean.
    Late and repeated messages are rejected and counted; car1's outputs stay in time order."""
    rig = fresh_rig()
    injected_dup = injected_swap = 0
    try:
        pending = None
        for k in paced(300):
            now = rig.now()
            p = rig.encode("car1", k, now - 0.003)
            rig.put("car2", rig.encode("car2", k, now - 0.003))
            if k % 10 == 3 and pending is None:
                pending = p
                continue
            rig.put("car1", p)
            if pending is not None:
                rig.put("car1", pending)
                pending = None
                injected_swap += 1
            if k % 7 == 0:
                rig.put("car1", p)
                injected_dup += 1
        rig.settle()
        with rig.lock:
            rej = dict(rig.pipe.rejected)
            c1 = [d.result for d in rig.results("car1") if d.payload is not None]
            monotonic = all(b.source_seq > a.source_seq for a, b in zip(c1, c1[1:]))
            c2_bad = [d for d in rig.results("car2")
                      if d.result.status not in (TargetStatus.VALID, TargetStatus.TIMEOUT)]
            c2_bad += _inconsistent(rig.results("car2"))
            per_target = dict(rig.pipe.tracks["car1"].rejected)
    finally:
        rig.close()
    dup_rej = rej.get("replay", 0) + rej.get("duplicate", 0)
    late_rej = rej.get("out_of_order", 0)
    ok = dup_rej == injected_dup and late_rej == injected_swap and monotonic and not c2_bad
    return FaultResult("reordering_and_duplicates", ok,
                       f"duplicates {injected_dup} sent / {dup_rej} rejected; swapped {injected_swap} / "
                       f"{late_rej} rejected as out of order; car1 rejected by reason {per_target}; outputs in "
                       f"order: {monotonic}; car2 wrong results: {len(c2_bad)}")


def fault_clock_jump_and_drift() -> FaultResult:
    """car1's clock drifts +3000 ppm; car2's clock jumps back 150 ms at 2.5 s and ahead 300 ms
    at 4 s. Both must be reported as clock skew (not only as latency); a clean run is not."""
    rig = fresh_rig()
    try:
        t_start = rig.now()
        for k in paced(600):
            now = rig.now()
            t1 = t_start + (now - t_start) * (1 + 3e-3) - 0.003
            rig.put("car1", rig.encode("car1", k, t1))
            off = -0.15 if 250 <= k < 400 else (0.3 if k >= 400 else 0.0)
            rig.put("car2", rig.encode("car2", k, now - 0.003 + off))
            if k == 380:
                with rig.lock:
                    mid = rig.auth.clock.status("car2")
        rig.settle()
        with rig.lock:
            s1, s2 = rig.auth.clock.status("car1"), rig.auth.clock.status("car2")
            future = rig.pipe.rejected.get("future", 0)
    finally:
        rig.close()
    ok = s1.skewed and abs(s1.drift_ppm - 3000) < 1200 and mid.skewed and s2.jumps >= 2 and future > 100
    return FaultResult("slave_clock_jump_and_drift", ok,
                       f"car1 drift estimate {s1.drift_ppm:+.0f} ppm (true +3000), flagged {s1.skewed}; car2 "
                       f"after -150 ms jump: {mid.reason or 'not flagged'}; car2 jumps detected {s2.jumps}; "
                       f"messages rejected as future after the +300 ms jump: {future}")


def fault_gnss_outage_and_fix_downgrades() -> FaultResult:
    """Master fix FIXED->FLOAT->SINGLE->NONE(outage)->FIXED and car1 FIXED->DEAD_RECKONING->FIXED;
    every result must carry the status and failing side the gate implies."""
    rig = fresh_rig()
    master_fix = {range(0, 50): FixStatus.FIXED, range(50, 100): FixStatus.FLOAT, range(100, 150): FixStatus.SINGLE,
                  range(150, 200): FixStatus.NONE, range(200, 350): FixStatus.FIXED}
    car1_fix = {range(0, 250): FixStatus.FIXED, range(250, 300): FixStatus.DEAD_RECKONING,
                range(300, 350): FixStatus.FIXED}

    def at(table, k):
        return next(v for r, v in table.items() if k in r)
    expected: dict[bytes, tuple] = {}
    try:
        for k in paced(350):
            with rig.lock:
                rig.master_fix = at(master_fix, k)
            now = rig.now()
            f1 = at(car1_fix, k)
            p1 = rig.encode("car1", k, now - 0.003, fix=f1)
            p2 = rig.encode("car2", k, now - 0.003)
            expected[p1] = (k, f1)
            expected[p2] = (k, FixStatus.FIXED)
            rig.put("car1", p1)
            rig.put("car2", p2)
        rig.settle()
        wrong = []
        n = 0
        with rig.lock:
            for d in rig.delivered:
                if d.payload is None or d.payload not in expected:
                    continue
                n += 1
                k, fs = expected[d.payload]
                fm = d.master_fix  # the master's own fix when the message was evaluated
                side = (1 if not fm.is_rtk else 0) | (2 if not fs.is_rtk else 0)
                want = (TargetStatus.VALID if side == 0 else TargetStatus.FIX_INVALID, side)
                if d.result.latency_s > DEFAULT_TIMEOUT_S:  # late on a loaded machine: staleness wins
                    want = (TargetStatus.TIMEOUT, 0)
                got = (d.result.status, int(d.result.fix_side))
                if got != want:
                    wrong.append((k, got, want))
            counts = _statuses(rig.delivered)
    finally:
        rig.close()
    return FaultResult("gnss_outage_and_fix_downgrades", not wrong and n >= 650,
                       f"{n} results checked, {len(wrong)} with a wrong status/side {wrong[:3]}; "
                       f"statuses {dict(counts)}")


def _router_main(port: int) -> int:
    """Standalone router process (killed and restarted by the router fault)."""
    from v2xpos.link import Link, LinkConfig
    link = Link(LinkConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    print("ready", flush=True)
    stop.wait()
    link.close()
    return 0


def _start_router(port: int) -> subprocess.Popen:
    repo = Path(__file__).resolve().parents[1]
    p = subprocess.Popen([sys.executable, "-m", "bench.trust_faults", "--router", str(port)], cwd=repo,
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    p.stdout.readline()
    return p


def fault_router_restart(down_s: float = 0.5) -> FaultResult:
    """Standalone router killed (SIGKILL) and restarted on the same port while the slave keeps
    publishing at 100 Hz; master and slave are zenoh clients with the link's connect/retry
    (100 ms initial, 500 ms max). Delivery must resume within 1 s of the new router listening."""
    port = free_tcp_port()
    router = {"p": _start_router(port)}
    rig = LiveRig(master_mode="client", router_endpoint=f"tcp/127.0.0.1:{port}")
    ready: dict[str, float] = {}

    def restart() -> None:
        router["p"] = _start_router(port)
        ready["t"] = time.time()
    try:
        wait_connected(rig)
        with rig.lock:
            rig.pipe.tracks.clear()
            rig.auth.reset_replay_windows()
        t_kill = None
        restarter = None
        seq = 0
        for k in paced(100000):
            rig.put("car1", rig.encode("car1", seq, rig.now() - 0.003))
            seq += 1
            if k == 100:
                router["p"].send_signal(signal.SIGKILL)
                router["p"].wait()
                t_kill = time.time()
            if t_kill is not None and restarter is None and time.time() - t_kill >= down_s:
                restarter = threading.Thread(target=restart, daemon=True)
                restarter.start()
            if "t" in ready and time.time() > ready["t"] + 3.0:
                break
            if k > 3000:
                break
        rig.settle()
        with rig.lock:
            before = sum(1 for d in rig.delivered if d.payload is not None and d.t_arrival_wall_s < t_kill)
            after = sorted(d.t_arrival_wall_s for d in rig.delivered
                           if d.payload is not None and d.t_arrival_wall_s > t_kill + 0.05)
        if "t" not in ready:
            return FaultResult("router_killed_and_restarted", False, "the router did not restart")
        resumed_ms = (after[0] - ready["t"]) * 1e3 if after else None
        ok = resumed_ms is not None and resumed_ms < 1000.0 and len(after) > 200 and before > 50
        detail = (f"router down {ready['t'] - t_kill:.2f} s (kill -> new router listening); first message "
                  f"delivered {max(resumed_ms, 0.0):.0f} ms after the new router was listening; "
                  f"{before} delivered before, {len(after)} after" if resumed_ms is not None
                  else "delivery did not resume within 3 s")
    finally:
        rig.close()
        router["p"].terminate()
        try:
            router["p"].wait(timeout=5)
        except subprocess.TimeoutExpired:
            router["p"].kill()
    return FaultResult("router_killed_and_restarted", ok, detail)


FAULTS: dict[str, Callable[[], FaultResult]] = {
    "slave_dropout_and_return": fault_dropout_and_return,
    "slave_restart_sequence_reset": fault_slave_restart,
    "router_killed_and_restarted": fault_router_restart,
    "delay_spikes_and_jitter": fault_delay_spikes_and_jitter,
    "reordering_and_duplicates": fault_reorder_and_duplicates,
    "slave_clock_jump_and_drift": fault_clock_jump_and_drift,
    "gnss_outage_and_fix_downgrades": fault_gnss_outage_and_fix_downgrades,
}


def run_faults(names: list[str] | None = None) -> list[FaultResult]:
    out = []
    for name, fn in FAULTS.items():
        if names and name not in names:
            continue
        try:
            out.append(fn())
        except Exception as exc:  # a scenario that breaks is a failed fault, reported, not a crash
            out.append(FaultResult(name, False, f"scenario error {type(exc).__name__}: {exc}"))
    return out



if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--router":
        sys.exit(_router_main(int(sys.argv[2])))
    print("usage: python -m bench.trust_faults --router PORT", file=sys.stderr)
    sys.exit(2)
