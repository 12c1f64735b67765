"""Every relative link of the README and docs/ points at a file of the checkout (docs/configuration.md
was linked before it existed)."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def broken_links(files: list[Path]) -> list[tuple[str, str]]:
    """(file, target) of every markdown link to a relative path that does not exist."""
    out = []
    for f in files:
        for target in LINK.findall(f.read_text()):
            if "://" not in target and not target.startswith("mailto:") and not (f.parent / target).exists():
                out.append((f.name, target))
    return out


def test_readme_and_docs_links_resolve():
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    assert len(files) > 10
    assert broken_links(files) == []


def test_a_missing_target_is_reported(tmp_path):
    (tmp_path / "there.md").write_text("# there\n")
    page = tmp_path / "page.md"
    page.write_text("see [this](nowhere.md), [that](there.md#there) and [web](https://example.org/x)\n")
    assert broken_links([page]) == [("page.md", "nowhere.md")]
