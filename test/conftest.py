"""Shared fixtures: dataset locations, seeded generators."""

from __future__ import annotations

import numpy as np
import pytest

from support import CACHE, dataset_archive


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def read_benchmark():
    """Return a cached reader of benchmark datasets (unpacked under .cache/datasets)."""
    from linear_slam_ros.io.datasets import read_dataset

    cache: dict[str, object] = {}

    def read(name: str):
        if name not in cache:
            cache[name] = read_dataset(dataset_archive(name), cache_dir=CACHE)
        return cache[name]

    return read
