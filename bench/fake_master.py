"""A stand-in master for ``v2xpos bench monitor`` and the monitor tests: a zenoh router that
publishes what a master publishes for monitors -- RelativeResult messages for N targets at a rate
on ``.../master/ego/relative`` and the status JSON at 2 Hz -- and flips one target's status
between VALID and FIX_INVALID every ``flip_every_s``, printing ``{"flip": id, "status": s,
"t_wall_s": t}`` (the wall time just before the first result with the new status is put)."""
from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from v2xpos.link import Link, LinkConfig
from v2xpos.types import FixStatus
from v2xpos.wire import FixSide, RelativeResult, TargetStatus, encode_relative, relative_key, status_key


def result(i: int, status: TargetStatus, seq: int, t_gps_s: float) -> RelativeResult:
    """Target ``t<i>``: 8 m further per index, alternating lanes; TTC grows with the index; master
    RTK fixed, the target fixed when VALID, float otherwise."""
    valid = status == TargetStatus.VALID
    x, y = 8.0 * (i + 1), 3.5 * (i % 3 - 1)
    r = RelativeResult(target_id=f"t{i:02d}", status=status, fleet="demo", master_id="ego", seq=seq,
                       source_seq=seq, t_gps_s=t_gps_s, latency_s=0.1,
                       fix_side=FixSide.NONE if valid else FixSide.SLAVE, master_fix=FixStatus.FIXED,
                       target_fix=FixStatus.FIXED if valid else FixStatus.FLOAT)
    if valid:
        r.rel_pos_body_m = np.array([x, y, 0.0])
        r.rel_pos_sd_m = np.array([0.02, 0.02, 0.03])
        r.rel_vel_body_mps = np.array([-0.5, 0.0, 0.0])
        r.rel_acc_body_mps2 = np.zeros(3)
        r.rel_rpy_rad = np.array([0.0, 0.0, 0.05])
        r.range_m, r.range_sd_m = math.hypot(x, y), 0.02
        r.bearing_rad, r.elevation_rad = math.atan2(y, x), 0.0
        r.longitudinal_m, r.lateral_m, r.gap_m = x - 4.0, y, max(0.1, x - 4.0)
        r.closing_speed_mps = 0.5
        r.ttc_s = r.gap_m / 0.5
    return r


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m v2xpos.monitor.fake_master")
    ap.add_argument("--endpoint", required=True)
    ap.add_argument("--targets", type=int, default=64)
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--flip-every", type=float, default=1.3)
    a = ap.parse_args(argv)
    link = Link(LinkConfig(mode="router", listen=[a.endpoint]))
    pub = link.publisher(relative_key("demo", "ego"), express=False)
    spub = link.publisher(status_key("demo", "ego"), express=False)
    # two pre-encoded payloads per target (the monitor does not look at sequence numbers), so this
    # process's own CPU stays small on the shared machine
    valid = [encode_relative(result(i, TargetStatus.VALID, 1, 1e9)) for i in range(a.targets)]
    bad = [encode_relative(result(i, TargetStatus.FIX_INVALID, 1, 1e9)) for i in range(a.targets)]
    flip_i = a.targets // 2
    flipped = False
    t0 = time.time()
    next_flip = t0 + 2.0
    next_status = t0
    k = 0
    while time.time() - t0 < a.duration:
        now = time.time()
        if now >= next_flip:
            flipped = not flipped
            next_flip += a.flip_every
            print(json.dumps({"flip": f"t{flip_i:02d}", "status": "fix_invalid" if flipped else "valid",
                              "t_wall_s": time.time()}), flush=True)
        for i in range(a.targets):
            pub.put(bad[i] if (flipped and i == flip_i) else valid[i])
        if now >= next_status:
            next_status += 0.5
            targets = {f"t{i:02d}": {"kind": "vehicle", "status": "fix_invalid" if (flipped and i == flip_i) else "valid",
                                     "fix_side": 0, "accepted": k, "restarts": 0, "results": {}, "rejected": {},
                                     "degraded": False, "last": None} for i in range(a.targets)}
            spub.put(json.dumps({"master_id": "ego", "master_fix": int(FixStatus.FIXED), "t_rel_s": now - t0,
                                 "processed": k * a.targets, "rejected": {}, "targets": targets,
                                 "imu_grades": {}, "scene": {"lanes": {"left": {"lateral_m": -1.75},
                                                                       "right": {"lateral_m": 1.75}}}}).encode())
        k += 1
        dt = t0 + k / a.rate_hz - time.time()
        if dt > 0:
            time.sleep(dt)
    link.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
