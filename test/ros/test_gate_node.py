"""The node with the χ² gate on a pose graph (Intel): forward loop closures are held, a wrong one is gated when the
chain reaches its pose, the global map equals the offline joiner's, and the refiner is given exactly what was joined."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.joiner.joiner import Joiner, global_result
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.refinement.online import refine_offline
from linear_slam_ros.ros.bag_from_dataset import load_source
from linear_slam_ros.ros.bagio import read_messages
from linear_slam_ros.ros.demo import decode_global_map, decode_refined_map
from linear_slam_ros.ros.spin import LatestMessage, wait_for_diagnostics
from msg_adapters.layout import encode_map
from ros_support import REPO

N_MAPS = 150  # Intel's first submaps: submap 5 closes on pose 121, reached by submap 120
GATE = 0.99999999
WRONG = 5


def test_a_wrong_forward_closure_is_gated_through_the_node_and_the_refiner_leaves_it_out(node, start_joiner) -> None:
    from msg_adapters.ros import to_msg

    bag = REPO / "bags" / "Intel"
    if not (bag / "metadata.yaml").exists():
        pytest.skip("the committed bag bags/Intel is missing")
    records = list(read_messages(bag))[:N_MAPS]
    maps: list[LocalMap] = list(load_source(bag).maps[:N_MAPS])
    m = maps[WRONG]
    assert m.ids.tolist() == [6, 121, 232]  # its end pose, closures forward to poses 121 and 232 (held to the end)
    x = m.x.copy()
    x[3:5] += [8.0, -6.0]  # the closure moved by 10 m and 60 degrees: early in the stream the variance factor rests
    x[5] += np.deg2rad(60.0)  # on its prior alone (nothing was tested yet) and the gate's F quantile is wide
    maps[WRONG] = m.replace(x=x)
    raw = bytes(serialize_message(to_msg(encode_map(maps[WRONG], WRONG + 1))))
    records[WRONG] = records[WRONG]._replace(raw=raw)

    offline = Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE)
    fused: list[LocalMap] = []
    offline.on_fused = lambda robot, seq, ms: fused.extend(ms)
    for seq, submap in enumerate(maps, start=1):
        offline.offer(submap, seq)
    assert [(g.submap, g.variables) for g in offline.gated] == [(WRONG + 1, (121,))]
    expected = global_result(offline.state)

    joiner = start_joiner(gate_probability=GATE, refine="true", publish_rate=20.0)
    with LatestMessage(node, joiner.topic("global_map_refined"), decode_refined_map) as refined, \
            LatestMessage(node, joiner.topic("global_map"), decode_global_map) as latest:
        assert refined.wait(lambda r: True, 20.0, joiner.process), "no global_map_refined from the refiner process"
        joiner.play(node, records)
        assert latest.wait(lambda g: g.n_submaps == N_MAPS, 120.0, joiner.process), "no global map of every submap"
        done = refined.wait(lambda r: r[0].n_submaps == N_MAPS and r[1].get("converged") == 1.0, 60.0, joiner.process)
        assert done, f"no converged global_map_refined of {N_MAPS} submaps"
        message, segment = refined.value
        published = latest.value.local_map
    assert published.keys.tolist() == expected.keys.tolist()
    np.testing.assert_allclose(published.x, expected.x, rtol=0, atol=1e-9)
    reference = refine_offline(fused)  # the measurements of the joined map: the wrong closure left out
    assert abs(segment["chi2"] - reference.chi2) <= 1e-8 * reference.chi2
    diag = wait_for_diagnostics(node, lambda v: v.get("n_gated", -1) >= 1, 10.0) or {}
    assert diag.get("n_gated") == 1 and diag.get("n_held") == len(offline.state.held), diag
    code, out = joiner.stop()
    assert code == 0, out[-3000:]
    assert "loop closure 5 -> 121 of submap seq 6" in out and "held until the chain reached pose 121" in out, out[-3000:]
