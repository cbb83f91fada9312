"""Joining: known answers (noise-free worlds), Lemma 1, frames, online divide and conquer."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.nonlinear import gauss_newton, refine
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.synthetic import exact_local_maps, exact_map, exact_pose_graph_maps, make_world, noisy_local_maps
from linear_slam_ros.joining.divide_conquer import OnlineDCState, join_divide_and_conquer, online_dc_result, online_dc_step
from linear_slam_ros.joining.pairwise import align_frames, join_in_shared_frame, join_pair
from support import join_online_dc, join_sequential, join_sequential_information

JOINERS = {
    "sequential": join_sequential,
    "sequential-information": join_sequential_information,
    "dc": join_divide_and_conquer,
    "online-dc": join_online_dc,
}


def _max_error(joined: LocalMap, truth) -> float:
    """Largest difference from the truth, angles compared modulo 2 pi."""
    worst = 0.0
    for i in range(joined.n_vars):
        diff = joined.x[joined.scalar_slice(i)] - truth[(int(joined.kinds[i]), int(joined.ids[i]))]
        if joined.kinds[i] == 0:
            diff[joined.dim :] = wrap_angle(diff[joined.dim :])
        worst = max(worst, float(np.abs(diff).max()))
    return worst


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("method", sorted(JOINERS))
@pytest.mark.parametrize("first_frame", [None, 2])
def test_noise_free_pose_feature_maps_give_the_truth(dim, method, first_frame, rng):
    world = make_world(dim, 30, 25, rng, loops=1.3)
    maps = exact_local_maps(world, rng, poses_per_map=3, first_frame=first_frame)
    joined = JOINERS[method](maps)
    assert joined.frame_id == 30  # robocentric: the last end pose
    in_first = change_frame(joined, 0)
    assert _max_error(in_first, world.truth()) < 1e-9
    assert chi2(joined, maps) < 1e-12
    refined = change_frame(refine(joined, maps).map, 0)
    assert _max_error(refined, world.truth()) < 1e-9


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("method", sorted(JOINERS))
def test_noise_free_pose_graphs_give_the_truth(dim, method, rng):
    world = make_world(dim, 40, 0, rng, loops=1.5)  # orientations wrap past pi
    maps = exact_pose_graph_maps(world, rng)
    joined = change_frame(JOINERS[method](maps), 0)
    assert _max_error(joined, world.truth()) < 1e-9
    assert chi2(joined, maps) < 1e-12


def _lemma_maps(dim, rng, pose_only):
    world = make_world(dim, 12, 20, rng)
    if pose_only:
        # both in the frame of pose 2, sharing poses 3 and 6; map 2 ends at pose 5
        a = exact_map(world, 2, [0, 1, 3, 6], [], rng, 3, "a")
        b = exact_map(world, 2, [3, 6, 4, 5], [], rng, 5, "b")
        return (
            a.replace(x=a.x + rng.normal(scale=0.05, size=a.state_dim)),
            b.replace(x=b.x + rng.normal(scale=0.05, size=b.state_dim)),
        )
    noisy = noisy_local_maps(world, rng, steps_per_map=3, sigma_observation=0.2)
    first = change_frame(noisy[0], noisy[0].end_id)  # Map 1 in the frame of its end pose P1
    return first, noisy[1]  # Map 2 in the frame of P1


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("pose_only", [False, True])
def test_lemma_1_linear_join_equals_gauss_newton(dim, pose_only, rng):
    map_1, map_2 = _lemma_maps(dim, rng, pose_only)
    linear = join_pair(map_1, map_2)
    assert linear.frame_id == map_2.end_id
    # Gauss-Newton on eq. (7) in the end-pose frame, from a perturbed start
    start = linear.replace(x=linear.x + rng.normal(scale=0.01, size=linear.state_dim))
    nonlinear = gauss_newton(start, [map_1, map_2], max_iterations=100, step_tol=1e-14).map
    np.testing.assert_allclose(nonlinear.x, linear.x, atol=1e-8)
    scale = np.abs(linear.info_dense()).max()
    np.testing.assert_allclose(nonlinear.info_dense() / scale, linear.info_dense() / scale, atol=1e-8)


def test_pose_only_common_angles_are_wrapped(rng):
    world = make_world(2, 10, 0, rng)
    maps = exact_pose_graph_maps(world, rng, loop_every=1, loop_span=2)
    a, b = align_frames(maps[3], maps[4])
    common = [k for k in b.keys.tolist() if k in a.key_set]
    assert common
    # shift b's angle of a common pose by 2 pi: the joined estimate must not change
    i = b.key_set[common[0]]
    shifted = b.x.copy()
    shifted[b.scalar_slice(i).stop - 1] += 2 * np.pi
    plain = join_in_shared_frame(a, b)
    wrapped = join_in_shared_frame(a, b.replace(x=shifted))
    np.testing.assert_allclose(wrapped.x, plain.x, atol=1e-12)


def test_frame_error_names_both_ids(rng):
    world = make_world(2, 12, 10, rng)
    maps = exact_local_maps(world, rng, 2)
    with pytest.raises(
        FrameError,
        match="map 'exact_4' \\(frame pose 6\\) does not hold pose 2, the end pose of map 'exact_1' \\(frame pose 0\\)",
    ):
        join_pair(maps[0], maps[3])
    with pytest.raises(FrameError, match="frame of pose 6, which is not in map .* \\(frame pose 0\\).*pose 0 is not in"):
        align_frames(maps[0], maps[3])
    with pytest.raises(
        FrameError, match="submap 'exact_4' is in the frame of pose 6 and does not hold pose 2, the end pose of the global map"
    ):
        online_dc_step(online_dc_step(OnlineDCState(), maps[0]), maps[3])


def test_dimension_and_frame_mismatch_in_shared_frame(rng):
    m2 = exact_local_maps(make_world(2, 6, 5, rng), rng, 2)
    m3 = exact_local_maps(make_world(3, 6, 5, rng), rng, 2)
    with pytest.raises(InvalidMapError, match="cannot join a 2D map 'exact_1' with a 3D map 'exact_1'"):
        join_in_shared_frame(m2[0], m3[0])
    with pytest.raises(InvalidMapError, match="are in frames 0 and 2; align them first"):
        join_in_shared_frame(m2[0], m2[1])
    with pytest.raises(InvalidMapError, match="no local maps to join"):
        join_divide_and_conquer([])
    with pytest.raises(InvalidMapError, match="no submaps joined yet"):
        online_dc_result(OnlineDCState())


def test_online_dc_stack_is_a_binary_counter_and_matches_batch(rng):
    world = make_world(2, 32, 30, rng)
    maps = noisy_local_maps(world, rng, steps_per_map=2)
    state = OnlineDCState()
    for i, m in enumerate(maps, start=1):
        state = online_dc_step(state, m)
        assert state.counts == tuple(1 << b for b in reversed(range(i.bit_length())) if i >> b & 1)
    assert state.n_joined == 16
    online = online_dc_result(state)
    batch = join_divide_and_conquer(maps)  # 16 maps: the same tree
    np.testing.assert_allclose(online.x, batch.x, atol=1e-12)


def test_online_dc_step_is_pure(rng):
    world = make_world(2, 12, 10, rng)
    maps = exact_local_maps(world, rng, 2)
    s1 = online_dc_step(OnlineDCState(), maps[0])
    s2 = online_dc_step(s1, maps[1])
    assert s1.counts == (1,) and s2.counts == (2,)
    x_before = s1.stack[0].x.copy()
    online_dc_step(s1, maps[1])
    np.testing.assert_array_equal(s1.stack[0].x, x_before)


def test_online_dc_refuses_a_submap_of_another_dimension_at_once(rng):
    maps_2d = noisy_local_maps(make_world(2, 12, 10, rng), rng, steps_per_map=3)
    maps_3d = noisy_local_maps(make_world(3, 12, 10, rng), rng, steps_per_map=3)
    state = online_dc_step(OnlineDCState(), maps_2d[0])
    with pytest.raises(InvalidMapError, match="is 3D, the global map is 2D"):
        online_dc_step(state, maps_3d[1])  # pushed alone it would wait unjoined on the stack


def _other_triples(local_map: LocalMap, every: int) -> tuple[np.ndarray, np.ndarray]:
    """The state and information of a 3D map with every ``every``-th pose given by the other Euler triple of its
    rotation, ``(alpha + pi, pi - beta, gamma + pi)``, the information carried exactly (``beta`` negated)."""
    x, info = local_map.x.copy(), local_map.info_dense().copy()
    for k, row in enumerate(local_map.angle_index):
        if k % every == 0:
            a, b, g = x[row]
            x[row] = [a + np.pi, np.pi - b, g - np.pi]  # not wrapped either
            info[row[1], :] *= -1.0
            info[:, row[1]] *= -1.0
    return x, info


@pytest.mark.parametrize("method", sorted(JOINERS))
def test_3d_poses_given_by_the_other_euler_triple_join_to_the_truth(method, rng):
    """Remark 3 wraps angle differences by 2 pi one angle at a time: two maps giving one rotation by its two triples
    were averaged into a wrong one (a review of session 26: 19 m off). Maps are made canonical on construction."""
    from linear_slam_ros.core.geometry import rot3

    world = make_world(3, 30, 0, rng, loops=1.2)
    maps = exact_pose_graph_maps(world, rng, loop_every=5, loop_span=2)
    other = []
    for k, m in enumerate(maps):
        x, info = _other_triples(m, every=1 + k % 2)
        alt = LocalMap(3, m.frame_id, m.end_id, m.ids, m.kinds, x, info, name=m.name)
        np.testing.assert_allclose(alt.x, m.x, atol=1e-12)  # canonical again, information with it
        np.testing.assert_allclose(alt.info_dense(), m.info_dense(), rtol=1e-12, atol=1e-9)
        assert np.abs(rot3(x[m.angle_index]) - rot3(alt.x[alt.angle_index])).max() < 1e-12  # the same rotations
        other.append(alt)
    joined = change_frame(JOINERS[method](other), 0)
    assert _max_error(joined, world.truth()) < 1e-9
    assert chi2(joined, other) < 1e-12
