"""Foxglove and MCAP: the bridge's WebSocket server, spoken to by a client written from the
ws-protocol spec (not the SDK), goals published from a client, and recordings read back with
the ``mcap`` reader."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import math
import os
import re
import struct
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from mcap.reader import make_reader

from conftest import wait_until
from rig import FAST_SIM, GENEROUS_TIMEOUT, ROBOT, USER, robot_on_hub
from telebot.apps.foxglove_bridge import (
    COMMANDS,
    GOAL_TOPIC,
    FoxgloveBridge,
    _trigger_problem,
    goal_from_pose_stamped,
)
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import AppConfig, CallSettings
from telebot.robot.grid import OccupancyGrid
from telebot.robot.sim.stack import SimNavStack
from telebot.services.client import RobotClient, connect
from telebot.services.schemas import BRIDGE_SCHEMAS, SCHEMAS
from telebot.services.video.wire import VideoSettings

#: The ws-protocol spec's subprotocol is "foxglove.websocket.v1"; foxglove-sdk servers speak
#: the same protocol as "foxglove.sdk.v1" (and refuse the old name), so a client offers both,
#: as the Foxglove app does.
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


# -- a minimal protobuf wire decoder (the foxglove schemas are protobuf) ---------------------


def _varint(data: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, i


def fields(data: bytes) -> dict[int, list[Any]]:
    """Field number -> values (varints, fixed64 as doubles, fixed32 as uint32, bytes)."""
    out: dict[int, list[Any]] = {}
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        number, wire = key >> 3, key & 7
        value: Any
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 1:
            (value,) = struct.unpack_from("<d", data, i)
            i += 8
        elif wire == 2:
            length, i = _varint(data, i)
            value = data[i : i + length]
            i += length
        elif wire == 5:
            (value,) = struct.unpack_from("<I", data, i)  # fixed32 (the schemas' uint32s)
            i += 4
        else:
            raise AssertionError(f"wire type {wire}")
        out.setdefault(number, []).append(value)
    return out


def position(pose: bytes) -> tuple[float, float]:
    """x, y of a foxglove.Pose (position = 1; Vector3 x = 1, y = 2; zero fields absent)."""
    vector = fields(fields(pose).get(1, [b""])[0])
    return vector.get(1, [0.0])[0], vector.get(2, [0.0])[0]


# -- a ws-protocol client -----------------------------------------------------------------


@dataclass
class WsChannel:
    id: int
    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: str


class FoxgloveWsClient:
    """Just enough of the Foxglove WebSocket protocol (v1): advertise, subscribe, publish,
    call services."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, WsChannel] = {}
        self.messages: dict[str, list[bytes]] = {}
        #: Advertised services by name, as the server described them.
        self.services: dict[str, dict[str, Any]] = {}
        self._subscriptions: dict[int, str] = {}
        self._calls: dict[int, asyncio.Future[tuple[str, bytes]]] = {}
        self._call_ids = 0
        self._reader: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._reader = asyncio.ensure_future(self._read())

    async def stop(self) -> None:
        await self.ws.close()
        if self._reader is not None:
            self._reader.cancel()
            await asyncio.gather(self._reader, return_exceptions=True)

    async def _read(self) -> None:
        async for msg in self.ws:
            if msg.type == aiohttp.WSMsgType.TEXT:
                data = json.loads(msg.data)
                if data["op"] == "serverInfo":
                    self.server_info = data
                elif data["op"] == "advertise":
                    for ch in data["channels"]:
                        self.channels[ch["topic"]] = WsChannel(
                            ch["id"],
                            ch["topic"],
                            ch["encoding"],
                            ch["schemaName"],
                            ch.get("schemaEncoding", ""),
                            ch["schema"],
                        )
                elif data["op"] == "advertiseServices":
                    for service in data["services"]:
                        self.services[service["name"]] = service
                elif data["op"] == "serviceCallFailure":
                    self._answer(data["callId"], ("failure", data["message"].encode()))
            elif msg.type == aiohttp.WSMsgType.BINARY:
                raw = msg.data
                if raw[0] == 0x03:  # serviceCallResponse: service, call, encoding, payload
                    _service, call_id, length = struct.unpack_from("<III", raw, 1)
                    encoding = raw[13 : 13 + length].decode()
                    self._answer(call_id, (encoding, bytes(raw[13 + length :])))
                    continue
                assert raw[0] == 0x01, f"opcode {raw[0]}"  # messageData
                subscription, _timestamp = struct.unpack_from("<IQ", raw, 1)
                topic = self._subscriptions[subscription]
                self.messages.setdefault(topic, []).append(bytes(raw[13:]))

    def _answer(self, call_id: int, answer: tuple[str, bytes]) -> None:
        future = self._calls.pop(call_id, None)
        if future is not None and not future.done():
            future.set_result(answer)

    async def call(self, service: str, request: bytes = b"{}") -> dict[str, Any]:
        """Call ``service`` (JSON) as the Service Call panel does; its JSON response."""
        await wait_until(lambda: service in self.services)
        self._call_ids += 1
        call_id = self._call_ids
        future: asyncio.Future[tuple[str, bytes]] = asyncio.get_running_loop().create_future()
        self._calls[call_id] = future
        header = struct.pack("<BIII", 0x02, self.services[service]["id"], call_id, 4)
        await self.ws.send_bytes(header + b"json" + request)
        encoding, payload = await asyncio.wait_for(future, 30)
        assert encoding == "json", payload.decode()  # not a failure
        answer: dict[str, Any] = json.loads(payload)
        return answer

    async def subscribe(self, *topics: str) -> None:
        subs = []
        for topic in topics:
            sub_id = len(self._subscriptions) + 1
            self._subscriptions[sub_id] = topic
            subs.append({"id": sub_id, "channelId": self.channels[topic].id})
        await self.ws.send_str(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def advertise(self, channel_id: int, topic: str, encoding: str, schema_name: str) -> None:
        channel = {
            "id": channel_id,
            "topic": topic,
            "encoding": encoding,
            "schemaName": schema_name,
        }
        await self.ws.send_str(json.dumps({"op": "advertise", "channels": [channel]}))

    async def publish(self, channel_id: int, payload: bytes) -> None:
        await self.ws.send_bytes(struct.pack("<BI", 0x01, channel_id) + payload)


@contextlib.asynccontextmanager
async def ws_client(url: str) -> AsyncIterator[FoxgloveWsClient]:
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(url, protocols=SUBPROTOCOLS) as ws,
    ):
        assert ws.protocol in SUBPROTOCOLS
        client = FoxgloveWsClient(ws)
        client.start()
        try:
            yield client
        finally:
            await client.stop()


# -- a robot on a memory hub, and a user ----------------------------------------------------


@contextlib.asynccontextmanager
async def robot_and_user(base: Path) -> AsyncIterator[tuple[SimNavStack, RobotClient]]:
    hub = MemoryHub(seed=3)
    video = VideoSettings(width=160, height=120, max_fps=10, quality=60, min_quality=30)
    config = AppConfig(call=CallSettings(timeout=GENEROUS_TIMEOUT))
    async with (
        robot_on_hub(base, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM, video=video) as (
            nav,
            _,
            _,
            _,
        ),
        MemoryTransport(hub, "user") as transport,
        connect(ROBOT, home=base / "user", config=config, transport=transport) as client,
    ):
        yield nav, client


async def test_foxglove_client_gets_map_pose_and_video_with_their_schemas(tmp_path: Path) -> None:
    async with (
        robot_and_user(tmp_path) as (nav, client),
        FoxgloveBridge(client, port=0) as bridge,
        ws_client(bridge.url) as fox,
    ):
        await wait_until(lambda: {"/map", "/pose", "/camera"} <= fox.channels.keys())
        schemas = {t: fox.channels[t].schema_name for t in ("/map", "/pose", "/camera", "/plan")}
        assert schemas == {
            "/map": "foxglove.Grid",
            "/pose": "foxglove.PoseInFrame",
            "/camera": "foxglove.CompressedImage",
            "/plan": "foxglove.PosesInFrame",
        }
        for topic in schemas:
            channel = fox.channels[topic]
            assert channel.encoding == "protobuf" and channel.schema_encoding == "protobuf"
            assert base64.b64decode(channel.schema)  # a FileDescriptorSet
        assert fox.channels["/telebot/safety"].encoding == "json"
        # No recording and nobody showing /camera: the robot is not asked for video.
        assert not client.video_feed.wanted
        await fox.subscribe("/map", "/pose", "/camera")
        await wait_until(lambda: client.video_feed.wanted)
        await wait_until(lambda: all(fox.messages.get(t) for t in ("/map", "/pose", "/camera")))

        grid = fields(fox.messages["/map"][-1])
        # Grid: frame_id 2, column_count 4, row_stride 6, cell_stride 7, data 9.
        assert bridge.map is not None
        cells = bridge.map.grid  # as the map transfer delivered it
        assert grid[2] == [b"map"]
        assert grid[4] == [cells.width] and grid[6] == [cells.width]
        assert len(grid[9][0]) == cells.width * cells.height
        assert grid[9][0] == cells.data.tobytes()

        pose = fields(fox.messages["/pose"][-1])  # PoseInFrame: frame_id 2, pose 3
        assert pose[2] == [b"map"]
        x, y = position(pose[3][0])
        truth = nav.true_pose
        assert math.hypot(x - truth.x, y - truth.y) < 0.5

        image = fields(fox.messages["/camera"][-1])  # CompressedImage: data 2, format 3
        assert image[3] == [b"jpeg"]
        assert image[2][0][:2] == b"\xff\xd8"  # a JPEG, as the robot sent it


async def test_a_map_that_changes_is_logged_again_on_map(tmp_path: Path) -> None:
    async with robot_and_user(tmp_path) as (nav, client), FoxgloveBridge(client) as bridge:
        await wait_until(lambda: bridge.counts.get("/map") == 1, timeout=15)
        grid = nav.map()
        data = grid.data.copy()
        row, col = grid.cell_of(9.5, 4.0)
        data[row - 5 : row + 6, col - 5 : col + 6] = 100  # SLAM found a wall
        nav.set_map(OccupancyGrid(data, grid.resolution, grid.origin_x, grid.origin_y))
        # Telemetry says the map changed: the bridge's map follower fetches and logs it.
        await wait_until(lambda: bridge.counts.get("/map") == 2, timeout=15)
        assert bridge.map is not None and bridge.map.version == 1
        assert bridge.map.grid.value_at(9.5, 4.0) == 100


async def test_a_goal_published_from_foxglove_drives_the_robot(tmp_path: Path) -> None:
    async with (
        robot_and_user(tmp_path) as (nav, client),
        FoxgloveBridge(client, port=0) as bridge,
        ws_client(bridge.url) as fox,
    ):
        assert "clientPublish" in (await _server_info(fox))["capabilities"]
        assert (await client.arm(timeout=10)).ok
        start = nav.true_pose
        goal = {"x": start.x + 1.0, "y": start.y}
        await fox.advertise(7, "/goal_pose", "json", "geometry_msgs/msg/PoseStamped")
        message = {
            "header": {"frame_id": "map", "stamp": {"sec": 0, "nanosec": 0}},
            "pose": {
                "position": {**goal, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            },
        }
        await fox.publish(7, json.dumps(message).encode())
        # Through the normal goal path: the robot takes it and drives there.
        await wait_until(lambda: bridge.goals_received == 1)
        await wait_until(
            lambda: math.hypot(nav.true_pose.x - goal["x"], nav.true_pose.y - goal["y"]) < 0.3,
            timeout=15,
        )
        assert bridge.goals_refused == 0
        # Garbage on /goal_pose is refused and never reaches the robot.
        await fox.publish(7, b"not json")
        await wait_until(lambda: bridge.goals_refused == 1)


def pose_stamped(x: float, y: float) -> bytes:
    """A ``geometry_msgs/msg/PoseStamped`` as Foxglove's 3D panel publishes it (json)."""
    message = {
        "header": {"frame_id": "map", "stamp": {"sec": 0, "nanosec": 0}},
        "pose": {
            "position": {"x": x, "y": y, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        },
    }
    return json.dumps(message).encode()


async def test_a_foxglove_user_arms_cancels_and_stops_through_services(tmp_path: Path) -> None:
    async with (
        robot_and_user(tmp_path) as (nav, client),
        FoxgloveBridge(client, port=0) as bridge,
        ws_client(bridge.url) as fox,
    ):
        assert "services" in (await _server_info(fox))["capabilities"]
        await wait_until(lambda: {f"/telebot/{what}" for what in COMMANDS} <= fox.services.keys())
        arm = fox.services["/telebot/arm"]
        assert arm["type"] == "telebot.Trigger"
        assert arm["request"]["schemaName"] == "telebot.TriggerRequest"
        assert arm["response"]["schemaName"] == "telebot.TriggerResult"

        def safety() -> Any:
            return client.latest_safety.value

        def away(start: Any) -> float:
            return math.hypot(nav.true_pose.x - start.x, nav.true_pose.y - start.y)

        def standing() -> bool:
            return abs(nav.velocity().linear) < 1e-3 and abs(nav.velocity().angular) < 1e-3

        await wait_until(lambda: safety() is not None)
        assert not safety().armed  # the robot starts stopped: nothing but a user arms it
        refused = await fox.call("/telebot/arm", b'{"force": true}')
        assert not refused["ok"] and "takes no fields" in refused["text"]
        assert await fox.call("/telebot/arm") == {"ok": True, "text": "armed", "code": "ok"}
        await wait_until(lambda: safety().armed and safety().holder == USER)

        # A goal from the 3D panel now drives the robot; cancel ends it, still armed.
        await fox.advertise(7, GOAL_TOPIC, "json", "geometry_msgs/msg/PoseStamped")
        start = nav.true_pose
        far = (start.x + 8.0, start.y)
        await fox.publish(7, pose_stamped(*far))
        await wait_until(lambda: away(start) > 0.3, timeout=15)
        cancelled = await fox.call("/telebot/cancel")
        assert cancelled["ok"] and cancelled["text"] == "cancelled", cancelled
        await wait_until(standing, timeout=15)
        assert (
            safety().armed and math.hypot(nav.true_pose.x - far[0], nav.true_pose.y - far[1]) > 1.0
        )

        # Stop: the robot stops and stays stopped (latched) until armed again.
        start = nav.true_pose
        await fox.publish(7, pose_stamped(*far))
        await wait_until(lambda: away(start) > 0.3, timeout=15)
        stopped = await fox.call("/telebot/stop")
        assert stopped["ok"], stopped
        await wait_until(lambda: not safety().armed and standing(), timeout=15)
        assert math.hypot(nav.true_pose.x - far[0], nav.true_pose.y - far[1]) > 1.0
        assert bridge.goals_received == 2 and bridge.goals_refused == 0

        # Release and take the drive back.
        assert (await fox.call("/telebot/release"))["ok"]
        await wait_until(lambda: safety().holder is None)
        assert (await fox.call("/telebot/take"))["ok"]
        await wait_until(lambda: safety().holder == USER)
        # What the services did is on /telebot/safety, as the page's buttons are.
        await wait_until(lambda: bridge.counts.get("/telebot/commands", 0) >= 5)


async def test_a_megabyte_of_garbage_on_goal_pose_is_refused_in_a_short_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="telebot.apps.foxglove_bridge")
    huge_number = json.dumps({"pose": {"position": {"x": "9" * 2**20 + "x", "y": 0}}})
    huge_key = json.dumps({"pose": {"X" * 2**20: 1}})
    garbage = os.urandom(2**20)
    async with (
        robot_and_user(tmp_path) as (_, client),
        FoxgloveBridge(client, port=0) as bridge,
        ws_client(bridge.url) as fox,
    ):
        await wait_until(lambda: "/telebot/goal" in fox.channels)
        await fox.subscribe("/telebot/goal")
        await fox.advertise(7, GOAL_TOPIC, "json", "geometry_msgs/msg/PoseStamped")
        await fox.advertise(8, GOAL_TOPIC, "cdr", "geometry_msgs/msg/PoseStamped")
        sent = [(7, huge_number.encode()), (7, huge_key.encode()), (7, garbage), (8, garbage)]
        for channel, payload in sent:
            assert len(payload) >= 2**20
            await fox.publish(channel, payload)
        await wait_until(lambda: len(fox.messages.get("/telebot/goal", [])) == len(sent))
        assert bridge.goals_refused == len(sent)
    refusals = fox.messages["/telebot/goal"]
    for raw in refusals:
        assert len(raw) < 1024, raw[:200]
        refusal = json.loads(raw)
        assert refusal["kind"] == "refused" and "PoseStamped" in refusal["text"]
    assert "characters)" in json.loads(refusals[0])["text"]  # said how long it was
    lines = [r.getMessage() for r in caplog.records if "was refused" in r.getMessage()]
    assert len(lines) == len(sent)
    assert all(len(line) < 1024 for line in lines), [len(line) for line in lines]


README = Path(__file__).resolve().parent.parent / "README.md"


def readme_foxglove_tables() -> tuple[dict[str, str], set[str]]:
    """The README's Foxglove section: its channel table (topic -> schema) and its services."""
    section = README.read_text().split("### Foxglove and MCAP", 1)[1].split("\n### ", 1)[0]
    topics: dict[str, str] = {}
    services: set[str] = set()
    for line in section.splitlines():
        if row := re.match(r"\| `(/[^`]*)` \| `([^`]*)` \|", line):
            topics[row[1]] = row[2]
        elif row := re.match(r"\| `(/telebot/[a-z]+)` \| [^`]", line):
            services.add(row[1])
    return topics, services


async def test_the_bridge_advertises_the_readme_topics_with_named_json_schemas(
    tmp_path: Path,
) -> None:
    readme_topics, readme_services = readme_foxglove_tables()
    assert readme_topics and readme_services
    async with (
        robot_and_user(tmp_path) as (_, client),
        FoxgloveBridge(client, port=0) as bridge,
        ws_client(bridge.url) as fox,
    ):
        await wait_until(lambda: len(fox.channels) >= len(readme_topics))
        await wait_until(lambda: len(fox.services) >= len(readme_services))
        advertised = {topic: channel.schema_name for topic, channel in fox.channels.items()}
        assert advertised == readme_topics
        assert set(fox.services) == readme_services
        for name, schema in BRIDGE_SCHEMAS.items():
            channel = fox.channels[f"/telebot/{name}"]
            assert (channel.encoding, channel.schema_encoding) == ("json", "jsonschema")
            assert channel.schema_name == schema["title"] and schema["title"].startswith("telebot.")
            assert json.loads(channel.schema) == schema
        # One definition: the robot's own recordings name their telemetry the same way.
        assert (
            json.loads(fox.channels["/telebot/telemetry"].schema) == SCHEMAS[("telemetry", "out")]
        )


async def _server_info(fox: FoxgloveWsClient) -> dict[str, Any]:
    await wait_until(lambda: bool(fox.server_info))
    return fox.server_info


def test_goal_decoding_json_and_cdr() -> None:
    from telebot.rosmsg.types import TypeLibrary

    pose_type = TypeLibrary().message("geometry_msgs/msg/PoseStamped")
    yaw = 0.7
    msg = pose_type.make(
        pose={
            "position": {"x": 1.5, "y": -2.0, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
        }
    )
    x, y, got = goal_from_pose_stamped(pose_type.serialize(msg), "cdr")
    assert (x, y) == (1.5, -2.0) and got == pytest.approx(yaw)
    text = json.dumps({"pose": {"position": {"x": 1, "y": 2}, "orientation": {}}}).encode()
    assert goal_from_pose_stamped(text, "json") == (1.0, 2.0, None)
    for data, encoding in ((b"{}", "json"), (b"\x00\x01", "cdr"), (b"", "ros1")):
        with pytest.raises(ValueError, match=r"PoseStamped|encoding"):
            goal_from_pose_stamped(data, encoding)


def read_mcap(path: Path) -> tuple[dict[str, str], dict[str, list[tuple[int, bytes]]]]:
    """(topic -> schema name, topic -> [(log_time, data)]) in file order."""
    schemas: dict[str, str] = {}
    messages: dict[str, list[tuple[int, bytes]]] = {}
    times: list[int] = []
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None  # a finished file
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            schemas[channel.topic] = schema.name if schema is not None else ""
            messages.setdefault(channel.topic, []).append((message.log_time, message.data))
            times.append(message.log_time)
    assert times == sorted(times), "message log times out of order"
    return schemas, messages


async def test_a_recording_reads_back_with_the_mcap_reader(tmp_path: Path) -> None:
    out = tmp_path / "session.mcap"
    async with (
        robot_and_user(tmp_path) as (nav, client),
        FoxgloveBridge(client, mcap=out) as bridge,
    ):
        assert (await client.arm(timeout=10)).ok
        start = nav.true_pose
        goal = asyncio.ensure_future(client.goto(start.x + 1.0, start.y, timeout=20))
        reply = await client.chat("where", timeout=10)
        assert reply.ok
        assert (await goal).status == "succeeded"
        await wait_until(lambda: all(bridge.counts.get(t) for t in ("/map", "/camera", "/plan")))
        await client.stop(timeout=10)
    schemas, messages = read_mcap(out)
    assert schemas["/map"] == "foxglove.Grid"
    assert schemas["/pose"] == "foxglove.PoseInFrame"
    assert schemas["/plan"] == "foxglove.PosesInFrame"
    assert schemas["/camera"] == "foxglove.CompressedImage"
    assert schemas["/telebot/chat"] == "telebot.ChatEvent"
    assert schemas["/telebot/telemetry"] == "telebot.Telemetry"
    for topic in ("/map", "/pose", "/tf", "/plan", "/camera", "/telebot/telemetry"):
        assert messages.get(topic), topic
    chat = [json.loads(data) for _, data in messages["/telebot/chat"]]
    assert {"kind": "chat", "command": "where"} in chat
    assert any(m["kind"] == "chat_reply" and m["final"] and m["ok"] for m in chat)
    safety = [json.loads(data) for _, data in messages["/telebot/safety"]]
    events = {m["event"] for m in safety}
    assert {"state", "safety", "safety_ack"} <= events
    assert any(m["event"] == "safety" and m["request"] == "stop" for m in safety)
    assert any(m["event"] == "state" and m["armed"] for m in safety)
    # The state's fields as on the wire (telebot.SafetyEvent): the words under "reason".
    state = next(m for m in safety if m["event"] == "state")
    assert set(state) == {"event", "armed", "reason", "holder", "cap", "blocked", "code"}
    goals = [json.loads(data) for _, data in messages["/telebot/goal"]]
    assert goals[0]["kind"] == "goal"
    assert goals[-1]["kind"] == "goal_update" and goals[-1]["status"] == "succeeded"
    commands = [json.loads(data)["kind"] for _, data in messages["/telebot/commands"]]
    # arm first, stop last; the goal and "where" ran side by side.
    assert commands[0] == commands[-1] == "safety"
    assert sorted(commands[1:-1]) == ["chat", "goal"]


async def test_relayed_topics_are_channels_with_their_ros2msg_schema(tmp_path: Path) -> None:
    async with (
        robot_and_user(tmp_path) as (_, client),
        FoxgloveBridge(client, port=0, topics=["/scan", "/no_such_topic"]) as bridge,
        ws_client(bridge.url) as fox,
    ):
        await wait_until(lambda: {"/scan", "/foxglove/scan"} <= fox.channels.keys())
        scan = fox.channels["/scan"]
        assert (scan.encoding, scan.schema_encoding) == ("cdr", "ros2msg")
        assert scan.schema_name == "sensor_msgs/msg/LaserScan"
        assert "float32[] ranges" in scan.schema
        assert fox.channels["/foxglove/scan"].schema_name == "foxglove.LaserScan"
        await fox.subscribe("/scan", "/foxglove/scan")
        await wait_until(
            lambda: bool(fox.messages.get("/scan") and fox.messages.get("/foxglove/scan"))
        )
        from telebot.rosmsg.types import TypeLibrary

        relayed = (
            TypeLibrary()
            .message("sensor_msgs/msg/LaserScan")
            .deserialize(fox.messages["/scan"][-1])
        )
        assert len(relayed.ranges) > 0
        laser = fields(fox.messages["/foxglove/scan"][-1])  # LaserScan: frame_id 2, ranges 6
        assert laser[6]  # packed doubles
        # An unknown topic is refused by the robot: said on /telebot/connection, nothing breaks.
        await wait_until(lambda: bool(bridge.counts.get("/telebot/connection")))


async def test_the_foxglove_command_serves_until_stopped(tmp_path: Path) -> None:
    from telebot.apps.foxglove_cli import serve_foxglove

    hub = MemoryHub(seed=4)
    config = AppConfig(call=CallSettings(timeout=GENEROUS_TIMEOUT))
    said: list[str] = []
    stop = asyncio.Event()
    async with (
        robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM),
        MemoryTransport(hub, "user") as transport,
    ):
        serving = asyncio.ensure_future(
            serve_foxglove(
                ROBOT,
                home=tmp_path / "user",
                config=config,
                port=0,
                record=tmp_path / "also.mcap",
                stop=stop,
                announce=said.append,
                transport=transport,
            )
        )
        await wait_until(lambda: bool(said) or serving.done())
        url = said[0].split("connection to ", 1)[1].split(" ")[0]
        async with ws_client(url) as fox:
            await wait_until(lambda: "/pose" in fox.channels)
            assert fox.server_info["name"] == f"telebot {ROBOT}"
            await fox.subscribe("/pose")
            await wait_until(lambda: bool(fox.messages.get("/pose")))
        stop.set()
        assert await serving == 0
    _, messages = read_mcap(tmp_path / "also.mcap")  # --record beside the server
    assert messages.get("/pose")


@pytest.mark.parametrize(
    "payload",
    [
        b"[" * 100_000 + b"]" * 100_000,  # deeper than Python's JSON parser goes
        b'{"pose": {"position": {"x": 1, "y": 2}, "orientation": [0, 0, 0, 1]}}',
        b'{"pose": {"position": {"x": 1, "y": 2}, "orientation": 7}}',
        b'{"pose": [1, 2]}',
    ],
    ids=["nested", "orientation-list", "orientation-number", "pose-list"],
)
def test_a_goal_or_service_request_of_the_wrong_shape_is_a_short_refusal(payload: bytes) -> None:
    with pytest.raises(ValueError, match="not a JSON PoseStamped") as refused:
        goal_from_pose_stamped(payload, "json")
    assert len(str(refused.value)) < 400
    problem = _trigger_problem(payload)
    assert problem is not None and len(problem) < 600
