"""ROS 2 types: RIHS01 hashes as ROS computes them, CDR against real bags, garbage -> CdrError."""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telebot.errors import CdrError, ConfigError, Ros2Error, UnknownRosType
from telebot.rosmsg.types import (
    MessageType,
    TypeLibrary,
    dds_type_name,
    rihs01_hash,
    ros_type_name,
)


def _ros2_data() -> Path:
    """The ROS 2 fixtures the tests carry (``tests/data/ros2``; SOURCES.md names their origin)."""
    return Path(__file__).resolve().parent / "data" / "ros2"


BAGS = ["bag_with_topics_and_service_events", "cm_moving_obstacle"]


@pytest.fixture(scope="module")
def jazzy() -> TypeLibrary:
    return TypeLibrary("jazzy")


@pytest.fixture(scope="module")
def kilted() -> TypeLibrary:
    return TypeLibrary("kilted")


# -- hashes ----------------------------------------------------------------------------------

# Published prefixes (issue 14); the full values are what rosidl generates for Jazzy.
MESSAGE_HASHES = {
    "geometry_msgs/msg/Twist": "9c45bf16",
    "geometry_msgs/msg/PoseStamped": "10f3786d",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "26432f98",
    "nav_msgs/msg/OccupancyGrid": "8d348150",
    "sensor_msgs/msg/LaserScan": "64c19139",
    "sensor_msgs/msg/BatteryState": "4bee5dfc",
}
SERVICE_HASHES = {
    "nav2_msgs/action/NavigateToPose_SendGoal": "a4fcb3be",
    "nav2_msgs/action/NavigateToPose_GetResult": "c4079203",
    "action_msgs/srv/CancelGoal": "573d8b0a",
    "example_interfaces/srv/AddTwoInts": "e118de",
    "std_srvs/srv/SetBool": "abe9e4bb",
}


@pytest.mark.parametrize("distro", ["jazzy", "kilted"])
@pytest.mark.parametrize(("name", "prefix"), MESSAGE_HASHES.items())
def test_message_hashes_match_ros(distro: str, name: str, prefix: str) -> None:
    mtype = TypeLibrary(distro).message(name)  # type: ignore[arg-type]
    assert mtype.type_hash.startswith("RIHS01_" + prefix)
    assert len(mtype.type_hash) == len("RIHS01_") + 64
    hex_part = mtype.type_hash.removeprefix("RIHS01_")
    assert hex_part == hex_part.lower()
    int(hex_part, 16)


@pytest.mark.parametrize(("name", "prefix"), SERVICE_HASHES.items())
def test_service_hashes_match_ros(jazzy: TypeLibrary, name: str, prefix: str) -> None:
    assert jazzy.service(name).type_hash.startswith("RIHS01_" + prefix)


def test_hashes_in_rmw_zenoh_design_doc_examples(jazzy: TypeLibrary) -> None:
    """rmw_zenoh's docs/design.md: ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``
    and ``2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118...``."""
    string = jazzy.message("std_msgs/msg/String")
    assert f"{string.dds_name}/{string.type_hash}" == (
        "std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )
    add = jazzy.service("example_interfaces/srv/AddTwoInts")
    assert f"{add.dds_name}/{add.type_hash}" == (
        "example_interfaces::srv::dds_::AddTwoInts_/"
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
    )


def test_action_services_reach_the_same_hashes_through_the_action(jazzy: TypeLibrary) -> None:
    nav = jazzy.action("nav2_msgs/action/NavigateToPose")
    assert nav.send_goal.type_hash.startswith("RIHS01_a4fcb3be")
    assert nav.get_result.type_hash.startswith("RIHS01_c4079203")
    assert nav.cancel_goal.type_hash.startswith("RIHS01_573d8b0a")


def test_char_hashes_as_uint8_unlike_rosbags(jazzy: TypeLibrary) -> None:
    """service_msgs/ServiceEventInfo has ``char[16] client_gid``: the IDL char id (13) would
    change every service hash; rosidl maps a .msg ``char`` to uint8 (id 3)."""
    described = jazzy.type_description("service_msgs/msg/ServiceEventInfo")
    gid = next(f for f in described["type_description"]["fields"] if f["name"] == "client_gid")
    assert gid["type"] == {
        "type_id": 51,  # FIELD_TYPE_UINT8_ARRAY
        "capacity": 16,
        "string_capacity": 0,
        "nested_type_name": "",
    }
    store = jazzy.message("std_srvs/srv/SetBool_Event").cls  # the store has it now
    assert store is not None
    from rosbags.typesys import Stores, get_typestore

    rosbags_own = get_typestore(Stores.ROS2_JAZZY).hash_rihs01("service_msgs/msg/ServiceEventInfo")
    assert rosbags_own != jazzy.type_hash("service_msgs/msg/ServiceEventInfo")


def test_service_description_has_request_response_and_event(jazzy: TypeLibrary) -> None:
    described = jazzy.type_description("example_interfaces/srv/AddTwoInts")
    top = described["type_description"]
    assert [(f["name"], f["type"]["nested_type_name"]) for f in top["fields"]] == [
        ("request_message", "example_interfaces/srv/AddTwoInts_Request"),
        ("response_message", "example_interfaces/srv/AddTwoInts_Response"),
        ("event_message", "example_interfaces/srv/AddTwoInts_Event"),
    ]
    refs = [td["type_name"] for td in described["referenced_type_descriptions"]]
    assert refs == sorted(refs)
    assert "service_msgs/msg/ServiceEventInfo" in refs
    assert "builtin_interfaces/msg/Time" in refs
    event = next(
        td
        for td in described["referenced_type_descriptions"]
        if td["type_name"] == "example_interfaces/srv/AddTwoInts_Event"
    )
    request = event["fields"][1]
    assert request["name"] == "request"
    assert request["type"]["type_id"] == 97  # FIELD_TYPE_NESTED_TYPE_BOUNDED_SEQUENCE
    assert request["type"]["capacity"] == 1
    assert rihs01_hash(described) == jazzy.service("example_interfaces/srv/AddTwoInts").type_hash


def test_default_values_are_not_hashed(jazzy: TypeLibrary) -> None:
    described = jazzy.type_description("geometry_msgs/msg/Twist")
    baseline = rihs01_hash(described)
    for field in described["type_description"]["fields"]:
        field["default_value"] = "something"
    assert rihs01_hash(described) == baseline
    described["type_description"]["fields"][0]["name"] = "lineal"
    assert rihs01_hash(described) != baseline


def test_kilted_behaviours_gained_a_field_so_their_hashes_differ(
    jazzy: TypeLibrary, kilted: TypeLibrary
) -> None:
    for name in ("Spin", "DriveOnHeading", "BackUp"):
        old, new = (
            jazzy.action(f"nav2_msgs/action/{name}"),
            kilted.action(f"nav2_msgs/action/{name}"),
        )
        assert old.type_hash != new.type_hash, name
        assert old.send_goal.type_hash != new.send_goal.type_hash, name
        assert old.goal.type_hash != new.goal.type_hash, name
        assert "disable_collision_checks" in new.goal.make().__dataclass_fields__
        assert "disable_collision_checks" not in old.goal.make().__dataclass_fields__
        # The result is the same text in both: the GetResult service hashes alike.
        assert old.get_result.type_hash == new.get_result.type_hash, name
    # Kilted's NavigateToPose only gained error constants: constants are not hashed.
    old_nav = jazzy.action("nav2_msgs/action/NavigateToPose")
    new_nav = kilted.action("nav2_msgs/action/NavigateToPose")
    assert old_nav.type_hash == new_nav.type_hash
    assert old_nav.send_goal.type_hash == new_nav.send_goal.type_hash
    assert old_nav.get_result.type_hash == new_nav.get_result.type_hash
    assert old_nav.feedback.type_hash == new_nav.feedback.type_hash


def test_action_derived_types_are_built_as_rosidl_does(jazzy: TypeLibrary) -> None:
    nav = jazzy.action("nav2_msgs/action/NavigateToPose")
    assert nav.name == "nav2_msgs/action/NavigateToPose"
    assert nav.goal.name == "nav2_msgs/action/NavigateToPose_Goal"
    assert nav.result.name == "nav2_msgs/action/NavigateToPose_Result"
    assert nav.feedback_body.name == "nav2_msgs/action/NavigateToPose_Feedback"
    assert nav.feedback.name == "nav2_msgs/action/NavigateToPose_FeedbackMessage"
    assert nav.status.name == "action_msgs/msg/GoalStatusArray"
    assert nav.send_goal.request.name == "nav2_msgs/action/NavigateToPose_SendGoal_Request"
    assert nav.get_result.response.name == "nav2_msgs/action/NavigateToPose_GetResult_Response"

    def fields(mtype: Any) -> list[str]:
        return [f["name"] for f in jazzy.type_description(mtype.name)["type_description"]["fields"]]

    assert fields(nav.send_goal.request) == ["goal_id", "goal"]
    assert fields(nav.send_goal.response) == ["accepted", "stamp"]
    assert fields(nav.get_result.request) == ["goal_id"]
    assert fields(nav.get_result.response) == ["status", "result"]
    assert fields(nav.feedback) == ["goal_id", "feedback"]
    top = jazzy.type_description(nav.name)["type_description"]["fields"]
    assert [f["name"] for f in top] == [
        "goal",
        "result",
        "feedback",
        "send_goal_service",
        "get_result_service",
        "feedback_message",
    ]


def test_derived_names_resolve_without_asking_for_the_parent_first() -> None:
    fresh = TypeLibrary("jazzy")
    fb = fresh.message("nav2_msgs/action/Spin_FeedbackMessage")
    assert fb.dds_name == "nav2_msgs::action::dds_::Spin_FeedbackMessage_"
    assert fresh.service("nav2_msgs/action/Spin_SendGoal").request.name.endswith("_Request")
    assert fresh.message("std_srvs/srv/SetBool_Request").make(data=True).data is True


# -- rmw_zenoh type names --------------------------------------------------------------------


def test_dds_names_as_rmw_zenoh_writes_them(jazzy: TypeLibrary) -> None:
    assert jazzy.message("geometry_msgs/msg/Twist").dds_name == "geometry_msgs::msg::dds_::Twist_"
    assert (
        jazzy.service("example_interfaces/srv/AddTwoInts").dds_name
        == "example_interfaces::srv::dds_::AddTwoInts_"
    )
    nav = jazzy.action("nav2_msgs/action/NavigateToPose")
    assert nav.send_goal.dds_name == "nav2_msgs::action::dds_::NavigateToPose_SendGoal_"
    assert nav.get_result.dds_name == "nav2_msgs::action::dds_::NavigateToPose_GetResult_"
    assert nav.cancel_goal.dds_name == "action_msgs::srv::dds_::CancelGoal_"
    assert nav.feedback.dds_name == "nav2_msgs::action::dds_::NavigateToPose_FeedbackMessage_"
    assert nav.status.dds_name == "action_msgs::msg::dds_::GoalStatusArray_"


def test_ros_type_name_inverts_dds_type_name() -> None:
    for name in ("geometry_msgs/msg/Twist", "nav2_msgs/action/Spin_SendGoal", "std_srvs/srv/Empty"):
        assert ros_type_name(dds_type_name(name)) == name
    for junk in ("", "Twist", "geometry_msgs::msg::Twist_", "a::msg::dds_::B", "x" * 500):
        with pytest.raises(UnknownRosType):
            ros_type_name(junk)


# -- lookup errors ---------------------------------------------------------------------------


def test_unknown_types_name_near_ones(jazzy: TypeLibrary) -> None:
    with pytest.raises(UnknownRosType, match="did you mean geometry_msgs/msg/Twist"):
        jazzy.message("geometry_msgs/msg/Twst")
    with pytest.raises(UnknownRosType, match="std_srvs/srv/SetBool"):
        jazzy.service("std_srvs/srv/SetBoo")
    with pytest.raises(UnknownRosType, match="nav2_msgs/action/Spin"):
        jazzy.action("nav2_msgs/action/Spinn")
    with pytest.raises(UnknownRosType, match="not a ROS type name"):
        jazzy.message("no such thing")


def test_short_names_and_unknown_distro(jazzy: TypeLibrary) -> None:
    assert jazzy.message("geometry_msgs/Twist") is jazzy.message("geometry_msgs/msg/Twist")
    assert jazzy.service("std_srvs/SetBool") is jazzy.service("std_srvs/srv/SetBool")
    assert jazzy.action("nav2_msgs/Spin") is jazzy.action("nav2_msgs/action/Spin")
    with pytest.raises(ConfigError, match="humble"):
        TypeLibrary("humble")  # type: ignore[arg-type]


def test_constructor_defers_the_type_store() -> None:
    """Building a library must stay cheap: rosbags' store (~150 ms) loads on first use."""
    fresh = TypeLibrary("kilted")
    assert fresh._typestore is None
    fresh.message("geometry_msgs/msg/TwistStamped")
    assert fresh._typestore is not None


# -- make / CDR ------------------------------------------------------------------------------


def test_make_fills_defaults(jazzy: TypeLibrary) -> None:
    imu = jazzy.message("sensor_msgs/msg/Imu").make()
    assert imu.header.frame_id == ""
    assert imu.header.stamp.sec == 0
    assert imu.orientation.w == 0.0
    assert list(imu.orientation_covariance) == [0.0] * 9
    grid = jazzy.message("nav_msgs/msg/OccupancyGrid").make(data=np.array([1, -1], np.int8))
    assert list(grid.data) == [1, -1]
    status = jazzy.message("action_msgs/msg/GoalStatusArray").make()
    assert status.status_list == []
    goal = jazzy.action("nav2_msgs/action/NavigateToPose").send_goal.request.make()
    assert bytes(goal.goal_id.uuid) == bytes(16)
    with pytest.raises(Ros2Error, match="Twist has no field linearr"):
        jazzy.message("geometry_msgs/msg/Twist").make(linearr=1)


def test_make_accepts_plain_python_values(jazzy: TypeLibrary) -> None:
    uuid = jazzy.message("unique_identifier_msgs/msg/UUID")
    assert uuid.serialize(uuid.make(uuid=bytes(range(16))))[4:] == bytes(range(16))
    assert uuid.serialize(uuid.make(uuid=list(range(16))))[4:] == bytes(range(16))
    with pytest.raises(Ros2Error, match=r"UUID.uuid: needs exactly 16 elements, got 15"):
        uuid.make(uuid=bytes(15))
    scan = jazzy.message("sensor_msgs/msg/LaserScan")
    assert list(scan.deserialize(scan.serialize(scan.make(ranges=[1.5, 2.5]))).ranges) == [
        1.5,
        2.5,
    ]
    with pytest.raises(Ros2Error, match=r"LaserScan.ranges: not float32"):
        scan.make(ranges=["far"])
    twist = jazzy.message("geometry_msgs/msg/Twist").make(linear={"x": 0.25}, angular={"z": 1.0})
    assert (twist.linear.x, twist.angular.z) == (0.25, 1.0)
    path = jazzy.message("nav_msgs/msg/Path").make(poses=[{"pose": {"position": {"x": 2.0}}}])
    assert path.poses[0].pose.position.x == 2.0
    event = jazzy.message("std_srvs/srv/SetBool_Event")
    with pytest.raises(Ros2Error, match=r"SetBool_Event.request: at most 1 elements, got 2"):
        event.make(request=[{"data": True}, {"data": False}])


def test_cdr_round_trip_and_layout(jazzy: TypeLibrary) -> None:
    twist = jazzy.message("geometry_msgs/msg/Twist")
    msg = twist.make(linear=jazzy.message("geometry_msgs/msg/Vector3").make(x=0.5))
    data = twist.serialize(msg)
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR little endian, no options
    assert len(data) == 4 + 6 * 8
    assert struct.unpack_from("<d", data, 4)[0] == 0.5
    assert twist.deserialize(data).linear.x == 0.5
    req = jazzy.service("std_srvs/srv/SetBool").request
    assert req.serialize(req.make(data=True)) == b"\x00\x01\x00\x00\x01"


def test_decoded_arrays_do_not_follow_a_reused_buffer(jazzy: TypeLibrary) -> None:
    image = jazzy.message("sensor_msgs/msg/CompressedImage")
    buffer = bytearray(image.serialize(image.make(data=np.arange(4, dtype=np.uint8))))
    msg = image.deserialize(buffer)
    buffer[-4:] = bytes(4)
    assert list(msg.data) == [0, 1, 2, 3]
    with pytest.raises(CdrError, match=r"CompressedImage.*not str"):
        image.deserialize("not bytes")  # type: ignore[arg-type]


def test_concurrent_first_use_builds_each_type_once() -> None:
    fresh = TypeLibrary("jazzy")
    names = ["nav2_msgs/action/NavigateToPose", "nav2_msgs/action/Spin", "nav2_msgs/action/BackUp"]
    with ThreadPoolExecutor(max_workers=6) as pool:
        got = list(pool.map(fresh.action, names * 4))
    for i, action in enumerate(got):
        assert action is got[i % len(names)]
    assert got[0].send_goal.type_hash.startswith("RIHS01_a4fcb3be")


def test_serialize_rejects_wrong_objects(jazzy: TypeLibrary) -> None:
    twist = jazzy.message("geometry_msgs/msg/Twist")
    with pytest.raises(CdrError, match="geometry_msgs/msg/Twist"):
        twist.serialize(object())


def _bag_connections() -> Iterator[tuple[str, Any]]:
    from rosbags.rosbag2 import Reader

    for bag in BAGS:
        with Reader(_ros2_data() / "bags" / bag) as reader:
            yield from ((bag, c) for c in reader.connections)


def _library_with_bag_types(bag: str) -> tuple[TypeLibrary, dict[str, Any], set[str]]:
    """A library that learnt the bag's own types from the schemas it recorded; also the
    names whose recorded definition differs from the distro's (changed since recording)."""
    from rosbags.rosbag2 import Reader

    lib = TypeLibrary("jazzy")
    conns, changed = {}, set()
    with Reader(_ros2_data() / "bags" / bag) as reader:
        for conn in reader.connections:
            conns[conn.topic] = conn
            name = conn.msgtype
            if name.endswith("_Event") and "/srv/" in name:
                service = name.removesuffix("_Event")
                if service not in lib.known():
                    lib.register_srv_text(service, conn.msgdef.data)
                continue
            with contextlib.suppress(Ros2Error):
                lib.register_msg_text(name, conn.msgdef.data)
                continue
            changed.add(name)  # "already present with different definition"
    return lib, conns, changed


@pytest.mark.parametrize("bag", BAGS)
def test_hashes_match_the_ones_recorded_in_real_bags(bag: str) -> None:
    """rosbag2 records each topic's RIHS01 hash: char, byte, bounded strings with default
    values, service events (test_msgs/srv/BasicTypes_Event), nav2_msgs/Costmap, Clock."""
    lib, conns, changed = _library_with_bag_types(bag)
    assert conns
    for topic, conn in conns.items():
        recorded = conn.digest
        assert recorded.startswith("RIHS01_"), topic
        if conn.msgtype in changed:
            continue
        assert lib.message(conn.msgtype).type_hash == recorded, (topic, conn.msgtype)
    if bag == "bag_with_topics_and_service_events":
        # Recorded before Jazzy's WriteSplitEvent gained node_name: hash the old description.
        assert changed == {"rosbag2_interfaces/msg/WriteSplitEvent"}
        recorded = conns["/events/write_split"].digest
        assert lib.message("rosbag2_interfaces/msg/WriteSplitEvent").type_hash != recorded
        string = {"type_id": 17, "capacity": 0, "string_capacity": 0, "nested_type_name": ""}
        old = {
            "type_description": {
                "type_name": "rosbag2_interfaces/msg/WriteSplitEvent",
                "fields": [
                    {"name": "closed_file", "type": string},
                    {"name": "opened_file", "type": string},
                ],
            },
            "referenced_type_descriptions": [],
        }
        assert rihs01_hash(old) == recorded
    else:
        assert changed == set()


@pytest.mark.parametrize("bag", BAGS)
def test_every_bag_message_round_trips_to_identical_bytes(bag: str) -> None:
    from rosbags.rosbag2 import Reader

    lib, _, _ = _library_with_bag_types(bag)
    count = 0
    with Reader(_ros2_data() / "bags" / bag) as reader:
        for conn, _, raw in reader.messages():
            mtype = lib.message(conn.msgtype)
            msg = mtype.deserialize(raw)
            assert mtype.serialize(msg) == bytes(raw), conn.topic
            count += 1
    assert count == {"bag_with_topics_and_service_events": 10, "cm_moving_obstacle": 693}[bag]


# -- garbage ---------------------------------------------------------------------------------

GARBAGE_TYPES = [
    "geometry_msgs/msg/Twist",
    "nav_msgs/msg/OccupancyGrid",
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/CompressedImage",
    "tf2_msgs/msg/TFMessage",
    "action_msgs/msg/GoalStatusArray",
    "action_msgs/srv/CancelGoal_Response",
    "nav2_msgs/action/NavigateToPose_FeedbackMessage",
    "nav2_msgs/action/NavigateToPose_GetResult_Response",
    "std_srvs/srv/SetBool_Event",
]


@pytest.mark.parametrize(
    "data",
    [b"", b"\x00", b"\x00\x01\x00", b"\x01\x00\x00\x00" + bytes(64), b"\x00\x01\x00\x00"],
    ids=["empty", "one", "short-header", "wrong-header", "header-only"],
)
def test_short_and_foreign_bytes_are_cdr_errors(jazzy: TypeLibrary, data: bytes) -> None:
    with pytest.raises(CdrError, match="nav_msgs/msg/OccupancyGrid") as info:
        jazzy.message("nav_msgs/msg/OccupancyGrid").deserialize(data)
    assert "\n" not in str(info.value)


def test_truncated_and_padded_messages_are_cdr_errors(jazzy: TypeLibrary) -> None:
    scan = jazzy.message("sensor_msgs/msg/LaserScan")
    good = scan.serialize(scan.make(ranges=np.ones(10, np.float32)))
    for cut in range(len(good)):
        with pytest.raises(CdrError, match="LaserScan"):
            scan.deserialize(good[:cut])
    with pytest.raises(CdrError, match="trailing"):
        scan.deserialize(good + bytes(8))


def test_huge_length_prefixes_are_cdr_errors(jazzy: TypeLibrary) -> None:
    grid = jazzy.message("nav_msgs/msg/OccupancyGrid")
    good = bytearray(grid.serialize(grid.make(data=np.zeros(4, np.int8))))
    # The data sequence length is the 4 bytes before its 4 elements, at the end.
    struct.pack_into("<I", good, len(good) - 8, 0xFFFFFFFF)
    with pytest.raises(CdrError, match="OccupancyGrid"):
        grid.deserialize(bytes(good))
    frame = jazzy.message("std_msgs/msg/Header")
    body = b"\x00\x01\x00\x00" + bytes(8) + struct.pack("<I", 0x7FFFFFFF) + b"map\x00"
    with pytest.raises(CdrError, match="Header"):
        frame.deserialize(body)
    status = jazzy.message("action_msgs/msg/GoalStatusArray")
    with pytest.raises(CdrError, match="GoalStatusArray"):
        status.deserialize(b"\x00\x01\x00\x00" + struct.pack("<I", 0xFFFFFFF0) + bytes(40))


def test_bad_utf8_is_a_cdr_error(jazzy: TypeLibrary) -> None:
    frame = jazzy.message("std_msgs/msg/Header")
    body = b"\x00\x01\x00\x00" + bytes(8) + struct.pack("<I", 3) + b"\xff\xfe\x00"
    with pytest.raises(CdrError, match="Header"):
        frame.deserialize(body)


@settings(max_examples=300)
@given(
    index=st.integers(0, len(GARBAGE_TYPES) - 1),
    body=st.binary(max_size=200),
    header=st.sampled_from([b"\x00\x01\x00\x00", b"\x00\x00\x00\x00", b""]),
)
def test_random_bytes_only_ever_raise_cdr_error(index: int, body: bytes, header: bytes) -> None:
    mtype = _GARBAGE_LIB.message(GARBAGE_TYPES[index])
    error = _cdr_error(mtype, header + body)
    if error is not None:
        assert GARBAGE_TYPES[index] in error
        assert "\n" not in error


@settings(max_examples=300)
@given(data=st.data())
def test_mutated_real_messages_only_ever_raise_cdr_error(data: st.DataObject) -> None:
    name = data.draw(st.sampled_from(GARBAGE_TYPES[:6]))
    mtype = _GARBAGE_LIB.message(name)
    good = bytearray(_SAMPLES[name])
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(good) - 1))
        good[pos] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(good)))
    error = _cdr_error(mtype, bytes(good[:cut]))
    assert error is None or name in error


def _cdr_error(mtype: MessageType, data: bytes) -> str | None:
    """The CdrError text ``deserialize`` raises, or None if it decoded; anything else fails."""
    try:
        mtype.deserialize(data)
    except CdrError as exc:
        return str(exc)
    return None


_GARBAGE_LIB = TypeLibrary("jazzy")


def _samples() -> dict[str, bytes]:
    lib = _GARBAGE_LIB
    scan = lib.message("sensor_msgs/msg/LaserScan")
    tf = lib.message("tf2_msgs/msg/TFMessage")
    status = lib.message("action_msgs/msg/GoalStatusArray")
    grid = lib.message("nav_msgs/msg/OccupancyGrid")
    image = lib.message("sensor_msgs/msg/CompressedImage")
    twist = lib.message("geometry_msgs/msg/Twist")
    header = lib.message("std_msgs/msg/Header").make(frame_id="map")
    return {
        "geometry_msgs/msg/Twist": twist.serialize(twist.make()),
        "nav_msgs/msg/OccupancyGrid": grid.serialize(
            grid.make(header=header, data=np.arange(12, dtype=np.int8))
        ),
        "sensor_msgs/msg/LaserScan": scan.serialize(
            scan.make(header=header, ranges=np.ones(5, np.float32))
        ),
        "sensor_msgs/msg/CompressedImage": image.serialize(
            image.make(header=header, format="jpeg", data=np.arange(9, dtype=np.uint8))
        ),
        "tf2_msgs/msg/TFMessage": tf.serialize(
            tf.make(
                transforms=[
                    lib.message("geometry_msgs/msg/TransformStamped").make(
                        header=header, child_frame_id="base_link"
                    )
                ]
            )
        ),
        "action_msgs/msg/GoalStatusArray": status.serialize(
            status.make(status_list=[lib.message("action_msgs/msg/GoalStatus").make(status=2)])
        ),
    }


_SAMPLES = _samples()
