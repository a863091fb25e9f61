"""The examples run as they are (in a temporary folder, for their outputs)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest
from conftest import SOURCE_TREE

EXAMPLES = sorted((SOURCE_TREE / "examples").glob("*.py"))


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_example_runs(script: Path, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [str(script)])  # as run with no arguments
    runpy.run_path(str(script), run_name="__main__")
    assert capsys.readouterr().out.strip()
