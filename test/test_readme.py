"""The README's parameter table and front-end example agree with the code."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from linear_slam_ros.joiner.config import parameter_declarations
from linear_slam_ros.ros.tf_output import TF_PARAMETERS
from msg_adapters import decode_map
from msg_adapters.ros import parts

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()
CONFIG = Path(__file__).resolve().parents[1] / "config" / "joiner.yaml"


def _table() -> dict[str, tuple[str, str]]:
    block = README.split("<!-- parameters-table")[1].split("<!-- end parameters-table -->")[0]
    rows = {}
    for line in block.splitlines():
        m = re.match(r"\| `(\w+)` \| `([^`]*)` \| (yes|no) \|", line)
        if m:
            rows[m.group(1)] = (m.group(2), m.group(3))
    return rows


PARAMETERS = {d.name: d for d in (*parameter_declarations(), *TF_PARAMETERS)}
"""The node declares exactly these (``JoinerNode.__init__``): the joiner's configuration and its TF output's."""


def test_parameter_table_matches_declarations():
    table = _table()
    assert set(table) == set(PARAMETERS)
    for name, decl in PARAMETERS.items():
        assert table[name] == (str(decl.default), "yes" if decl.spec.read_only else "no"), name


def test_config_file_sets_declared_parameters_to_their_defaults():
    params = yaml.safe_load(CONFIG.read_text())["/**/joiner"]["ros__parameters"]
    assert set(params) == set(PARAMETERS)
    assert {k: v for k, v in params.items()} == {k: d.default for k, d in PARAMETERS.items()}


def test_front_end_example_produces_a_valid_local_map():
    code = README.split("**A front-end in 25 lines**")[1].split("```python")[1].split("```")[0]
    function = code.split("rclpy.init()")[0]  # the example without starting ROS
    assert len(code.strip().splitlines()) <= 27
    # a stream's QoS: keep all, reliable; never the keep-last-10 idiom (it drops submaps under load)
    assert "HistoryPolicy.KEEP_ALL" in code and "ReliabilityPolicy.RELIABLE" in code
    assert not re.search(r"create_publisher\([^)]*, 10\)", code)
    assert "get_subscription_count()" in code and "wait_for_all_acked()" in code
    namespace: dict[str, object] = {}
    exec(function, namespace)  # noqa: S102 - the README's own example
    msg = namespace["local_map_msg"](1, 0, 1, [1, 7], [0, 1], [1.0, 0.0, 0.05, 2.0, 1.0], [(i, i, 100.0) for i in range(5)])
    decoded = decode_map(*parts(msg))
    assert decoded.seq == 1 and decoded.local_map.frame_id == 0 and decoded.local_map.end_id == 1
    assert list(decoded.local_map.ids) == [1, 7] and decoded.local_map.info_dense()[4, 4] == 100.0


def test_core_never_imports_ros():
    """Only ros/ uses ROS and message libraries; the CLI, an application too, may read bags, through
    msg_adapters.bags alone (rosbags: no ROS install), so that it takes a bag wherever it takes a dataset."""
    root = Path(__file__).resolve().parents[1] / "linear_slam_ros"
    for path in root.rglob("*.py"):
        if "ros" in path.relative_to(root).parts[:-1]:
            continue
        text = path.read_text()
        if path.relative_to(root).parts[0] == "cli":
            text = re.sub(r"^\s*from msg_adapters\.bags import .*$", "", text, flags=re.M)
        assert not re.search(r"^\s*(import|from)\s+(rclpy|rosbags|std_msgs|msg_adapters)", text, re.M), path
