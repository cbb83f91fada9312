"""The joiner node with ``refine:=true``: ``global_map_refined`` reaches the offline optimum once the stream ends, and
``~/reset`` and shutdown end the refiner process cleanly (no orphan left behind)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from linear_slam_ros.evaluation.nonlinear import refine
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.ros.bag_from_dataset import load_source
from linear_slam_ros.ros.bagio import read_messages
from linear_slam_ros.ros.demo import decode_refined_map
from linear_slam_ros.ros.spin import LatestMessage, spin_until
from ros_support import REPO, call_trigger, global_map_subscription, set_parameter

N_MAPS = 40  # the first VicPark200 submaps (features and poses; loop closures within them)


def _refiner_children(parent: int) -> list[int]:
    """Process ids of the ``multiprocessing`` spawn children of ``parent`` that run the refiner."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().decode(errors="replace")
        except OSError:  # ended meanwhile
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == parent and fields[0] != "Z" and "spawn_main" in cmdline:
            found.append(int(entry.name))
    return found


def _running(pid: int) -> bool:
    """Whether ``pid`` is a live process (a zombie counts as ended)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _ended_within(pid: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while _running(pid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_refined_map_reaches_offline_optimum_and_refiner_stops_on_reset_and_shutdown(node, start_joiner) -> None:
    bag = REPO / "bags" / "vicpark200"
    if not (bag / "metadata.yaml").exists():
        pytest.skip("the committed bag bags/vicpark200 is missing")
    records = list(read_messages(bag))[:N_MAPS]
    maps = load_source(bag).maps[:N_MAPS]
    joiner = start_joiner(refine="true", publish_rate=20.0)
    topic = joiner.topic("global_map_refined")
    with LatestMessage(node, topic, decode_refined_map) as refined:
        # the refiner process is up (its latched empty map) before the stream starts
        assert refined.wait(lambda r: True, 20.0, joiner.process), "no global_map_refined from the refiner process"
        children = _refiner_children(joiner.process.pid)
        assert len(children) == 1, f"refiner processes of the joiner: {children}"
        first = children[0]
        joiner.play(node, records)
        done = refined.wait(lambda r: r[0].n_submaps == N_MAPS and r[1].get("converged") == 1.0, 30.0, joiner.process)
        assert done, f"no converged global_map_refined of {N_MAPS} submaps (last: {refined.value and refined.value[1]})"
        message, segment = refined.value

    offline = refine(run_join(maps, "online-dc").result, maps)
    assert abs(segment["chi2"] - offline.chi2) <= 1e-8 * offline.chi2
    assert abs(chi2(message.local_map, maps) - offline.chi2) <= 1e-8 * offline.chi2  # the published estimate itself
    assert segment["lag_s"] >= 0 and segment["cpu_s"] > 0

    # a new output_frame reaches both latched maps at once, with no submap after it (the refiner's publisher kept the
    # frame it started with; global_map waited for the next submap)
    assert message.local_map.frame_id == maps[N_MAPS - 1].end_id  # end_pose, the default
    first = maps[0].frame_id
    with LatestMessage(node, topic, decode_refined_map) as refined, \
            global_map_subscription(node, joiner.topic("global_map")) as linear:
        assert set_parameter(node, joiner.topic("joiner"), "output_frame", "first_pose").successful
        assert refined.wait(lambda r: r[0].local_map.frame_id == first, 20.0, joiner.process), "refined map not moved"
        assert linear.wait(lambda m: m.local_map.frame_id == first, 20.0, joiner.process), "global_map not moved"
        moved = refined.value[0]
    assert moved.n_submaps == N_MAPS and abs(chi2(moved.local_map, maps) - offline.chi2) <= 1e-8 * offline.chi2

    assert call_trigger(node, joiner.topic("joiner/reset"), 20.0).success  # the node's ~/reset
    assert _ended_within(first, 5.0), "the refiner process outlived ~/reset"
    assert spin_until(node, lambda: len(_refiner_children(joiner.process.pid)) == 1, 10.0), "no fresh refiner after ~/reset"
    second = _refiner_children(joiner.process.pid)[0]
    assert second != first

    code, out = joiner.stop()
    assert code == 0, out[-3000:]
    assert _ended_within(second, 5.0), f"refiner process {second} left behind after shutdown"
    assert out.count("refiner process restarted (the old one's exit code 0)") == 1, out[-3000:]  # ~/reset: clean
    assert out.count("refiner process stopped (exit code 0)") == 1, out[-3000:]  # shutdown: clean


def test_the_refined_publisher_refuses_a_setting_it_does_not_have_and_republishes_only_a_new_frame() -> None:
    from types import SimpleNamespace

    from linear_slam_ros.core.errors import ConfigError
    from linear_slam_ros.ros.refine_sink import RosSink

    sent: list[object] = []
    sink = SimpleNamespace(output_frame="end_pose", _last=("refined", 1.0, 0.5), _send=lambda *last: sent.append(last))
    with pytest.raises(ConfigError, match="no setting 'map_frame'"):
        RosSink.configure(sink, {"map_frame": "odom"})  # type: ignore[arg-type]
    RosSink.configure(sink, {"output_frame": "end_pose"})  # type: ignore[arg-type]
    assert sent == []  # the same frame: nothing to republish
    RosSink.configure(sink, {"output_frame": "first_pose"})  # type: ignore[arg-type]
    assert sink.output_frame == "first_pose" and sent == [("refined", 1.0, 0.5)]  # the newest map, its CPU and lag kept
