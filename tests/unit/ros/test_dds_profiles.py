"""The channel's multicast Fast DDS profiles: the shipped ones with a data_reader profile per feature topic."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from co3sop_nodes.ros.dds import (
    CHANNEL_PROFILES,
    V2X_MULTICAST_GROUP,
    channel_environment,
    fastdds_profile_path,
    multicast_profiles,
    v2x_multicast_port,
)

NS = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}


def test_every_feature_reader_listens_on_the_group_and_the_rest_is_the_shipped_profile(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "3")
    topics = ["/cav_1/voxel_features", "/cav_7/voxel_features"]
    folder = multicast_profiles(tmp_path / "dds", topics)
    for name in CHANNEL_PROFILES:
        root = ET.parse(folder / name).getroot()
        readers = root.findall("p:profiles/p:data_reader", NS)
        assert [r.get("profile_name") for r in readers] == topics
        for reader in readers:
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
