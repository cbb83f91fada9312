"""Forward loop closures held back (joining/hold.py): which variables are held, and the exact split."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, pose_key
from linear_slam_ros.joining.hold import HeldClosure, split_forward


def _star(info: np.ndarray | sp.csr_matrix) -> LocalMap:
    """A star from pose 5: end pose 6, loop closures to poses 9 and 40 (2D, three variables)."""
    x = np.array([1.0, 0.1, 0.05, 3.0, -0.5, 0.3, 20.0, 4.0, -1.2])
    return LocalMap(2, 5, 6, np.array([6, 9, 40]), np.full(3, POSE, dtype=np.int8), x, info)


def _block_info() -> np.ndarray:
    rng = np.random.default_rng(3)
    blocks = []
    for _ in range(3):
        a = rng.normal(size=(3, 3))
        blocks.append(a @ a.T + 3.0 * np.eye(3))
    out = np.zeros((9, 9))
    for i, b in enumerate(blocks):
        out[3 * i:3 * i + 3, 3 * i:3 * i + 3] = b
    return out


def test_an_uncoupled_pose_the_map_lacks_is_held_and_the_rest_is_cut_exactly():
    info = _block_info()
    submap = _star(info)
    known = {pose_key(9)}  # pose 9 is in the map (a backward closure), pose 40 is not
    rest, held = split_forward(submap, known.__contains__, seq=6, robot="r")
    assert rest is not None and rest.ids.tolist() == [6, 9] and rest.end_id == 6 and rest.frame_id == 5
    np.testing.assert_array_equal(rest.x, submap.x[:6])
    np.testing.assert_array_equal(rest.info, info[:6, :6])
    (closure,) = held
    assert isinstance(closure, HeldClosure)
    assert (closure.seq, closure.robot, closure.name, closure.target, closure.origin) == (6, "r", submap.name, 40, 5)
    assert closure.describe() == f"loop closure 5 -> 40 of submap seq 6 ({submap.name!r})"
    # in pose 40's frame it holds pose 5: the edge alone, moved by the closed-form change of frame
    alone = LocalMap(2, 5, None, np.array([40]), np.array([POSE], dtype=np.int8), submap.x[6:], info[6:, 6:])
    expected = change_frame(alone, 40)
    m = closure.measured  # as measured: in pose 5's frame, pose 40 with its block
    assert (m.frame_id, m.end_id, m.ids.tolist()) == (5, None, [40])
    np.testing.assert_array_equal(m.x, submap.x[6:])
    np.testing.assert_array_equal(m.info, info[6:, 6:])
    c = closure.in_target_frame()
    assert (c.frame_id, c.end_id, c.ids.tolist(), c.kinds.tolist()) == (40, 40, [5], [POSE])
    assert c.name == f"{submap.name}/closure_40"
    np.testing.assert_array_equal(c.x, expected.x)
    np.testing.assert_array_equal(c.info, expected.info)
    c.validate()


def test_the_end_pose_known_poses_coupled_poses_and_features_are_never_held():
    info = _block_info()
    info[3:6, 6:9] = info[6:9, 3:6] = 0.5  # poses 9 and 40 coupled: no exact split
    coupled = _star(info)
    rest, held = split_forward(coupled, lambda key: False, 1)
    assert rest is coupled and held == ()
    feature = LocalMap(2, 5, 6, np.array([6, 9, 40]), np.array([POSE, POSE, FEATURE], dtype=np.int8),
                       _star(_block_info()).x[:8], _block_info()[:8, :8])  # a 2D feature is 2 scalars
    rest, held = split_forward(feature, lambda key: False, 1)  # pose 9 is held, never the feature
    assert [h.target for h in held] == [9] and rest is not None and rest.ids.tolist() == [6, 40]
    np.testing.assert_array_equal(held[0].measured.info, _block_info()[3:6, 3:6])  # its block, after a pose, before a feature
    np.testing.assert_array_equal(rest.info, _block_info()[np.ix_([0, 1, 2, 6, 7], [0, 1, 2, 6, 7])])
    no_end = LocalMap(2, 5, None, np.array([9]), np.array([POSE], dtype=np.int8), np.ones(3), np.eye(3))
    rest, held = split_forward(no_end, lambda key: False, 1)
    assert rest is no_end and held == ()  # no end pose: nothing tells a closure from the chain
    assert split_forward(_star(_block_info()), lambda key: True, 1)[1] == ()


def test_a_sparse_information_stays_sparse_and_a_submap_of_closures_only_leaves_its_end_pose():
    submap = _star(sp.csr_matrix(_block_info()))
    rest, held = split_forward(submap, lambda key: False, 2)
    assert [h.target for h in held] == [9, 40]
    assert rest is not None and sp.issparse(rest.info) and rest.ids.tolist() == [6]
    np.testing.assert_array_equal(rest.info.toarray(), _block_info()[:3, :3])


@pytest.mark.parametrize("dim", [2, 3])
def test_a_held_closure_measures_the_same_relative_pose(dim):
    """Known answer: in the target's frame the origin pose is the inverse of the measured relative pose."""
    from linear_slam_ros.core.geometry import compose_relative, relative_pose

    n = 3 if dim == 2 else 6
    rng = np.random.default_rng(dim)
    x = rng.normal(size=2 * n) * 0.3
    submap = LocalMap(dim, 0, 1, np.array([1, 7]), np.array([POSE, POSE], dtype=np.int8), x, np.eye(2 * n) * 50.0)
    _, (closure,) = split_forward(submap, lambda key: False, 1)
    back = closure.in_target_frame().x
    np.testing.assert_allclose(compose_relative(dim, x[n:], back), np.zeros(n), atol=1e-12)
    np.testing.assert_allclose(back, relative_pose(dim, x[n:], np.zeros(n)), atol=1e-12)
