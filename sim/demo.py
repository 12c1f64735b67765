"""``v2xpos demo [--vehicles N] [--duration S] [--latency-ms L] [--out DIR]``: the main job end to end.

Starts the master and N-1 slaves plus one pedestrian as separate OS processes on loopback (zenoh
router embedded in the master on ``tcp/127.0.0.1:<free port>``, multicast scouting off), driven
by the ``sim.scenarios.convoy`` scenario (curves, braking, a cut-in, fix degradation
fixed->float->single->fixed, link delay + jitter + a delay spike). Every process runs the INS
filter on its own simulated sensors. Shows a live table (``sim.live_table``), then writes
``DIR/report.json`` and plots (relative position error vs time, range, latency histogram,
statuses) from the master's recorded results evaluated against the scenario truth
(``sim.evaluate``).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from sim import evaluate
from sim.launcher import Fleet, FleetPlan, release_when_ready, write_configs
from v2xpos.launch import free_tcp_port, free_udp_port
from sim.scenarios import build, check_rtk_vertical_factor
from v2xpos.provenance import provenance
from v2xpos.stop_signals import interrupt_on_stop_signals

STARTUP_LEAD_S = 1.5
"""Wall time between the last process signalling ready and the scenario epoch (the filters start
``WARMUP_S`` = 1 s before the epoch)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vehicles", type=int, default=4, help="vehicles including the master (default 4)")
    parser.add_argument("--duration", type=float, default=30.0, help="scenario duration [s] (default 30)")
    parser.add_argument("--latency-ms", type=float, default=100.0, help="injected link latency [ms] (default 100)")
    parser.add_argument("--jitter-ms", type=float, default=5.0, help="injected link jitter 1-sigma [ms] (default 5)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="out/demo", help="output directory (report.json, plots, logs)")
    parser.add_argument("--source", choices=["ins", "truth_noise"], default="ins",
                        help="state source of every vehicle (default ins: the real filter)")
    parser.add_argument("--no-pedestrian", action="store_true")
    parser.add_argument("--no-degradations", action="store_true", help="no fix degradation on any target")
    parser.add_argument("--no-spikes", action="store_true", help="no link delay spike")
    parser.add_argument("--no-live", action="store_true", help="do not show the live table")
    parser.add_argument("--port", type=int, default=0, help="router TCP port on 127.0.0.1 (0 = ask the OS)")
    parser.add_argument("--rtk-vertical-factor", type=float, default=1.0,
                        help="simulated RTK-fixed vertical noise / horizontal noise (1 cm); default 1.0")


def run_demo(vehicles: int = 4, duration_s: float = 40.0, latency_ms: float = 100.0, jitter_ms: float = 5.0,
             seed: int = 0, out: str | Path = "out/demo", source: str = "ins", pedestrian: bool = True,
             degradations: bool = True, spikes: bool = True, live: bool = True, port: int = 0,
             plots: bool = True, log=None, rtk_vertical_factor: float = 1.0) -> dict:
    """Run the multi-process demo and return the report dict (also written to out/report.json).
    ``log``: progress lines (default the current ``sys.stderr``)."""
    log = sys.stderr if log is None else log      # resolved per call: a stream bound at import may be closed
    # absolute: the services resolve every path in their configs against the config's directory
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    sc = build("convoy", vehicles=vehicles, duration_s=duration_s, latency_ms=latency_ms, jitter_ms=jitter_ms,
               seed=seed, pedestrian=pedestrian, degradations=degradations, spikes=spikes,
               rtk_vertical_factor=rtk_vertical_factor)
    start_file = out / "start_stamp"
    plan = FleetPlan(out_dir=out, router_port=port or free_tcp_port(), udp_port=free_udp_port(), source_type=source,
                     start_file=start_file)
    write_configs(sc, plan, duration_s)
    for stale in (plan.results_npz, plan.summary_json):
        if stale is not None and stale.exists():
            stale.unlink()
    for old in out.glob("start_stamp*"):
        old.unlink()
    fleet = Fleet(plan, sc.master_id, start_file)
    print(f"demo: {len(sc.actors)} processes ({vehicles} vehicles + {'1 pedestrian' if pedestrian else 'no pedestrian'}),"
          f" router tcp/127.0.0.1:{plan.router_port}, duration {duration_s:.0f} s,"
          f" latency {latency_ms:.0f} ms, source {source}", file=log, flush=True)
    t_launch = time.time()
    with interrupt_on_stop_signals():
        codes, interrupted = _run_fleet(fleet, plan, sc, start_file, duration_s, live, t_launch, log)
    try:
        report = make_report(sc, plan, duration_s, codes)
    except Exception as exc:  # noqa: BLE001 -- a partial run may lack what a full report needs
        if not interrupted:
            raise
        report = {"duration_s": duration_s, "exit_codes": codes, "targets": [],
                  "report_error": f"{type(exc).__name__}: {exc}"}
    report["partial"] = interrupted
    if interrupted:
        report["interrupted_after_s"] = time.time() - t_launch
    arguments = {"vehicles": vehicles, "duration_s": duration_s, "latency_ms": latency_ms, "jitter_ms": jitter_ms,
                 "seed": seed, "source": source, "pedestrian": pedestrian, "degradations": degradations,
                 "spikes": spikes, "rtk_vertical_factor": rtk_vertical_factor}
    report["provenance"] = provenance("demo", {"demo_arguments": arguments, **plan.configs},
                                      seeds={"scenario": seed}, started_utc=t_launch)
    report["latency_ms_injected"] = latency_ms
    ego = sc.actors[sc.master_id]
    report["rtk_fixed_sd_m"] = {"horizontal": ego.gnss_sd_fixed_m,
                                "vertical": ego.gnss_sd_fixed_m * ego.gnss_vertical_factor}
    if not interrupted:
        report["sensor_evaluation"] = evaluate_sensor(sc, out, duration_s, log)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    if plots:
        try:
            make_plots(sc, plan, out)
        except Exception:  # noqa: BLE001
            if not interrupted:
                raise
    return report


def _run_fleet(fleet: Fleet, plan: FleetPlan, sc, start_file: Path, duration_s: float, live: bool,
               t_launch: float, log) -> tuple[dict, bool]:
    """Start the processes, release them together, wait for the run's end (showing the live table)
    and stop them; on a stop signal (``KeyboardInterrupt``) stop them early. Returns (exit codes,
    interrupted)."""
    table = None
    interrupted = False
    codes: dict = {}
    fleet.start()
    try:
        start = release_when_ready(start_file, list(plan.configs), lead_s=STARTUP_LEAD_S, fleet=fleet)
        print(f"demo: watch it with `v2xpos monitor --connect tcp/127.0.0.1:{plan.router_port} --web`; "
              f"recording {plan.out_dir / 'session.mcap'}", file=log, flush=True)
        print(f"demo: all processes ready after {start - STARTUP_LEAD_S - t_launch:.1f} s; scenario epoch at start stamp",
              file=log, flush=True)
        if live:
            from sim.live_table import LiveTable
            from v2xpos.link import LinkConfig
            table = LiveTable(LinkConfig(mode="client", connect=[f"tcp/127.0.0.1:{plan.router_port}"],
                                         connect_timeout_ms=10000),
                              plan.fleet, sc.master_id, scenario=sc)
        deadline = start + duration_s + 30.0
        while fleet.running() and time.time() < deadline:
            time.sleep(0.5)
            if table is not None:
                table.refresh()
        codes = fleet.stop()
    except KeyboardInterrupt:
        # Ctrl-C: stop the processes (they write what they recorded) and report that much
        interrupted = True
        print(f"demo: interrupted after {time.time() - t_launch:.1f} s: stopping the processes, "
              "writing a partial report", file=log, flush=True)
        codes = fleet.stop()
    finally:
        if table is not None:
            table.close()
        if fleet.running():
            fleet.stop()
    return codes, interrupted


def evaluate_sensor(sc, out: Path, duration_s: float, log) -> dict | None:
    """The demo's last step: a front radar on the master simulated from the scenario truth
    (``sim.object_sensor``, error model ``radar_biased``) and judged by ``v2xpos evaluate`` against
    the master's own session recording; writes ``DIR/sensor/`` and ``DIR/sensor_evaluation/``."""
    from sim.object_sensor import MODELS, DeclaredSensor, scenario_truth, simulate_objects, write_sensor
    from v2xpos.evaluate.config import load_sensor_config
    from v2xpos.evaluate.evaluation import evaluate
    from v2xpos.evaluate.objects import read_objects
    from v2xpos.evaluate.reference import read_reference
    from v2xpos.evaluate.report import summary_text, write_outputs
    session = out / "session.mcap"
    if not session.exists():
        return None
    truths = scenario_truth(sc, sc.epoch_gps_s, sc.epoch_gps_s + duration_s)
    front_m = float(sc.master.geometry.points_body_m[:, 0].max())
    sensor = DeclaredSensor(name="demo_front_radar", mount_m=(front_m, 0.0, -0.5))
    objs = simulate_objects(truths, sensor, MODELS["radar_biased"], seed=int(sc.params.get("seed", 0)))
    write_sensor(objs, out / "sensor", sensor, {k: t.reference_point_m for k, t in truths.items()})
    cfg = load_sensor_config(out / "sensor" / "sensor.toml")
    try:
        ev = evaluate(read_objects(out / "sensor" / "objects.csv", cfg), read_reference(session), cfg)
    except ValueError as exc:
        print(f"demo: sensor evaluation not possible: {exc}", file=log, flush=True)
        return {"error": str(exc)}
    write_outputs(ev, out / "sensor_evaluation", {"reference": session, "sensor": out / "sensor" / "objects.csv",
                                                  "sensor_config": out / "sensor" / "sensor.toml"}, "csv")
    print("demo: simulated front radar judged against the session (v2xpos evaluate):\n" + summary_text(ev.metrics)
          + f"\n  report {out / 'sensor_evaluation' / 'report.html'}; injected "
          + json.dumps(objs.truth["expected"]), file=log, flush=True)
    m = ev.metrics
    return {"report": str(out / "sensor_evaluation" / "report.html"), "injected": objs.truth["expected"],
            **{k: m[k] for k in ("latency_ms", "mount_yaw_deg", "range_bias_m", "false_objects_per_min")},
            "detection_rate": {k: t["detection_rate"] for k, t in m["targets"].items()}}


def run_latency(rows: dict, t_from_gps_s: float) -> dict:
    """Master pipeline (arrival to outputs written) and slave publish -> output percentiles [ms]
    over the results the accuracy figures use: message-driven, master time >= ``t_from_gps_s``
    (the run; the filters' warm-up before it, while every process is still starting, is left out
    and reported in the ``*_incl_warmup`` keys from the master's whole session)."""
    f = evaluate.F
    picked = [r[(r[:, f["t_gps_s"]] >= t_from_gps_s) & np.isfinite(r[:, f["t_slave_gps_s"]])]
              for r in rows.values()]
    both = np.concatenate(picked) if picked else np.zeros((0, len(evaluate.RECORD_FIELDS)))
    out = {}
    for name, col in (("master_pipeline_ms", "pipeline_ms"), ("e2e_ms", "e2e_ms")):
        x = both[:, f[col]]
        x = x[np.isfinite(x)]
        for q in (50, 99):
            out[f"{name}_p{q}"] = float(np.percentile(x, q)) if len(x) else None
    return out


def make_report(sc, plan: FleetPlan, duration_s: float, exit_codes: dict) -> dict:
    """report.json content (keys documented in docs/services.md)."""
    summary = json.loads(plan.summary_json.read_text()) if plan.summary_json and plan.summary_json.exists() else {}
    rows = {}
    if plan.results_npz and plan.results_npz.exists():
        with np.load(plan.results_npz) as z:
            rows = {k[len("target_"):]: z[k] for k in z.files if k.startswith("target_")}
    targets = []
    floor = evaluate.gnss_relative_error_rms(sc, [a.actor_id for a in sc.slaves], sc.epoch_gps_s,
                                             sc.epoch_gps_s + duration_s) if plan.source_type == "ins" else {}
    for a in sc.slaves:
        r = rows.get(a.actor_id, np.zeros((0, len(evaluate.RECORD_FIELDS))))
        entry = evaluate.evaluate_target(sc, a.actor_id, r, sc.epoch_gps_s)
        entry["gnss_rel_err_rms_1s_m"] = floor.get(a.actor_id)
        entry["rejected"] = (summary.get("targets", {}).get(a.actor_id, {}) or {}).get("rejected", {})
        entry["fix_schedule_rel_s"] = [{"start_rel_s": t0, "end_rel_s": t1, "fix": st.name.lower()}
                                       for t0, t1, st in a.fix_schedule]
        entry["delay_spikes_rel_s"] = [{"start_rel_s": t0, "end_rel_s": t1, "extra_delay_ms": extra}
                                       for t0, t1, extra in a.link.spikes]
        targets.append(entry)
    clean = [t for t in targets if not t["fix_schedule_rel_s"] and t["rel_pos_err_rms_m"] is not None]
    scene = evaluate_scene(sc, plan)
    return {
        "vehicles": sum(1 for a in sc.actors.values() if a.kind == "vehicle"),
        "duration_s": duration_s,
        "source": plan.source_type,
        "targets": targets,
        **run_latency(rows, sc.epoch_gps_s),
        "master_pipeline_ms_p99_incl_warmup": summary.get("pipeline_ms_p99"),
        "e2e_ms_p99_incl_warmup": summary.get("e2e_ms_p99"),
        "can_frames": summary.get("can_frames", 0),
        "udp_datagrams": summary.get("udp_datagrams", 0),
        "rejected": summary.get("rejected", {}),
        "processed": summary.get("processed", 0),
        "master_nav_ms_p50": summary.get("nav_ms_p50"),
        "rel_pos_err_rms_m_rtk_fixed_targets": (float(np.sqrt(np.mean([t["rel_pos_err_rms_m"] ** 2 for t in clean])))
                                                if clean else None),
        "scene": scene,
        "imu_grades": summary.get("imu_grades", {}),
        "imu_grades_final": summary.get("imu_grades_final"),
        "imu_faults_injected": {a.actor_id: {"unit": f"imu{a.imu_fault[0] + 1}", "fault": a.imu_fault[1]}
                                for a in sc.actors.values() if a.imu_fault},
        "degraded_vehicles": summary.get("degraded_vehicles", []),
        "degraded_vehicles_ever": sorted(vid for vid, g in (summary.get("imu_grades") or {}).items()
                                         if (g or {}).get("degraded_regrades")),
        "exit_codes": exit_codes,
        "notes": ("errors against the scenario truth at the master time of each VALID result, reference point "
                  "to reference point; latency = master GPS time - target time of validity (includes the "
                  "injected link delay); e2e = slave publish wall time to outputs written (excludes it)"),
    }


def evaluate_scene(sc, plan: FleetPlan) -> dict | None:
    """V2L / V2X errors: the master's recorded lane lateral distances and object distances against
    the same scene evaluated with the master's true state."""
    if not (plan.results_npz and plan.results_npz.exists() and plan.geojson and plan.geojson.exists()):
        return None
    with np.load(plan.results_npz) as z:
        if "scene" not in z.files:
            return None
        rec = z["scene"]
    from v2xpos.scene import Scene
    from v2xpos.types import NavState
    scene = Scene.load(plan.geojson)
    mp = np.array([float(sc.master.geometry.points_body_m[:, 0].max()), 0.0, 0.0])
    rec = rec[rec[:, 0] >= sc.epoch_gps_s]
    if not len(rec):
        return None
    tr = sc.master.truth.sample(rec[:, 0])
    truth = []
    for i in range(len(rec)):
        st = NavState(t_s=float(rec[i, 0]), lla=tr["lla"][i], v_ned_mps=tr["v_ned_mps"][i],
                      acc_body_mps2=tr["acc_body_mps2"][i], rate_body_rps=tr["w_nb_b_rps"][i], rpy_rad=tr["rpy_rad"][i])
        r = scene.evaluate(st, mp)
        truth.append([*r.lane_lateral_m, *r.object_distance_m])
    truth = np.asarray(truth)
    n_lanes = len(scene.evaluate(st, mp).lane_lateral_m)
    err = rec[:, 1:] - truth
    names = [*scene.lane_ids, *scene.evaluate(st, mp).object_ids]
    return {"updates": int(len(rec)),
            "lane_lateral_err_rms_m": {str(n): float(np.sqrt(np.mean(err[:, i] ** 2))) for i, n in enumerate(names[:n_lanes])},
            "object_distance_err_rms_m": {str(n): float(np.sqrt(np.mean(err[:, n_lanes + i] ** 2)))
                                          for i, n in enumerate(names[n_lanes:])}}


def make_plots(sc, plan: FleetPlan, out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = {}
    if plan.results_npz and plan.results_npz.exists():
        with np.load(plan.results_npz) as z:
            rows = {k[len("target_"):]: z[k] for k in z.files if k.startswith("target_")}
    ser = {vid: evaluate.series(sc, vid, r) for vid, r in rows.items() if vid in sc.actors}
    paths = []
    fig, ax = plt.subplots(figsize=(10, 5))
    for k, (vid, s) in enumerate(sorted(ser.items())):
        # one colour per target: compensated dots, uncompensated crosses (markers big enough to
        # show in the legend, which is drawn with larger markers still)
        ax.plot(s["t_rel_s"], s["err_m"] * 100, ".", ms=2, color=f"C{k}", label=f"{vid} compensated")
        ax.plot(s["t_rel_s"], s["unc_err_m"] * 100, "x", ms=2, mew=0.5, alpha=0.5, color=f"C{k}",
                label=f"{vid} uncompensated")
    ax.set_yscale("log")
    ax.set_xlabel("time since epoch [s]")
    ax.set_ylabel("relative position error [cm]")
    ax.set_title("Relative position error vs truth (VALID results), with and without latency compensation")
    ax.legend(fontsize=7, ncol=2, markerscale=4)
    ax.grid(True, which="both", alpha=0.3)
    paths.append(out / "rel_pos_error.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 5))
    for vid, s in sorted(ser.items()):
        ok = s["status"] == 0
        ax.plot(s["t_rel_s"][ok], s["range_m"][ok], ".", ms=1.5, label=f"{vid} master")
        ax.plot(s["t_rel_s"], s["range_true_m"], "k-", lw=0.5)
    ax.set_xlabel("time since epoch [s]")
    ax.set_ylabel("range [m]")
    ax.set_title("Range to each target (dots: master output, black: truth)")
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)
    paths.append(out / "range.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 5))
    lat = np.concatenate([s["latency_ms"][np.isfinite(s["latency_ms"])] for s in ser.values()]) if ser else np.zeros(0)
    if len(lat):
        ax.hist(lat, bins=100)
    ax.set_xlabel("latency = master time - target time of validity [ms]")
    ax.set_ylabel("results")
    ax.set_title("Latency histogram (includes injected link delay)")
    paths.append(out / "latency_hist.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 4))
    names = sorted(ser)
    from v2xpos.output.foxglove import STATUS_RGBA
    from v2xpos.wire import TargetStatus
    for i, vid in enumerate(names):
        s = ser[vid]
        for st in TargetStatus:
            m = s["status"] == int(st)
            if m.any():
                ax.plot(s["t_rel_s"][m], np.full(m.sum(), i), "|", color=STATUS_RGBA[st.name.lower()], ms=8,
                        label=st.name.lower())
    handles = {h.get_label(): h for h in ax.get_lines()}   # one legend entry per status seen
    ax.legend(handles.values(), handles.keys(), fontsize=7, loc="upper right", ncol=3)
    ax.set_yticks(range(len(names)))
    ax.set_yticklabels(names)
    ax.set_ylim(-0.7, len(names) - 0.3 + 0.8)
    ax.set_xlabel("time since epoch [s]")
    ax.set_ylabel("target")
    ax.set_title("Target status of every result over time")
    paths.append(out / "status.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


def run(args: argparse.Namespace) -> int:
    if args.vehicles < 2:
        print("v2xpos demo: --vehicles must be >= 2 (master + at least one slave)", file=sys.stderr)
        return 2
    if not (math.isfinite(args.duration) and args.duration > 0):
        print(f"v2xpos demo: --duration must be > 0 s, got {args.duration:g}", file=sys.stderr)
        return 2
    try:
        check_rtk_vertical_factor(args.rtk_vertical_factor)
    except ValueError as exc:
        print(f"v2xpos demo: --{str(exc).replace('_', '-')}", file=sys.stderr)
        return 2
    report = run_demo(args.vehicles, args.duration, args.latency_ms, args.jitter_ms, args.seed, args.out,
                      args.source, not args.no_pedestrian, not args.no_degradations, not args.no_spikes,
                      not args.no_live, args.port, rtk_vertical_factor=args.rtk_vertical_factor)
    partial = " (PARTIAL: interrupted)" if report.get("partial") else ""
    print(f"\nreport: {Path(args.out) / 'report.json'}{partial}")
    if "report_error" in report:
        print(f"v2xpos demo: interrupted before results: {report['report_error']}", file=sys.stderr)
        return 130
    for t in report["targets"]:
        def g(k, fmt=".3f"):
            return "-" if t.get(k) is None else format(t[k], fmt)
        print(f"  {t['id']:<4} {t['kind']:<10} samples={t['samples']:<5} valid={t['valid_fraction']:.2f} "
              f"rel_pos_rms={g('rel_pos_err_rms_m')} m (GNSS floor {g('gnss_rel_err_rms_1s_m')}) p99={g('rel_pos_err_p99_m')} m "
              f"uncomp_rms={g('uncompensated_rel_pos_err_rms_m')} m vel_rms={g('rel_vel_err_rms_mps')} m/s "
              f"lat p50/p99={g('latency_ms_p50', '.1f')}/{g('latency_ms_p99', '.1f')} ms rejected={t['rejected']}")
    ms = (lambda x: "-" if x is None else f"{x:.2f}")
    print(f"  master pipeline p50/p99 = {ms(report['master_pipeline_ms_p50'])}/{ms(report['master_pipeline_ms_p99'])} ms; "
          f"e2e p50/p99 = {ms(report['e2e_ms_p50'])}/{ms(report['e2e_ms_p99'])} ms; CAN frames {report['can_frames']}, "
          f"UDP datagrams {report['udp_datagrams']}")
    se = report.get("sensor_evaluation") or {}
    if "report" in se:
        lat, yaw, rb = se["latency_ms"], se["mount_yaw_deg"], se["range_bias_m"]
        print(f"  simulated front radar judged against the session: latency {lat['value']:.1f} +- {lat['sd']:.1f} ms, "
              f"mounting yaw {yaw['value']:.2f} +- {yaw['sd']:.2f} deg, range bias {rb['value']:.3f} +- {rb['sd']:.3f} m "
              f"(injected {se['injected']['latency_ms']:g} ms, {se['injected']['mount_yaw_deg']:g} deg, "
              f"{se['injected']['range_bias_m']:g} m); report {se['report']}")
    if report.get("partial"):
        print(f"v2xpos demo: interrupted; partial report in {Path(args.out) / 'report.json'}", file=sys.stderr)
        return 130
    bad = {k: v for k, v in report["exit_codes"].items() if v != 0}
    if bad:
        print(f"  processes with non-zero exit: {bad} (see {Path(args.out) / 'logs'})", file=sys.stderr)
        return 1
    return 0
