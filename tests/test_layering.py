"""The floors of the code base (README "Layout", PLAN): each module imports only modules on its own
floor or below, read from the source with ``ast`` -- every ``import`` statement, also those inside
functions and under ``TYPE_CHECKING`` -- so that a lazy ``import sim`` inside a library function
fails here as surely as one at the top of the file.

Floors, bottom to top:
0 foundations (geo, rotation and their compiled twin kernels, timebase, types, stats, provenance, compat,
  schema, plugins)
1 formats and the wire (datasets/, devices/, wire/, scene)
2 estimation, relative kinematics, link, security, outputs (ins/, relative*, link, tls, security,
  verify_worker, output/)
3 vehicle sources and clocks, quality, diagnose, sensor evaluation, tools on the library (sources/,
  quality/, diagnose/, evaluate/, config, launch, stop_signals, monitor/, commands/)
4 services (master/, slave/)
5 simulation and benches (sim/, bench/)
6 the CLI (v2xpos.cli, which imports the commands by name at run time)
7 what drives the CLI as a user would (bench.corpus: broken inputs through ``run_command``)

Besides the floors: no module of v2xpos/ imports master, slave, sim or bench (the CLI included);
master/ and slave/ do not import each other; sim/ does not import bench/; no import cycles.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("v2xpos", "master", "slave", "sim", "bench")

FLOORS: dict[str, int] = {
    "v2xpos": 0, "v2xpos.geo": 0, "v2xpos.rotation": 0, "v2xpos.kernels": 0, "v2xpos.timebase": 0, "v2xpos.types": 0,
    "v2xpos.stats": 0, "v2xpos.provenance": 0, "v2xpos.compat": 0, "v2xpos.schema": 0,
    "v2xpos.plugins": 0,
    "v2xpos.datasets": 1, "v2xpos.devices": 1, "v2xpos.wire": 1, "v2xpos.scene": 1,
    "v2xpos.ins": 2, "v2xpos.relative": 2, "v2xpos.relative_jit": 2, "v2xpos.link": 2, "v2xpos.tls": 2,
    "v2xpos.security": 2, "v2xpos.verify_worker": 2, "v2xpos.output": 2,
    "v2xpos.sources": 3, "v2xpos.quality": 3, "v2xpos.diagnose": 3, "v2xpos.evaluate": 3, "v2xpos.config": 3,
    "v2xpos.launch": 3, "v2xpos.stop_signals": 3, "v2xpos.monitor": 3, "v2xpos.commands": 3,
    "master": 4, "slave": 4,
    "sim": 5, "bench": 5,
    "v2xpos.cli": 6, "v2xpos.__main__": 6,
    "bench.corpus": 7,
}
FORBIDDEN: list[tuple[str, tuple[str, ...]]] = [
    ("v2xpos", ("master", "slave", "sim", "bench")),
    ("master", ("slave",)),
    ("slave", ("master",)),
    ("sim", ("bench",)),
]


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = path
    return mods


MODULES = _modules()


def _known(name: str) -> str | None:
    """The longest project module that ``name`` (a module, or a module's attribute) names."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(module: str) -> list[tuple[str, int]]:
    """(project module imported, line) for every import statement of ``module``."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            # ``from pkg import sub`` imports the submodule when there is one, else pkg's attribute
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base for alias in node.names]
        else:
            continue
        for name in names:
            target = _known(name)
            if target is not None and target != module:
                found.append((target, node.lineno))
    return found


def floor_of(module: str) -> int:
    """The floor of ``module`` or of its nearest package in FLOORS; a module directly under
    ``v2xpos`` must be listed itself (the package's own floor is only its ``__init__``)."""
    name = module
    while name:
        if name in FLOORS and (name != "v2xpos" or module == "v2xpos"):
            return FLOORS[name]
        name = name.rpartition(".")[0]
    raise KeyError(module)


def _import_graph() -> dict[str, set[str]]:
    return {m: {t for t, _ in imports_of(m)} for m in MODULES}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan 1972), iteratively."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_every_module_has_a_floor():
    unplaced = []
    for m in MODULES:
        try:
            floor_of(m)
        except KeyError:
            unplaced.append(m)
    assert not unplaced, f"place these modules on a floor in FLOORS (and in the README layout): {unplaced}"


def test_each_module_imports_only_its_floor_and_below():
    wrong = [f"{m} (floor {floor_of(m)}) imports {t} (floor {floor_of(t)}) at line {line}"
             for m in MODULES for t, line in imports_of(m) if floor_of(t) > floor_of(m)]
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("importer,forbidden", FORBIDDEN, ids=[f"{a}-not-{'-'.join(b)}" for a, b in FORBIDDEN])
def test_forbidden_imports(importer, forbidden):
    wrong = [f"{m} imports {t} at line {line}" for m in MODULES if m.split(".")[0] == importer
             for t, line in imports_of(m) if t.split(".")[0] in forbidden]
    assert not wrong, "\n".join(wrong)


def test_no_import_cycles_outside_ins():
    cycles = [c for c in _cycles(_import_graph())
              if not all(m == "v2xpos.ins" or m.startswith("v2xpos.ins.") for m in c)]
    assert not cycles, cycles


def test_no_import_cycles_in_ins():
    assert not _cycles(_import_graph())


def test_the_checks_see_a_lazy_import(tmp_path, monkeypatch):
    """A function-level ``import sim`` inside the library is found, with its line."""
    probe = ROOT / "v2xpos" / "geo.py"
    source = probe.read_text() + "\n\ndef _probe():\n    import sim.demo\n    from master import pipeline\n"
    fake = tmp_path / "geo.py"
    fake.write_text(source)
    monkeypatch.setitem(MODULES, "v2xpos.geo", fake)
    found = dict(imports_of("v2xpos.geo"))
    assert found.get("sim.demo") == source.count("\n") - 1
    assert "master.pipeline" in found
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
