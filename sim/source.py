"""The simulator as a vehicle source (``[source] type = "sim"``): one actor of a scenario, on the
scenario's clock. The services reach it only through ``v2xpos.sources.make_source`` (the config
names ``factory = "sim.source:from_config"``, or the ``v2xpos.sources`` entry point ``sim``); no
module of the library or the services imports ``sim``.

``[source]`` table::

    type = "sim"
    factory = "sim.source:from_config"
    scenario = "convoy"          # sim.scenarios builder
    actor = "t1"                 # default: the service's vehicle id
    model = "ins"                # ins: simulated sensors through the INS filter | truth_noise
    start_file = "out/demo/start_stamp"   # start handshake with the launcher (optional)
    start_unix_s = 0             # or a fixed wall time of the scenario epoch (0: now + 1 s)
    [source.params]              # scenario parameters, identical in every process
    vehicles = 4

Models, advanced by ``advance(t_gps_s)`` (every sample with time of validity <= t_gps_s; one
NavState per IMU epoch, in order):

* ``InsSimSource``: the actor's simulated IMU (100 Hz, error model ``sim.sensors.ImuErrorModel``
  preset) and RTK GNSS (10 Hz, 1 cm fixed, the scenario's fix schedule, antenna lever arm) run
  through the navigation filter ``v2xpos.ins.InsFilter`` -- the product path.
* ``TruthNoiseSource``: truth plus first-order Gauss-Markov position noise scaled by the fix
  status. No filter: a load generator / fallback for link tests only.

Clock (``ScenarioClock``): ``t_gps = epoch + (wall - start stamp)``; the start stamp comes from the
launcher's handshake file (every process of a run shares it) or the config.

Initialisation of the filter (a vehicle that was aligned before the run starts): position from
truth + N(0, 1 cm), velocity + N(0, 2 cm/s), roll/pitch + N(0, 0.1 deg), yaw + N(0, 0.3 deg),
drawn from the actor's seed, at the first IMU epoch of the run.
"""
from __future__ import annotations

import math
import time

import numpy as np

from sim.scenarios import Actor, Scenario, build, check_params
from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from v2xpos import geo
from v2xpos.sources.base import SessionClock, SourceContext, SourceError, VehicleSource
from v2xpos.types import FixStatus, NavState

IMU_RATE_HZ = 100.0
GNSS_RATE_HZ = 10.0
WARMUP_S = 1.0
"""The filters run this long before the scenario epoch (states are published from then on)."""
HISTORY_S = 1.5
"""``warm_up`` runs the filter through the driving history up to this long before the epoch."""


class _SimSensors:
    """Precomputed sensor streams of one actor over its whole truth trajectory."""

    def __init__(self, sc: Scenario, actor: Actor):
        rng = np.random.default_rng(actor.seed)
        self.imu = simulate_imu(actor.truth, ImuErrorModel.preset(actor.imu_grade, rng), rate_hz=IMU_RATE_HZ,
                                rng=rng)
        sd = GnssErrorModel().sd_h_m
        sd[FixStatus.FIXED] = actor.gnss_sd_fixed_m
        gm = GnssErrorModel(rate_hz=GNSS_RATE_HZ, sd_h_m=sd, vertical_factor=actor.gnss_vertical_factor,
                            lever_arm_m=np.asarray(actor.lever_arm_m, float))
        self.gnss = simulate_gnss(actor.truth, gm, rng=rng, fix_schedule=sc.fix_schedule_abs(actor.actor_id))
        self.i_imu = 0
        self.i_gnss = 0

    def seek(self, t_gps_s: float) -> None:
        """Skip every sample before t_gps_s."""
        self.i_imu = int(np.searchsorted(self.imu.t_s, t_gps_s - 1e-9))
        self.i_gnss = int(np.searchsorted(self.gnss.t_s, t_gps_s - 1e-9))


def filter_noise(imu_grade: str, margin: float = 3.0) -> dict:
    """InsConfig stochastic model (fields of its ``imu`` group) from the simulated IMU's
    specification (``ImuErrorModel.preset``, the datasheet of the unit): white noise densities x
    ``margin``, bias priors at 3x the preset's 1-sigma turn-on bias, bias instability at the
    preset's bias / 3 (floors keep the model sane for the ideal preset)."""
    rng = np.random.default_rng(0)
    draws = [ImuErrorModel.preset(imu_grade, rng) for _ in range(200)]
    spec = draws[0]
    bg = max(float(np.std([d.gyro_bias_rps for d in draws])), 1e-6)      # the preset's 1-sigma
    ba = max(float(np.std([d.accel_bias_mps2 for d in draws])), 1e-4)
    return {"gyro_noise_rps_rthz": max(spec.gyro_noise_rps_rthz * margin, 1e-5),
            "accel_noise_mps2_rthz": max(spec.accel_noise_mps2_rthz * margin, 1e-4),
            "gyro_bias_init_sd_rps": 3 * bg, "accel_bias_init_sd_mps2": 3 * ba,
            "gyro_bias_sd_rps": bg / 3, "accel_bias_sd_mps2": ba / 3}


class InsSimSource:
    """Simulated sensors of one actor through the real GNSS/INS filter on the driver (see module
    docstring): the samples up to the session time go to ``v2xpos.ins.driver.InsDriver`` as they
    become due, which orders and applies them as for every other source."""

    def __init__(self, sc: Scenario, actor: Actor, platform: str | None = None, effects: tuple = (),
                 cov_every: int = 10):
        from v2xpos.ins import InsFilter
        from v2xpos.ins.driver import InsDriver
        from v2xpos.ins.profiles import vehicle_config
        self.name = "ins"
        self.actor = actor
        self.sensors = _SimSensors(sc, actor)
        plat = platform or ("pedestrian" if actor.kind == "pedestrian" else "car")
        # the simulated vehicle as declared (identity mounting, its lever arm) in the plain profile,
        # with the filter noise of its IMU's datasheet (``filter_noise``) and the effect states asked for
        self.filter = InsFilter(vehicle_config(plat, np.eye(3), np.asarray(actor.lever_arm_m, float), 0.1,
                                               profile="plain", effects={"states": tuple(effects)},
                                               numerics={"cov_every": cov_every},
                                               # a simulated vehicle is exactly as declared: nothing for
                                               # turning to verify and a failed test is a false alarm,
                                               # lifted when it passes again (docs/integrity.md)
                                               consistency={"verify_turn_deg": 0.0, "consistency_reverify": True},
                                               imu=filter_noise(actor.imu_grade)))
        self.driver = InsDriver(self.filter, emit_states=True)
        self._init_rng = np.random.default_rng(actor.seed + 7)
        self.initialized = False

    def warm_up(self) -> None:
        """Compile the filter's kernels (or load the numba cache) before real time starts."""
        from v2xpos.ins.driver import warm_up
        warm_up(self.filter.cfg)

    def _initialize(self, t_s: float) -> None:
        s = self.actor.truth.sample(t_s)
        rng = self._init_rng
        r_ned = s["r_ned_m"][0] + rng.normal(0, 0.01, 3)
        lla = geo.ned_to_lla(r_ned, self.actor.truth.lla0)
        v = s["v_ned_mps"][0] + rng.normal(0, 0.02, 3)
        rpy = s["rpy_rad"][0] + rng.normal(0, 1.0, 3) * np.radians([0.1, 0.1, 0.3])
        self.driver.initialize(t_s, lla, v, rpy)
        self.initialized = True

    def advance(self, t_gps_s: float) -> list[NavState]:
        imu, gnss, sen = self.sensors.imu, self.sensors.gnss, self.sensors
        if not self.initialized:
            if sen.i_imu >= len(imu.t_s) or imu.t_s[sen.i_imu] > t_gps_s:
                return []
            t_k = float(imu.t_s[sen.i_imu])
            sen.seek(t_k)
            self._initialize(t_k)
            sen.i_imu += 1
        j = int(np.searchsorted(imu.t_s, t_gps_s, side="right"))
        if j > sen.i_imu:
            self.driver.push_imu_block(imu.t_s[sen.i_imu:j], imu.acc_mps2[sen.i_imu:j], imu.gyro_rps[sen.i_imu:j])
            sen.i_imu = j
        j = int(np.searchsorted(gnss.t_s, t_gps_s, side="right"))
        for k in range(sen.i_gnss, j):
            self.driver.push_gnss(float(gnss.t_s[k]), gnss.lla[k], gnss.sd_ned_m[k], FixStatus(int(gnss.fix[k])),
                                  gnss.vel_ned_mps[k], gnss.vel_sd_ned_mps[k])
        sen.i_gnss = max(sen.i_gnss, j)
        return self.driver.run()


class TruthNoiseSource:
    """Truth at 100 Hz plus Gauss-Markov position noise (tau 30 s) of the fix status' 1-sigma;
    fix status from the scenario schedule. Not a navigation filter (see module docstring)."""

    SD_M = {FixStatus.FIXED: 0.01, FixStatus.FLOAT: 0.15, FixStatus.SINGLE: 1.5}

    def __init__(self, sc: Scenario, actor: Actor, rate_hz: float = IMU_RATE_HZ):
        self.name = "truth_noise"
        self.actor = actor
        self.epoch = sc.epoch_gps_s
        self.schedule = actor.fix_schedule
        self.dt = 1.0 / rate_hz
        self.rng = np.random.default_rng(actor.seed)
        self.gm = np.zeros(3)
        self.next_t: float | None = None

    def warm_up(self) -> None:
        """Nothing to compile."""

    def _fix(self, t_s: float) -> FixStatus:
        rel = t_s - self.epoch
        for t0, t1, st in self.schedule:
            if t0 <= rel < t1:
                return FixStatus(st)
        return FixStatus.FIXED

    def advance(self, t_gps_s: float) -> list[NavState]:
        if self.next_t is None:
            self.next_t = math.ceil(t_gps_s / self.dt) * self.dt
        times = []
        while self.next_t <= t_gps_s:
            times.append(self.next_t)
            self.next_t += self.dt
        if not times:
            return []
        tr = self.actor.truth
        phi = math.exp(-self.dt / 30.0)
        out = []
        for t in times:
            k = min(max(int(round((t - tr.t_s[0]) / tr.dt_s)), 0), len(tr.t_s) - 1)   # nearest truth sample
            fix = self._fix(t)
            sd = self.SD_M.get(fix, 5.0)
            self.gm = phi * self.gm + math.sqrt(1 - phi * phi) * self.rng.normal(0, 1, 3)
            r = tr.r_ned_m[k] + self.gm * sd
            out.append(NavState(t_s=t, lla=geo.ned_to_lla(r, tr.lla0), v_ned_mps=tr.v_ned_mps[k].copy(),
                                acc_body_mps2=tr.C_nb[k].T @ tr.a_ned_mps2[k], rate_body_rps=tr.w_nb_b_rps[k].copy(),
                                rpy_rad=tr.rpy_rad[k].copy(), pos_sd_m=np.full(3, sd), vel_sd_mps=np.full(3, 0.02),
                                att_sd_rad=np.full(3, 0.002), fix=fix))
        return out


def imu_units(sc: Scenario, actor: Actor, nav_imu=None) -> tuple[dict, dict]:
    """All IMU units of an actor for grading: ``({unit_id: ImuData}, {unit_id: mounting X-Y-Z deg})``.

    imu1 is the navigation unit (``nav_imu`` when given, mounted along the body axes); unit k >= 2 is
    mounted rotated by 90 (k-1) deg about z (declared), with its own error draw from the actor's
    IMU grade; the scenario's ``imu_fault`` (``sim.imu_faults.inject_fault``) is applied to its unit.
    """
    from sim.imu_faults import DEFAULT_MAGNITUDE, FaultSpec, inject_fault
    rng = np.random.default_rng(actor.seed + 555)
    units, mounting = {}, {}
    for k in range(actor.imu_units):
        uid = f"imu{k + 1}"
        yaw = 90.0 * k
        c, s_ = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        C_body_imu = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        model = ImuErrorModel.preset(actor.imu_grade, rng)
        imu = nav_imu if (k == 0 and nav_imu is not None) else simulate_imu(
            actor.truth, model, rate_hz=IMU_RATE_HZ, rng=rng, imu_to_body=C_body_imu)
        if actor.imu_fault is not None and actor.imu_fault[0] == k:
            _, kind, t_rel = actor.imu_fault
            noise = model.gyro_noise_rps_rthz * math.sqrt(IMU_RATE_HZ)
            start = max(0.0, sc.epoch_gps_s + t_rel - float(imu.t_s[0]))
            imu = inject_fault(imu, FaultSpec(kind, DEFAULT_MAGNITUDE[kind], 2, start), noise, rng)
        units[uid] = imu
        mounting[uid] = [0.0, 0.0, yaw]
    return units, mounting


SOURCES = {"ins": InsSimSource, "truth_noise": TruthNoiseSource}


def simulated_gnss(sc: Scenario, actor: Actor):
    """The GNSS solutions (GnssData) the simulated source of ``actor`` feeds its filter: the same
    seed and the same draws as ``make_source``'s ins source."""
    return _SimSensors(sc, actor).gnss




class ScenarioClock(SessionClock):
    """Scenario time: ``t_gps = epoch + (wall - start)``. ``start()`` takes the start stamp from the
    launcher's handshake file (``start_file``: signal ``<file>.ready.<id>``, then wait for the
    stamp), else from ``start_unix_s`` (0: one second from now)."""

    def __init__(self, epoch_gps_s: float, vehicle_id: str, start_file: str | None = None,
                 start_unix_s: float = 0.0, timeout_s: float = 120.0):
        self.epoch_gps_s = float(epoch_gps_s)
        self.t_start_gps_s = self.epoch_gps_s
        self.vehicle_id = vehicle_id
        self.start_file = start_file
        self.start_unix_s = float(start_unix_s) if start_unix_s > 0 else time.time() + WARMUP_S
        self.timeout_s = timeout_s

    def now_gps_s(self) -> float:
        return self.epoch_gps_s + (time.time() - self.start_unix_s)

    def wall_of(self, t_gps_s: float) -> float:
        return self.start_unix_s + (t_gps_s - self.epoch_gps_s)

    def start(self, stop=lambda: False) -> bool:
        if self.start_file is None:
            return not stop()
        from sim.launcher import signal_ready_and_wait
        got = signal_ready_and_wait(self.start_file, self.vehicle_id, timeout_s=self.timeout_s, stop=stop)
        if got is None:
            if stop():
                return False
            raise TimeoutError(f"no start stamp in {self.start_file} after {self.timeout_s:.0f} s")
        self.start_unix_s = got
        return True

    def status(self) -> dict:
        return {"kind": "scenario", "epoch_gps_s": self.epoch_gps_s, "t_rel_s": self.now_gps_s() - self.epoch_gps_s}


class SimSource(VehicleSource):
    """One actor of a scenario as a vehicle source (see the module docstring)."""

    name = "sim"

    def __init__(self, sc: Scenario, actor: Actor, model: str = "ins", start_file: str | None = None,
                 start_unix_s: float = 0.0):
        self.sc = sc
        self.actor = actor
        self.kind = actor.kind
        self.geometry = actor.geometry
        self.model = SOURCES[model](sc, actor)
        self.start_file = start_file
        self.start_unix_s = start_unix_s

    def make_clock(self, ctx: SourceContext) -> SessionClock:
        return ScenarioClock(self.sc.epoch_gps_s, ctx.vehicle_id, self.start_file, self.start_unix_s)

    def warm_up(self) -> None:
        """JIT warm-up, then the driving history up to HISTORY_S before the epoch (filter converged)."""
        self.model.warm_up()
        if isinstance(self.model, InsSimSource):
            self.model.advance(self.sc.epoch_gps_s - HISTORY_S)

    def prime(self, t_gps_s: float):
        return None

    def advance(self, t_gps_s: float) -> list[NavState]:
        return self.model.advance(t_gps_s)

    def finished(self, t_gps_s: float) -> bool:
        return t_gps_s > self.sc.epoch_gps_s + self.sc.duration_s + 5.0

    def imu_units(self):
        if self.actor.imu_units < 2:
            return None
        sen = getattr(self.model, "sensors", None)
        return imu_units(self.sc, self.actor, sen.imu if sen is not None else None)

    def status(self) -> dict:
        return {"source": self.name, "scenario": self.sc.name, "actor": self.actor.actor_id,
                "model": self.model.name}


SIM_KEYS = ("factory", "scenario", "actor", "model", "params", "start_file", "start_unix_s")


def check_table(table: dict, where: str) -> None:
    """Validate a ``sim`` ``[source]`` table (keys, model, scenario parameters) without building the
    scenario; SourceError naming ``where`` and the key."""
    from v2xpos.schema import check_choice, check_keys
    check_keys(table, SIM_KEYS, where, SourceError)
    model = table.get("model", "ins")
    check_choice(model, sorted(SOURCES), f"{where}.model", SourceError)
    params = table.get("params", {})
    if not isinstance(params, dict):
        raise SourceError(f"{where}.params: expected a table of scenario parameters")
    name = str(table.get("scenario", "convoy"))
    try:
        check_params(name, params, f"{where.rstrip(']')}.params]" if where.endswith("]") else f"{where}.params")
    except ValueError as exc:
        raise SourceError(str(exc)) from None
    start_unix = table.get("start_unix_s", 0.0)
    if isinstance(start_unix, bool) or not isinstance(start_unix, (int, float)):
        raise SourceError(f"{where}.start_unix_s: expected a number, got {start_unix!r}")
    for key in ("scenario", "actor", "start_file"):
        if key in table and not isinstance(table[key], str):
            raise SourceError(f"{where}.{key}: expected a string, got {table[key]!r}")


def from_config(table: dict, where: str, ctx: SourceContext) -> SimSource:
    """``[source] type = "sim"`` (see the module docstring); errors name ``where`` and the key."""
    check_table(table, where)
    name = str(table.get("scenario", "convoy"))
    try:
        sc = build(name, **table.get("params", {}))
    except (TypeError, ValueError) as exc:
        raise SourceError(str(exc)) from None
    actor_id = table.get("actor") or ctx.vehicle_id
    if actor_id not in sc.actors:
        raise SourceError(f"{where}.actor: {actor_id!r} not in scenario actors {sorted(sc.actors)}")
    start_file = table.get("start_file")
    start_unix = table.get("start_unix_s", 0.0)
    return SimSource(sc, sc.actors[actor_id], table.get("model", "ins"), None if start_file is None else str(ctx.resolve(start_file)),
                     float(start_unix))
