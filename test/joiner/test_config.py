"""The typed config: defaults, conversions, and every rejection naming parameter, value and allowed values."""

from __future__ import annotations

import pytest

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.joiner.config import JoinerConfig, OutputFrame, parameter_declarations
from linear_slam_ros.joiner.strategy import JoinMethod, MapType


def test_defaults_and_conversions():
    assert JoinerConfig.from_mapping({}) == JoinerConfig()
    config = JoinerConfig.from_mapping(
        {"mode": "online-dc", "map_type": "feature-only", "output_frame": "first_pose", "publish_rate": 5, "queue_depth": 10}
    )
    assert config.mode is JoinMethod.ONLINE_DC and config.map_type is MapType.FEATURE_ONLY
    assert config.output_frame is OutputFrame.FIRST_POSE
    assert config.publish_rate == 5.0 and isinstance(config.publish_rate, float) and config.queue_depth == 10


def test_declarations_follow_the_config_fields():
    decls = {d.name: d for d in parameter_declarations()}
    assert list(decls) == [f for f in JoinerConfig.__dataclass_fields__]
    assert decls["mode"].default == "online-dc" and decls["mode"].spec.read_only
    assert decls["mode"].choices == ("sequential", "dc", "online-dc")
    assert decls["publish_rate"].spec.bounds == (0.05, 100.0) and not decls["publish_rate"].spec.read_only


@pytest.mark.parametrize(
    ("values", "online", "match"),
    [
        ({"mode": "online_dc"}, True,
         r"parameter mode='online_dc' is not valid: allowed values are \['sequential', 'dc', 'online-dc'\]"),
        ({"map_type": "features"}, True,
         r"parameter map_type='features' is not valid: allowed values are \['as-is', 'feature-only'\]"),
        ({"mode": "dc"}, True,
         r"parameter mode='dc' is not allowed with map_type='as-is': allowed values are \['sequential', 'online-dc'\]"),
        ({"output_frame": "world"}, True,
         r"parameter output_frame='world' is not valid: allowed values are \['end_pose', 'first_pose'\]"),
        ({"publish_rate": 0.0}, True, r"parameter publish_rate=0.0 is outside its range \[0.05, 100\]"),
        ({"reorder_window": 0}, True, r"parameter reorder_window=0 is outside its range \[1, 1000000\]"),
        ({"queue_depth": 1.5}, True, r"parameter queue_depth=1.5 must be of type int"),
        ({"queue_depth": True}, True, r"parameter queue_depth=True must be of type int"),
        ({"map_frame": 3}, True, r"parameter map_frame=3 must be of type str"),
        ({"colour": "red"}, True, r"unknown parameter 'colour'"),
        ({"map_frame": ""}, True, r"parameter map_frame='' is not a frame id"),
        ({"robots": ["robót"]}, True, r"robots\[0\]='robót' is not a robot namespace \(ASCII letters"),
        ({"robots": ["r²"]}, True, r"robots\[0\]='r²' is not a robot namespace"),
        ({"map_type": "feature-only", "gate_probability": 0.99}, True,
         r"parameter gate_probability=0.99: mode 'online-dc' with map_type 'feature-only' cannot gate"),
        ({"map_type": "feature-only", "hold_closures": True}, True,
         r"parameter hold_closures=True: mode 'online-dc' with map_type 'feature-only' cannot hold loop closures"),
    ],
)
def test_invalid_values_name_parameter_value_and_allowed_values(values, online, match):
    with pytest.raises(ConfigError, match=match):
        JoinerConfig.from_mapping(values, online=online)


def test_batch_methods_are_allowed_offline():
    assert JoinerConfig.from_mapping({"mode": "dc"}, online=False).mode is JoinMethod.DC


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"mode": "bogus"}, r"'bogus' is not a valid JoinMethod: valid values are \['sequential', 'dc', 'online-dc'\]"),
        ({"mode": "online-dc", "map_type": "bogus"}, r"'bogus' is not a valid MapType: valid values are \['as-is', "),
        ({"mode": "online-dc", "reorder_window": 0}, r"reorder_window=0 must be an integer >= 1"),
        ({"mode": "online-dc", "reorder_timeout": -1.0}, r"reorder_timeout=-1.0 must be a finite number of seconds > 0"),
        ({"mode": "online-dc", "reorder_max_bytes": -1}, r"reorder_max_bytes=-1 must be an integer >= 1"),
        ({"mode": "online-dc", "defer_above": -1}, r"defer_above=-1 must be >= 0"),
        ({"mode": "online-dc", "map_type": "feature-only", "gate_probability": 0.9}, r"cannot gate"),
    ],
)
def test_a_joiner_made_through_the_api_refuses_what_cannot_work(kwargs, match):
    from linear_slam_ros.joiner.joiner import Joiner

    with pytest.raises(ConfigError, match=match):
        Joiner(**kwargs)


def test_the_gate_cannot_be_turned_on_at_run_time_where_it_cannot_work():
    from linear_slam_ros.joiner.joiner import Joiner

    j = Joiner("online-dc", "feature-only")
    with pytest.raises(ConfigError, match="cannot gate"):
        j.set_gate(0.99)
    assert j.gate_probability is None
    with pytest.raises(ConfigError, match=r"reorder_window=0 must be an integer >= 1"):
        j.set_reorder(window=0)
    assert j.reorder_window == 100


def test_a_leading_tilde_in_a_path_parameter_is_the_home_folder(monkeypatch):
    """No shell expands ``~`` in a parameter file or ``-p``: the journal landed in a folder named ``~`` under the
    node's working directory, and a restart from elsewhere found no state."""
    monkeypatch.setenv("HOME", "/home/robot")
    names = ("state_dir", "save_directory", "load_path", "initial_map", "timing_file")
    config = JoinerConfig.from_mapping({name: f"~/.ros/run1/{name}" for name in names})
    assert [getattr(config, name) for name in names] == [f"/home/robot/.ros/run1/{name}" for name in names]
    assert JoinerConfig.from_mapping({"map_frame": "~odom"}).map_frame == "~odom"  # not a path: as given
