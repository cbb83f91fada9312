"""sim_frontend: a seeded simulated front-end whose live local maps the installed joiner joins.

The simulation itself is checked in-process (seeded, numbered, consistent with its ground
truth); end to end, the front-end runs as its own process (``python -m``, as ``ros2 run`` would
start its console script) against the joiner process, over DDS on loopback.
"""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from collections.abc import Callable

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import points_to_frame, relative_pose, wrap_angle
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.evaluation.metrics import nees, rmse
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.ros.process import stop_process
from linear_slam_ros.ros.qos import latched_qos
from linear_slam_ros.ros.sim_frontend import WORLDS, SimFrontend, Simulation
from linear_slam_ros.ros.spin import spin_until
from msg_adapters import MapMessage
from ros_support import REPO, JoinerProcess, wait_for_global_map

SEED = 7
N_MAPS = 20
STEPS = 4


def sim_frontend(namespace: str, *params: str) -> subprocess.Popen[bytes]:
    """Start ``sim_frontend`` in ``namespace`` with ``name:=value`` parameters, as its own process."""
    args = [a for p in params for a in ("-p", p)]
    cmd = [sys.executable, "-m", "linear_slam_ros.ros.sim_frontend", "--ros-args", "-r", f"__ns:=/{namespace}", *args]
    return subprocess.Popen(cmd, cwd=REPO, env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def output(process: subprocess.Popen[bytes]) -> str:
    return process.stdout.read().decode(errors="replace") if process.stdout else ""


def truth(simulation: Simulation, frame_step: int, local_map: LocalMap) -> dict[tuple[int, int], np.ndarray]:
    """Return the true value of every variable of ``local_map``, seen from the robot at ``frame_step``."""
    frame = simulation.true_pose(frame_step)
    out = {}
    for var_id, kind in zip(local_map.ids.tolist(), local_map.kinds.tolist(), strict=True):
        if kind == POSE:
            out[(POSE, var_id)] = relative_pose(2, frame, simulation.true_pose(var_id))
        else:
            out[(FEATURE, var_id)] = points_to_frame(2, frame[:2], frame[2:], simulation.features[var_id]).points
    return out


@pytest.mark.parametrize("world", WORLDS)
def test_a_seed_gives_the_same_maps_numbered_by_step(world: str) -> None:
    a, b, other = Simulation(world, SEED, STEPS), Simulation(world, SEED, STEPS), Simulation(world, SEED + 1, STEPS)
    for i in range(5):
        ma, mb, mo = a.next_local_map(), b.next_local_map(), other.next_local_map()
        assert (ma.frame_id, ma.end_id, int(ma.ids[0]), int(ma.kinds[0])) == (STEPS * i, STEPS * (i + 1), STEPS * (i + 1), POSE)
        assert np.all(ma.kinds[1:] == FEATURE) and ma.n_vars > 3
        np.testing.assert_array_equal(ma.ids, mb.ids)
        np.testing.assert_array_equal(ma.x, mb.x)
        np.testing.assert_array_equal(ma.info_dense(), mb.info_dense())
        assert ma.x.shape != mo.x.shape or not np.array_equal(ma.x, mo.x)


def test_worlds_drive_for_ever_in_one_metre_steps() -> None:
    loop = Simulation("loop", SEED)
    np.testing.assert_array_equal(loop.true_pose(120), loop.true_pose(0))  # round and round
    park = Simulation("park", SEED)
    steps = np.stack([park.true_pose(k) for k in range(2 * len(park.route) + 1)])
    np.testing.assert_allclose(np.hypot(*np.diff(steps[:, :2], axis=0).T), 1.0, atol=1e-9)  # forth, back, forth: no jump
    with pytest.raises(ValueError, match="unknown world 'moon'"):
        Simulation("moon")
    with pytest.raises(ValueError, match="steps_per_map"):
        Simulation("park", steps_per_map=0)


@pytest.mark.parametrize("world", WORLDS)
def test_local_maps_are_consistent_with_the_ground_truth(world: str) -> None:
    """The noise has exactly the information the maps carry: summed NEES within the chi-square bounds."""
    simulation = Simulation(world, SEED, STEPS)
    total, dof = 0.0, 0
    for i in range(N_MAPS):
        local_map = simulation.next_local_map()
        result = nees(local_map, truth(simulation, STEPS * i, local_map))
        total, dof = total + result.nees, dof + result.dof
    assert 0.7 * dof < total < 1.3 * dof, (total, dof)  # chi-square(dof ~ 500..1000): sd sqrt(2 dof) ~ 5 %


def all_joined(message: object) -> bool:
    """Return whether a decoded ``global_map`` has joined all ``N_MAPS`` submaps."""
    return isinstance(message, MapMessage) and message.n_submaps == N_MAPS


def test_joiner_joins_the_live_stream(node: Node, start_joiner: Callable[..., JoinerProcess]) -> None:
    """20 maps at 50 Hz: all joined, equal to the offline join of the seeded maps, and close to the truth."""
    simulation = Simulation("park", SEED, STEPS)
    end = simulation.true_pose(STEPS * N_MAPS)  # the true end pose of the last map
    true_poses: list[PoseStamped] = []
    namespace = f"t{uuid.uuid4().hex[:8]}"
    truth_sub = node.create_subscription(PoseStamped, f"/{namespace}/sim_frontend/true_pose", true_poses.append, latched_qos())
    sim = sim_frontend(namespace, f"seed:={SEED}", f"steps_per_map:={STEPS}", f"n_maps:={N_MAPS}", "rate:=50.0")
    try:
        # The front-end waits for the joiner before its first map; this node (a participant of long
        # standing: DDS may take a few seconds to discover a newcomer) finds its ground truth first.
        assert spin_until(node, lambda: truth_sub.get_publisher_count() > 0, 30.0), "~/true_pose not discovered in 30 s"
        joiner = start_joiner(namespace, publish_rate=20.0, output_frame="first_pose")
        final, _ = wait_for_global_map(node, joiner.topic("global_map"), all_joined, 60.0, joiner)  # ~8 s on an idle machine
        assert sim.wait(20.0) == 0, output(sim)  # exits by itself once every map is acknowledged
        spin_until(node, lambda: bool(true_poses) and true_poses[-1].pose.position.x == end[0], 5.0)
    finally:
        stop_process(sim)
    assert isinstance(final, MapMessage) and final.stats is not None
    assert final.stats["n_joined"] == N_MAPS and final.stats["n_rejected"] == 0
    joined = final.local_map
    assert joined.frame_id == 0

    # The process published exactly the maps of the seed: its join equals the offline join of them.
    maps = [simulation.next_local_map() for _ in range(N_MAPS)]
    offline = change_frame(run_join(maps, "online-dc").result, 0)
    np.testing.assert_array_equal(joined.ids, offline.ids)
    np.testing.assert_array_equal(joined.kinds, offline.kinds)
    np.testing.assert_allclose(joined.x, offline.x, rtol=0, atol=1e-9)

    # Close to the simulation's ground truth: errors of a few sigma at most, centimetres.
    true_values = truth(simulation, 0, joined)
    result = nees(joined, true_values)
    assert result.nees < 4 * result.dof, result  # RMS of the normalised errors below 2 sigma
    assert result.consistent, result
    reference = LocalMap(2, 0, None, joined.ids, joined.kinds, np.concatenate(list(true_values.values())), np.eye(joined.x.size))
    assert rmse(joined, reference, POSE) < 0.2 and rmse(joined, reference, FEATURE) < 0.2

    # ~/true_pose: the true end pose of the last map, in the frame of pose 0.
    assert true_poses, "nothing received on ~/true_pose"
    last = true_poses[-1]
    assert last.header.frame_id == "map"
    assert (last.pose.position.x, last.pose.position.y) == pytest.approx((end[0], end[1]), abs=1e-12)
    assert wrap_angle(2 * np.arctan2(last.pose.orientation.z, last.pose.orientation.w) - end[2]) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    ("name", "value", "error", "match"),
    [
        ("world", "moon", ValueError, "unknown world 'moon'"),
        ("rate", 0.0, InvalidParameterValueException, "rate"),  # below the declared range
        ("rate", 10, InvalidParameterTypeException, "rate"),  # an integer for a double
        ("map_frame", "", ValueError, r"^parameter map_frame='' is not a frame id$"),  # as the joiner refuses it
    ],
)
def test_an_invalid_parameter_is_refused(
    rclpy_session: None, name: str, value: object, error: type[Exception], match: str
) -> None:
    with pytest.raises(error, match=match):
        SimFrontend(parameter_overrides=[Parameter(name, value=value)])


def test_an_invalid_parameter_exits_with_code_2() -> None:
    sim = sim_frontend("t_bad_params", "world:=moon")
    try:
        code = sim.wait(30.0)
    finally:
        stop_process(sim)
    text = output(sim)
    assert code == 2 and "cannot start: unknown world 'moon'" in text, text


@pytest.mark.parametrize("context_ok", [False, True])
def test_an_error_once_sigterm_shut_the_context_down_is_a_normal_stop(monkeypatch, context_ok: bool) -> None:
    """SIGTERM (ros2 launch, docker) shut the context down under a publication or the wait for acknowledgements:
    rclpy's RCLError ended the node with code 1 and a traceback in 5 of 11 runs. While the context runs it is an error."""
    from types import SimpleNamespace

    from linear_slam_ros.ros import sim_frontend as module

    class Stopped(Exception):
        pass

    destroyed: list[bool] = []
    fake = SimpleNamespace(context=SimpleNamespace(ok=lambda: context_ok), finished=None,
                           destroy_node=lambda: destroyed.append(True))

    def spin(node: object, future: object) -> None:
        raise Stopped("Failed to publish: publisher's context is invalid")

    monkeypatch.setattr(module, "SimFrontend", lambda: fake)
    monkeypatch.setattr(module.rclpy, "init", lambda args=None: None)
    monkeypatch.setattr(module.rclpy, "try_shutdown", lambda: None)
    monkeypatch.setattr(module.rclpy, "spin_until_future_complete", spin)
    if context_ok:
        with pytest.raises(Stopped, match="context is invalid"):
            module.main([])
    else:
        module.main([])  # returns: exit code 0
    assert destroyed == [True]
