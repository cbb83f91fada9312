"""The package layout holds: layers only import downwards, ROS stays in ros/, no import cycles.

Every module of ``linear_slam_ros`` and ``msg_adapters`` is parsed with :mod:`ast`; its imports,
top-level and function-local, absolute and relative, are checked against :data:`LAYERS` and
the rules below. Nothing is imported, so a broken module cannot hide a violation.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("linear_slam_ros", "msg_adapters")

# The layer of every unit (a sub-package, or a single module), lowest first. A module may import
# from its own unit or from units of a strictly lower layer; units of the same layer are peers and
# must not import each other. ``linear_slam_ros`` names only the top package's __init__: every other
# module imports it implicitly, so it imports none of them.
LAYERS: dict[str, int] = {
    "linear_slam_ros": -1,
    "linear_slam_ros.core": 0,
    "linear_slam_ros.joining": 1,
    "linear_slam_ros.pose_graph": 1,
    "linear_slam_ros.feature_only": 2,
    "linear_slam_ros.io": 3,
    "msg_adapters": 3,
    "linear_slam_ros.joiner": 4,
    "linear_slam_ros.evaluation": 5,
    "linear_slam_ros.refinement": 6,
    "linear_slam_ros.cli": 7,
    "linear_slam_ros.ros": 8,
    "linear_slam_ros.__main__": 9,
}

CLI = "linear_slam_ros.cli"
ROS = "linear_slam_ros.ros"
MAIN = "linear_slam_ros.__main__"
# Third-party ROS libraries: rclpy (and the ROS node layer) only in linear_slam_ros/ros/; bag libraries
# and message packages only there too, or in msg_adapters, whose job is converting them.
RCLPY = frozenset({"rclpy"})
BAG_LIBRARIES = frozenset({"rosbags", "mcap", "mcap_ros2"})
# ROS message packages by name: std_msgs, geometry_msgs, std_srvs, builtin_interfaces, rcl_interfaces, ...
MESSAGE_SUFFIXES = ("_msgs", "_srvs", "_interfaces")


@dataclass(frozen=True)
class Import:
    """One import statement's target, as seen from the importing module."""

    module: str  # the importing module, dotted (a package's __init__ is the package's name)
    target: str  # the imported module, dotted: a module of ours when it names one, else as written
    line: int
    local: bool  # inside a function (or class) body rather than at module level

    def __str__(self) -> str:
        where = "function-local " if self.local else ""
        return f"{self.module}:{self.line}: {where}import of {self.target}"


def module_name(root: Path, path: Path) -> str:
    """Return the dotted name of the module at ``path`` below ``root``."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def discover(root: Path, packages: Iterable[str] = PACKAGES) -> dict[str, Path]:
    """Return every module of ``packages`` below ``root``, by dotted name."""
    modules = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            if "__pycache__" not in path.parts:
                modules[module_name(root, path)] = path
    return modules


def _resolve(name: str, known: Mapping[str, Path]) -> str:
    """Return ``name`` if it is a module of ours, else its longest prefix that is (else ``name``)."""
    probe = name
    while probe:
        if probe in known:
            return probe
        probe = probe.rpartition(".")[0]
    return name


def _statements(tree: ast.Module) -> Iterator[tuple[ast.Import | ast.ImportFrom, bool]]:
    """Yield every import statement of ``tree`` and whether it sits inside a function or class."""

    def walk(node: ast.AST, local: bool) -> Iterator[tuple[ast.Import | ast.ImportFrom, bool]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import | ast.ImportFrom):
                yield child, local
            nested = local or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda | ast.ClassDef)
            yield from walk(child, nested)

    yield from walk(tree, False)


def imports_of(module: str, source: str, known: Mapping[str, Path], is_package: bool = False) -> list[Import]:
    """Return the imports of one module's ``source``; relative imports resolved, targets resolved to our modules."""
    found = []
    for node, local in _statements(ast.parse(source)):
        if isinstance(node, ast.Import):
            targets = [_resolve(alias.name, known) for alias in node.names]
        else:
            base = node.module or ""
            if node.level:
                anchor = module.split(".") if is_package else module.split(".")[:-1]
                if node.level - 1 > len(anchor):
                    raise ValueError(f"{module}:{node.lineno}: relative import beyond the top-level package")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            # ``from pkg import name``: name is a submodule when we have one by that name, else an attribute of pkg.
            targets = [
                _resolve(f"{base}.{alias.name}" if alias.name != "*" and f"{base}.{alias.name}" in known else base, known)
                for alias in node.names
            ]
        for target in dict.fromkeys(targets):
            found.append(Import(module, target, node.lineno, local))
    return found


def collect(root: Path = REPO, packages: Iterable[str] = PACKAGES) -> tuple[dict[str, Path], list[Import]]:
    """Return the modules of ``packages`` below ``root`` and all their imports."""
    modules = discover(root, packages)
    found = []
    for name, path in modules.items():
        found += imports_of(name, path.read_text(encoding="utf-8"), modules, is_package=path.name == "__init__.py")
    return modules, found


def unit_of(module: str, layers: Mapping[str, int] = LAYERS) -> str | None:
    """Return the entry of ``layers`` that ``module`` belongs to (longest matching prefix), or None."""
    for unit in sorted(layers, key=len, reverse=True):
        if module == unit or (module.startswith(unit + ".") and unit != "linear_slam_ros"):
            return unit
    return None


def _within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _is_message_package(top: str) -> bool:
    return top.endswith(MESSAGE_SUFFIXES)


def violations(modules: Iterable[str], found: Iterable[Import], layers: Mapping[str, int] = LAYERS) -> list[str]:
    """Return one line per broken rule: the importing module and line, the import, and the rule."""
    ours = set(modules)
    problems = []
    for name in sorted(ours):
        if unit_of(name, layers) is None:
            problems.append(f"{name}: module is in no unit of the layer table (add its sub-package to LAYERS)")
    for imp in found:
        source_unit = unit_of(imp.module, layers)
        top = imp.target.split(".")[0]
        in_ros = _within(imp.module, ROS)
        if imp.target in ours:
            target_unit = unit_of(imp.target, layers)
            if _within(imp.target, CLI) and imp.module != MAIN and not _within(imp.module, CLI):
                problems.append(f"{imp}: only {MAIN} imports {CLI}")
            elif _within(imp.target, ROS) and not in_ros:
                problems.append(f"{imp}: nothing outside {ROS} imports {ROS}")
            elif source_unit is None or target_unit is None or source_unit == target_unit:
                continue
            elif layers[target_unit] > layers[source_unit]:
                problems.append(
                    f"{imp}: upward import, layer {layers[source_unit]} ({source_unit}) "
                    f"imports layer {layers[target_unit]} ({target_unit})"
                )
            elif layers[target_unit] == layers[source_unit]:
                problems.append(f"{imp}: peers of layer {layers[source_unit]} ({source_unit}, {target_unit}) import each other")
        elif top in RCLPY and not in_ros:
            problems.append(f"{imp}: nothing outside {ROS} imports rclpy")
        elif (top in BAG_LIBRARIES or _is_message_package(top)) and not in_ros and not _within(imp.module, "msg_adapters"):
            problems.append(f"{imp}: within linear_slam_ros only {ROS} imports bag libraries and ROS message packages")
    return problems


def cycles(found: Iterable[Import], modules: Iterable[str]) -> list[list[str]]:
    """Return the import cycles between ``modules``: one closed path per strongly connected component."""
    ours = set(modules)
    graph: dict[str, set[str]] = {m: set() for m in ours}
    for imp in found:
        if imp.target in ours and imp.target != imp.module:
            graph[imp.module].add(imp.target)

    # Tarjan's strongly connected components, iteratively (no recursion limit on long chains).
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    components.append(set(component))

    def closed_path(component: set[str]) -> list[str]:
        """Return a shortest cycle through the component's first module (breadth-first)."""
        first = min(component)
        parents: dict[str, str] = {}
        frontier = [first]
        while frontier:
            following = []
            for node in frontier:
                for child in sorted(graph[node] & component):
                    if child == first:
                        path = [node]
                        while path[-1] != first:
                            path.append(parents[path[-1]])
                        return [first, *reversed(path[:-1]), first] if node != first else [first, first]
                    if child not in parents:
                        parents[child] = node
                        following.append(child)
            frontier = following
        raise AssertionError(f"no cycle through {first}")  # unreachable for a strongly connected component

    return sorted(closed_path(c) for c in components)


def _report(title: str, lines: list[str]) -> str:
    return f"{len(lines)} {title}:\n  " + "\n  ".join(lines)


def test_imports_follow_the_layers() -> None:
    modules, found = collect()
    assert "linear_slam_ros.core.geometry" in modules and found, "no modules or imports found: the checker is blind"
    problems = violations(modules, found)
    assert not problems, _report("architecture violation(s)", problems)


def test_no_import_cycles() -> None:
    modules, found = collect()
    loops = cycles(found, modules)
    assert not loops, _report("import cycle(s)", [" -> ".join(loop) for loop in loops])


def test_every_unit_of_the_layer_table_exists() -> None:
    modules, _ = collect()
    missing = [unit for unit in LAYERS if unit not in modules]
    assert not missing, f"layer table names units that do not exist: {missing}"


# --- the checker itself, on a made-up tree: it must see what it is meant to catch ---

FAKE_TREE = {
    "linear_slam_ros/__init__.py": "",
    "linear_slam_ros/__main__.py": "from linear_slam_ros.cli.main import main\nimport linear_slam_ros.ros.node\n",
    "linear_slam_ros/core/__init__.py": "",
    "linear_slam_ros/core/geometry.py": "import numpy as np\n\ndef f():\n    from ..evaluation import plots\n",
    "linear_slam_ros/core/errors.py": "from . import geometry\n",
    "linear_slam_ros/joining/__init__.py": "",
    "linear_slam_ros/joining/pairwise.py": (
        "from linear_slam_ros.core import geometry\nfrom linear_slam_ros.pose_graph.graph import G\n"
    ),
    "linear_slam_ros/pose_graph/__init__.py": "",
    "linear_slam_ros/pose_graph/graph.py": "import linear_slam_ros.pose_graph.lago\nG = 1\n",
    "linear_slam_ros/pose_graph/lago.py": "class A:\n    def m(self):\n        from .graph import G\n",
    "linear_slam_ros/io/__init__.py": "",
    "linear_slam_ros/io/datasets.py": "import std_msgs.msg\nfrom mcap.reader import make_reader\n",
    "linear_slam_ros/joiner/__init__.py": "",
    "linear_slam_ros/joiner/joiner.py": "from ..core.geometry import *\nfrom linear_slam_ros.cli import run\n",
    "linear_slam_ros/evaluation/__init__.py": "",
    "linear_slam_ros/evaluation/plots.py": "def g():\n    import rclpy\n",
    "linear_slam_ros/cli/__init__.py": "",
    "linear_slam_ros/cli/main.py": "from linear_slam_ros.joiner.joiner import x\n",
    "linear_slam_ros/ros/__init__.py": "",
    "linear_slam_ros/ros/node.py": "import rclpy\nfrom rosbags.typesys import Stores\nfrom std_msgs.msg import Header\n",
    "linear_slam_ros/extra/__init__.py": "",
    "msg_adapters/__init__.py": "from msg_adapters.ros import parts\n",
    "msg_adapters/ros.py": "from std_msgs.msg import Header\nfrom rosbags.typesys import Stores\nfrom rclpy.node import Node\n",
    "msg_adapters/bags.py": "from linear_slam_ros.io import datasets\n",
}

EXPECTED = {
    ("linear_slam_ros.extra", "in no unit of the layer table"),
    ("linear_slam_ros.__main__:2", f"nothing outside {ROS} imports {ROS}"),
    ("linear_slam_ros.core.geometry:4: function-local import of linear_slam_ros.evaluation.plots", "upward import, layer 0"),
    ("linear_slam_ros.joining.pairwise:2: import of linear_slam_ros.pose_graph.graph", "peers of layer 1"),
    ("linear_slam_ros.io.datasets:1: import of std_msgs.msg", "only linear_slam_ros.ros imports bag libraries"),
    ("linear_slam_ros.io.datasets:2: import of mcap.reader", "only linear_slam_ros.ros imports bag libraries"),
    ("linear_slam_ros.joiner.joiner:2: import of linear_slam_ros.cli", f"only {MAIN} imports {CLI}"),
    ("linear_slam_ros.evaluation.plots:2: function-local import of rclpy", "nothing outside linear_slam_ros.ros imports rclpy"),
    ("msg_adapters.ros:3: import of rclpy.node", "nothing outside linear_slam_ros.ros imports rclpy"),
    ("msg_adapters.bags:1: import of linear_slam_ros.io.datasets", "peers of layer 3"),
}


@pytest.fixture
def fake_tree(tmp_path: Path) -> Path:
    for name, text in FAKE_TREE.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    return tmp_path


def test_checker_reports_each_kind_of_violation(fake_tree: Path) -> None:
    modules, found = collect(fake_tree)
    problems = violations(modules, found)
    for where, rule in EXPECTED:
        assert any(p.startswith(where) and rule in p for p in problems), (where, rule, problems)
    assert len(problems) == len(EXPECTED), problems  # and nothing allowed is reported


def test_checker_resolves_relative_star_and_submodule_imports(fake_tree: Path) -> None:
    modules, found = collect(fake_tree)
    targets = {(i.module, i.target, i.local) for i in found}
    assert ("linear_slam_ros.core.errors", "linear_slam_ros.core.geometry", False) in targets  # from . import geometry
    assert ("linear_slam_ros.joiner.joiner", "linear_slam_ros.core.geometry", False) in targets  # from ..core.geometry import *
    assert ("linear_slam_ros.joining.pairwise", "linear_slam_ros.core.geometry", False) in targets  # from pkg import submodule
    assert ("linear_slam_ros.joiner.joiner", "linear_slam_ros.cli", False) in targets  # from pkg import attribute-or-missing
    assert ("linear_slam_ros.pose_graph.lago", "linear_slam_ros.pose_graph.graph", True) in targets  # method body
    assert ("msg_adapters", "msg_adapters.ros", False) in targets


def test_checker_reports_cycles(fake_tree: Path) -> None:
    modules, found = collect(fake_tree)
    assert cycles(found, modules) == [
        ["linear_slam_ros.pose_graph.graph", "linear_slam_ros.pose_graph.lago", "linear_slam_ros.pose_graph.graph"],
    ]


# --- the README's architecture section names every sub-package, and only existing ones ---

README = REPO / "README.md"


def architecture_section(text: str) -> str | None:
    """Return the README section whose heading starts with ``## Architecture``, up to the next # or ## heading.

    Lines inside fenced code blocks (shell comments start with ``#``) are never headings.
    """
    section: list[str] | None = None
    fenced = False
    for line in text.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
        heading = not fenced and re.match(r"#{1,2} ", line) is not None
        if section is not None:
            if heading:
                break
            section.append(line)
        elif heading and line.startswith("## Architecture"):
            section = []
    return None if section is None else "\n".join(section)


def subpackages(root: Path = REPO / "linear_slam_ros") -> list[str]:
    """Return the names of the direct sub-packages of ``root``."""
    return sorted(p.parent.name for p in root.glob("*/__init__.py"))


def listed_directories(section: str) -> list[str]:
    """Return the directory paths written as ``name/`` (or ``a/b/``) in ``section``.

    A path must end at its slash (``core/geometry.py``, ``and/or`` are not directory listings).
    """
    return sorted(set(re.findall(r"(?<![\w./-])((?:[A-Za-z_]\w*/)+)(?!\w)", section)))


def unlisted(section: str, names: Iterable[str]) -> list[str]:
    """Return the ``names`` that never appear as ``name/`` in ``section`` (also inside a path)."""
    return [n for n in names if not re.search(rf"(?<![\w.-]){re.escape(n)}/", section)]


def missing(section: str, package: Path, repo: Path) -> list[str]:
    """Return the directories listed in ``section`` that exist neither in the repository's top level
    nor at any depth of ``package`` (a nested sub-package may be named alone: ``strategies/``)."""

    def exists(d: str) -> bool:
        return (repo / d).is_dir() or any(p.is_dir() for p in package.rglob(d.rstrip("/")))

    return [d for d in listed_directories(section) if not exists(d)]


def test_readme_architecture_lists_the_subpackages() -> None:
    section = architecture_section(README.read_text(encoding="utf-8"))
    assert section is not None, "README.md has no section whose heading starts with '## Architecture'"
    absent = unlisted(section, subpackages())
    assert not absent, f"README's Architecture section does not list sub-package(s) {[f'{n}/' for n in absent]}"
    stale = missing(section, REPO / "linear_slam_ros", REPO)
    assert not stale, f"README's Architecture section lists {stale}: no such directory under linear_slam_ros/ or the repository"


def test_readme_checker_sees_unlisted_and_missing_directories(tmp_path: Path) -> None:
    text = (
        "# T\n\n## Architecture (layers)\n\n- `core/` and joiner/strategies/ (strategies/) and/or `pose_graph/lago.py`,"
        " see https://x.org/a/b/\n```bash\n# a comment, not a heading: cli/\n```\n### Sub\nio/\n## Next\nros/\n"
    )
    section = architecture_section(text)
    assert section is not None and "ros/" not in section
    assert listed_directories(section) == ["cli/", "core/", "io/", "joiner/strategies/", "strategies/"]
    assert unlisted(section, ["core", "io", "pose_graph", "strategies", "ros", "joiner_x"]) == ["ros", "joiner_x"]
    for d in ("pkg/core", "pkg/joiner/strategies", "io"):
        (tmp_path / d).mkdir(parents=True)
    assert missing(section, tmp_path / "pkg", tmp_path) == ["cli/"]
    assert architecture_section("# T\n## Design\ncore/\n") is None
