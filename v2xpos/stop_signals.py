"""Stop signals (SIGINT, SIGTERM) that arrive before a service has installed its own handlers.

A service process spends its first second or so importing numpy, numba and zenoh. A signal in
that window would otherwise end it with Python's default (a KeyboardInterrupt traceback, or death
by SIGTERM) instead of a clean stop. Nothing is open yet and nothing can be lost, so the clean stop
is to exit at once with code 0 and the one JSON line a service prints when it ends
(``{"phase": "starting", "stopped_early": true}``). The CLI calls :func:`exit_until_handled`
before it imports a service's module; the service's own handlers replace this one.
"""
from __future__ import annotations

import json
import os
import signal
import sys


def exit_until_handled(service: str) -> None:
    """Until a handler replaces it: on SIGINT or SIGTERM say so and exit with code 0."""
    def _exit(signum: int, _frame: object) -> None:
        print(f"v2xpos {service}: stopped ({signal.Signals(signum).name}) while starting", file=sys.stderr,
              flush=True)
        print(json.dumps({"phase": "starting", "stopped_early": True}), flush=True)
        os._exit(0)          # nothing is open yet; skip the interpreter shutdown (seconds under load)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _exit)
