"""``v2xpos bench corpus``: a corpus of broken inputs, each run the way a user would run it.

Unlike ``v2xpos bench fuzz`` (random bytes into one reader at a time), every case here is one
deliberate, named damage of a real input -- a descriptor, an IMU csv, a ``.pos``, a TIMETAG, a
multi-IMU folder or a service config -- and it goes through the command that reads it:

* dataset cases: ``v2xpos replay DESCRIPTOR --check --json F`` and ``v2xpos calibrate ... --check``
  (the commands' own input path: ``load_for_command`` = loader + plausibility checks, exit codes,
  messages; ``--check`` stops before the filter runs, which is what makes 500 cases cheap);
* grade cases: ``v2xpos grade PATH --check --json F`` (loading, ``[grade]`` table, coverage);
* config cases: ``MasterConfig.load`` / ``SlaveConfig.load``, which validate every table including
  ``[source]`` (its type's own ``check_table``: a simulator source checks its scenario parameters).

The commands are called through ``v2xpos.cli.run_command`` (the dispatcher without the top-level
guard), so an exception a command did not turn into a message counts as a traceback. Outcomes:

* ``error``: exit code 2 and the damaged file's name in the message;
* ``warning``: exit code 0 (or 1) with the damage stated in the report (``input_checks.warnings`` /
  ``warnings`` in the JSON);
* failures: ``traceback`` (an exception escaped), ``silent`` (exit 0 and nothing stated),
  ``unnamed`` (exit 2 but the damaged file is not named), ``wrong_code`` (any other exit code).

Every generated case is damage that must be noticed (a mutation that leaves the input valid with
the same meaning, such as deleting a key whose default equals its value, is not generated).
Bases: the first ``BASE_SECONDS`` of ``drive_0708`` (written into the work folder, never into the
repository), the ``quadrotor_mimu/path_1`` folder (damaged files copied, the others linked) and
``configs/master.toml`` / ``configs/slave_t1.toml`` (recordings) and ``configs/master_sim.toml`` /
``configs/slave_p1.toml`` (the simulator, with scenario parameters).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import random
import re
import shutil
import sys
import tempfile
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from bench.corpus_damages import (config_damages, csv_damages, dataset_toml_damages, grade_damages, pos_damages,
                                  tag_damages)

ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = ROOT / ".." / "shared" / "data"
BASE_SECONDS = 60.0


@dataclass
class Case:
    """One broken input: ``kind`` says how it is run, ``target`` is what is passed to the command,
    ``damaged`` the file whose name an error message must carry."""
    name: str
    kind: str            # "dataset" | "grade" | "master_config" | "slave_config"
    target: Path
    damaged: Path


@dataclass
class Outcome:
    case: str
    kind: str
    status: str          # error | warning | traceback | silent | unnamed | wrong_code
    code: int | None
    message: str


@dataclass
class Corpus:
    cases: list[Case] = field(default_factory=list)
    base: dict = field(default_factory=dict)



# ------------------------------------------------------------------------------------ bases
def _write(path: Path, data: bytes | str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    path.write_bytes(data)
    return path


def make_dataset_base(work: Path, data_dir: Path = DATA_DIR, seconds: float = BASE_SECONDS) -> dict:
    """The first ``seconds`` of drive_0708 (IMU csv, its TIMETAG cut to match, the ``.pos`` epochs
    of that span) plus a descriptor naming them: returns the file contents by name."""
    from v2xpos.datasets.rtklib_pos import read_rtklib_pos
    from v2xpos.datasets.timetag import HEADER_BYTES, RECORD_DTYPE
    import numpy as np

    src = data_dir / "drive_0708"
    desc = (src / "dataset.toml").read_text()
    csv_raw = (src / "imu_1934.csv").read_bytes()
    ends = [m.end() for m in re.finditer(rb"\n", csv_raw)]
    n_lines = int(round(seconds * 100))
    csv = csv_raw[:ends[min(n_lines, len(ends)) - 1]]
    tag_raw = (src / "imu_1934.csv.tag").read_bytes()
    rec = np.frombuffer(tag_raw[HEADER_BYTES:], RECORD_DTYPE,
                        (len(tag_raw) - HEADER_BYTES) // RECORD_DTYPE.itemsize)
    n_rec = int(np.searchsorted(rec["byte_offset"], len(csv), side="left")) + 1
    tag = tag_raw[:HEADER_BYTES + n_rec * RECORD_DTYPE.itemsize]
    gnss, _ = read_rtklib_pos(src / "gnss_1934.pos")
    pos_lines = (src / "gnss_1934.pos").read_text().splitlines(keepends=True)
    header = [ln for ln in pos_lines if ln.startswith("%")]
    data_lines = [ln for ln in pos_lines if ln.strip() and not ln.startswith("%")]
    work.mkdir(parents=True, exist_ok=True)
    _write(work / "probe.csv", csv)
    _write(work / "probe.csv.tag", tag)
    from v2xpos.datasets.imu_csv import read_imu_csv
    t_end = float(read_imu_csv(work / "probe.csv", work / "probe.csv.tag").imu.t_s[-1])
    keep = [ln for ln, t in zip(data_lines, gnss.t_s) if t <= t_end]
    pos = "".join(header + keep)
    return {"dataset.toml": desc, "imu_1934.csv": csv, "imu_1934.csv.tag": tag, "gnss_1934.pos": pos}


def _materialise(folder: Path, files: dict, damaged: str | None = None, content=None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        _write(folder / name, content if name == damaged else data)
    return folder



# ------------------------------------------------------------------------------------ building
def build_corpus(work: Path, data_dir: Path = DATA_DIR, seed: int = 17) -> Corpus:
    """Write every case into ``work`` and return the list."""
    rng = random.Random(seed)
    corpus = Corpus()
    base = make_dataset_base(work / "base_probe", data_dir)
    corpus.base["dataset"] = _materialise(work / "dataset_base", base) / "dataset.toml"
    k = 0

    def add_dataset(name: str, damaged: str, content) -> None:
        nonlocal k
        folder = _materialise(work / f"d{k:04d}", base, damaged, content)
        corpus.cases.append(Case(name, "dataset", folder / "dataset.toml", folder / damaged))
        k += 1

    for name, content in dataset_toml_damages(base["dataset.toml"], rng):
        add_dataset(name, "dataset.toml", content)
    for name, content in csv_damages(base["imu_1934.csv"], rng):
        add_dataset(name, "imu_1934.csv", content)
    for name, content in pos_damages(base["gnss_1934.pos"], rng):
        add_dataset(name, "gnss_1934.pos", content)
    for name, content in tag_damages(base["imu_1934.csv.tag"], rng):
        add_dataset(name, "imu_1934.csv.tag", content)

    quad = data_dir / "quadrotor_mimu" / "path_1"
    if (quad / "IMU_1.csv").is_file():
        corpus.base["grade"] = quad
        for i, (name, fname, content) in enumerate(grade_damages(quad, rng)):
            folder = work / f"g{i:04d}"
            if folder.exists():
                shutil.rmtree(folder)       # links into the shared data: never write through them
            folder.mkdir(parents=True)
            for f in quad.glob("*.csv"):
                if f.name != fname:
                    (folder / f.name).symlink_to(f.resolve())
            _write(folder / fname, content)
            target = folder / "grade.toml" if fname == "grade.toml" else folder
            corpus.cases.append(Case(name, "grade", target, folder / fname))

    for kind, cfg in (("master_config", ROOT / "configs" / "master.toml"),
                      ("slave_config", ROOT / "configs" / "slave_t1.toml"),
                      ("master_config", ROOT / "configs" / "master_sim.toml"),
                      ("slave_config", ROOT / "configs" / "slave_p1.toml")):
        corpus.base.setdefault(kind, cfg)
        for i, (name, content) in enumerate(config_damages(cfg.read_text(), rng)):
            path = _write(work / f"{kind}_{cfg.stem}_{i:04d}" / cfg.name, content)
            corpus.cases.append(Case(f"{cfg.name}: {name}", kind, path, path))
    return corpus


# ------------------------------------------------------------------------------------ running
def _run_cli(argv: list[str]) -> tuple[int | None, str, str, str | None]:
    from v2xpos.cli import run_command
    out, err = io.StringIO(), io.StringIO()
    tb = None
    code: int | None = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = run_command(argv)
        except SystemExit as exc:   # argparse
            code = exc.code if isinstance(exc.code, int) else 2
        except Exception:  # noqa: BLE001 -- exactly what the corpus is looking for
            tb = traceback.format_exc()
    return code, out.getvalue(), err.getvalue(), tb


def _classify(case: Case, code, err: str, tb: str | None, warnings: list[str]) -> Outcome:
    if tb is not None:
        return Outcome(case.name, case.kind, "traceback", None, tb.strip().splitlines()[-1])
    line = " ".join(err.strip().splitlines()[-1:])
    if code == 2:
        named = case.damaged.name in err
        return Outcome(case.name, case.kind, "error" if named else "unnamed", code, line)
    if code in (0, 1):
        if warnings:
            return Outcome(case.name, case.kind, "warning", code, warnings[0])
        return Outcome(case.name, case.kind, "silent", code, line)
    return Outcome(case.name, case.kind, "wrong_code", code, line)


def run_case(case: Case, out_dir: Path) -> list[Outcome]:
    """Run one case through every command that reads it (see the module doc)."""
    results = []
    if case.kind == "dataset":
        for command in ("replay", "calibrate"):
            js = out_dir / f"{command}.json"
            js.unlink(missing_ok=True)
            code, _, err, tb = _run_cli([command, str(case.target), "--check", "--json", str(js)])
            warnings = json.loads(js.read_text())["input_checks"]["warnings"] if js.is_file() else []
            o = _classify(case, code, err, tb, warnings)
            o.kind = f"dataset/{command}"
            results.append(o)
    elif case.kind == "grade":
        js = out_dir / "grade.json"
        js.unlink(missing_ok=True)
        code, _, err, tb = _run_cli(["grade", str(case.target), "--check", "--json", str(js)])
        warnings = json.loads(js.read_text())["warnings"] if js.is_file() else []
        results.append(_classify(case, code, err, tb, warnings))
    else:
        results.append(_run_config(case))
    return results


def _run_config(case: Case) -> Outcome:
    """Config loading as the service does it before starting: the file, then the scenario it names."""
    err = io.StringIO()
    tb = None
    code = 0
    try:
        if case.kind == "master_config":
            from master.config import MasterConfig
            cfg = MasterConfig.load(case.target)
        else:
            from slave.config import SlaveConfig
            cfg = SlaveConfig.load(case.target)
        del cfg    # loading validates the [source] table too (v2xpos.sources.check_source_table)
    except ValueError as exc:      # ConfigError, ScenarioError
        code = 2
        err.write(str(exc))
    except Exception:  # noqa: BLE001
        tb = traceback.format_exc()
    return _classify(case, code, err.getvalue(), tb, [])


def run_corpus(corpus: Corpus, out_dir: Path, progress: bool = False,
               select: Callable[[Case], bool] | None = None) -> dict:
    """Run every (selected) case; returns counts by status and kind and every failure."""
    import logging
    logging.getLogger("v2xpos").setLevel(logging.ERROR)
    out_dir.mkdir(parents=True, exist_ok=True)
    outcomes: list[Outcome] = []
    cases = [c for c in corpus.cases if select is None or select(c)]
    t0 = time.perf_counter()
    it = cases
    if progress:
        from tqdm import tqdm
        it = tqdm(cases, desc="corpus", unit="case", file=sys.stderr)
    for c in it:
        outcomes += run_case(c, out_dir)
    by_status = Counter(o.status for o in outcomes)
    by_kind: dict[str, Counter] = {}
    for o in outcomes:
        by_kind.setdefault(o.kind, Counter())[o.status] += 1
    failures = [o for o in outcomes if o.status not in ("error", "warning")]
    return {"cases": len(cases), "runs": len(outcomes), "by_status": dict(by_status),
            "by_kind": {k: dict(v) for k, v in by_kind.items()},
            "tracebacks": by_status.get("traceback", 0), "silent": by_status.get("silent", 0),
            "unnamed": by_status.get("unnamed", 0), "wrong_code": by_status.get("wrong_code", 0),
            "failures": [o.__dict__ for o in failures], "outcomes": [o.__dict__ for o in outcomes],
            "wall_s": time.perf_counter() - t0}


# ------------------------------------------------------------------------------------ bench
def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=17)
    parser.add_argument("--json", type=Path, help="write every outcome here")
    parser.add_argument("--keep", type=Path, help="write the corpus into this folder (default: a temporary one)")


def run_bench(args: argparse.Namespace) -> int:
    """``v2xpos bench corpus``: cases, outcomes, tracebacks and silent exits (0 and 0 expected)."""
    if not (DATA_DIR / "drive_0708" / "imu_1934.csv").is_file():
        print(f"v2xpos bench corpus: the shared recordings are not at {DATA_DIR}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="v2xpos-corpus-") as tmp:
        work = args.keep or Path(tmp)
        t0 = time.perf_counter()
        corpus = build_corpus(work / "cases", seed=args.seed)
        t_build = time.perf_counter() - t0
        res = run_corpus(corpus, work / "out", progress=True)
        if args.keep is None:
            shutil.rmtree(work / "cases", ignore_errors=True)
    kinds = Counter(c.kind for c in corpus.cases)
    print(f"corpus: {res['cases']} broken inputs ({', '.join(f'{n} {k}' for k, n in kinds.items())}), "
          f"{res['runs']} command runs, built in {t_build:.1f} s, run in {res['wall_s']:.1f} s")
    for kind, counts in res["by_kind"].items():
        print(f"  {kind:<18} " + ", ".join(f"{s} {n}" for s, n in sorted(counts.items())))
    print(f"tracebacks {res['tracebacks']}, silent exits {res['silent']}, errors without the file named "
          f"{res['unnamed']}, other exit codes {res['wrong_code']}")
    for f in res["failures"][:20]:
        print(f"  FAIL {f['status']:<10} {f['kind']:<18} {f['case']}: {f['message'][:160]}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=1))
    return 0 if not res["failures"] else 1
