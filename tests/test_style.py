"""The code stays clean: ruff over the library, workflow scripts, tests and benchmarks; the
stages and scripts stay thin."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_ruff_is_clean():
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.skip("ruff is not installed (pip install -e '.[test]')")
    proc = subprocess.run([ruff, "check", "--no-cache", str(REPO)], capture_output=True,
                          text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_stage_modules_and_scripts_have_short_functions():
    """Every function of a stage module (robo3d/stages/) and of a rule's script is under
    120 lines, docstring included: a stage reads its inputs, builds its options, calls the
    algorithm and writes its outputs; longer means logic that belongs in the library."""
    import ast

    files = sorted((REPO / "robo3d" / "stages").glob("*.py")) + sorted(
        (REPO / "workflow" / "scripts").glob("*.py"))
    assert len(files) >= 15
    long = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n >= 120:
                    long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long
