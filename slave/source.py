"""State sources of a slave (and of the master's own vehicle), advanced in real time.

A source turns sensor data into navigation states: ``advance(t_gps_s)`` consumes every sample with
time of validity <= t_gps_s and returns the NavStates produced (one per IMU epoch), in order.

* ``InsSimSource``: the actor's simulated IMU (100 Hz, error model ``sim.sensors.ImuErrorModel``
  preset) and RTK GNSS (10 Hz, 1 cm fixed, the scenario's fix schedule, antenna lever arm) run
  through the navigation filter ``v2xpos.ins.InsFilter`` -- the product path.
* ``DatasetSource``: a recorded drive (``v2xpos.datasets``) through the same filter, paced at real
  time (its GPS times shifted onto the scenario epoch when asked).
* ``TruthNoiseSource``: truth plus first-order Gauss-Markov position noise scaled by the fix
  status. No filter: a load generator / fallback for link tests only.

Initialisation of the filter (a vehicle that was aligned before the run starts): position from
truth + N(0, 1 cm), velocity + N(0, 2 cm/s), roll/pitch + N(0, 0.1 deg), yaw + N(0, 0.3 deg),
drawn from the actor's seed, at the first IMU epoch of the run.
"""
from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from sim.scenarios import Actor, Scenario
from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from v2xpos import geo
from v2xpos.types import FixStatus, NavState

IMU_RATE_HZ = 100.0
GNSS_RATE_HZ = 10.0


class NavSource(Protocol):
    """Anything that yields navigation states as time advances."""
    name: str

    def advance(self, t_gps_s: float) -> list[NavState]: ...


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
    """InsConfig stochastic model from the simulated IMU's specification (``ImuErrorModel.preset``,
    the datasheet of the unit): white noise densities x ``margin``, bias priors at 3x the preset's
    1-sigma turn-on bias, bias instability at the preset's bias / 3 (floors keep the model sane for
    the ideal preset)."""
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
    """Simulated sensors of one actor through the real GNSS/INS filter (see module docstring)."""

    def __init__(self, sc: Scenario, actor: Actor, platform: str | None = None, effects: tuple = (),
                 cov_every: int = 10):
        from v2xpos.ins import InsConfig, InsFilter
        self.name = "ins"
        self.actor = actor
        self.sensors = _SimSensors(sc, actor)
        plat = platform or ("pedestrian" if actor.kind == "pedestrian" else "car")
        self.filter = InsFilter(InsConfig(platform=plat, imu_to_body=np.eye(3),
                                          lever_arm_m=np.asarray(actor.lever_arm_m, float),
                                          effects=tuple(effects), cov_every=cov_every,
                                          **filter_noise(actor.imu_grade)))
        self._init_rng = np.random.default_rng(actor.seed + 7)
        self.initialized = False
        self._make_filter = lambda: InsFilter(self.filter.cfg)

    def warm_up(self) -> None:
        """Run a throw-away filter over 0.3 s of data so JIT compilation (or loading the numba cache)
        happens before real time starts."""
        f = self._make_filter()
        imu, gnss = self.sensors.imu, self.sensors.gnss
        s = self.actor.truth.sample(float(imu.t_s[0]))
        f.initialize(float(imu.t_s[0]), s["lla"][0], s["v_ned_mps"][0], s["rpy_rad"][0])
        for k in range(1, 31):
            f.process_imu(float(imu.t_s[k]), imu.acc_mps2[k], imu.gyro_rps[k])
        f.update_gnss(float(gnss.t_s[1]), gnss.lla[1], gnss.sd_ned_m[1], FixStatus(int(gnss.fix[1])),
                      vel_ned_mps=gnss.vel_ned_mps[1], vel_sd_ned_mps=gnss.vel_sd_ned_mps[1])
        f.nav_state()

    def _initialize(self, t_s: float) -> None:
        s = self.actor.truth.sample(t_s)
        rng = self._init_rng
        r_ned = s["r_ned_m"][0] + rng.normal(0, 0.01, 3)
        lla = geo.ned_to_lla(r_ned, self.actor.truth.lla0)
        v = s["v_ned_mps"][0] + rng.normal(0, 0.02, 3)
        rpy = s["rpy_rad"][0] + rng.normal(0, 1.0, 3) * np.radians([0.1, 0.1, 0.3])
        self.filter.initialize(t_s, lla, v, rpy)
        self.initialized = True

    def advance(self, t_gps_s: float) -> list[NavState]:
        imu, gnss, sen = self.sensors.imu, self.sensors.gnss, self.sensors
        out: list[NavState] = []
        n_imu = len(imu.t_s)
        while sen.i_imu < n_imu and imu.t_s[sen.i_imu] <= t_gps_s:
            k = sen.i_imu
            t_k = float(imu.t_s[k])
            if not self.initialized:
                sen.seek(t_k)
                self._initialize(t_k)
                sen.i_imu = k + 1
                continue
            self.filter.process_imu(t_k, imu.acc_mps2[k], imu.gyro_rps[k])
            while sen.i_gnss < len(gnss.t_s) and gnss.t_s[sen.i_gnss] <= t_k + 1e-6:
                j = sen.i_gnss
                self.filter.update_gnss(float(gnss.t_s[j]), gnss.lla[j], gnss.sd_ned_m[j], FixStatus(int(gnss.fix[j])),
                                        vel_ned_mps=gnss.vel_ned_mps[j], vel_sd_ned_mps=gnss.vel_sd_ned_mps[j])
                sen.i_gnss += 1
            sen.i_imu = k + 1
            out.append(self.filter.nav_state())
        return out


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


class DatasetSource:
    """A recorded drive (``v2xpos.datasets.load_dataset``: IMU + GNSS with the declared mounting and
    lever arm) through the INS filter, paced by the caller's clock.

    ``time_shift_s`` is added to the recording's GPS times so that its first IMU sample falls on the
    scenario epoch (``align_to_epoch``); ``advance(t)`` consumes every sample with shifted time <= t.
    The filter aligns itself from the data (no truth). GNSS epochs are fed when their time is reached.
    """

    def __init__(self, path: str, epoch_gps_s: float | None = None, t_skip_s: float = 0.0):
        from v2xpos.datasets.loader import load_dataset
        from v2xpos.ins import InsConfig, InsFilter
        self.name = "dataset"
        self.ds = load_dataset(path)
        self.kind = "pedestrian" if self.ds.platform == "pedestrian" else "vehicle"
        plat = self.ds.platform if self.ds.platform in ("car", "pedestrian") else "generic"
        self.filter = InsFilter(InsConfig(platform=plat, imu_to_body=self.ds.imu_to_body,
                                          lever_arm_m=self.ds.lever_arm_m, lever_arm_sd_m=self.ds.lever_arm_sd_m))
        t0 = float(self.ds.imu.t_s[0]) + t_skip_s
        self.time_shift_s = 0.0 if epoch_gps_s is None else epoch_gps_s - t0
        self.i_imu = int(np.searchsorted(self.ds.imu.t_s, t0))
        self.i_gnss = int(np.searchsorted(self.ds.gnss.t_s, t0))
        self.last_t_s = -math.inf
        self.non_monotonic = 0

    def warm_up(self) -> None:
        """Nothing precomputed beyond loading; the JIT is warmed by the first samples."""

    def advance(self, t_gps_s: float) -> list[NavState]:
        imu, gnss = self.ds.imu, self.ds.gnss
        t_data = t_gps_s - self.time_shift_s
        out = []
        n = len(imu.t_s)
        while self.i_imu < n and imu.t_s[self.i_imu] <= t_data:
            k = self.i_imu
            t_k = float(imu.t_s[k])
            while self.i_gnss < len(gnss.t_s) and gnss.t_s[self.i_gnss] <= t_k:
                j = self.i_gnss
                vel = None if gnss.vel_ned_mps is None else gnss.vel_ned_mps[j]
                vsd = None if gnss.vel_sd_ned_mps is None else gnss.vel_sd_ned_mps[j]
                self.filter.update_gnss(float(gnss.t_s[j]), gnss.lla[j], gnss.sd_ned_m[j], FixStatus(int(gnss.fix[j])),
                                        vel_ned_mps=vel, vel_sd_ned_mps=vsd)
                self.i_gnss += 1
            self.filter.process_imu(t_k, imu.acc_mps2[k], imu.gyro_rps[k])
            self.i_imu = k + 1
            if self.filter.initialized:
                nav = self.filter.nav_state()
                nav.t_s = nav.t_s + self.time_shift_s
                if nav.t_s <= self.last_t_s:       # the estimated IMU time offset moved the label back
                    self.non_monotonic += 1
                    continue
                self.last_t_s = nav.t_s
                out.append(nav)
        return out


SOURCES = {"ins": InsSimSource, "truth_noise": TruthNoiseSource}


def simulated_gnss(sc: Scenario, actor: Actor):
    """The GNSS solutions (GnssData) the simulated source of ``actor`` feeds its filter: the same
    seed and the same draws as ``make_source``'s ins source."""
    return _SimSensors(sc, actor).gnss


def make_source(kind: str, sc: Scenario, actor: Actor, dataset: str | None = None,
                align_to_epoch: bool = True) -> NavSource:
    """Source by config name: ``ins`` (default, the real filter on simulated sensors),
    ``truth_noise``, or ``dataset`` (a recording through the filter, ``dataset`` = its path)."""
    if kind == "dataset":
        if not dataset:
            raise ValueError("[source] type 'dataset' needs [source].dataset = <path>")
        return DatasetSource(dataset, sc.epoch_gps_s if align_to_epoch else None)
    if kind not in SOURCES:
        raise ValueError(f"[source] type {kind!r} is not one of {sorted(SOURCES) + ['dataset']}")
    return SOURCES[kind](sc, actor)
