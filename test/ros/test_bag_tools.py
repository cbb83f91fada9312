"""The bag tools' guards: an --out that is not a bag is never deleted; numeric options that cannot work are refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from linear_slam_ros.core.errors import DatasetError
from linear_slam_ros.ros import bag_from_dataset
from linear_slam_ros.ros.bagio import read_messages, write_messages


def test_overwrite_replaces_a_bag_and_never_anything_else(tmp_path):
    bag = tmp_path / "bag"
    assert write_messages(bag, [("local_map", 1, b"\x00\x01\x00\x00" + bytes(12))], overwrite=True) == 1
    assert write_messages(bag, [], overwrite=True) == 0  # a bag is replaced
    assert list(read_messages(bag)) == []
    user = tmp_path / "thesis"
    user.mkdir()
    (user / "thesis.txt").write_text("four years")
    with pytest.raises(DatasetError, match=r"thesis exists and is not a bag \(it holds thesis.txt\): not replaced"):
        write_messages(user, [], overwrite=True)
    (user / "metadata.yaml").write_text("x")  # a bag's name, but a foreign file beside it
    with pytest.raises(DatasetError, match=r"is not a bag \(it holds thesis.txt\)"):
        write_messages(user, [], overwrite=True)
    assert (user / "thesis.txt").read_text() == "four years"
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match=r"empty exists and is not a bag \(it has no metadata.yaml\)"):
        write_messages(empty, [], overwrite=True)
    a_file = tmp_path / "notes.txt"
    a_file.write_text("keep")
    with pytest.raises(DatasetError, match="notes.txt exists and is not a bag folder: not replaced"):
        write_messages(a_file, [], overwrite=True)
    assert a_file.read_text() == "keep"


def test_bags_store_fully_qualified_topic_names_as_rosbag2_does(tmp_path):
    """`ros2 bag play --topics /local_map` and QoS override files match names as written: rosbag2 writes `/local_map`."""
    from rosbags.interfaces import QosDurability
    from rosbags.rosbag2 import Reader

    raw = b"\x00\x01\x00\x00" + bytes(12)
    bag = tmp_path / "bag"
    write_messages(bag, [("local_map", 1, raw), ("/robot1/pose_graph", 2, raw), ("global_map", 3, raw)], latched={"global_map"})
    with Reader(bag) as reader:
        stored = {c.topic: c.ext.offered_qos_profiles[0].durability for c in reader.connections}
    assert stored == {"/local_map": QosDurability.VOLATILE, "/robot1/pose_graph": QosDurability.VOLATILE,
                      "/global_map": QosDurability.TRANSIENT_LOCAL}
    assert "name: /local_map" in (bag / "metadata.yaml").read_text()
    for wanted in (["local_map"], ["/local_map"]):  # a reader's filter takes either form
        assert [r.topic for r in read_messages(bag, wanted)] == ["/local_map"]
    assert [r.latched for r in read_messages(bag)] == [False, False, True]


def test_committed_bags_store_fully_qualified_topic_names():
    import subprocess

    from rosbags.rosbag2 import Reader

    from support import REPO

    listed = subprocess.run(["git", "ls-files", "bags/*/metadata.yaml"], cwd=REPO, capture_output=True, text=True, check=True)
    committed = [REPO / Path(line).parent for line in listed.stdout.split()]
    assert len(committed) == 7
    for bag in committed:
        with Reader(bag) as reader:
            assert all(c.topic.startswith("/") for c in reader.connections), bag


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--rate", "0"], "--rate 0.0: must be within"),
        (["--rate", "nan"], "--rate nan: must be within"),
        (["--rate", "-10"], "--rate -10.0: must be within"),
        (["--rate", "1e-12"], "--rate 1e-12: must be within"),
        (["--as-pose-graph", "--maps-per-chunk", "0"], "--maps-per-chunk 0: must be >= 1"),
    ],
)
def test_bag_from_dataset_refuses_options_that_cannot_work(options, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        bag_from_dataset.main(["--synthetic", "city2d-20", "--out", str(tmp_path / "b"), *options])
    assert stop.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_topics_of_other_types_are_not_read_and_are_named(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    from linear_slam_ros.ros.bagio import other_topics
    from msg_adapters.bags import TYPESTORE

    bag = tmp_path / "mixed"
    string = TYPESTORE.types["std_msgs/msg/String"]
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        floats = writer.add_connection("local_map", "std_msgs/msg/Float64MultiArray", typestore=TYPESTORE)
        words = writer.add_connection("chatter", "std_msgs/msg/String", typestore=TYPESTORE)
        writer.write(words, 1, TYPESTORE.serialize_cdr(string(data="hi"), "std_msgs/msg/String"))
        array = TYPESTORE.types["std_msgs/msg/Float64MultiArray"]
        layout = TYPESTORE.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        writer.write(floats, 2, TYPESTORE.serialize_cdr(array(layout=layout, data=np.zeros(1)), "std_msgs/msg/Float64MultiArray"))
    assert [r.topic for r in read_messages(bag)] == ["local_map"]  # a String was played as a Float64MultiArray
    assert other_topics(bag) == {"chatter": "std_msgs/msg/String"}


def test_the_recorder_refuses_an_out_that_is_not_a_bag_before_recording(tmp_path, capsys):
    from linear_slam_ros.ros.recorder import main

    user = tmp_path / "home"
    user.mkdir()
    (user / "notes.txt").write_text("keep")
    assert main(["bag_recorder", "--out", str(user), "--duration", "0.1"]) == 2
    assert "home exists and is not a bag (it holds notes.txt): not replaced" in capsys.readouterr().err
    assert (user / "notes.txt").read_text() == "keep"
