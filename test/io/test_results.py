"""Result files: TUM trajectories checked by the format's definition (evo's reader), formats."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from linear_slam_ros.core.errors import ConfigError, InvalidMapError
from linear_slam_ros.core.geometry import rot3, wrap_angle
from linear_slam_ros.evaluation.synthetic import exact_local_maps, exact_pose_graph_maps, make_world
from linear_slam_ros.io.results import TUM_HEADER, write_result, write_tum_poses, write_tum_stamped
from support import read_rows


def read_tum(path):
    """Parse a TUM file as evo does: '#' lines are comments, 8 space-separated floats per line."""
    rows = []
    for line in path.read_text().splitlines():
        if line.startswith("#"):
            continue
        fields = line.split(" ")
        assert len(fields) == 8, line
        rows.append([float(f) for f in fields])
    return np.array(rows)


@pytest.mark.parametrize("dim", [2, 3])
def test_tum_trajectory_by_its_definition(dim, tmp_path, rng):
    world = make_world(dim, 12, 10, rng, loops=1.5)
    joined = exact_local_maps(world, rng, 12, sensor_range=60)[0]  # every pose, in the frame of pose 0
    in_origin = write_result(tmp_path, joined, 0, formats=("reference", "tum"))
    assert (tmp_path / "poses.tum").read_text().splitlines()[0] == TUM_HEADER
    tum = read_tum(tmp_path / "poses.tum")
    reference = read_rows(tmp_path / "poses.txt")
    assert tum[:, 0].tolist() == [float(k) for k in sorted(reference)]  # stamp = pose id, increasing
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, rtol=0, atol=1e-15)
    assert np.all(tum[:, 7] >= 0)
    for row in tum:
        pose = reference[int(row[0])]
        np.testing.assert_array_equal(row[1 : 1 + dim], pose[:dim])
        if dim == 2:
            assert row[3] == 0.0 and row[4] == 0.0 and row[5] == 0.0
            yaw = 2.0 * np.arctan2(row[6], row[7])
            assert abs(wrap_angle(yaw - pose[2])) < 1e-15
        else:  # the quaternion is the pose's orientation (frame to origin): R^T of the datasets' convention
            np.testing.assert_allclose(Rotation.from_quat(row[4:]).as_matrix(), rot3(pose[3:]).T, atol=1e-15)
            np.testing.assert_allclose(Rotation.from_quat(row[4:]).as_euler("ZYX"), pose[3:], atol=1e-14)
    assert tum[0, 1:].tolist() == [0.0] * 6 + [1.0]  # the origin pose
    assert in_origin.frame_id == 0


def test_tum_of_a_pose_only_map_and_wrong_frame(tmp_path, rng):
    world = make_world(2, 6, 0, rng)
    m = exact_pose_graph_maps(world, rng)[2]
    write_tum_poses(tmp_path / "t.tum", m, m.frame_id)
    assert read_tum(tmp_path / "t.tum")[:, 0].tolist() == sorted([float(m.frame_id), *map(float, m.ids)])
    with pytest.raises(InvalidMapError, match=f"poses must be written in the frame of pose 0, map .* is in {m.frame_id}"):
        write_tum_poses(tmp_path / "t.tum", m, 0)


def test_unknown_format_is_rejected(tmp_path, rng):
    world = make_world(2, 6, 0, rng)
    m = exact_pose_graph_maps(world, rng)[0]
    with pytest.raises(ConfigError, match=r"unknown pose file format\(s\) \['kitti'\]"):
        write_result(tmp_path, m, m.frame_id, formats=("kitti",))


def test_tum_with_stamps_writes_the_stamped_poses_in_time_order(tmp_path, rng):
    world = make_world(2, 12, 10, rng)
    joined = exact_local_maps(world, rng, 12, sensor_range=60)[0]  # poses 1..12 in the frame of pose 0
    stamps = {5: 1_700_000_002.5, 3: 1_700_000_001.25, 12: 1_700_000_003.0, 99: 7.0}  # 99: not in the map
    assert write_tum_stamped(tmp_path / "s.tum", joined, 0, stamps) == 3
    tum = read_tum(tmp_path / "s.tum")
    assert tum[:, 0].tolist() == [1_700_000_001.25, 1_700_000_002.5, 1_700_000_003.0]  # by stamp, not by id
    for row, pid in zip(tum, (3, 5, 12), strict=True):
        np.testing.assert_array_equal(row[1:3], joined.pose(pid)[:2])
        assert abs(wrap_angle(2.0 * np.arctan2(row[6], row[7]) - joined.pose(pid)[2])) < 1e-15
    with pytest.raises(InvalidMapError, match="poses must be written in the frame of pose 4"):
        write_tum_stamped(tmp_path / "s.tum", joined, 4, stamps)
