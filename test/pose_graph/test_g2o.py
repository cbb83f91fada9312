"""g2o files: SE2 and SE3 lines, exact round trips, g2o's information convention, unknown lines, malformed files."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import relative_pose, rot2, rot3, wrap_angle
from linear_slam_ros.evaluation.objective import MapObjective
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.pose_graph.chunks import edge_maps, star_local_maps
from linear_slam_ros.pose_graph.g2o import g2o_to_graph, graph_to_g2o, read_g2o, read_g2o_file, write_g2o, write_g2o_file
from linear_slam_ros.pose_graph.graph import PoseGraph


def test_g2o_round_trip_and_errors(tmp_path, rng, circle_graph):
    _, graph = circle_graph(rng, sigma=(0.01, 0.002))
    write_g2o(tmp_path / "g.g2o", graph)
    back = read_g2o(tmp_path / "g.g2o")
    np.testing.assert_array_equal(back.measurements, graph.measurements)
    np.testing.assert_array_equal(back.information, graph.information)
    (tmp_path / "bad.g2o").write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 2 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(GraphError, match=r"edge 0 \(0 -> 2\) names unknown pose 2"):
        read_g2o(tmp_path / "bad.g2o")
    (tmp_path / "short.g2o").write_text("EDGE_SE2 0 1 1 0 0 1 0 0\n")
    with pytest.raises(GraphError, match="short.g2o:1: EDGE_SE2 needs 11 values, got 8"):
        read_g2o(tmp_path / "short.g2o")


def test_vertices_without_edges_and_estimates_are_written(tmp_path):
    graph = PoseGraph.from_edges([0], [1], [[1.0, 0, 0.5]], [np.eye(3)], pose_ids=[0, 1, 5])
    write_g2o(tmp_path / "g.g2o", graph, {1: np.array([1.0, 0, 0.5])})
    lines = (tmp_path / "g.g2o").read_text().splitlines()
    assert lines[:3] == ["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0.5", "VERTEX_SE2 5 0 0 0"]
    back = read_g2o(tmp_path / "g.g2o")
    np.testing.assert_array_equal(back.pose_ids, [0, 1, 5])
    assert back.dim == 2 and back.n_edges == 1




def _random_graph(rng, dim, n=8, isotropic=False):
    """Odometry and a few loop closures (some from a later pose to an earlier one), anisotropic coupled information."""
    p = 3 if dim == 2 else 6
    pairs = [(k, k + 1) for k in range(n)] + [(5, 1), (2, 7), (8, 3)]
    z = rng.normal(size=(len(pairs), p))
    z[:, dim:] = rng.uniform(-1.2, 1.2, size=(len(pairs), p - dim))
    if isotropic:
        info = np.stack([np.diag([4.0] * dim + list(rng.uniform(10, 20, p - dim))) for _ in pairs])
    else:
        a = rng.normal(size=(len(pairs), p, p))
        info = np.einsum("mij,mkj->mik", a, a) + p * np.eye(p)
    return PoseGraph.from_edges([a for a, _ in pairs], [b for _, b in pairs], z, info, name="random")


@pytest.mark.parametrize("dim", [2, 3])
def test_export_then_import_is_exact(dim, tmp_path, rng):
    """A g2o file's numbers round-trip bit for bit; the graph round-trips to rounding (bit for bit when it can)."""
    graph = _random_graph(rng, dim)
    poses = {k: np.r_[rng.normal(size=dim), rng.uniform(-1, 1, size=dim * (dim - 1) // 2)] for k in graph.pose_ids.tolist()}
    g2o = graph_to_g2o(graph, poses)
    write_g2o_file(tmp_path / "a.g2o", g2o)
    back = read_g2o_file(tmp_path / "a.g2o")
    assert back.dim == dim and back.skipped == {}
    for name in ("vertex_ids", "vertex_estimates", "from_ids", "to_ids", "measurements", "information"):
        assert getattr(back, name).tobytes() == getattr(g2o, name).tobytes(), name
    write_g2o_file(tmp_path / "b.g2o", back)
    assert (tmp_path / "b.g2o").read_text() == (tmp_path / "a.g2o").read_text()
    tag = "VERTEX_SE2" if dim == 2 else "VERTEX_SE3:QUAT"
    assert (tmp_path / "a.g2o").read_text().splitlines()[0].split()[0] == tag
    # the graph and the vertex estimates, through g2o's parameters and information
    graph_back = read_g2o(tmp_path / "a.g2o")
    np.testing.assert_array_equal(graph_back.from_ids, graph.from_ids)
    np.testing.assert_array_equal(graph_back.pose_ids, graph.pose_ids)
    np.testing.assert_allclose(graph_back.measurements, graph.measurements, rtol=0, atol=1e-14)
    np.testing.assert_allclose(graph_back.information, graph.information, rtol=1e-12, atol=1e-12)
    for k, x in back.poses().items():
        np.testing.assert_allclose(x, poses[k], rtol=0, atol=1e-14)
    iso = _random_graph(rng, dim, isotropic=True)
    write_g2o(tmp_path / "iso.g2o", iso)
    iso_back = read_g2o(tmp_path / "iso.g2o")
    if dim == 2:  # no conversion at all
        assert iso_back.information.tobytes() == iso.information.tobytes()
    np.testing.assert_array_equal(iso_back.information[:, :dim, :dim], iso.information[:, :dim, :dim])


def _active(dim, pose):
    """g2o's isometry of a pose in the datasets' convention (frame to parent)."""
    d = np.eye(dim + 1)
    d[:dim, :dim] = (rot2(np.array(pose[2])) if dim == 2 else rot3(pose[3:])).T
    d[:dim, dim] = pose[:dim]
    return d


def _g2o_error(dim, z, x):
    """g2o's error of an edge with measurement z at relative pose x (EdgeSE2/EdgeSE3::computeError)."""
    delta = np.linalg.inv(_active(dim, z)) @ _active(dim, x)
    if dim == 2:
        return np.r_[delta[:2, 2], np.arctan2(delta[1, 0], delta[0, 0])]
    q = Rotation.from_matrix(delta[:3, :3]).as_quat()
    return np.r_[delta[:3, 3], np.sign(q[3]) * q[:3]]


@pytest.mark.parametrize("dim", [2, 3])
def test_information_follows_g2os_error_definition(dim, tmp_path, rng):
    """The graph's information is g2o's pulled back through g2o's own error function (numerical Jacobian)."""
    p = 3 if dim == 2 else 6
    z = np.r_[rng.normal(size=dim), rng.uniform(-1, 1, size=p - dim)]
    a = rng.normal(size=(p, p))
    info_g2o = a @ a.T + np.eye(p)
    tag = "EDGE_SE2" if dim == 2 else "EDGE_SE3:QUAT"
    params = z if dim == 2 else np.r_[z[:3], Rotation.from_matrix(_active(3, z)[:3, :3]).as_quat()]
    upper = info_g2o[np.triu_indices(p)]
    (tmp_path / "e.g2o").write_text(f"{tag} 0 1 " + " ".join(repr(float(v)) for v in np.r_[params, upper]) + "\n")
    graph = read_g2o(tmp_path / "e.g2o")
    np.testing.assert_allclose(graph.measurements[0], z, atol=1e-12)
    h = 1e-6
    jac = np.stack([(_g2o_error(dim, z, z + h * e) - _g2o_error(dim, z, z - h * e)) / (2 * h) for e in np.eye(p)], 1)
    np.testing.assert_allclose(graph.information[0], jac.T @ info_g2o @ jac, rtol=1e-7, atol=1e-7)


def test_unknown_line_types_are_listed_in_one_warning(tmp_path, caplog):
    text = (
        "# a comment\nVERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_XY 7 1 2\nVERTEX_XY 8 1 3\nFIX 0\n"
        "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2_XY 0 7 1 2 1 0 1\nEDGE_SE2_XY 1 7 0 2 1 0 1\nEDGE_SE2_XY 1 8 0 3 1 0 1\n"
    )
    (tmp_path / "lm.g2o").write_text(text)
    with caplog.at_level(logging.WARNING):
        g2o = read_g2o_file(tmp_path / "lm.g2o")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    listed = "lines not read (only SE2 and SE3:QUAT poses and edges are): EDGE_SE2_XY (3), FIX (1), VERTEX_XY (2)"
    assert warnings[0].endswith(listed)
    assert "lm.g2o" in warnings[0]
    assert g2o.skipped == {"VERTEX_XY": 2, "FIX": 1, "EDGE_SE2_XY": 3}
    assert g2o_to_graph(g2o).n_edges == 1


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1" + " 1" * 21 + "\n",
            r"mixes SE2 \(from line 1\) and SE3 \(from line 2\)",
        ),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n", "m.g2o:2: vertex 0 is already listed on line 1"),
        ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 1 0 0\n", "m.g2o:1: EDGE_SE3:QUAT needs 30 values, got 12"),
        ("EDGE_SE2 0 1 1 0 zero 1 0 0 1 0 1\n", "m.g2o:1: could not convert string to float: 'zero'"),
        ("VERTEX_XY 1 0 0\n", "m.g2o has no edges"),
        ("EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 0" + " 1" * 21 + "\n",  # a zero quaternion (review of session 26: a traceback)
         r"m.g2o:1: quaternion \(qx qy qz qw\) = \(0.0, 0.0, 0.0, 0.0\) has norm 0: not a rotation"),
        ("VERTEX_SE3:QUAT 0 0 0 0 nan 0 0 1\n", r"m.g2o:1: quaternion \(qx qy qz qw\) = \(nan, 0.0, 0.0, 1.0\) has norm nan"),
        ("EDGE_SE2 0 4611686018427387904 1 0 0 1 0 0 1 0 1\n",
         r"m.g2o:1: pose id 4611686018427387904 is out of range \(0 <= id < 2\*\*53\)"),
        ("VERTEX_SE2 99999999999999999999 0 0 0\n", r"m.g2o:1: pose id 99999999999999999999 is out of range"),
        ("EDGE_SE2 -1 0 1 0 0 1 0 0 1 0 1\n", r"m.g2o:1: pose id -1 is out of range"),
        (  # pitched by 90 deg about y (active): its information is fine, its Euler angles are not
            "EDGE_SE3:QUAT 0 1 1 0 0 0 0.7071067811865476 0 0.7071067811865476" + " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n",
            r"m.g2o: measurement of edge 0 \(0->1\) has pitch at \+-90 deg .*Euler angles are singular there \(gimbal lock\)",
        ),
    ],
)
def test_malformed_files_name_the_file_and_line(text, match, tmp_path):
    (tmp_path / "m.g2o").write_text(text)
    with pytest.raises(GraphError, match=match):
        read_g2o(tmp_path / "m.g2o")


def test_missing_file_is_named(tmp_path):
    with pytest.raises(GraphError, match=r"cannot read .*nope\.g2o: \[Errno 2\]"):
        read_g2o(tmp_path / "nope.g2o")


def test_se3_file_is_joined_as_pose_only_local_maps(tmp_path, rng):
    """A 3D g2o graph (loop closures both ways) joins as star local maps; noise-free, the joined poses are the truth."""
    world = make_world(3, 30, 0, rng, loops=1.5)
    pairs = [(k, k + 1) for k in range(30)] + [(k + 20, k) for k in range(0, 10, 3)] + [(2, 25)]
    z = np.array([relative_pose(3, world.poses[a], world.poses[b]) for a, b in pairs])
    info = np.stack([np.diag([100.0, 100, 100, 400, 400, 400]) + 10 * np.eye(6)] * len(pairs))
    graph = PoseGraph.from_edges([a for a, _ in pairs], [b for _, b in pairs], z, info)
    write_g2o(tmp_path / "helix.g2o", graph)
    back = read_g2o(tmp_path / "helix.g2o")
    maps = star_local_maps(back)
    assert [m.frame_id for m in maps] == list(range(30)) and all(m.dim == 3 for m in maps)
    assert maps[20].name == f"{tmp_path / 'helix.g2o'}: edges from pose 20" and maps[20].ids.tolist() == [21, 0]
    joined = change_frame(run_join(maps, JoinMethod.DC).result, 0)
    for i, k in enumerate(joined.ids.tolist()):
        error = joined.x[joined.scalar_slice(i)] - relative_pose(3, world.poses[0], world.poses[k])
        np.testing.assert_allclose(np.r_[error[:3], wrap_angle(error[3:])], 0.0, atol=1e-9)
    # the χ² of the star maps is the graph objective's
    edges = edge_maps(back)
    assert MapObjective.build(joined, edges).chi2(joined.x) == pytest.approx(0.0, abs=1e-12)


def test_a_byte_order_mark_is_not_part_of_the_first_line(tmp_path):
    """An editor's UTF-8 BOM made line 1 an unknown type ('\\ufeffEDGE_SE2'): skipped with a warning, pose 0 lost."""
    text = "EDGE_SE2 0 1 1 0 0 100 0 0 100 0 1000\nEDGE_SE2 1 2 1 0 0 100 0 0 100 0 1000\n"
    (tmp_path / "bom.g2o").write_bytes(b"\xef\xbb\xbf" + text.encode())
    g2o = read_g2o_file(tmp_path / "bom.g2o")
    assert g2o.skipped == {} and g2o.from_ids.tolist() == [0, 1]
