"""The channel's Fast DDS profiles: the shipped ones with reliability timers scaled by the play rate and a data_reader
profile per multicast topic."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.ros.dds import (
    CHANNEL_PROFILES,
    READER_TIMES,
    V2X_MULTICAST_GROUP,
    WRITER_TIMES,
    channel_environment,
    channel_profiles,
    fastdds_profile_path,
    v2x_multicast_port,
    v2x_priority_port,
)

NS = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}


def test_every_feature_reader_listens_on_the_group_and_the_rest_is_the_shipped_profile(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "3")
    topics = ["/cav_1/voxel_features", "/cav_7/voxel_features"]
    folder = channel_profiles(tmp_path / "dds", multicast_topics=topics)
    for name in CHANNEL_PROFILES:
        root = ET.parse(folder / name).getroot()
        readers = root.findall("p:profiles/p:data_reader", NS)
        assert [r.get("profile_name") for r in readers] == ["v2x_default", *topics]
        for reader in readers[1:]:
            udp = reader.find("p:multicastLocatorList/p:locator/p:udpv4", NS)
            assert udp.find("p:address", NS).text == V2X_MULTICAST_GROUP
            assert int(udp.find("p:port", NS).text) == 7401 + 250 * 3 == v2x_multicast_port()
        # the participant and its transports as shipped
        shipped = ET.parse(fastdds_profile_path(name)).getroot()
        for tag in ("participant", "transport_descriptors"):
            assert ET.tostring(root.find(f"p:profiles/p:{tag}", NS)) == ET.tostring(
                shipped.find(f"p:profiles/p:{tag}", NS)
            )
    assert channel_environment("cav_3", folder)["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(folder / "fastdds_udp.xml")
    assert channel_environment(None, folder)["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(folder / "fastdds_onboard.xml")
    assert channel_environment("ego")["FASTRTPS_DEFAULT_PROFILES_FILE"] == fastdds_profile_path("fastdds_onboard.xml")
    assert v2x_multicast_port() % 2 == 1  # user data's parity: the channel keeps even (discovery) ports off the radio


def seconds(element) -> float:
    return int(element.find("p:sec", NS).text) + int(element.find("p:nanosec", NS).text) / 1e9


def test_reliability_timers_run_as_slow_as_the_channel(tmp_path):
    """At play rate 0.05 every writer's and reader's timers are 20 times Fast DDS's defaults (a heartbeat every 60 s
    of wall time is every 3 s of the channel's), in the default profiles and in each multicast reader's; a reader
    answers a heartbeat after the medium's queue time (200 ms of real time, 4 s of wall time) instead of 5 ms."""
    folder = channel_profiles(tmp_path / "dds", 1 / 0.05, 0.2, ["/cav_1/voxel_features"])
    for name in CHANNEL_PROFILES:
        profiles = ET.parse(folder / name).getroot().find("p:profiles", NS)
        (writer,) = profiles.findall("p:data_writer", NS)
        assert writer.get("is_default_profile") == "true"
        for timer, default in WRITER_TIMES.items():
            assert abs(seconds(writer.find(f"p:times/p:{timer}", NS)) - 20 * default) < 1e-9, timer
        default_reader, multicast_reader = profiles.findall("p:data_reader", NS)
        assert default_reader.get("is_default_profile") == "true"
        for reader in (default_reader, multicast_reader):
            acknack = seconds(reader.find("p:times/p:initialAcknackDelay", NS))
            assert abs(acknack - 20 * READER_TIMES["initialAcknackDelay"]) < 1e-9
            assert seconds(reader.find("p:times/p:heartbeatResponseDelay", NS)) == 4.0
    assert seconds(writer.find("p:times/p:heartbeatPeriod", NS)) == 60.0
    # what goes to the machine's side keeps Fast DDS's own timers
    harness = channel_profiles(tmp_path / "harness", 20.0, 0.2, harness_topics=["/diagnostics"])
    profiles = ET.parse(harness / CHANNEL_PROFILES[0]).getroot().find("p:profiles", NS)
    for endpoint, defaults in (("data_writer", WRITER_TIMES), ("data_reader", READER_TIMES)):
        (own,) = [e for e in profiles.findall(f"p:{endpoint}", NS) if e.get("profile_name") == "/diagnostics"]
        for timer, default in defaults.items():
            assert abs(seconds(own.find(f"p:times/p:{timer}", NS)) - default) < 1e-9, timer
    # without a queue to wait for, a reader answers at Fast DDS's own delay, scaled
    reader = ET.parse(channel_profiles(tmp_path / "own", 2.0) / CHANNEL_PROFILES[1]).getroot()
    (default_reader,) = reader.findall("p:profiles/p:data_reader", NS)
    assert seconds(default_reader.find("p:times/p:heartbeatResponseDelay", NS)) == 0.01


def test_a_time_scale_that_is_not_positive_is_refused(tmp_path):
    with pytest.raises(Co3sopError, match="time_scale"):
        channel_profiles(tmp_path, 0.0)


def test_priority_topics_listen_on_the_group_port_the_medium_carries_first(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "0")
    topics = ["/cav_1/voxel_features", "/cav_1/ego/request_map"]
    folder = channel_profiles(tmp_path / "dds", multicast_topics=topics, priority_topics=topics[1:])
    readers = ET.parse(folder / CHANNEL_PROFILES[1]).getroot().findall("p:profiles/p:data_reader", NS)
    ports = {r.get("profile_name"): r.find("p:multicastLocatorList/p:locator/p:udpv4/p:port", NS) for r in readers}
    assert int(ports[topics[0]].text) == v2x_multicast_port() == 7401
    assert int(ports[topics[1]].text) == v2x_priority_port() == 7403  # odd (user data), unused by the mapping
    with pytest.raises(Co3sopError, match="not multicast"):
        channel_profiles(tmp_path / "bad", multicast_topics=topics[:1], priority_topics=topics[1:])
