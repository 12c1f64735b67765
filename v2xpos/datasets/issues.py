"""Bookkeeping of malformed input records: readers skip them, count them and keep the first reasons."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ParseIssues:
    """Malformed records of one input file.

    count: records skipped; examples: the first ``max_examples`` (line or record number, reason).
    Line numbers are 1-based; binary formats use the record index or the byte offset, as the
    reason says.
    """
    source: str
    count: int = 0
    examples: list[tuple[int, str]] = field(default_factory=list)
    max_examples: int = 5

    def add(self, where: int, reason: str) -> None:
        """Count one skipped record at ``where`` (line, record index or byte offset)."""
        self.count += 1
        if len(self.examples) < self.max_examples:
            self.examples.append((int(where), reason))

    def merge(self, other: "ParseIssues", prefix: str = "") -> None:
        """Add all of ``other``'s count and as many of its examples as fit (reasons prefixed)."""
        self.count += other.count
        room = self.max_examples - len(self.examples)
        self.examples += [(n, prefix + r) for n, r in other.examples[:max(room, 0)]]

    def summary(self) -> str:
        """One line: the file, how many records were skipped and the first reasons."""
        if not self.count:
            return f"{self.source}: no malformed records"
        shown = "; ".join(f"line {n}: {r}" for n, r in self.examples)
        return f"{self.source}: {self.count} malformed record(s) skipped ({shown})"

    def as_dict(self) -> dict:
        """JSON-ready ``{"source", "count", "examples": [{"line", "reason"}]}``."""
        return {"source": self.source, "count": self.count,
                "examples": [{"line": n, "reason": r} for n, r in self.examples]}
