"""The documentation stands on its own: it cites the paper (its sections, equations and figures), the authors'
published code and our own docs, never files outside this repository."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUTSIDE = re.compile(r"fact sheet|reference-implementation|shared/reference|shared/notes|\.\./shared/", re.IGNORECASE)


def test_nothing_cites_files_outside_the_repository() -> None:
    files = [ROOT / "README.md", ROOT / "Makefile", ROOT / "Dockerfile", ROOT / "pyproject.toml"]
    for folder in ("ttompc", "docs", "tests", "bench", "zoo", "recipes", "data_cards"):
        files += [p for p in (ROOT / folder).rglob("*") if p.suffix in (".py", ".md", ".yaml", ".toml", ".txt")]
    hits = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in files
        if path.is_file() and path != Path(__file__)
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not hits, "cite the paper or our own docs instead:\n" + "\n".join(hits)
