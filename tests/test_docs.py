"""The documentation stands on its own: it cites the paper (its sections, equations and figures), the authors'
published code and our own docs, never files outside this repository. And it reads in a minute: the README opens with
its two commands and stays short, the benchmarks page holds one newest table per bench (history is in git), and no
module is kept under its length by packing lines past the formatter."""

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


def test_readme_and_benchmarks_stay_short_and_the_commands_come_first() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(readme) <= 150, f"README.md has {len(readme)} lines (at most 150)"
    first_screen = "\n".join(readme[:20])
    assert "make demo" in first_screen and "make test" in first_screen, "the two commands belong in the first 20 lines"
    benchmarks = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8").splitlines()
    assert len(benchmarks) <= 300, f"docs/benchmarks.md has {len(benchmarks)} lines (at most 300)"


def test_modules_are_short_without_packed_lines() -> None:
    """Every module of ttompc is at most 450 lines as ``ruff format`` writes it: split along a concern, never kept
    short by ``# fmt: skip``."""
    for path in sorted((ROOT / "ttompc").rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        name = path.relative_to(ROOT)
        assert len(text.splitlines()) <= 450, f"{name} has {len(text.splitlines())} lines (at most 450)"
        assert "fmt: skip" not in text and "fmt: off" not in text, f"{name} packs lines past the formatter"
