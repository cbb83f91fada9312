"""Conventional ROS packaging: rosdep keys, requirement files, the launch file and the RViz config.

No ``launch``, ``launch_ros``, ``rviz2`` or ``rosdep`` is installed here (ROS 2 Jazzy from PyPI), so:

- ``package.xml``'s keys are checked against :data:`KNOWN_KEYS`, each with where it was verified;
- ``launch/joiner.launch.py`` is parsed with :mod:`ast`: its imports are launch APIs of Jazzy
  (:data:`LAUNCH_API`), its arguments and defaults are the documented ones, and every executable
  and share file it names exists in ``install/`` after ``colcon build`` (on a machine with
  ``launch_ros`` it is also executed: :func:`test_launch_description_builds_where_launch_is_installed`);
- ``rviz/linear_slam.rviz`` is YAML whose displays subscribe to the node's topics with the display
  class of the type the node publishes (read from ``node.py`` with :mod:`ast`) and a QoS that
  matches the node's latched publishers.
"""

from __future__ import annotations

import ast
import importlib.util
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from support import install_prefix

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "linear_slam_ros"
LAUNCH_FILE = REPO / "launch" / "joiner.launch.py"
RVIZ_FILE = REPO / "rviz" / "linear_slam.rviz"
NODE_FILE = REPO / PACKAGE / "ros" / "node.py"
INSTALL = install_prefix(PACKAGE)  # the repository's install/ (make setup), or a colcon workspace's
SHARE = INSTALL / "share" / PACKAGE
LIB = INSTALL / "lib" / PACKAGE

# Every rosdep key package.xml may name, and where it was verified to exist for ROS 2 Jazzy
# (Ubuntu 24.04 / Debian). ros/rosdistro = https://github.com/ros/rosdistro. A key not listed here
# fails test_package_xml_names_only_known_rosdep_keys: verify it, then add it with its source.
_JAZZY = "ROS 2 Jazzy package (ros/rosdistro jazzy/distribution.yaml; rclpy, common_interfaces, launch_ros)"
KNOWN_KEYS: dict[str, str] = {
    # ROS packages: released into Jazzy, resolved by rosdep from the distribution file.
    "rclpy": _JAZZY,
    "std_msgs": _JAZZY,
    "geometry_msgs": _JAZZY,
    "nav_msgs": _JAZZY,
    "visualization_msgs": _JAZZY,
    "diagnostic_msgs": _JAZZY,
    "std_srvs": _JAZZY,
    "builtin_interfaces": _JAZZY,
    "rcl_interfaces": _JAZZY,
    "rosgraph_msgs": _JAZZY + ": rosgraph_msgs is in ros2/rcl_interfaces",
    "tf2_ros_py": _JAZZY + ": tf2_ros_py (the Python module tf2_ros) is in ros2/geometry2",
    "tf2_msgs": _JAZZY + ": tf2_msgs is in ros2/geometry2",
    "ament_index_python": _JAZZY,
    "launch": _JAZZY,
    "launch_ros": _JAZZY,
    # System and Python rules of ros/rosdistro.
    "python3-numpy": "rosdep/python.yaml (debian/ubuntu: python3-numpy)",
    "python3-scipy": "rosdep/python.yaml (debian/ubuntu: python3-scipy)",
    "python3-matplotlib": "rosdep/python.yaml (debian/ubuntu: python3-matplotlib)",
    "python3-tqdm": "rosdep/python.yaml (debian: python3-tqdm; ubuntu '*': python3-tqdm)",
    "python3-pytest": "rosdep/python.yaml (debian/ubuntu: python3-pytest)",
    "python3-yaml": "rosdep/python.yaml (debian/ubuntu: python3-yaml)",
    "python3-ruamel.yaml": "rosdep/python.yaml (ubuntu: python3-ruamel.yaml)",
    "python3-rosbags-pip": "rosdep/python.yaml, pip rosbags: added by ros/rosdistro PR #37795 (merged 2023-06-26)",
    "python3-scikit-sparse-pip": "rosdep/python.yaml, pip scikit-sparse: added by ros/rosdistro PR #40045 (merged 2024-03-01)",
    "suitesparse": "rosdep/base.yaml (debian/ubuntu: libsuitesparse-dev)",
    "libopenblas-dev": "rosdep/base.yaml: added by ros/rosdistro PR #18700 (merged 2018-08)",
}
# Names package.xml must not use: pip-only packages that look like keys but are not (they go to requirements.txt),
# and tf2_ros, a real key, but the C++ library: the Python module tf2_ros comes with tf2_ros_py.
NOT_KEYS = {"python3-threadpoolctl", "python3-cholespy", "python3-rosbags", "python3-scikit-sparse", "python3-mcap", "tf2_ros"}
DEPEND_TAGS = ("depend", "build_depend", "build_export_depend", "exec_depend", "test_depend", "buildtool_depend")

# The launch APIs the launch file may import, as documented for Jazzy (docs.ros.org/en/jazzy/p/launch,
# .../p/launch_ros: launch.actions.DeclareLaunchArgument (default_value, description, choices),
# launch.conditions.IfCondition, launch.substitutions.{LaunchConfiguration, PathJoinSubstitution},
# launch_ros.actions.Node, launch_ros.substitutions.FindPackageShare,
# launch_ros.parameter_descriptions.ParameterValue (value, value_type)).
LAUNCH_API: dict[str, set[str]] = {
    "launch": {"LaunchDescription"},
    "launch.actions": {"DeclareLaunchArgument"},
    "launch.conditions": {"IfCondition"},
    "launch.substitutions": {"LaunchConfiguration", "PathJoinSubstitution"},
    "launch_ros.actions": {"Node"},
    "launch_ros.substitutions": {"FindPackageShare"},
    "launch_ros.parameter_descriptions": {"ParameterValue"},
}

# RViz2 display class for each message type a display subscribes to (rviz_default_plugins).
RVIZ_DISPLAY = {
    "PathMsg": "rviz_default_plugins/Path",
    "Path": "rviz_default_plugins/Path",
    "MarkerArray": "rviz_default_plugins/MarkerArray",
    "PoseStamped": "rviz_default_plugins/Pose",
    "PoseWithCovarianceStamped": "rviz_default_plugins/PoseWithCovariance",
}
RVIZ_TOPICS = ("path", "features", "pose")  # the node's latched views


def _installed(path: Path) -> Path:
    if not INSTALL.is_dir():
        pytest.fail("install/linear_slam_ros is missing: run `make setup` (colcon build) first")
    return path


# --- package.xml and requirement files ----------------------------------------------------------


def _package_keys() -> dict[str, list[str]]:
    root = ET.parse(REPO / "package.xml").getroot()
    return {tag: [e.text.strip() for e in root.iter(tag) if e.text] for tag in DEPEND_TAGS}


def test_package_xml_names_only_known_rosdep_keys() -> None:
    keys = [k for tag in _package_keys().values() for k in tag]
    assert keys, "package.xml names no dependency"
    unknown = sorted(set(keys) - set(KNOWN_KEYS))
    assert not unknown, f"not in the verified rosdep key list (test/test_packaging.py KNOWN_KEYS): {unknown}"
    assert not set(keys) & NOT_KEYS
    assert len(keys) == len(set(keys)), "a key is named twice"


def test_package_xml_depends_on_what_the_package_imports() -> None:
    exec_depends = set(_package_keys()["exec_depend"])
    # ROS interfaces and libraries the node and tools import, the launch file's packages, the solver stack.
    expected = {"rclpy", "std_msgs", "geometry_msgs", "nav_msgs", "visualization_msgs", "diagnostic_msgs", "std_srvs",
                "builtin_interfaces", "rcl_interfaces", "ament_index_python", "launch", "launch_ros",
                "python3-numpy", "python3-scipy", "python3-matplotlib", "python3-tqdm", "python3-rosbags-pip",
                "python3-ruamel.yaml", "suitesparse", "python3-scikit-sparse-pip", "tf2_ros_py", "tf2_msgs"}
    assert expected <= exec_depends, sorted(expected - exec_depends)


def _requirements(name: str) -> dict[str, str]:
    pins = {}
    for line in (REPO / name).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            m = re.fullmatch(r"([A-Za-z0-9_.\-]+)(\[[a-z0-9,]+\])?==([\w.]+)", line)
            assert m, f"{name}: not a pinned requirement: {line!r}"
            pins[m.group(1).lower()] = m.group(3)
    return pins


def test_requirements_are_split_by_where_they_belong() -> None:
    runtime, ros, dev = (_requirements(n) for n in ("requirements.txt", "requirements-ros-pypi.txt", "requirements-dev.txt"))
    # What the package needs at run time beyond ROS: nothing ROS, nothing for development.
    assert {"numpy", "scipy", "scikit-sparse", "matplotlib", "tqdm", "rosbags", "mcap"} <= set(runtime)
    assert not [p for p in runtime if p.startswith("ros-") or p.startswith("colcon") or p in dev]
    # ROS 2 from PyPI, for machines without ROS only.
    assert {"ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "colcon-common-extensions"} == set(ros)
    assert {"pytest", "ruff", "mypy"} <= set(dev)
    assert not set(runtime) & set(ros) and not set(ros) & set(dev)


def test_makefile_installs_all_three_requirement_files() -> None:
    makefile = (REPO / "Makefile").read_text()
    assert "REQUIREMENTS := requirements.txt requirements-ros-pypi.txt requirements-dev.txt" in makefile
    assert "$(VENV)/.installed: $(REQUIREMENTS)" in makefile
    assert "$(foreach r,$(REQUIREMENTS),-r $(r))" in makefile


# --- launch file ----------------------------------------------------------------------------------


def _launch_tree() -> ast.Module:
    return ast.parse(LAUNCH_FILE.read_text(), filename=str(LAUNCH_FILE))


def _calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == name]


def _kw(call: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _literal(node: ast.expr | None) -> object:
    assert node is not None
    return ast.literal_eval(node)


def _path_parts(node: ast.expr | None) -> list[object]:
    """Return the parts of ``PathJoinSubstitution([FindPackageShare(PACKAGE), "a", "b"])``: ["<share>", "a", "b"]."""
    assert isinstance(node, ast.Call) and getattr(node.func, "id", "") == "PathJoinSubstitution", node
    assert isinstance(node.args[0], ast.List)
    parts: list[object] = []
    for element in node.args[0].elts:
        if isinstance(element, ast.Name) and element.id == "share":
            parts.append("<share>")
        elif isinstance(element, ast.Constant):
            parts.append(element.value)
        else:
            raise AssertionError(f"unexpected path part {ast.dump(element)}")
    return parts


def _package(node: ast.expr | None) -> object:
    """Return a ``package=`` argument: a string, or the launch file's ``PACKAGE`` constant."""
    return PACKAGE if isinstance(node, ast.Name) and node.id == "PACKAGE" else _literal(node)


def test_launch_file_imports_only_documented_launch_apis() -> None:
    tree = _launch_tree()
    imported: dict[str, set[str]] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            imported.setdefault(node.module or "", set()).update(a.name for a in node.names)
        elif isinstance(node, ast.Import):
            raise AssertionError(f"plain import in the launch file: {[a.name for a in node.names]}")
    for module, names in imported.items():
        assert module in LAUNCH_API and names <= LAUNCH_API[module], (module, names)
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in functions
    # The share lookup names this package.
    share = next(n for n in tree.body if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "PACKAGE")
    assert _literal(share.value) == PACKAGE


def test_launch_arguments_and_defaults() -> None:
    tree = _launch_tree()
    arguments = {_literal(c.args[0]): c for c in _calls(tree, "DeclareLaunchArgument")}
    assert set(arguments) == {"params_file", "use_sim_time", "rviz"}
    assert _path_parts(_kw(arguments["params_file"], "default_value")) == ["<share>", "config", "joiner.yaml"]
    assert _literal(_kw(arguments["use_sim_time"], "default_value")) == "false"
    assert _literal(_kw(arguments["rviz"], "default_value")) == "false"
    for call in arguments.values():
        assert isinstance(_literal(_kw(call, "description")), str)
    # Every LaunchConfiguration refers to a declared argument.
    used = {_literal(c.args[0]) for c in _calls(tree, "LaunchConfiguration")}
    assert used == set(arguments)


def test_launch_nodes_name_installed_executables_and_files() -> None:
    tree = _launch_tree()
    nodes = {(_package(_kw(c, "package")), _literal(_kw(c, "executable"))): c for c in _calls(tree, "Node")}
    assert set(nodes) == {(PACKAGE, "joiner"), ("rviz2", "rviz2")}
    joiner = nodes[(PACKAGE, "joiner")]
    # The node name matches the /**/joiner block of config/joiner.yaml, so params_file applies.
    assert _literal(_kw(joiner, "name")) == "joiner"
    assert "/**/joiner" in yaml.safe_load((REPO / "config" / "joiner.yaml").read_text())
    assert _kw(joiner, "condition") is None
    rviz = nodes[("rviz2", "rviz2")]
    condition = _kw(rviz, "condition")
    assert isinstance(condition, ast.Call) and getattr(condition.func, "id", "") == "IfCondition"
    arguments = _kw(rviz, "arguments")
    assert isinstance(arguments, ast.List) and _literal(arguments.elts[0]) == "-d"
    rviz_parts = _path_parts(arguments.elts[1])
    assert rviz_parts == ["<share>", "rviz", RVIZ_FILE.name]
    # What the launch file names exists where `ros2 launch` resolves it after colcon build.
    exe = _installed(LIB / "joiner")
    assert exe.is_file() and exe.stat().st_mode & 0o111
    assert (SHARE / "config" / "joiner.yaml").is_file()
    # the FastDDS profile the joiner loads from its share directory (linear_slam_ros.ros.qos.inbound_dds_profile)
    assert (SHARE / "config" / "fastdds_inbound.xml").read_bytes() == (REPO / "config" / "fastdds_inbound.xml").read_bytes()
    assert (SHARE / "rviz" / RVIZ_FILE.name).read_bytes() == RVIZ_FILE.read_bytes()
    assert (SHARE / "launch" / LAUNCH_FILE.name).read_bytes() == LAUNCH_FILE.read_bytes()


def test_console_scripts_are_installed_including_sim_frontend() -> None:
    """Every console script lands in lib/linear_slam_ros; sim_frontend installs even before its module exists."""
    setup = ast.parse((REPO / "setup.py").read_text())
    scripts = [ast.literal_eval(e) for n in ast.walk(setup) if isinstance(n, ast.List)
               for e in n.elts if isinstance(e, ast.Constant) and isinstance(e.value, str) and " = " in e.value]
    names = {s.split(" = ")[0] for s in scripts}
    assert {"joiner", "bag_from_dataset", "bag_player", "bag_recorder", "demo", "sim_frontend"} <= names
    assert "sim_frontend = linear_slam_ros.ros.sim_frontend:main" in scripts
    for name in names:
        assert _installed(LIB / name).is_file(), name


@pytest.mark.skipif(importlib.util.find_spec("launch_ros") is None, reason="launch_ros is not installed (ROS 2 from PyPI)")
def test_launch_description_builds_where_launch_is_installed() -> None:  # pragma: no cover - real ROS 2 machines only
    spec = importlib.util.spec_from_file_location("joiner_launch", LAUNCH_FILE)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    assert {a.name for a in description.get_launch_arguments()} == {"params_file", "use_sim_time", "rviz"}


# --- RViz config ----------------------------------------------------------------------------------


def _node_publishers() -> dict[str, tuple[str, str]]:
    """Return topic -> (message class name, QoS argument name) of the node's ``create_publisher`` calls."""
    publishers: dict[str, tuple[str, str]] = {}
    for call in ast.walk(ast.parse(NODE_FILE.read_text())):
        if isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and call.func.attr == "create_publisher":
            kind, topic, qos = call.args[:3]
            if isinstance(kind, ast.Name) and isinstance(topic, ast.Constant) and isinstance(topic.value, str):
                publishers[topic.value] = (kind.id, qos.id if isinstance(qos, ast.Name) else ast.dump(qos))
    return publishers


def test_rviz_config_shows_the_node_topics_with_matching_types_and_qos() -> None:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from linear_slam_ros.ros.qos import latched_qos

    config = yaml.safe_load(RVIZ_FILE.read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == "map"
    displays = {d["Topic"]["Value"]: d for d in manager["Displays"] if "Topic" in d}
    assert set(displays) == {f"/{t}" for t in RVIZ_TOPICS}
    publishers = _node_publishers()
    latched = latched_qos()
    assert latched.durability == DurabilityPolicy.TRANSIENT_LOCAL and latched.reliability == ReliabilityPolicy.RELIABLE
    for topic in RVIZ_TOPICS:
        kind, qos = publishers[topic]
        display = displays[f"/{topic}"]
        assert display["Class"] == RVIZ_DISPLAY[kind], (topic, kind, display["Class"])
        assert qos == "latched", f"{topic} is not published with latched_qos()"
        assert display["Enabled"] is True
        # Transient local and reliable like the publisher: a late RViz receives the held message at once.
        assert display["Topic"]["Durability Policy"] == "Transient Local", topic
        assert display["Topic"]["Reliability Policy"] == "Reliable", topic
        assert display["Topic"]["History Policy"] == "Keep Last" and display["Topic"]["Depth"] >= 1, topic
    # The node's map_frame default is the fixed frame.
    assert "map_frame: map " in (REPO / "config" / "joiner.yaml").read_text()
