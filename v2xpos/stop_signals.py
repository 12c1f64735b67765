"""Stop signals (SIGINT, SIGTERM) that arrive before a service has installed its own handlers.

A service process spends its first second or so importing numpy, numba and zenoh. A signal in
that window would otherwise end it with Python's default (a KeyboardInterrupt traceback, or death
by SIGTERM) instead of a clean stop. Nothing is open yet and nothing can be lost, so the clean stop
is to exit at once with code 130 (interrupted, README exit codes) and the one JSON line a service prints when it ends
(``{"phase": "starting", "stopped_early": true}``). The CLI calls :func:`exit_until_handled`
before it imports a service's module; the service's own handlers replace this one.

A launcher that runs services as child processes (``demo``, ``convoy``) must stop them and say so
when it is asked to stop. A process started in the background of a non-interactive shell inherits
SIGINT *ignored* (POSIX: asynchronous lists ignore SIGINT and SIGQUIT when job control is off) and
Python then keeps ignoring it; its children, which install their own handlers, would stop on a
process-group SIGINT while the launcher carried on and reported a cut-short run as complete.
:func:`interrupt_on_stop_signals` makes SIGINT and SIGTERM raise ``KeyboardInterrupt`` in the
launcher whatever it inherited.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import threading
from collections.abc import Iterator


def exit_until_handled(service: str) -> None:
    """Until a handler replaces it: on SIGINT or SIGTERM say so and exit with code 130 (interrupted)."""
    def _exit(signum: int, _frame: object) -> None:
        print(f"v2xpos {service}: stopped ({signal.Signals(signum).name}) while starting", file=sys.stderr,
              flush=True)
        print(json.dumps({"phase": "starting", "stopped_early": True}), flush=True)
        os._exit(130)        # nothing is open yet; skip the interpreter shutdown (seconds under load)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _exit)


@contextlib.contextmanager
def interrupt_on_stop_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise ``KeyboardInterrupt`` in the main thread (also
    when SIGINT was inherited ignored); the previous handlers are restored on exit. Off the main
    thread, where Python cannot set handlers, the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, _raise) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
