"""Messages that reach the master before its own first state are kept and handled with it."""
from __future__ import annotations

from collections import Counter

from master.dispatch import REJECT_MASTER_NOT_READY, InlineDispatch, StartupHold


class _Pipe:
    def __init__(self) -> None:
        self.rejected: Counter = Counter()
        self.handled: list = []

    def handle(self, payload, key, nav, t_now, t_arr, signature_valid=None):
        self.handled.append((payload, nav))

    def batch(self):
        import contextlib
        return contextlib.nullcontext()


class _Service:
    def __init__(self, limit: int) -> None:
        import threading
        self.lock = threading.Lock()
        self.closing = False
        self.pipeline = _Pipe()
        self.nav = None
        self.startup = StartupHold(limit)

    def gps_now(self) -> float:
        return 0.0


def test_messages_before_the_own_state_are_kept_in_order_and_counted_beyond_the_limit():
    svc = _Service(limit=3)
    dispatch = InlineDispatch(svc, verifier=None)
    for k in range(5):                                    # the master has no state yet
        dispatch.on_sample(b"m%d" % k, "key", None, 1.0)
    assert svc.pipeline.handled == [] and svc.pipeline.rejected == {REJECT_MASTER_NOT_READY: 2}
    svc.nav = "own state"
    dispatch.on_sample(b"m5", "key", None, 1.1)
    assert [p for p, _ in svc.pipeline.handled] == [b"m2", b"m3", b"m4", b"m5"]
    assert all(nav == "own state" for _, nav in svc.pipeline.handled)
    dispatch.on_sample(b"m6", "key", None, 1.2)           # nothing held twice
    assert [p for p, _ in svc.pipeline.handled][-2:] == [b"m5", b"m6"]
