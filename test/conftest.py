"""Shared fixtures: dataset locations, seeded generators."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("LINEAR_SLAM_DATASETS", REPO.parent / "shared" / "datasets"))
CACHE = REPO / ".cache" / "datasets"


def dataset_archive(name: str) -> Path:
    """Return the archive of a benchmark dataset, skipping the test when it is absent."""
    path = DATASETS / f"{name}.tar.xz"
    if not path.exists():
        pytest.fail(f"benchmark dataset {path} is missing: ../shared must sit beside the repository")
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def read_benchmark():
    """Return a cached reader of benchmark datasets (unpacked under .cache/datasets)."""
    from linear_slam_ros.datasets import read_dataset

    cache: dict[str, object] = {}

    def read(name: str):
        if name not in cache:
            cache[name] = read_dataset(dataset_archive(name), cache_dir=CACHE)
        return cache[name]

    return read
