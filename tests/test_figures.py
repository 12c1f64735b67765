"""The figures the README and docs state agree with docs/figures.md (written by
``v2xpos bench figures``).

A document cites a figure as a Markdown link to its key in docs/figures.md,
``[2.38 m](figures.md#replay.drive_0708.outage_h_rms_m)`` (from the README
``docs/figures.md#...``). The check: every cited key has a row in docs/figures.md, and when the
link text starts with a number, it equals the row's value to the digits stated (2.38 for 2.382
holds, 2.39 does not); a text that does not start with a number (``[h RMS](...)``) only names it. It reads files only; it runs no benchmark.
"""
from __future__ import annotations

import re
import shutil
from pathlib import Path

from bench.figures import COLUMNS, FIGURES, NOT_MEASURED, read_rows

ROOT = Path(__file__).resolve().parents[1]
FIGURES_MD = ROOT / "docs" / "figures.md"
CITATION = re.compile(r"\[([^\[\]]+)\]\((?:docs/)?figures\.md#([A-Za-z0-9_.\-]+)\)")
NUMBER = re.compile(r"\s*([-+−]?\d[\d,]*(?:\.\d+)?)")


def documents(root: Path = ROOT) -> list[Path]:
    """The README and every docs/*.md except the generated figures file."""
    return [root / "README.md"] + sorted(p for p in (root / "docs").glob("*.md") if p.name != "figures.md")


def citations(paths: list[Path]) -> list[tuple[Path, int, str, str]]:
    """(file, line, link text, key) of every figure cited in ``paths``."""
    out = []
    for path in paths:
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            out.extend((path, n, m.group(1), m.group(2)) for m in CITATION.finditer(line))
    return out


def stated_number(text: str) -> tuple[float, int] | None:
    """The number a link text starts with and its decimals (``−1,234.5 m`` -> (-1234.5, 1)); None
    when the text does not start with one (``[within 3 sd](...)`` names the figure, states none)."""
    m = NUMBER.match(text)
    if not m:
        return None
    s = m.group(1).replace(",", "").replace("−", "-")
    return float(s), len(s.split(".")[1]) if "." in s else 0


def disagreements(paths: list[Path], figures_md: Path) -> list[str]:
    """What the documents state that docs/figures.md does not hold: a missing key or a value that
    differs at the digits stated."""
    rows = read_rows(figures_md)
    out = []
    for path, line, text, key in citations(paths):
        where = f"{path.name}:{line}"
        if key not in rows:
            out.append(f"{where}: [{text}] cites {key}, which docs/figures.md does not have")
            continue
        stated = stated_number(text)
        if stated is None:
            continue
        value, digits = stated
        try:
            actual = float(rows[key]["value"])
        except ValueError:
            out.append(f"{where}: [{text}] states {value} for {key}, docs/figures.md has {rows[key]['value']!r}")
            continue
        if abs(actual - value) > 0.5 * 10 ** -digits + 1e-9:
            out.append(f"{where}: [{text}] states {value} for {key}, docs/figures.md has {rows[key]['value']}")
    return out


def test_every_cited_figure_is_in_figures_md_and_agrees():
    cited = citations(documents())
    assert len(cited) >= 10, "the README and docs cite figures by key (see docs/figures.md)"
    assert disagreements(documents(), FIGURES_MD) == []


def test_the_check_fails_on_a_wrong_value_and_on_a_missing_key(tmp_path):
    (tmp_path / "docs").mkdir()
    for p in documents():
        shutil.copy(p, tmp_path / p.relative_to(ROOT))
    shutil.copy(FIGURES_MD, tmp_path / "docs" / "figures.md")
    copies = documents(tmp_path)
    fig = tmp_path / "docs" / "figures.md"
    assert disagreements(copies, fig) == []
    numeric = next((c for c in citations(copies) if stated_number(c[2]) is not None), None)
    assert numeric is not None, "at least one citation states a number"
    path, _, text, key = numeric
    value, digits = stated_number(text)
    wrong = f"{value + 3 * 10 ** -digits:.{digits}f}"
    path.write_text(path.read_text(encoding="utf-8").replace(f"[{text}](", f"[{wrong} (deliberately wrong)](", 1),
                    encoding="utf-8")
    found = disagreements(copies, fig)
    assert len(found) == 1 and key in found[0] and "states" in found[0], found
    kept = [ln for ln in fig.read_text(encoding="utf-8").splitlines() if f'<a id="{key}">' not in ln]
    fig.write_text("\n".join(kept) + "\n", encoding="utf-8")
    assert any("does not have" in d and key in d for d in disagreements(copies, fig))


def test_stated_number_reads_the_digits_stated():
    assert stated_number("2.38 m") == (2.38, 2)
    assert stated_number("39,575 samples/s") == (39575.0, 0)
    assert stated_number("−0.5 %") == (-0.5, 1)
    assert stated_number("after calibration") is None
    assert stated_number("within 3 sd") is None


def test_figures_md_holds_every_figure_with_its_provenance():
    rows = read_rows(FIGURES_MD)
    assert sorted(set(FIGURES) - set(rows)) == [], "run `v2xpos bench figures` to write a row for these"
    for key, row in rows.items():
        assert len(row) == len(COLUMNS)
        assert row["command"], f"{key}: no command"
        assert row["run"] in ("measured", "carried", NOT_MEASURED), key
        if row["run"] == NOT_MEASURED:
            assert row["value"] == "-", key
            continue
        for column in ("value", "commit", "machine"):
            assert row[column] and row[column] != "-", f"{key}: no {column}"
        assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d", row["date (UTC)"]), key
