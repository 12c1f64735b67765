"""The in-process convoy's loop (``v2xpos convoy --in-process``, forward or smoothed): recorded
vehicles' states through one master pipeline without a link."""
from __future__ import annotations

import sys
import time

STATUS_PERIOD_S = 5.0
"""Seconds between progress lines."""


def feed_pipeline(sink, master_id: str, msrc, ssrc: dict, rate_hz: float = 100.0, log=None,
                  before_handle=None) -> dict:
    """The in-process convoy's loop: session time in steps of 10 ms from the later start to the
    master's end; at each step every source (``advance(t)`` -> new NavStates, ``t_begin_gps_s``,
    ``t_end_gps_s``, ``geometry``, ``kind``) is advanced, and every slave state (at most ``rate_hz``
    per slave) goes through the master pipeline against the master's latest state into ``sink``.
    ``before_handle(master_state, slave_id, slave_state)``: called before each. ``log``: progress
    lines (default the current ``sys.stderr``)."""
    log = sys.stderr if log is None else log      # resolved per call: a stream bound at import may be closed
    from master.pipeline import MasterPipeline, PipelineConfig
    from v2xpos.wire import StateMessage, encode_state, state_key
    pipe = MasterPipeline(PipelineConfig(fleet="convoy", master_id=master_id, known_vehicles=tuple(ssrc)), [sink])
    t = max(msrc.t_begin_gps_s, min(s.t_begin_gps_s for s in ssrc.values()))
    t_end = msrc.t_end_gps_s
    step = 0.01
    nav = None
    seq = {k: 0 for k in ssrc}
    next_pub = {k: -1e300 for k in ssrc}
    period = 1.0 / rate_hz
    n_steps = 0
    t_print = time.time() + STATUS_PERIOD_S
    while t <= t_end:
        states = msrc.advance(t)
        if states:
            nav = states[-1]
        for sid, src in ssrc.items():
            for st in src.advance(t):
                if st.t_s + 1e-6 < next_pub[sid]:
                    continue
                next_pub[sid] = st.t_s + period
                seq[sid] += 1
                if nav is None:
                    continue
                if before_handle is not None:
                    before_handle(nav, sid, st)
                msg = StateMessage.from_nav_state(st, "convoy", sid, seq[sid], geometry=src.geometry, kind=src.kind)
                pipe.handle(encode_state(msg), state_key("convoy", sid), nav, float(nav.t_s), time.time())
        t += step
        n_steps += 1
        if time.time() > t_print:
            t_print += STATUS_PERIOD_S
            print(f"convoy (in process): {100 * (t - msrc.t_begin_gps_s) / (t_end - msrc.t_begin_gps_s):5.1f} %",
                  file=log, flush=True)
    return {"processed": pipe.processed, "rejected": dict(pipe.rejected)}
