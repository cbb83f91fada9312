"""Test support shared by the suites: where the benchmark datasets are."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("LINEAR_SLAM_DATASETS", REPO.parent / "shared" / "datasets"))
CACHE = REPO / ".cache" / "datasets"


def dataset_archive(name: str) -> Path:
    """Return the archive of a benchmark dataset; fail (not skip) when ../shared is missing."""
    path = DATASETS / f"{name}.tar.xz"
    if not path.exists():
        pytest.fail(f"benchmark dataset {path} is missing: ../shared must sit beside the repository")
    return path
