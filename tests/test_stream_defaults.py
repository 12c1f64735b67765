"""No function takes ``sys.stdout`` / ``sys.stderr`` as a default argument value.

A default is evaluated once, at import: the stream bound then may be closed by the time the
function runs (a caller that redirected the streams while importing -- pytest's ``capsys`` did, and
an in-process ``v2xpos convoy`` in a later test failed with "I/O operation on closed file").
Functions take ``None`` and look the stream up when called."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("v2xpos", "master", "slave", "sim", "bench")


def bound_stream_defaults(source: str) -> list[tuple[int, str]]:
    """(line, function) of every default argument that is ``sys.stdout`` or ``sys.stderr``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            for d in [*node.args.defaults, *[k for k in node.args.kw_defaults if k is not None]]:
                if (isinstance(d, ast.Attribute) and isinstance(d.value, ast.Name) and d.value.id == "sys"
                        and d.attr in ("stdout", "stderr")):
                    out.append((d.lineno, getattr(node, "name", "<lambda>")))
    return out


def test_no_default_argument_binds_a_standard_stream():
    found = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            hits = bound_stream_defaults(path.read_text())
            if hits:
                found[str(path.relative_to(ROOT))] = hits
    assert found == {}


def test_the_scan_finds_one():
    assert bound_stream_defaults("import sys\ndef f(log=sys.stderr, *, out=sys.stdout):\n    pass\n") == [
        (2, "f"), (2, "f")]
