"""``v2xpos bench trust --json FILE``: attack, fault and robustness report of the V2V link.

Everything runs over real zenoh sessions on loopback (``bench.live_rig``): slave sessions publish
signed StateMessages at 100 Hz to a master running ``master.pipeline.MasterPipeline`` with a
``MessageAuthenticator``. Link impairments are applied at the sender (a held message = delay;
swapped = reordering; re-sent = duplicate; shifted time of validity = clock fault); the fault
scenarios are in ``bench.trust_faults``; fuzzing is ``bench.fuzz``; the soak ``bench.soak``.

Report keys: ``forged_sent``, ``forged_accepted``, ``replayed_sent``,
``replayed_accepted``, ``fuzz_inputs``, ``fuzz_crashes``, ``faults`` (``name``, ``passed``,
``detail``) and the soak's ``sent``, ``received``, ``recorded``, ``lost``, ``rss_growth_pct``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

from bench.live_rig import fresh_rig, paced
from bench.trust_faults import run_faults
from v2xpos.types import FixStatus
from v2xpos.wire import encode_state


# ----------------------------------------------------------------------------- attacks

def attack_forged_and_replayed(n_each: int = 50) -> dict:
    """Forged messages (unknown key, another vehicle's key, tampered body, signature moved to
    another body, unsigned) and replays (captured payloads re-sent 0.05-2 s later, and after
    the age window) over zenoh; counts how many the master accepted."""
    from v2xpos.security import Ed25519PrivateKey, MessageSigner
    from v2xpos.wire import pack_envelope, unpack_envelope

    rig = fresh_rig()
    outsider = MessageSigner(Ed25519PrivateKey.generate())
    forged: list[bytes] = []
    replayed: list[bytes] = []
    captured: list[bytes] = []
    try:
        seq = 0
        for k in paced(4 * n_each):
            now = rig.now()
            good = rig.encode("car1", seq, now - 0.003)
            rig.put("car1", good)
            rig.put("car2", rig.encode("car2", seq, now - 0.003))
            captured.append(good)
            seq += 1
            now += 0.001  # forgeries look fresher than the genuine message, so only authentication stops them
            kind = k % 4
            if kind == 0:
                f = rig.encode("car1", seq + 5000, now - 0.003, signer=outsider)
            elif kind == 1:
                f = rig.encode("car1", seq + 5000, now - 0.003, signer=rig.signers["car2"])
            elif kind == 2:
                env = unpack_envelope(rig.encode("car1", seq + 5000, now - 0.003))
                tampered = rig.encode("car1", seq + 5000, now - 0.003, fix=FixStatus.FLOAT)
                f = pack_envelope(unpack_envelope(tampered).body, env.sig, env.key_id)
            else:
                f = encode_state(rig.state("car1", seq + 5000, now - 0.003))
            forged.append(f)
            rig.put("car1", f)
            if k >= 10 and k % 2 == 0:  # replay a capture from 50 ms to 2 s ago
                r = captured[max(0, k - 5 - 25 * (k % 8))]
                replayed.append(r)
                rig.put("car1", r)
        time.sleep(5.2)  # beyond the 5 s age window: replay a batch of old captures
        for r in captured[: n_each]:
            replayed.append(r)
            rig.put("car1", r)
        rig.settle()
        with rig.lock:
            forged_acc = sum(1 for f in forged if f in rig.accepted_payloads)
            # a replay is accepted if its delivery produced a second result for the same payload
            per_payload = Counter(d.payload for d in rig.delivered if d.payload is not None)
            replay_acc = sum(1 for r in set(replayed) if per_payload[r] > 1)
            genuine = sum(1 for c in captured if c in rig.accepted_payloads)
            rejected = dict(rig.pipe.rejected)
    finally:
        rig.close()
    return {"forged_sent": len(forged), "forged_accepted": forged_acc, "replayed_sent": len(replayed),
            "replayed_accepted": replay_acc, "genuine_sent": len(captured), "genuine_accepted": genuine,
            "rejected": rejected}



# ----------------------------------------------------------------------------- CLI

def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", help="write the report here")
    parser.add_argument("--fuzz-inputs", type=int, default=100_000)
    parser.add_argument("--soak-json", help="use this soak report (from `v2xpos bench soak --json`) instead of "
                                            "running the soak")
    parser.add_argument("--soak-slaves", type=int, default=32)
    parser.add_argument("--soak-rate", type=float, default=100.0)
    parser.add_argument("--soak-duration", type=float, default=60.0)
    parser.add_argument("--skip-soak", action="store_true")
    parser.add_argument("--faults", nargs="*", help="fault names to run (default all)")


def run_bench(args: argparse.Namespace) -> int:
    from bench.fuzz import run_fuzz
    report: dict = {}
    print("attacks: forged and replayed messages over zenoh ...", file=sys.stderr)
    report.update(attack_forged_and_replayed())
    print("faults ...", file=sys.stderr)
    faults = run_faults(args.faults)
    report["faults"] = [f.as_dict() for f in faults]
    print(f"fuzz: {args.fuzz_inputs} inputs ...", file=sys.stderr)
    fz = run_fuzz(args.fuzz_inputs)
    report["fuzz_inputs"], report["fuzz_crashes"] = fz["fuzz_inputs"], fz["fuzz_crashes"]
    report["fuzz_targets"] = {k: {kk: v[kk] for kk in ("inputs", "decoded", "rejected", "crashes")}
                              for k, v in fz["targets"].items()}
    soak = None
    if args.soak_json:
        soak = json.loads(Path(args.soak_json).read_text())
    elif not args.skip_soak:
        from bench.soak import run_soak
        print("soak ...", file=sys.stderr)
        soak = run_soak(args.soak_slaves, args.soak_rate, args.soak_duration, "out/soak")
    for k in ("sent", "received", "recorded", "lost", "rss_growth_pct"):
        report[k] = None if soak is None else soak.get(k)
    if soak is not None:
        report["soak"] = soak
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text)
    ok = (report["forged_accepted"] == 0 and report["replayed_accepted"] == 0 and report["fuzz_crashes"] == 0
          and all(f.passed for f in faults))
    return 0 if ok else 1

