"""The FastDDS profile the joiner loads (linear_slam_ros.ros.qos.inbound_dds_profile, config/fastdds_inbound.xml)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from linear_slam_ros.ros.qos import INBOUND_PROFILE, inbound_dds_profile

REPO = Path(__file__).resolve().parents[2]


def test_the_shipped_profile_raises_the_default_readers_limits() -> None:
    root = ET.parse(REPO / "config" / INBOUND_PROFILE).getroot()
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    reader = root.find("f:data_reader", ns)
    assert reader is not None and reader.get("is_default_profile") == "true"
    limits = {e.tag.split("}")[1]: int(e.text or "0") for e in reader.find("f:topic/f:resourceLimitsQos", ns)}
    assert limits["max_samples_per_instance"] == limits["max_samples"] >= 20_000  # a city2d-20000 backlog fits
    assert limits["allocated_samples"] <= 1000  # grown on demand, not reserved


def test_installed_share_directory_is_used(tmp_path: Path) -> None:
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / INBOUND_PROFILE).write_text("<profiles/>")
    assert inbound_dds_profile({}, tmp_path) == tmp_path / "config" / INBOUND_PROFILE
    assert inbound_dds_profile({"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}, tmp_path) == tmp_path / "config" / INBOUND_PROFILE


def test_source_tree_is_used_when_not_installed() -> None:
    assert inbound_dds_profile({}, None) == REPO / "config" / INBOUND_PROFILE


@pytest.mark.parametrize("environ", [
    {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"},
    {"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"},
    {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"},
    {"RMW_IMPLEMENTATION": "rmw_zenoh_cpp"},
])
def test_a_users_profile_or_another_middleware_is_left_alone(environ: dict[str, str]) -> None:
    assert inbound_dds_profile(environ, None) is None


def test_no_profile_when_the_file_is_missing(tmp_path: Path) -> None:
    assert inbound_dds_profile({}, tmp_path) is None
