"""How received state messages reach the master's pipeline with ``dispatch = "inline"`` (the
default): a dedicated thread drains the zenoh subscriber in batches, optionally with the Ed25519
checks in a worker process (``v2xpos.verify_worker``), and runs each batch under the service's
lock (``master.service.MasterService``)."""
from __future__ import annotations

import os
import threading
import time
from collections import deque
from typing import Any, Protocol

from v2xpos.link import Link
from v2xpos.types import NavState

REJECT_MASTER_NOT_READY = "master_not_ready"
"""Rejection reason of a message that arrived before the master had its own state and could not be
kept for it (``StartupHold``)."""
STARTUP_HOLD_MESSAGES = 512
"""Messages kept while the master has no state of its own yet (about a second of 4 slaves at
100 Hz)."""


class StartupHold:
    """Messages that arrive before the master's first own state (its filter still starting while a
    slave already sends) are kept, in order, and handled with that first state instead of being
    dropped; beyond ``limit`` the oldest is rejected as ``master_not_ready`` (counted)."""

    def __init__(self, limit: int = STARTUP_HOLD_MESSAGES):
        self.limit = int(limit)
        self.items: deque = deque()

    def hold(self, pipe: Any, item: tuple) -> None:
        if len(self.items) >= self.limit:
            self.items.popleft()
            pipe.rejected[REJECT_MASTER_NOT_READY] += 1
        self.items.append(item)

    def release(self) -> list:
        out = list(self.items)
        self.items.clear()
        return out


class DispatchTarget(Protocol):
    """What the dispatch needs of the service (``MasterService``): its lock, whether it is closing,
    its pipeline (``MasterPipeline`` or the recording wrapper around it), its latest own state."""
    lock: Any
    closing: bool
    pipeline: Any
    nav: NavState | None
    startup: StartupHold

    def gps_now(self) -> float: ...


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


class InlineDispatch:
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

    def __init__(self, svc: DispatchTarget, verifier=None):
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
                        svc.startup.hold(pipe, (payload, key, t_arrival_wall_s, signature_valid))
                        continue
                    for held in svc.startup.release():
                        pipe.handle(held[0], held[1], svc.nav, svc.gps_now(), held[2], held[3])
                    pipe.handle(payload, key, svc.nav, svc.gps_now(), t_arrival_wall_s, signature_valid)
        self.cpu_s += time.thread_time() - c0

    def on_sample(self, payload: bytes, key: str, attachment: bytes | None, t_arrival_wall_s: float) -> None:
        """One sample (``Link.subscribe`` callback signature)."""
        self.on_batch([(payload, key, None)], t_arrival_wall_s)
