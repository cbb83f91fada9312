"""City-sized synthetic streams (evaluation/city.py), at small sizes: determinism, ground truth,
loop-closure density, honest local maps, joining recovers the truth, the synthetic: dataset source."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from linear_slam_ros.core.errors import DatasetError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import points_to_frame, relative_pose, rot3
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.evaluation import city
from linear_slam_ros.evaluation.metrics import nees
from linear_slam_ros.evaluation.nonlinear import gauss_newton
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.io import datasets
from linear_slam_ros.io.datasets import read_dataset

SMALL = {"city2d": 600, "garage3d": 400, "features2d": 80}


@pytest.fixture(scope="module")
def streams() -> dict[str, city.SyntheticStream]:
    return {family: city.generate(f"{family}-{size}", seed=3) for family, size in SMALL.items()}


def _same_maps(a: tuple[LocalMap, ...], b: tuple[LocalMap, ...]) -> bool:
    return len(a) == len(b) and all(
        m.frame_id == n.frame_id
        and m.end_id == n.end_id
        and np.array_equal(m.ids, n.ids)
        and np.array_equal(m.kinds, n.kinds)
        and np.array_equal(m.x, n.x)
        and np.array_equal(m.info_dense(), n.info_dense())
        for m, n in zip(a, b, strict=True)
    )


@pytest.mark.parametrize("family", sorted(SMALL))
def test_generation_is_deterministic_per_seed(family: str, streams: dict[str, city.SyntheticStream]) -> None:
    name = f"{family}-{SMALL[family]}"
    again = city.generate(name, seed=3)
    assert _same_maps(again.maps, streams[family].maps)
    assert np.array_equal(again.world.poses, streams[family].world.poses)
    assert not np.array_equal(city.generate(name, seed=4).world.poses, again.world.poses)


@pytest.mark.parametrize("family", sorted(SMALL))
def test_maps_are_valid_chain_and_consistent_with_ground_truth(family: str, streams: dict[str, city.SyntheticStream]) -> None:
    stream = streams[family]
    maps = stream.maps
    for m in maps:
        m.validate()
    assert maps[0].frame_id == 0 and np.all(stream.world.poses[0] == 0.0)
    assert all(b.frame_id == a.end_id for a, b in zip(maps[:-1], maps[1:], strict=True))  # each starts at the previous end
    if family == "features2d":
        assert len(maps) == SMALL[family]
    else:
        assert len(maps) == len(stream.world.poses) - 1 == SMALL[family]
    # The maps' errors against the truth match their information: chi2 of the truth ~ chi2(n scalars).
    n = sum(m.x.size for m in maps)
    value = chi2(stream.truth_map(), maps)
    assert scipy.stats.chi2.cdf(value, n) == pytest.approx(0.5, abs=0.499), (value, n)
    assert abs(value / n - 1.0) < 5 * np.sqrt(2.0 / n)


def test_city_loop_closures_have_city_block_density(streams: dict[str, city.SyntheticStream]) -> None:
    stream = city.generate("city2d-3000", seed=1)
    policy = city.LoopPolicy()
    assert 0.35 < stream.loop_closures_per_pose() < 0.9  # manhattanOlson3500: 0.56
    n_loops = 0
    for k, m in enumerate(stream.maps, start=1):
        assert m.ids[0] == k and m.end_id == k  # odometry first
        for j in m.ids[1:].tolist():  # loop closures: from pose k - 1 back to an earlier pose near it
            frame = k - 1
            assert frame - j >= policy.min_gap
            assert np.linalg.norm(stream.world.poses[frame, :2] - stream.world.poses[j, :2]) <= policy.radius
            n_loops += 1
    assert n_loops == stream.n_loop_closures
    # the streets form a grid: every truth heading is a multiple of 90 degrees from pose 0's
    assert np.allclose(np.sin(2 * stream.world.poses[:, 2]), 0.0, atol=1e-12)


def test_garage_has_floors_ramps_and_loops_within_a_floor(streams: dict[str, city.SyntheticStream]) -> None:
    stream = city.generate("garage3d-2000", seed=2)
    poses = stream.world.poses
    floors = np.unique(np.round(poses[:, 2] / 3.0)[np.abs(poses[:, 4]) < 1e-12])
    assert floors.size >= 2 and stream.loop_closures_per_pose() > 0.5
    # the forward axis R^T e_x follows the direction of travel (pitch sign: the datasets' convention)

    forward = rot3(poses[1:-1, 3:])[:, 0, :]
    travel = poses[2:, :3] - poses[1:-1, :3]
    same_segment = np.all(np.abs(poses[2:, 3:] - poses[1:-1, 3:]) < 1e-12, axis=1)
    cosine = np.sum(forward * travel, axis=1) / np.linalg.norm(travel, axis=1)
    assert np.allclose(cosine[same_segment], 1.0)
    assert np.any(np.abs(poses[:, 4]) > 0.1)  # ramps
    for k, m in enumerate(stream.maps, start=1):
        for j in m.ids[1:].tolist():
            assert abs(poses[k - 1, 2] - poses[j, 2]) <= city.LoopPolicy().radius


def test_feature_maps_are_the_gauss_newton_optimum_of_their_measurements() -> None:
    rng = np.random.default_rng(7)
    world = city.park_world(12, rng, side=40.0)
    meas = city.measure_features(world, rng, steps_per_map=4)
    fast = city.feature_local_maps(meas, "f")
    s = meas.steps_per_map
    for i, built in enumerate(fast):
        start, end = s * i, s * (i + 1)
        pieces: list[LocalMap] = []
        for q in range(s):
            j = start + q + 1
            info = np.diag(meas.sigma_odometry**-2.0)
            pieces.append(LocalMap(2, j - 1, j, np.array([j]), np.array([POSE], np.int8), meas.odometry[i, q], info))
        observed = sorted(set(meas.obs_feature[meas.obs_map == i].tolist()))
        for r in np.flatnonzero(meas.obs_map == i).tolist():
            info = np.eye(2) * meas.sigma_observation**-2.0
            f = np.array([meas.obs_feature[r]])
            pieces.append(LocalMap(2, int(meas.obs_pose[r]), None, f, np.array([FEATURE], np.int8), meas.obs[r], info))
        pose_ids = list(range(start + 1, end + 1))
        ids = np.array(pose_ids + observed, dtype=np.int64)
        kinds = np.array([POSE] * s + [FEATURE] * len(observed), dtype=np.int8)
        truth = np.concatenate(
            [relative_pose(2, world.poses[start], world.poses[j]) for j in pose_ids]
            + [points_to_frame(2, world.poses[start, :2], world.poses[start, 2:], world.features[f]).points for f in observed]
        )
        solved = gauss_newton(LocalMap.trusted(2, start, end, ids, kinds, truth, np.eye(truth.size)), pieces).map
        info = solved.info_dense()
        keep = np.arange(3 * (s - 1), truth.size)
        drop = np.arange(3 * (s - 1))
        coupling = info[np.ix_(keep, drop)]
        marg = info[np.ix_(keep, keep)] - coupling @ np.linalg.solve(info[np.ix_(drop, drop)], coupling.T)
        assert built.frame_id == start and built.end_id == end
        assert np.array_equal(built.ids, ids[np.r_[s - 1, s : ids.size]])
        assert np.allclose(built.x, solved.x[keep], atol=1e-8)
        assert np.allclose(built.info_dense(), marg, rtol=1e-8, atol=1e-6)


@pytest.mark.parametrize("family", sorted(SMALL))
def test_divide_and_conquer_recovers_the_truth_within_the_noise(family: str, streams: dict[str, city.SyntheticStream]) -> None:
    stream = streams[family]
    figures = city.join_figures(stream, "dc")
    assert abs(figures["chi2_per_dof"] - 1.0) < 5 * np.sqrt(2.0 / figures["dof"]), figures
    result = run_join(stream.maps, "dc").result
    result = change_frame(result, 0) if result.frame_id != 0 else result
    kinds = (POSE, FEATURE) if stream.kind.has_features else (POSE,)
    check = nees(result, stream.world.truth(), kinds, confidence=0.999)
    assert check.consistent, check  # the joined estimate's error is within its information
    # ... and the position RMSE is what that information predicts (per coordinate, frame of pose 0)
    variance = np.diag(np.linalg.inv(result.info_dense()))
    positions = result.scalar_index(np.flatnonzero(result.kinds == POSE))
    positions = positions.reshape(-1, 3 if stream.world.dim == 2 else 6)[:, : stream.world.dim].reshape(-1)
    predicted = float(np.sqrt(variance[positions].mean()))
    assert 0.3 * predicted < figures["rmse_pose_m"] < 3.0 * predicted, (figures, predicted)


def test_online_dc_joins_like_dc(streams: dict[str, city.SyntheticStream]) -> None:
    stream = streams["features2d"]
    assert city.join_figures(stream, "online-dc")["chi2"] == pytest.approx(city.join_figures(stream, "dc")["chi2"], rel=1e-6)


def test_synthetic_dataset_source_generates_and_reads_the_cache(tmp_path, monkeypatch) -> None:
    ds = read_dataset("synthetic:city2d-200@5", cache_dir=tmp_path)  # registered: generated
    stream = city.generate("city2d-200", seed=5)
    assert ds.name == "city2d-200@5" and ds.kind == datasets.MapKind.PG2D and _same_maps(ds.maps, stream.maps)
    with pytest.raises(DatasetError, match="3DPG stream, not 2DPG"):
        read_dataset("synthetic:garage3d-50", kind="2DPG", cache_dir=tmp_path)
    with pytest.raises(DatasetError, match="unknown synthetic stream"):
        read_dataset("synthetic:city2d-x", cache_dir=tmp_path)
    with pytest.raises(DatasetError, match="malformed"):
        read_dataset("synthetic:city2d-20@x", cache_dir=tmp_path)
    # with no generator registered (the offline CLI), the cache file is read, or its absence named
    monkeypatch.setattr(datasets, "_SYNTHETIC_SOURCES", {})
    with pytest.raises(DatasetError, match="not generated.*evaluation.city city2d-200 --seed 5"):
        read_dataset("synthetic:city2d-200@5", cache_dir=tmp_path)
    features = city.generate("features2d-20", seed=5)
    for s in (stream, features):
        path = city.cache(s, tmp_path)
        assert path == tmp_path / "synthetic" / f"{s.name}-seed5.npz" and city.is_cached(s.name, 5, tmp_path)
        assert _same_maps(read_dataset(f"synthetic:{s.name}@5", cache_dir=tmp_path).maps, s.maps)
        back = city.read_cached(s.name, 5, tmp_path)
        assert np.array_equal(back.world.poses, s.world.poses) and back.world.features.keys() == s.world.features.keys()
        assert back.n_loop_closures == s.n_loop_closures
