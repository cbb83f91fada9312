"""Lint and type check: ruff and mypy (configured in pyproject.toml, pinned in requirements-dev.txt) find nothing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    """Run ``python -m <tool> ...`` from the repository root, as a developer would."""
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=600, check=False)


def _require(module: str) -> None:
    if _run(module, "--version").returncode != 0:
        pytest.fail(f"{module} is not installed in {sys.executable}: pip install -r requirements-dev.txt")


def test_ruff_finds_nothing() -> None:
    _require("ruff")
    result = _run("ruff", "check", "--no-fix", "--output-format", "concise")
    if result.returncode != 0:
        pytest.fail(f"ruff check found problems:\n{result.stdout}{result.stderr}", pytrace=False)


def test_mypy_finds_nothing() -> None:
    _require("mypy")
    # Packages, strictness and the cache directory (.cache/mypy, so reruns are quick) come from pyproject.toml.
    result = _run("mypy", "--no-color-output", "--no-error-summary", "--hide-error-context")
    if result.returncode != 0:
        pytest.fail(f"mypy found problems:\n{result.stdout}{result.stderr}", pytrace=False)
