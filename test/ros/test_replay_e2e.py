"""End to end: a dataset's bag replayed through the joiner process over DDS, checked against the core.

Each run writes its figures (end-to-end time, per-submap latency in the node, offline time) to
``out/e2e/<dataset>_<mode>.json``.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import rclpy
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.local_map import POSE
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.ros.bag_from_dataset import make_bag
from linear_slam_ros.ros.bagio import BagRecord, read_messages
from linear_slam_ros.ros.player import play
from msg_adapters import Stamp, decode_map, encode_map
from msg_adapters.ros import to_msg
from ros_support import REPO, call_trigger, wait_for_global_map
from ros_support import dataset_bag as _bag
from support import dataset_source

CASES = [
    pytest.param("VicPark_200_local_maps", "sequential", id="VicPark200-sequential"),
    pytest.param("Intel", "online-dc", id="Intel-online-dc"),
    pytest.param("Simu_3D_870_Loop", "online-dc", id="Simu3D870-online-dc", marks=pytest.mark.slow),
    pytest.param("sphere2500", "online-dc", id="sphere2500-online-dc", marks=pytest.mark.slow),
]


def _publish_all(node, topic, messages):
    """Publish ``messages`` on ``topic`` as the bag player does (reliable, keep all), at once."""
    play(node, [BagRecord(topic, 0, serialize_message(m), False) for m in messages], rate_factor=0.0, wait_s=30.0)


@pytest.mark.parametrize("name, mode", CASES)
def test_replay_equals_offline_core(name, mode, node, start_joiner, read_benchmark):
    maps = read_benchmark(name).maps
    records = list(read_messages(_bag(name)))
    assert len(records) == len(maps)
    joiner = start_joiner(mode=mode, publish_rate=10.0)
    t0 = time.monotonic()
    publish_s = joiner.play(node, records)
    final, t_final = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 600.0, joiner)
    code, output = joiner.stop()
    assert code == 0, output[-2000:]

    # every submap received and joined, in order, none rejected
    assert final.n_submaps == len(maps) and final.seq == len(maps)
    assert final.stats["n_joined"] == len(maps) and final.stats["n_rejected"] == 0
    offline = run_join(maps, mode)
    np.testing.assert_array_equal(final.local_map.ids, offline.result.ids)
    np.testing.assert_allclose(final.local_map.x, offline.result.x, rtol=0, atol=1e-9)
    scale = np.abs(offline.result.info_dense()).max()
    np.testing.assert_allclose(final.local_map.info_dense() / scale, offline.result.info_dense() / scale, rtol=0, atol=1e-9)
    chi2_node, chi2_core = chi2(final.local_map, maps), chi2(offline.result, maps)
    assert chi2_node == pytest.approx(chi2_core, rel=1e-9)

    figures = {
        "dataset": name, "mode": mode, "n_submaps": len(maps), "end_to_end_seconds": t_final - t0,
        "publish_seconds": publish_s, "node_join_ms_p50": final.stats["join_ms_p50"],
        "node_join_ms_p99": final.stats["join_ms_p99"], "node_join_ms_max": final.stats["join_ms_max"],
        "node_join_seconds_total": final.stats["join_seconds_total"], "offline_seconds": offline.seconds,
        "chi2": chi2_node,
    }
    out = REPO / "out" / "e2e"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}_{mode}.json").write_text(json.dumps(figures, indent=2) + "\n")


def test_feature_only_map_type_equals_offline_core(node, start_joiner, read_benchmark, tmp_path):
    """map_type feature-only: VicPark200's pose-feature bag becomes the feature-only global map."""
    from linear_slam_ros.feature_only.conversion import to_feature_only
    from linear_slam_ros.feature_only.joining import join_features_sequential
    from linear_slam_ros.feature_only.precondition import precondition
    from msg_adapters import decode_feature_map

    name = "VicPark_200_local_maps"
    maps = read_benchmark(name).maps
    records = list(read_messages(_bag(name)))
    saved = tmp_path / "saved_map"
    joiner = start_joiner(mode="sequential", map_type="feature-only", publish_rate=10.0, save_directory=str(saved))
    joiner.play(node, records)
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 300.0, joiner,
                                   decode=decode_feature_map)
    result = call_trigger(node, f"/{joiner.namespace}/joiner/save_map")
    assert result.success, result.message
    assert (saved / "features.txt").exists() and not (saved / "poses.txt").exists()
    back = [decode_feature_map(*parts_of(r.raw)) for r in read_messages(saved / "global_map_bag")]
    np.testing.assert_array_equal(back[0].feature_map.x, final.feature_map.x)
    code, output = joiner.stop()
    assert code == 0, output[-2000:]
    assert "map_type=feature-only" in output
    assert final.stats["n_joined"] == len(maps) and final.stats["n_rejected"] == 0
    from threadpoolctl import threadpool_limits

    from linear_slam_ros.core.runtime import SHARED_MACHINE_BLAS_THREADS

    # the node's BLAS thread count: the feature-only chain carries rounding differences of the
    # BLAS schedule to ~1e-6 m (VicPark200), so the bit-level comparison uses the same one
    with threadpool_limits(limits=SHARED_MACHINE_BLAS_THREADS):
        offline = join_features_sequential([to_feature_only(g) for g in precondition(maps)])
    got = final.feature_map
    assert got.frame_ids == offline.frame_ids
    np.testing.assert_array_equal(got.ids, offline.ids)
    np.testing.assert_allclose(got.x, offline.x, rtol=0, atol=1e-9)


def _synthetic(n_maps=8):
    world = make_world(2, 4 * n_maps, 25, np.random.default_rng(21))
    return noisy_local_maps(world, np.random.default_rng(22), steps_per_map=4)


def test_late_subscriber_gets_the_latched_map(node, start_joiner):
    maps = _synthetic()
    joiner = start_joiner(publish_rate=20.0)
    _publish_all(node, joiner.topic("local_map"), [to_msg(encode_map(m, i)) for i, m in enumerate(maps, start=1)])
    first, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 60.0, joiner)
    time.sleep(0.5)
    late = rclpy.create_node("late_subscriber")
    try:
        got, _ = wait_for_global_map(late, joiner.topic("global_map"), lambda m: True, 30.0, joiner)
    finally:
        late.destroy_node()
    assert got.n_submaps == len(maps) and got.local_map.x.tobytes() == first.local_map.x.tobytes()


def test_path_and_features_are_built_only_for_subscribers_and_a_late_one_gets_them(node, start_joiner):
    """Nobody subscribes to ``path``: it is skipped (counted); a subscriber after the stream gets the final one."""
    from nav_msgs.msg import Path as PathMsg
    from visualization_msgs.msg import MarkerArray

    from linear_slam_ros.ros.qos import latched_qos
    from linear_slam_ros.ros.spin import spin_until, wait_for_diagnostics

    maps = _synthetic()
    joiner = start_joiner(publish_rate=20.0, summary_period=0.2)
    _publish_all(node, joiner.topic("local_map"), [to_msg(encode_map(m, i)) for i, m in enumerate(maps, start=1)])
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 60.0, joiner)
    diag = wait_for_diagnostics(node, lambda v: v.get("n_views_skipped", 0) >= 1, 10.0) or {}
    assert diag.get("n_views_skipped", 0) >= 1, diag
    late = rclpy.create_node("late_viewer")
    got: dict[str, object] = {}
    try:
        late.create_subscription(PathMsg, joiner.topic("path"), lambda m: got.update(path=m), latched_qos())
        late.create_subscription(MarkerArray, joiner.topic("features"), lambda m: got.update(features=m), latched_qos())
        assert spin_until(late, lambda: len(got) == 2, 30.0), f"the late viewer got only {sorted(got)}"
    finally:
        late.destroy_node()
    code, output = joiner.stop()
    assert code == 0, output[-2000:]
    n_poses = int(np.sum(final.local_map.kinds == POSE)) + 1  # and the map's frame, the newest pose
    assert len(got["path"].poses) == n_poses  # type: ignore[attr-defined]
    assert got["features"].markers  # type: ignore[attr-defined]


def test_bad_input_is_rejected_counted_and_harmless(node, start_joiner, tmp_path):
    maps = _synthetic()
    good = [to_msg(encode_map(m, i)) for i, m in enumerate(maps, start=1)]
    garbage = Float64MultiArray(data=[1.0, 2.0, 3.0])  # no layout
    nan_map = to_msg(encode_map(maps[2].replace(x=np.full(maps[2].state_dim, np.nan)), 3))
    wrong_frame = to_msg(encode_map(maps[6], 99))  # seq 99 is early: buffered, never joined
    duplicate = good[1]
    stream = good[:2] + [garbage, duplicate, nan_map] + good[2:] + [wrong_frame]
    saved = tmp_path / "saved_map"
    joiner = start_joiner(mode="sequential", publish_rate=20.0, reorder_window=5, save_directory=str(saved))
    _publish_all(node, joiner.topic("local_map"), stream)
    final, _ = wait_for_global_map(
        node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps) and m.stats["n_rejected"] >= 2, 60.0, joiner
    )
    offline = run_join(maps, "sequential").result
    np.testing.assert_allclose(final.local_map.x, offline.x, atol=1e-9)
    assert final.stats["n_rejected"] == 2  # garbage, NaN map; the duplicate is skipped, not rejected (issue 10)

    # ~/save_map writes the reference format and a bag; ~/reset clears the map
    for service, expect in (("save_map", "saved 8 submaps"), ("reset", "global map cleared")):
        result = call_trigger(node, f"/{joiner.namespace}/joiner/{service}")
        assert result.success and expect in result.message
    assert (saved / "poses.txt").exists() and (saved / "global_map_bag" / "metadata.yaml").exists()
    back = [decode_map(*parts_of(r.raw)) for r in read_messages(saved / "global_map_bag")]
    assert back[0].n_submaps == len(maps)
    code, output = joiner.stop()
    assert code == 0
    assert output.count("local_map rejected") == 2 and "non-finite values in segment(s) ['state']" in output
    assert "seq 2 rejected" not in output  # the duplicate of seq 2 was skipped


def parts_of(raw: bytes):
    from msg_adapters.bags import bag_parts, deserialize

    return bag_parts(deserialize(raw))


CHUNK_CASES = [
    pytest.param("Intel", id="Intel-chunks"),
    pytest.param("manhattanOlson3500", id="Manhattan-chunks", marks=pytest.mark.slow),
]
MAPS_PER_CHUNK = 5


@pytest.mark.parametrize("name", CHUNK_CASES)
def test_pose_graph_chunks_through_lago(name, node, start_joiner, read_benchmark):
    """Raw relative-pose chunks (5 local maps' edges each: chains with loop closures) -> LAGO ->
    joining, with no iteration and no initial guess anywhere."""
    from linear_slam_ros.core.frames import change_frame
    from linear_slam_ros.evaluation.nonlinear import gauss_newton
    from linear_slam_ros.evaluation.objective import MapObjective
    from linear_slam_ros.pose_graph.chunks import chunk_to_local_map, edge_maps, graph_from_local_maps
    from linear_slam_ros.ros.bag_from_dataset import chunk_of

    maps = list(read_benchmark(name).maps)
    bag = REPO / "bags" / f"{name}_chunks{MAPS_PER_CHUNK}"
    if not (bag / "metadata.yaml").exists():
        make_bag(dataset_source(name), bag, as_pose_graph=True, maps_per_chunk=MAPS_PER_CHUNK)
    records = list(read_messages(bag))
    joiner = start_joiner(mode="online-dc", publish_rate=10.0)
    t0 = time.monotonic()
    joiner.play(node, records)
    final, t_final = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(records), 600.0, joiner)
    code, output = joiner.stop()
    assert code == 0, output[-2000:]
    assert final.stats["n_rejected"] == 0

    chunks = [chunk_of(maps[i : i + MAPS_PER_CHUNK], i // MAPS_PER_CHUNK + 1) for i in range(0, len(maps), MAPS_PER_CHUNK)]
    offline = run_join([chunk_to_local_map(c) for c in chunks], "online-dc")
    np.testing.assert_allclose(final.local_map.x, offline.result.x, rtol=0, atol=1e-9)

    in_first = change_frame(final.local_map, 0)
    edges = edge_maps(graph_from_local_maps(maps))
    objective = MapObjective.build(in_first, edges)
    chi2_graph = objective.chi2(in_first.x)
    chi2_dc = chi2(run_join(maps, "dc").result, maps)
    chi2_nls = gauss_newton(in_first, edges).chi2
    assert chi2_graph == pytest.approx(chi2(in_first, maps), rel=1e-9)  # star maps: the same objective
    assert chi2_nls <= chi2_graph <= 1.1 * chi2_dc
    out = REPO / "out" / "e2e"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}_pose_graph_chunks.json").write_text(json.dumps({
        "dataset": name, "chunks": len(records), "maps_per_chunk": MAPS_PER_CHUNK,
        "end_to_end_seconds": t_final - t0, "node_join_ms_p99": final.stats["join_ms_p99"],
        "chi2_lago_chunks_joined": chi2_graph, "chi2_dataset_maps_dc": chi2_dc, "chi2_nonlinear_ls": chi2_nls,
    }, indent=2) + "\n")


def test_outputs_carry_the_newest_joined_submaps_stamp(node, start_joiner):
    """global_map (and the views) are stamped with the data's time, not the node's clock."""
    maps = _synthetic(4)
    joiner = start_joiner(publish_rate=20.0)
    stamps = [Stamp(1_700_000_000 + i, 1000 * i) for i in range(1, len(maps) + 1)]
    _publish_all(node, joiner.topic("local_map"), [to_msg(encode_map(m, i, stamps[i - 1])) for i, m in enumerate(maps, start=1)])
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 60.0, joiner)
    assert final.stamp == stamps[-1]
