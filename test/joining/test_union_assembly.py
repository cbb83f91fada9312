"""The sparse union assembly of the pairwise join: canonical CSR, equal to the scatter-sum, keys derived."""

from __future__ import annotations

import weakref

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joining import pairwise
from linear_slam_ros.joining.pairwise import canonical_csr, join_at_seam, scatter_csr, solve_union


def _spd(n: int, rng: np.random.Generator, density: float = 0.2) -> sp.csr_matrix:
    a = sp.random(n, n, density, random_state=np.random.RandomState(int(rng.integers(1 << 30))), format="csr")
    return sp.csr_matrix(a @ a.T + sp.identity(n) * n)


@pytest.mark.parametrize("monotone", [True, False])
def test_scatter_csr_is_the_scatter_and_canonical(monotone, rng):
    k, n = 30, 80
    m = _spd(k, rng)
    index = np.sort(rng.choice(n, k, replace=False)) if monotone else rng.choice(n, k, replace=False)
    out = scatter_csr(canonical_csr(m), index, n)
    expected = np.zeros((n, n))
    expected[index[:, None], index[None, :]] = m.toarray()
    assert out.has_canonical_format
    np.testing.assert_array_equal(out.toarray(), expected)


def test_sparse_solve_union_equals_dense_scatter_sum(rng):
    n_a, k = 150, 60
    info_a, info_b = _spd(n_a, rng, 0.05), _spd(k, rng, 0.1)
    index = np.concatenate([rng.choice(n_a, 10, replace=False), n_a + np.arange(k - 10)])
    rng.shuffle(index)
    n = n_a + k - 10
    z_a, z_b = rng.normal(size=n_a), rng.normal(size=k)
    x, joined = solve_union(info_a, z_a, info_b, z_b, index, n)
    dense = np.zeros((n, n))
    dense[:n_a, :n_a] = info_a.toarray()
    dense[index[:, None], index[None, :]] += info_b.toarray()
    rhs = np.zeros(n)
    rhs[:n_a] = info_a @ z_a
    rhs[index] += info_b @ z_b
    assert sp.issparse(joined) and joined.has_canonical_format
    np.testing.assert_allclose(joined.toarray(), dense, rtol=0, atol=1e-12 * np.abs(dense).max())
    np.testing.assert_allclose(x, np.linalg.solve(dense, rhs), rtol=1e-9, atol=1e-12)


def _lookup_is_consistent(m: LocalMap) -> bool:
    fresh = {int(key): i for i, key in enumerate((m.ids * 2 + m.kinds).tolist())}
    return m.key_set == fresh and np.array_equal(m.keys, m.ids * 2 + m.kinds)


@pytest.mark.parametrize("dim", [2, 3])
def test_derived_key_lookups_equal_fresh_ones(dim, rng):
    world = make_world(dim, n_poses=24, n_features=30, rng=rng)
    maps = noisy_local_maps(world, rng, steps_per_map=4)
    joined = join_at_seam(maps[0], maps[1])
    assert _lookup_is_consistent(joined)
    moved = change_frame(joined, int(joined.pose_ids[0]))
    assert _lookup_is_consistent(moved)


def test_a_seam_join_lets_the_moved_maps_go_before_it_factorises(rng, monkeypatch):
    """Peak memory: the maps moved to the seam are not alive while the union is factorised."""
    world = make_world(2, n_poses=24, n_features=30, rng=rng)
    maps = noisy_local_maps(world, rng, steps_per_map=4)
    a = join_at_seam(maps[0], maps[1])  # in maps[0]'s frame, its end pose elsewhere: it moves
    b = maps[2]
    assert a.frame_id != a.end_id and b.frame_id == a.end_id
    moved: list[weakref.ref] = []
    alive_at_solve: list[int] = []
    real_change, real_solve = pairwise.change_frame, pairwise._solve_spd

    def noting_change(local_map, frame_id):
        out = real_change(local_map, frame_id)
        if out is not local_map:
            moved.append(weakref.ref(out))
        return out

    def noting_solve(info, rhs):
        alive_at_solve.append(sum(ref() is not None for ref in moved))
        return real_solve(info, rhs)

    monkeypatch.setattr(pairwise, "change_frame", noting_change)
    monkeypatch.setattr(pairwise, "_solve_spd", noting_solve)
    joined = join_at_seam(a, b)
    assert len(moved) == 1 and alive_at_solve == [0]
    monkeypatch.undo()
    expected = pairwise.join_in_shared_frame(change_frame(a, a.end_id), b)
    np.testing.assert_array_equal(joined.x, expected.x)
    np.testing.assert_array_equal(joined.ids, expected.ids)
