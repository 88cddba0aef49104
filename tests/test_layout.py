"""The package layout in docs/design.md is the one ``python -m ttompc.layout`` renders from the module docstrings,
as the documented commands are the ones the CLI takes (tests/test_doc_commands.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from ttompc import layout


def test_the_layout_block_is_current() -> None:
    text = layout.DOC.read_text(encoding="utf-8")
    assert layout.block(text) == layout.render(), (
        "docs/design.md's package layout is stale: run `python -m ttompc.layout --write` (it reads the docstrings)"
    )


def test_every_module_and_package_has_a_sentence() -> None:
    """A module without a docstring would be a blank row: every row of the table says what its path holds."""
    rows = layout.render().splitlines()[2:]
    blank = [row for row in rows if row.split(" | ")[1].strip() in ("", "|")]
    assert not blank, blank
    assert "ttompc/layout.py" in layout.render() and "`ttompc/mpc/`" in layout.render()
    assert "ttompc/commands/train.py" in layout.render()  # a namespace package's modules get rows of their own
    assert all(": " in line for line in layout.render_modules().splitlines())


@pytest.mark.parametrize(
    ("docstring", "sentence"),
    [
        ("One line.", "One line."),
        ("First, e.g. this. Second.", "First, e.g. this."),
        ("DAgger (paper Alg. 1): rollouts.\n\nMore text.", "DAgger (paper Alg. 1): rollouts."),
        ("Wrapped\n    over lines. ``Next`` sentence.", "Wrapped over lines."),
        ("``a|b``: a pipe.", "``a\\|b``: a pipe."),
        ("No full stop", "No full stop"),
    ],
)
def test_first_sentence(tmp_path: Path, docstring: str, sentence: str) -> None:
    module = tmp_path / "m.py"
    module.write_text(f'"""{docstring}"""\n', encoding="utf-8")
    assert layout.first_sentence(module) == sentence


def test_check_fails_on_a_stale_block_and_write_fixes_it(tmp_path: Path) -> None:
    doc = tmp_path / "design.md"
    doc.write_text(f"# Design\n\n{layout.BEGIN}\n\n| old |\n\n{layout.END}\n\nMore.\n", encoding="utf-8")
    assert layout.main(["--check", "--doc", str(doc)]) == 1
    assert layout.main(["--write", "--doc", str(doc)]) == 0
    assert layout.main(["--check", "--doc", str(doc)]) == 0
    text = doc.read_text(encoding="utf-8")
    assert text.startswith("# Design\n\n") and text.endswith(f"{layout.END}\n\nMore.\n")
    assert layout.block(text) == layout.render()
