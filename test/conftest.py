"""Shared fixtures: dataset locations, seeded generators."""

from __future__ import annotations

import numpy as np
import pytest

from support import CACHE, dataset_source


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def read_benchmark():
    """Return a cached reader of benchmark datasets: the archives of ../shared/datasets (unpacked under
    .cache/datasets), else the committed bags (:func:`support.dataset_source`)."""
    from linear_slam_ros.cli.main import read_source
    from linear_slam_ros.io.datasets import read_dataset

    cache: dict[str, object] = {}

    def read(name: str):
        if name not in cache:
            source = dataset_source(name)
            cache[name] = read_source(source) if source.is_dir() else read_dataset(source, cache_dir=CACHE)
        return cache[name]

    return read
