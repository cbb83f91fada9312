"""Dataset reading and writing: format errors, kind detection, archives, round trips."""

from __future__ import annotations

import re
import tarfile

import numpy as np
import pytest

from linear_slam_ros.core.errors import DatasetError, InvalidMapError
from linear_slam_ros.core.local_map import FEATURE, POSE
from linear_slam_ros.evaluation.synthetic import exact_local_maps, exact_pose_graph_maps, make_world
from linear_slam_ros.io.datasets import (
    MapKind,
    detect_kind,
    parse_local_map_text,
    read_dataset,
    to_local_map,
    write_features,
    write_poses,
)
from support import format_local_map, read_rows, write_dataset

PF_TEXT = """0
5
-1 1.0
-1 0.5
-1 0.1
7 2.0
7 3.0
""" + "\n".join(" ".join("10" if i == j else "0" for j in range(5)) for i in range(5))


def test_parse_and_interpret_pose_feature_map():
    raw = parse_local_map_text(PF_TEXT, "localmap_1")
    assert detect_kind(raw) is MapKind.PF2D
    m = to_local_map(raw, MapKind.PF2D)
    np.testing.assert_array_equal(m.ids, [1, 7])
    np.testing.assert_array_equal(m.kinds, [POSE, FEATURE])
    assert m.frame_id == 0 and m.end_id == 1


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "expected 'Ref' and 'n'"),
        ("0 0", "'Ref' and 'n' must be integers with n >= 1, got 0 and 0"),
        ("0.5 1 1 0 1", "'Ref' and 'n' must be integers"),
        ("0 2 1 0 1 0 1 0", "n = 2 needs 10 numbers \\(2 \\+ 2n \\+ n\\^2\\), found 8"),
        ("0 1 1.5 0 1", "variable ids must be integers"),
    ],
)
def test_parse_errors_name_the_file(text, match):
    with pytest.raises(DatasetError, match="localmap_9: " + match):
        parse_local_map_text(text, "localmap_9")


def test_variable_size_mismatch_is_rejected():
    text = "0 3 -1 1 -1 2 -1 3 " + " ".join("1" if i == j else "0" for i in range(3) for j in range(3))
    raw = parse_local_map_text(text, "localmap_2")
    with pytest.raises(DatasetError, match="localmap_2: variable -1 spans 3 lines, a 3DPF pose needs 6"):
        to_local_map(raw, MapKind.PF3D)


def test_unknown_sizes_cannot_be_detected():
    text = "0 4 3 1 3 1 3 1 3 1 " + " ".join("1" if i == j else "0" for i in range(4) for j in range(4))
    with pytest.raises(DatasetError, match="cannot tell the map kind from variable sizes \\[4\\]"):
        detect_kind(parse_local_map_text(text, "localmap_3"))


def test_repeated_pose_is_fused_exactly(caplog):
    # pose 5 listed twice (two edges), with information 1 and 3: fused estimate is the weighted mean
    vals = [1.0, 2.0, 0.1, 2.0, 2.0, 0.3]
    info = np.diag([1.0, 1, 1, 3, 3, 3])
    text = "0 6 " + " ".join(f"5 {v}" for v in vals) + " " + " ".join(map(str, info.ravel()))
    m = to_local_map(parse_local_map_text(text, "localmap_4"), MapKind.PG2D)
    np.testing.assert_array_equal(m.ids, [5])
    np.testing.assert_allclose(m.x, [1.75, 2.0, 0.25])
    np.testing.assert_allclose(m.info_dense(), np.diag([4.0, 4, 4]))
    # the constant the fused map's objective drops: 1 * 0.75^2 + 3 * 0.25^2 + 1 * 0.15^2 + 3 * 0.05^2
    assert "localmap_4: fused 1 repeated variable(s) into one each" in caplog.text
    assert "the objective drops a constant, here 0.78 " in caplog.text


def test_invalid_map_in_file_is_rejected(tmp_path):
    bad = PF_TEXT.replace("10", "-10", 1)
    (tmp_path / "localmap_1.txt").write_text(bad)
    with pytest.raises(InvalidMapError, match="local map 'localmap_1': information matrix is not positive definite"):
        read_dataset(tmp_path)


@pytest.mark.parametrize("kind", [MapKind.PF2D, MapKind.PF3D, MapKind.PG2D, MapKind.PG3D])
def test_write_then_read_round_trip(kind, tmp_path, rng):
    world = make_world(kind.dim, 10, 12, rng)
    maps = exact_local_maps(world, rng, 2) if kind.has_features else exact_pose_graph_maps(world, rng)
    write_dataset(maps, tmp_path / "ds", kind)
    back = read_dataset(tmp_path / "ds")
    assert back.kind is kind and len(back.maps) == len(maps)
    for a, b in zip(maps, back.maps, strict=True):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.info_dense(), b.info_dense())
        assert (a.frame_id, a.end_id) == (b.frame_id, b.end_id)


def test_archive_is_unpacked_into_cache(tmp_path, rng):
    world = make_world(2, 6, 5, rng)
    write_dataset(exact_local_maps(world, rng, 2), tmp_path / "tiny", MapKind.PF2D)
    archive = tmp_path / "tiny.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(tmp_path / "tiny", arcname="tiny")
    ds = read_dataset(archive, cache_dir=tmp_path / "cache")
    assert ds.name == "tiny" and len(ds.maps) == 3
    assert (tmp_path / "cache" / "tiny" / ".complete").exists()
    assert len(read_dataset(archive, cache_dir=tmp_path / "cache").maps) == 3  # from the cache


def test_missing_numbers_and_paths_are_reported(tmp_path, caplog):
    with pytest.raises(DatasetError, match="neither a folder nor a .tar.xz archive"):
        read_dataset(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no localmap_<i>.txt files"):
        read_dataset(tmp_path / "empty")
    (tmp_path / "gap").mkdir()
    for i in (1, 3):
        (tmp_path / "gap" / f"localmap_{i}.txt").write_text(PF_TEXT)
    gap = read_dataset(tmp_path / "gap")  # a lost submap: read in the order of the numbers, joined as islands
    assert gap.seqs == (1, 3) and len(gap.maps) == 2 and "missing (numbers [2])" in caplog.text
    assert read_dataset(tmp_path / "gap").numbers == (1, 3)
    (tmp_path / "zero").mkdir()
    (tmp_path / "zero" / "localmap_0.txt").write_text(PF_TEXT)
    with pytest.raises(DatasetError, match=r"numbers start at 1 \(found localmap_0.txt\)"):
        read_dataset(tmp_path / "zero")
    bad = tmp_path / "bad.tar.xz"
    bad.write_bytes(b"not an archive")
    with pytest.raises(DatasetError, match="cannot unpack"):
        read_dataset(bad, cache_dir=tmp_path / "c")


def test_poses_and_features_files(tmp_path, rng):
    world = make_world(2, 6, 5, rng)
    m = exact_local_maps(world, rng, 6, sensor_range=30)[0]
    write_poses(tmp_path / "poses.txt", m)
    write_features(tmp_path / "features.txt", m)
    poses = read_rows(tmp_path / "poses.txt")
    assert sorted(poses) == list(range(7))
    np.testing.assert_allclose(poses[3], world.poses[3], atol=1e-12)
    feats = read_rows(tmp_path / "features.txt")
    np.testing.assert_allclose(feats[2], world.features[2], atol=1e-12)
    with pytest.raises(InvalidMapError, match="poses must be written in the frame of pose 2"):
        write_poses(tmp_path / "p.txt", m, origin_id=2)
    assert format_local_map(m, MapKind.PF2D).startswith("0\n")


def _tiny_archive(tmp_path, rng):
    world = make_world(2, 6, 5, rng)
    write_dataset(exact_local_maps(world, rng, 2), tmp_path / "tiny", MapKind.PF2D)
    archive = tmp_path / "tiny.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(tmp_path / "tiny", arcname="tiny")
    return archive


def test_truncated_archive_names_the_file_and_leaves_nothing(tmp_path, rng):
    data = _tiny_archive(tmp_path, rng).read_bytes()
    truncated = tmp_path / "cut.tar.xz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"^cannot unpack .*cut\.tar\.xz: the archive is truncated$"):
        read_dataset(truncated, cache_dir=tmp_path / "cache")
    assert list((tmp_path / "cache").iterdir()) == []  # no half-unpacked folder, no scratch folder


def test_corrupt_archive_names_the_file(tmp_path, rng):
    data = bytearray(_tiny_archive(tmp_path, rng).read_bytes())
    data[200:260] = b"x" * 60
    corrupt = tmp_path / "bad.tar.xz"
    corrupt.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"^cannot unpack .*bad\.tar\.xz: \S"):
        read_dataset(corrupt, cache_dir=tmp_path / "cache")


def test_garbage_line_names_the_file_and_line(tmp_path):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "localmap_1.txt").write_text(PF_TEXT)
    lines = PF_TEXT.splitlines()
    lines[4] = "-1 0.5O"  # a letter O for a zero
    (tmp_path / "ds" / "localmap_2.txt").write_text("\n".join(lines))
    with pytest.raises(DatasetError, match=r"ds/localmap_2\.txt:5: '0\.5O' is not a number$"):
        read_dataset(tmp_path / "ds")
    with pytest.raises(DatasetError, match=r"^localmap_7:2: 'n' is not a number$"):
        parse_local_map_text("0\nn\n", "localmap_7")
    with pytest.raises(DatasetError, match=r"^x/localmap_7\.txt:1: 'a' is not a number$"):
        parse_local_map_text("0\ta", "localmap_7", source="x/localmap_7.txt")  # the tab-separated path


def test_format_errors_name_the_file_path(tmp_path):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "localmap_1.txt").write_text("0 2 1 0 1 0 1 0")
    with pytest.raises(DatasetError, match=r"ds/localmap_1\.txt: n = 2 needs 10 numbers"):
        read_dataset(tmp_path / "ds")


def test_an_unpack_never_replaces_a_complete_folder_another_process_is_reading(tmp_path):
    """Two processes unpacking one archive (two test workers, two CLI runs): the later one keeps the first's
    folder, which the first may be reading; only a folder without the completion marker is replaced."""
    from linear_slam_ros.io.datasets import _move_into_place

    target, marker = tmp_path / "d", tmp_path / "d" / ".complete"
    target.mkdir()
    (target / "localmap_1.txt").write_text("theirs")
    marker.write_text("the archive")
    ours = tmp_path / "scratch" / "d"
    ours.mkdir(parents=True)
    (ours / "localmap_1.txt").write_text("ours")
    _move_into_place(ours, target, marker, "the archive")
    assert (target / "localmap_1.txt").read_text() == "theirs" and ours.exists()  # dropped with the scratch folder
    marker.unlink()  # an unfinished unpack of an earlier version: replaced
    (ours / ".complete").write_text("the archive")
    _move_into_place(ours, target, marker, "the archive")
    assert (target / "localmap_1.txt").read_text() == "ours" and marker.exists() and not ours.exists()


def test_another_archive_of_the_same_name_is_unpacked_again(tmp_path, rng):
    """The cache was keyed on the archive's name alone: a second mymaps.tar.xz of 10 maps was joined as the first
    one's 5 cached maps, with exit code 0 and no warning."""
    world = make_world(2, 12, 5, rng)
    maps = exact_local_maps(world, rng, 1)
    cache = tmp_path / "cache"
    for n, folder in ((5, "one"), (10, "two")):
        write_dataset(maps[:n], tmp_path / folder / "mymaps", MapKind.PF2D)
        with tarfile.open(tmp_path / folder / "mymaps.tar.xz", "w:xz") as tar:
            tar.add(tmp_path / folder / "mymaps", arcname="mymaps")
    assert len(read_dataset(tmp_path / "one" / "mymaps.tar.xz", cache_dir=cache).maps) == 5
    assert len(read_dataset(tmp_path / "two" / "mymaps.tar.xz", cache_dir=cache).maps) == 10
    assert len(read_dataset(tmp_path / "one" / "mymaps.tar.xz", cache_dir=cache).maps) == 5  # and back


def _identity_text(ref: int, ids: list[int]) -> str:
    n = len(ids)
    return f"{ref} {n} " + " ".join(f"{i} 0.{k % 10}" for k, i in enumerate(ids)) + " " + " ".join(
        "1" if r == c else "0" for r in range(n) for c in range(n)
    )


@pytest.mark.parametrize(
    ("ids", "kind"),
    [
        ([1] * 3 + [2] * 3 + [2] * 3, MapKind.PG2D),  # pose 2 listed twice: sizes 3 and 6
        ([1] * 6 + [2] * 6, MapKind.PG3D),  # 6 lines each: 3D (or 2D poses each listed twice)
        ([-1] * 6 + [4] * 2, MapKind.PF2D),  # a 2D pose listed twice, a 2D feature
        ([-1] * 6 + [4] * 3, MapKind.PF3D),
    ],
)
def test_kind_is_detected_with_repeated_variables(ids, kind):
    assert detect_kind(parse_local_map_text(_identity_text(0, ids), "localmap_1")) is kind


def test_a_later_map_that_does_not_fit_the_detected_kind_says_where_the_kind_came_from(tmp_path):
    (tmp_path / "localmap_1.txt").write_text(_identity_text(0, [1] * 6))  # reads as 3D
    (tmp_path / "localmap_2.txt").write_text(_identity_text(1, [2] * 3))
    with pytest.raises(DatasetError, match=r"localmap_2.txt: variable 2 spans 3 lines, a 3DPG pose needs 6 "
                                           r"\(kind 3DPG detected from localmap_1: give the kind if it is another\)"):
        read_dataset(tmp_path)
    assert read_dataset(tmp_path, kind="2DPG").kind is MapKind.PG2D  # pose 1 listed twice in map 1
    with pytest.raises(DatasetError, match=r"pose variables span \[4\] lines and features \[2\]; expected multiples"):
        detect_kind(parse_local_map_text(_identity_text(0, [-1] * 4 + [3] * 2), "localmap_1"))


def test_an_information_matrix_written_as_one_triangle_is_refused_naming_the_file_and_entry(tmp_path):
    """It was averaged with its transpose: every off-diagonal entry silently halved (a 5 cm different end pose over
    10 VicPark maps), where the pose-graph path refuses an asymmetric matrix."""
    text = _identity_text(0, [1] * 3).split()
    n = 3
    info = np.eye(n) * 10.0
    info[0, 1] = 2.0  # the upper triangle only
    lines = [text[0], text[1], *[f"{text[2 + 2 * k]} {text[3 + 2 * k]}" for k in range(n)],
             *[" ".join(f"{v:g}" for v in row) for row in info]]
    (tmp_path / "localmap_1.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"localmap_1.txt: the information matrix is not symmetric: entry \(0, 1\) is 2 "
                                           r"and \(1, 0\) 0 .*write the whole matrix, not one triangle"):
        read_dataset(tmp_path, kind=MapKind.PG2D)
    info[1, 0] = 2.0 * (1 + 1e-9)  # the benchmark files' printed digits: averaged
    lines[-n:] = [" ".join(f"{v:.12g}" for v in row) for row in info]
    (tmp_path / "localmap_1.txt").write_text("\n".join(lines) + "\n")
    assert read_dataset(tmp_path, kind=MapKind.PG2D).maps[0].info_dense()[0, 1] == pytest.approx(2.0, rel=1e-8)


def test_an_invalid_map_names_its_file(tmp_path):
    text = _identity_text(0, [1] * 3).split()
    lines = [text[0], text[1], *[f"{text[2 + 2 * k]} {text[3 + 2 * k]}" for k in range(3)], "1 0 0", "0 -1 0", "0 0 1"]
    (tmp_path / "localmap_1.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InvalidMapError, match=rf"^{re.escape(str(tmp_path / 'localmap_1.txt'))}: .*not positive definite"):
        read_dataset(tmp_path, kind=MapKind.PG2D)


def test_two_files_of_one_number_are_refused(tmp_path):
    """localmap_1.txt and localmap_01.txt were both read: map 1 joined twice, and "0 local maps missing"."""
    text = _identity_text(0, [1] * 3)
    for name in ("localmap_1.txt", "localmap_01.txt", "localmap_2.txt"):
        (tmp_path / name).write_text(text)
    with pytest.raises(DatasetError, match=r": localmap_01.txt and localmap_1.txt both have number 1$"):
        read_dataset(tmp_path, kind=MapKind.PG2D)
