"""rmw_zenoh's key expressions, liveliness tokens and attachments (sans-IO), against the
examples in rmw_zenoh's docs/design.md (Jazzy 0.2.10 / Kilted 0.6.7 write them alike)."""

from __future__ import annotations

import struct

import pytest

from telebot.errors import CdrError
from telebot.robot.ros2.keys import (
    ATTACHMENT_SIZE,
    Attachment,
    Durability,
    EntityKind,
    GraphEntity,
    History,
    QoS,
    Reliability,
    action_names,
    entity_gid,
    mangle,
    new_gid,
    parse_liveliness,
    resolve_name,
    topic_key,
)

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
STRING = "std_msgs::msg::dds_::String_"
ADD = "example_interfaces::srv::dds_::AddTwoInts_"

# Tokens quoted from rmw_zenoh's design doc.
LISTENER_NODE = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
LISTENER_SUB = (
    "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
    f"{STRING}/{STRING_HASH}/::,10:,:,:,,"
)
TALKER_PUB = (
    "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    f"{STRING}/{STRING_HASH}/::,7:,:,:,,"
)
ADD_SERVER = (
    "@ros2_lv/0/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/"
    f"%add_two_ints/{ADD}/{ADD_HASH}/::,10:,:,:,,"
)
ADD_CLIENT = (
    "@ros2_lv/0/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/"
    f"%add_two_ints/{ADD}/{ADD_HASH}/::,10:,:,:,,"
)


def test_topic_keys_as_in_the_design_doc() -> None:
    assert topic_key(0, "/chatter", STRING, STRING_HASH) == f"0/chatter/{STRING}/{STRING_HASH}"
    assert (
        topic_key(0, resolve_name("chatter", "/robot1"), STRING, STRING_HASH)
        == f"0/robot1/chatter/{STRING}/{STRING_HASH}"
    )
    assert topic_key(2, "/add_two_ints", ADD, ADD_HASH) == f"2/add_two_ints/{ADD}/{ADD_HASH}"


def test_resolve_names() -> None:
    assert resolve_name("map") == "/map"
    assert resolve_name("map", "robot1/") == "/robot1/map"
    assert resolve_name("/map", "/robot1") == "/map"
    for bad in ("", "/", "a//b"):
        with pytest.raises(ValueError, match="invalid ROS name"):
            resolve_name(bad)


@pytest.mark.parametrize("key", [LISTENER_NODE, LISTENER_SUB, TALKER_PUB, ADD_SERVER, ADD_CLIENT])
def test_design_doc_tokens_parse_and_recompose(key: str) -> None:
    entity = parse_liveliness(key)
    assert entity is not None
    rebuilt = GraphEntity(
        kind=entity.kind,
        domain_id=entity.domain_id,
        zid=entity.zid,
        node_id=entity.node_id,
        entity_id=entity.entity_id,
        namespace=entity.namespace,
        node_name=entity.node_name,
        enclave=entity.enclave,
        topic=entity.topic,
        dds_type=entity.dds_type,
        type_hash=entity.type_hash,
        qos=entity.qos,
    )
    assert rebuilt.key == key


def test_parsed_fields() -> None:
    sub = parse_liveliness(LISTENER_SUB)
    assert sub is not None
    assert (sub.kind, sub.zid, sub.node_id, sub.entity_id) == (
        EntityKind.SUBSCRIPTION,
        "aac3178e146ba6f1fc6e6a4085e77f21",
        "0",
        "10",
    )
    assert (sub.enclave, sub.namespace, sub.node_name, sub.topic) == (
        "/",
        "/",
        "listener",
        "/chatter",
    )
    assert (sub.dds_type, sub.type_hash) == (STRING, STRING_HASH)
    assert sub.qos == QoS(depth=10)
    pub = parse_liveliness(TALKER_PUB)
    assert pub is not None and pub.qos is not None and pub.qos.depth == 7
    node = parse_liveliness(LISTENER_NODE)
    assert node is not None and node.topic is None and node.node_fqn == "/listener"


def test_namespaced_node_mangles_slashes() -> None:
    entity = GraphEntity(
        kind=EntityKind.PUBLISHER,
        domain_id=3,
        zid="ab",
        node_id="1",
        entity_id="4",
        namespace="/robot1/arm",
        node_name="telebot",
        topic="/robot1/arm/map",
        dds_type="nav_msgs::msg::dds_::OccupancyGrid_",
        type_hash="RIHS01_" + "8" * 64,
        qos=QoS.transient_local(),
    )
    assert entity.key == (
        "@ros2_lv/3/ab/1/4/MP/%/%robot1%arm/telebot/%robot1%arm%map/"
        "nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_" + "8" * 64 + "/:1:,1:,:,:,,"
    )
    assert parse_liveliness(entity.key) == entity
    assert mangle("/a/b") == "%a%b"


def test_qos_text() -> None:
    assert QoS().keyexpr() == "::,10:,:,:,,"
    assert QoS(depth=42).keyexpr() == "::,:,:,:,,"
    assert QoS.sensor_data().keyexpr() == "2::,5:,:,:,,"
    text = QoS(
        reliability=Reliability.BEST_EFFORT,
        durability=Durability.TRANSIENT_LOCAL,
        history=History.KEEP_ALL,
        depth=3,
        deadline=(1, 500),
        lifespan=(2, 0),
    ).keyexpr()
    assert text == "2:1:2,3:1,500:2,0:,,"
    parsed = QoS.parse(text)
    assert parsed is not None and parsed.keyexpr() == text and parsed.deadline == (1, 500)
    assert QoS.parse("::,:,:,:,,") == QoS(depth=42)


@pytest.mark.parametrize(
    "text",
    ["", "::::", "::,10:,:,:,", "x::,10:,:,:,,", "::,-1:,:,:,,", "9::,10:,:,:,,", "::,1x:,:,:,,"],
)
def test_bad_qos_text_is_none(text: str) -> None:
    assert QoS.parse(text) is None


@pytest.mark.parametrize(
    "key",
    [
        "",
        "@ros2_lv/0/zid/0/0/NN/%/%",  # too short
        "@other/0/zid/0/0/NN/%/%/n",  # not the admin space
        "@ros2_lv/x/zid/0/0/NN/%/%/n",  # domain not a number
        "@ros2_lv/0/zid/0/0/XX/%/%/n",  # unknown entity
        "@ros2_lv/0/zid/0/0/NN/%/%/n/extra",  # node with a topic
        "@ros2_lv/0/zid/0/0/MP/%/%/n",  # publisher without topic
        "@ros2_lv/0/zid/0/0/MP/%/%/n/%t/T/H/not-qos",
        "@ros2_lv/0/zid/0//0/NN/%/%/n",  # empty chunk
    ],
)
def test_garbage_tokens_are_none(key: str) -> None:
    assert parse_liveliness(key) is None


def test_attachment_bytes() -> None:
    gid = bytes(range(16))
    data = Attachment(7, 1_700_000_000_123_456_789, gid).encode()
    assert len(data) == ATTACHMENT_SIZE == 33
    assert data == struct.pack("<qq", 7, 1_700_000_000_123_456_789) + b"\x10" + gid
    assert Attachment.decode(data) == Attachment(7, 1_700_000_000_123_456_789, gid)


@pytest.mark.parametrize(
    "data", [b"", bytes(32), bytes(34), struct.pack("<qqB", 1, 2, 15) + bytes(16)]
)
def test_bad_attachment_is_cdr_error(data: bytes) -> None:
    with pytest.raises(CdrError, match="attachment"):
        Attachment.decode(data)


def test_gids() -> None:
    assert len(new_gid()) == 16 and new_gid() != new_gid()
    # XXH3-128 of the token, low 64 bits first (as rmw_zenoh's Entity constructor copies it).
    # XXH3-128("") is 0x99aa06d3014798d8_6001c324468d497f; the GID is low64 then high64,
    # each little endian, as rmw_zenoh's Entity constructor copies them.
    assert entity_gid("") == bytes.fromhex("7f498d4624c30160d8984701d306aa99")
    entity = parse_liveliness(ADD_CLIENT)
    assert entity is not None and entity.gid == entity_gid(ADD_CLIENT)


def test_action_names() -> None:
    assert action_names("/navigate_to_pose") == {
        "send_goal": "/navigate_to_pose/_action/send_goal",
        "get_result": "/navigate_to_pose/_action/get_result",
        "cancel_goal": "/navigate_to_pose/_action/cancel_goal",
        "feedback": "/navigate_to_pose/_action/feedback",
        "status": "/navigate_to_pose/_action/status",
    }
