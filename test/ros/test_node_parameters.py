"""The node's parameter callback: values it applies to the running joiner at once."""

from __future__ import annotations

import threading
import time
import uuid
from types import SimpleNamespace

import pytest
from rclpy.parameter import Parameter

from linear_slam_ros.joiner.config import JoinerConfig, parameter_declarations
from linear_slam_ros.joiner.joiner import Joiner
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.ros import node as node_module
from linear_slam_ros.ros.node import JoinerNode


def _fake_node(config: JoinerConfig) -> SimpleNamespace:
    """What ``JoinerNode._on_set_parameters`` uses of the node: its configuration, joiner, lock, output version,
    refiner and output thread (``woken`` counts its wake-ups)."""
    fake = SimpleNamespace(config=config, joiner=Joiner(JoinMethod.ONLINE_DC), _lock=threading.Lock(), _version=0,
                           refiner=None, woken=[])
    fake._outputs = SimpleNamespace(wake=lambda: fake.woken.append(True))
    fake._config_values = lambda: JoinerNode._config_values(fake)  # type: ignore[arg-type]
    fake._join_and_publish = lambda join: JoinerNode._join_and_publish(fake, join)  # type: ignore[arg-type]
    return fake


def test_gate_probability_set_at_run_time_reaches_the_joiner_and_holding_follows_it():
    fake = _fake_node(JoinerConfig())
    result = JoinerNode._on_set_parameters(fake, [Parameter("gate_probability", value=0.99999999)])  # type: ignore[arg-type]
    assert result.successful
    assert fake.joiner.gate_probability == 0.99999999 and fake.joiner.state.hold_closures
    assert fake.config.gate_probability == 0.99999999
    result = JoinerNode._on_set_parameters(fake, [Parameter("gate_probability", value=0.0)])  # type: ignore[arg-type]
    assert result.successful and fake.joiner.gate_probability is None and not fake.joiner.state.hold_closures


def test_a_gate_probability_out_of_range_is_refused_and_changes_nothing():
    fake = _fake_node(JoinerConfig())
    result = JoinerNode._on_set_parameters(fake, [Parameter("gate_probability", value=1.5)])  # type: ignore[arg-type]
    assert not result.successful and "gate_probability=1.5 is outside its range" in result.reason
    assert fake.joiner.gate_probability is None and fake.config.gate_probability == 0.0


def test_the_largest_gate_probability_is_named_in_full_when_one_is_refused():
    """``:g`` printed the bound 0.999999999 as 1, and refused 1.0 as "outside its range [0, 1]"."""
    fake = _fake_node(JoinerConfig())
    result = JoinerNode._on_set_parameters(fake, [Parameter("gate_probability", value=1.0)])  # type: ignore[arg-type]
    assert not result.successful and "outside its range [0, 0.999999999]" in result.reason, result.reason


@pytest.mark.parametrize(("name", "value"), [("output_frame", "first_pose"), ("map_frame", "odom"), ("ellipse_max_state", 10)])
def test_a_new_output_frame_is_published_at_once_not_with_the_next_submap(name, value):
    """After a bag has ended no submap comes: the latched outputs kept the old frame for good."""
    fake = _fake_node(JoinerConfig())
    sent: list[dict[str, object]] = []
    fake.refiner = SimpleNamespace(configure_sink=lambda **settings: sent.append(settings))
    result = JoinerNode._on_set_parameters(fake, [Parameter(name, value=value)])  # type: ignore[arg-type]
    assert result.successful and getattr(fake.config, name) == value
    assert fake._version == 1 and fake.woken == [True]  # the publisher compares the version: it republishes
    assert sent == ([{"output_frame": "first_pose"}] if name == "output_frame" else [])  # global_map_refined follows


@pytest.mark.parametrize(("name", "value"), [("publish_rate", 10.0), ("summary_period", 1.0)])
def test_a_shorter_output_period_applies_at_once(name, value):
    """The output thread had fixed the next run at the old period: 20 s at publish_rate 0.05, up to an hour for a summary."""
    fake = _fake_node(JoinerConfig())
    result = JoinerNode._on_set_parameters(fake, [Parameter(name, value=value)])  # type: ignore[arg-type]
    assert result.successful and fake.woken == [True] and fake._version == 0  # nothing new to publish


def test_reorder_settings_reach_the_joiner():
    fake = _fake_node(JoinerConfig())
    result = JoinerNode._on_set_parameters(fake, [Parameter("reorder_window", value=7)])  # type: ignore[arg-type]
    assert result.successful and fake.joiner.reorder_window == 7


@pytest.mark.parametrize("robots", [None, ["a", "b"]])
def test_every_parameter_has_a_value_that_the_parameter_services_can_answer(rclpy_session, monkeypatch, robots):
    """``robots`` was declared by type alone: unset, so ``GetParameters`` (``ros2 param get``/``dump``)
    answered nothing for any request naming it."""
    monkeypatch.setattr(node_module, "set_blas_threads", lambda n: None)
    monkeypatch.setattr(node_module, "tune_allocator", lambda threshold: True)
    overrides = [] if robots is None else [Parameter("robots", Parameter.Type.STRING_ARRAY, robots)]
    joiner = node_module.JoinerNode(namespace=f"t{uuid.uuid4().hex[:8]}", parameter_overrides=overrides)
    try:
        names = [d.name for d in parameter_declarations()]
        values = joiner.get_parameters(names)  # raises ParameterUninitializedException for an unset one
        assert all(p.type_ != Parameter.Type.NOT_SET for p in values)
        robots_param = joiner.get_parameter("robots")
        assert robots_param.type_ == Parameter.Type.STRING_ARRAY and robots_param.value == (robots or [])
        assert joiner.describe_parameter("robots").read_only
        # rclpy's own parameters are rclpy's: use_sim_time was refused as "unknown parameter" at run time
        assert joiner.set_parameters([Parameter("use_sim_time", value=True)])[0].successful
        assert joiner.get_parameter("use_sim_time").value is True
        refused = joiner.set_parameters([Parameter("robots", Parameter.Type.STRING_ARRAY, ["c"])])[0]
        assert not refused.successful and "read-only" in refused.reason, refused
        assert list(joiner.config.robots) == (robots or [])
    finally:
        joiner.destroy_node()


def test_a_lowered_reorder_window_joins_what_waits_and_records_and_publishes_it():
    import numpy as np

    from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps

    maps = noisy_local_maps(make_world(2, 24, 20, np.random.default_rng(11)), np.random.default_rng(12), steps_per_map=3)
    fake = _fake_node(JoinerConfig())
    recorded: list[list[object]] = []
    published: list[tuple[object, str]] = []
    fake._record_joined = lambda keys: recorded.append(keys) or "state"
    fake._publish_pose = lambda state, keys, robot: published.append((keys, robot))
    assert fake.joiner.offer(maps[0], 1) == [1]
    for seq in (3, 4, 5):  # 2 is missing: they wait
        assert fake.joiner.offer(maps[seq - 1], seq) == []
    result = JoinerNode._on_set_parameters(fake, [Parameter("reorder_window", value=2)])  # type: ignore[arg-type]
    assert result.successful and fake.joiner.reorder_window == 2
    assert recorded == [[3, 4, 5]] and published == [([3, 4, 5], "")]  # as on arrival


def test_the_reorder_timeout_runs_on_the_steady_clock_with_sim_time(rclpy_session, monkeypatch):
    """With use_sim_time and no /clock (a bag that has ended), a ROS-clock timer never fires: submaps
    waiting behind a lost number were never joined."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    monkeypatch.setattr(node_module, "set_blas_threads", lambda n: None)
    monkeypatch.setattr(node_module, "tune_allocator", lambda threshold: True)
    ticks: list[float] = []
    monkeypatch.setattr(node_module.JoinerNode, "_on_expire_timer", lambda self: ticks.append(1.0))
    overrides = [Parameter("use_sim_time", value=True)]
    joiner = node_module.JoinerNode(namespace=f"t{uuid.uuid4().hex[:8]}", parameter_overrides=overrides)
    executor = SingleThreadedExecutor()
    executor.add_node(joiner)
    try:
        assert joiner.get_clock().ros_time_is_active  # sim time, and no /clock published
        deadline = time.monotonic() + 1.2
        while time.monotonic() < deadline and rclpy.ok():
            executor.spin_once(timeout_sec=0.05)
        assert len(ticks) >= 3, ticks  # every 0.25 s
    finally:
        executor.remove_node(joiner)
        joiner.destroy_node()


def test_diagnostics_warn_while_submaps_are_rejected_and_are_ok_again_after_a_quiet_period(rclpy_session, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticStatus

    monkeypatch.setattr(node_module, "set_blas_threads", lambda n: None)
    monkeypatch.setattr(node_module, "tune_allocator", lambda threshold: True)
    joiner = node_module.JoinerNode(namespace=f"t{uuid.uuid4().hex[:8]}")
    sent: list[object] = []
    joiner.pub_diag = SimpleNamespace(publish=sent.append)
    try:
        joiner.joiner.reject("bad_message", "a bad one")
        joiner._on_summary_timer()
        joiner._on_summary_timer()  # a quiet period: one lost submap kept it WARN for the process's life
        joiner.joiner.reject("bad_message", "another")
        joiner._on_summary_timer()
        levels = [(a.status[0].level, a.status[0].message) for a in sent]
        assert levels == [
            (DiagnosticStatus.WARN, "1 submaps rejected in the last 5 s (1 in all)"),
            (DiagnosticStatus.OK, "waiting for submaps"),
            (DiagnosticStatus.WARN, "1 submaps rejected in the last 5 s (2 in all)"),
        ]
        assert {v.key: v.value for v in sent[1].status[0].values}["n_rejected"] == "1"  # the total stays
        assert {v.key: v.value for v in sent[2].status[0].values}["n_rejected_bad_message"] == "2"  # and by reason
        monkeypatch.setattr(joiner.joiner, "stats", lambda: {"n_joined": 1234570.0, "n_rejected": 2e6, "last_join_ms": 0.1234567})
        joiner._on_summary_timer()
        values = {v.key: v.value for v in sent[-1].status[0].values}  # counts in full (%g: 1.23457e+06, 2e+06)
        assert (values["n_joined"], values["n_rejected"], values["last_join_ms"]) == ("1234570", "2000000", "0.1234567")
    finally:
        joiner.destroy_node()


def test_help_prints_the_usage_instead_of_starting_the_node(capsys):
    from linear_slam_ros.ros import sim_frontend

    node_module.main(["joiner", "--ros-args", "-p", "mode:=sequential", "--", "--help"])
    text = capsys.readouterr().out
    assert text.startswith("usage: ros2 run linear_slam_ros joiner [--ros-args")
    assert "  gate_probability = 0.0: " in text and "  mode = 'online-dc' *: " in text  # every parameter, read-only starred
    sim_frontend.main(["sim_frontend", "-h"])
    assert "a simulated robot and SLAM front-end" in capsys.readouterr().out


@pytest.mark.parametrize(("override", "match"), [
    (Parameter("reorder_timeout", value=10), r"^parameter reorder_timeout: Trying to set parameter 'reorder_timeout' to '10' "
     r"of type 'INTEGER', expecting type .*DOUBLE.* \(write a floating-point value with a decimal point, e\.g\. 10\.0\)$"),
    (Parameter("publish_rate", value=0.0), r"^parameter publish_rate: .*publish_rate.*0\.0"),
    (Parameter("queue_depth", value="deep"), r"^parameter queue_depth: Trying to set parameter 'queue_depth' to 'deep'.*INTEGER"),
])
def test_an_override_rclpy_refuses_stops_the_start_with_a_config_error(rclpy_session, monkeypatch, override, match):
    """rclpy refuses it before the joiner's own check: it ended in a traceback and exit code 1, not 2."""
    from linear_slam_ros.core.errors import ConfigError

    monkeypatch.setattr(node_module, "set_blas_threads", lambda n: None)
    monkeypatch.setattr(node_module, "tune_allocator", lambda threshold: True)
    with pytest.raises(ConfigError, match=match):
        node_module.JoinerNode(namespace=f"t{uuid.uuid4().hex[:8]}", parameter_overrides=[override])
