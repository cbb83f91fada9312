"""Golden results on the benchmark datasets: the paper's and the reference program's figures.

Figures from ``shared/datasets/README.md`` (paper Tables 2 and 4, reference program runs).
Fast datasets run by default; the long ones are marked ``slow`` (``pytest -m slow``).
"""

from __future__ import annotations

import pytest

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, POSE
from linear_slam_ros.evaluation.metrics import rmse
from linear_slam_ros.evaluation.nonlinear import refine
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.joiner.strategy import JoinMethod

# dataset: (D&C chi2, Nonlinear LS chi2, RMSE pose, RMSE feature) from the paper
PAPER = {
    "VicPark_200_local_maps": (3645, 3643, 0.0391, 0.0643),
    "DLR_200_local_maps": (12577, 11164, 0.1537, 0.1545),
    "Intel": (546.51, 546.46, 0.006571, None),
    "manhattanOlson3500": (214.12, 137.91, 1.114862, None),
    "sphere2500": (1363.8, 1154.5, None, None),  # Sphere RMSE not reproducible (README): chi2 only
}
# reference program's sequential chi2
SEQUENTIAL = {"VicPark_200_local_maps": 3656.9, "DLR_200_local_maps": 12583.2, "8240_data_50_local_maps": 1399.6}
SLOW = {"manhattanOlson3500", "sphere2500"}


def _params(names):
    return [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in names]


@pytest.mark.parametrize("name", _params(PAPER))
def test_divide_and_conquer_and_nonlinear_ls_match_the_paper(name, read_benchmark):
    dataset = read_benchmark(name)
    chi2_dc, chi2_nls, rmse_pose, rmse_feat = PAPER[name]
    run = run_join(dataset.maps, JoinMethod.DC)
    assert chi2(run.result, dataset.maps) == pytest.approx(chi2_dc, rel=0.005)
    refined = refine(run.result, dataset.maps)
    assert refined.chi2 == pytest.approx(chi2_nls, rel=0.005)
    linear = change_frame(run.result, 0)
    if rmse_pose is not None:
        assert rmse(linear, refined.map, POSE) == pytest.approx(rmse_pose, rel=0.10)
    if rmse_feat is not None:
        assert rmse(linear, refined.map, FEATURE) == pytest.approx(rmse_feat, rel=0.10)


@pytest.mark.parametrize("name", sorted(SEQUENTIAL))
def test_exact_sequential_matches_the_reference_program(name, read_benchmark):
    dataset = read_benchmark(name)
    run = run_join(dataset.maps, JoinMethod.SEQUENTIAL)
    assert chi2(run.result, dataset.maps) == pytest.approx(SEQUENTIAL[name], rel=0.005)


@pytest.mark.parametrize(
    "name", _params(["VicPark_200_local_maps", "Intel", "8240_data_50_local_maps", "manhattanOlson3500", "sphere2500"])
)
def test_online_dc_within_one_percent_of_batch(name, read_benchmark):
    dataset = read_benchmark(name)
    batch = chi2(run_join(dataset.maps, JoinMethod.DC).result, dataset.maps)
    online = chi2(run_join(dataset.maps, JoinMethod.ONLINE_DC).result, dataset.maps)
    assert online == pytest.approx(batch, rel=0.01)


def test_vicpark_reads_into_the_expected_shape(read_benchmark):
    dataset = read_benchmark("VicPark_200_local_maps")
    assert dataset.kind.value == "2DPF" and len(dataset.maps) == 200
    assert dataset.maps[0].frame_id == 0 and dataset.maps[0].end_id == 1
    assert all(m.frame_id + 1 == m.end_id for m in dataset.maps)
