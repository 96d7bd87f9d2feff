"""The topic relay: robot topics reach the user as CDR over the call.

Wire format (sans-IO), then a simulated robot served to users on a memory hub (list, rate
limit, latest only, unknown topics, refusals, flooding, the end of the call), then across
processes: ``telebot-sim`` and ``telebot-robot run --robot ros2``.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import threading
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import ROBOT, USER, wait_until
from rig import Daemon, start_telebot_sim
from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings, RelaySettings, ServiceSettings, SimSettings
from telebot.errors import ProtocolError, RelayRefused, UnknownTopic
from telebot.identity import ContactBook, KnownRobots, Role, create_paired_homes
from telebot.robot.nav import SourceTopic
from telebot.robot.ros2.node import Ros2Node
from telebot.robot.sim.stack import SimNavStack
from telebot.rosmsg.types import TypeLibrary
from telebot.services.client import RobotClient
from telebot.services.relay.robot import RelayService, near_topics
from telebot.services.relay.wire import (
    MAX_LIST_TEXT,
    ListRequest,
    RelayEnded,
    RelayRefusal,
    Started,
    StartRequest,
    Stopped,
    StopRequest,
    TopicInfo,
    TopicList,
    allowed_topic,
    decode_relay_message,
    encode_topic_list,
    fragment_message,
    relay_reassembler,
)
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver

LIB = TypeLibrary()

# --------------------------------------------------------------------------- sans-IO

INFO = TopicInfo("/scan", "sensor_msgs/msg/LaserScan", "float32[] ranges\n")


@pytest.mark.parametrize(
    "message",
    [
        ListRequest(1),
        TopicList(2, 0, 1, (INFO,)),
        StartRequest(3, "/scan", 5.0, True),
        StartRequest(4, "/odom"),
        Started(3, 7, INFO),
        RelayRefusal(3, "unknown_topic", "no topic '/scna'", ("/scan",)),
        StopRequest(5, 7),
        Stopped(5, 7, 100, 3),
        RelayEnded(7, "the source closed"),
    ],
)
def test_messages_round_trip(message: object) -> None:
    assert decode_relay_message(message.encode()) == message  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("payload", "error"),
    [
        (b"\x00\x01", "expected a JSON text datagram"),
        ("[]", "expected a JSON object"),
        ('{"type": "list"}', "'id' must be an integer"),
        ('{"type": "warp", "id": 1}', "unknown type 'warp'"),
        ('{"type": "start", "id": 1, "topic": ""}', "'topic' must be text of 1..256"),
        ('{"type": "start", "id": 1, "topic": "/a", "rate": -1}', "'rate' must be null"),
        ('{"type": "start", "id": 1, "topic": "/a", "rate": 1e9}', "'rate' must be null"),
        ('{"type": "start", "id": 1, "topic": "/a", "latest_only": 1}', "'latest_only'"),
        ('{"type": "stop", "id": 1, "stream": 0}', "'stream' must be an integer"),
        ('{"type": "topics", "id": 1, "part": 2, "parts": 2, "topics": []}', "'part'"),
        ('{"type": "topics", "id": 1, "part": 0, "parts": 1, "topics": [3]}', "a topic must be"),
        ('{"type": "refused", "id": 1, "code": "x", "text": "", "near": "a"}', "'near'"),
    ],
)
def test_garbage_is_a_one_line_protocol_error(payload: str | bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match="relay message") as caught:
        decode_relay_message(payload)
    assert error in str(caught.value) and "\n" not in str(caught.value)


def test_a_long_topic_list_comes_in_parts_that_each_fit_a_datagram() -> None:
    topics = [TopicInfo(f"/robot/t{i}", "sensor_msgs/msg/LaserScan", "x" * 3000) for i in range(40)]
    parts = encode_topic_list(9, topics)
    assert len(parts) > 1 and all(len(p) <= MAX_LIST_TEXT for p in parts)
    decoded = [decode_relay_message(p) for p in parts]
    assert all(isinstance(d, TopicList) and d.parts == len(parts) for d in decoded)
    assert [t for d in decoded for t in d.topics] == topics  # type: ignore[union-attr]


def test_a_large_message_is_fragmented_and_rebuilt_byte_for_byte() -> None:
    data = bytes(range(256)) * 4000  # ~1 MB: many fragments
    fragments = fragment_message(3, 1, 1700000000.25, data, seq=0, interval=0.5)
    assert len(fragments) > 30 and all(len(f) <= 32768 for f in fragments)
    reassembler = relay_reassembler()
    done = [reassembler.on_datagram(f, 1.0) for f in reversed(fragments)]
    complete = done[-1]
    assert complete is not None and complete.data == data
    assert complete.camera == "3" and complete.capture_time == pytest.approx(1700000000.25)
    # A video fragment is not a relay fragment (and the other way round).
    assert reassembler.on_datagram(b"\x01\x01" + fragments[0][2:], 1.0) is None
    assert reassembler.stats.malformed == 1


def test_permissions_follow_the_globs_of_the_role() -> None:
    settings = RelaySettings(observer=["/scan", "/*/image/compressed"], driver=["*"])
    assert allowed_topic(settings, Role.OBSERVER, "/scan")
    assert allowed_topic(settings, Role.OBSERVER, "/navcam/image/compressed")
    assert not allowed_topic(settings, Role.OBSERVER, "/cmd_vel")
    assert allowed_topic(settings, Role.DRIVER, "/cmd_vel")
    assert allowed_topic(settings, Role.ADMIN, "/anything/at/all")
    assert near_topics("/scna", ["/scan", "/odom", "/scan_filtered"])[0] == "/scan"


# --------------------------------------------------------------------------- over a call

FAST = SimSettings(map="small", control_hz=50)


class FloodingSim(SimNavStack):
    """The simulator plus ``/flood``: 1 MB messages from a thread, as fast as it can."""

    def topics(self) -> list[SourceTopic]:
        return [*super().topics(), SourceTopic("/flood", "sensor_msgs/msg/PointCloud2", "")]

    def subscribe_topic(
        self, name: str, callback: Callable[[bytes, float], None]
    ) -> contextlib.AbstractContextManager[None] | object:
        if name != "/flood":
            return super().subscribe_topic(name, callback)
        done = threading.Event()
        self.flooded = 0

        def flood() -> None:
            blob = b"\x00\x01\x00\x00" + bytes(1_000_000)
            while not done.is_set():
                callback(blob, 0.0)
                self.flooded += 1
                done.wait(0.002)

        threading.Thread(target=flood, daemon=True).start()

        class Handle:
            def close(self) -> None:
                done.set()

        return Handle()


class VanishingSim(SimNavStack):
    """The simulator plus ``/blip``, a topic whose source goes away when ``vanish`` is set."""

    vanish = threading.Event()

    def topics(self) -> list[SourceTopic]:
        blip = [] if self.vanish.is_set() else [SourceTopic("/blip", "std_msgs/msg/Empty", "")]
        return [*super().topics(), *blip]

    def subscribe_topic(
        self, name: str, callback: Callable[[bytes, float], None]
    ) -> contextlib.AbstractContextManager[None] | object:
        if name != "/blip":
            return super().subscribe_topic(name, callback)
        callback(b"\x00\x01\x00\x00", 0.0)  # one message, then silence

        class Handle:
            def close(self) -> None:
                pass

        return Handle()


@dataclass
class Rig:
    nav: SimNavStack
    server: RobotServer
    client: RobotClient
    audit: Path


@contextlib.asynccontextmanager
async def robot_in_a_call(
    base: Path, *, role: Role = Role.DRIVER, nav_class: type[SimNavStack] = SimNavStack
) -> AsyncIterator[Rig]:
    """A simulated robot with its safety supervisor (audit log) in a call with one user."""
    robot_id, user_id = create_paired_homes(base, ROBOT, USER, role=role)
    loop = asyncio.get_running_loop()
    nav = nav_class.from_settings(FAST, now=loop.time())
    audit = base / "audit.jsonl"
    hub = MemoryHub(seed=3)
    settings = CallSettings(timeout=2.0)
    with SafetyDriver(nav, timeout=2.0, max_speed=1.0, audit_path=audit) as safety:
        server = RobotServer(nav, ServiceSettings(), control_hz=50, safety=safety)
        await server.prepare()
        async with (
            MemoryTransport(hub, "robot") as robot_transport,
            MemoryTransport(hub, "user") as user_transport,
            RobotEndpoint(
                robot_transport, robot_id, ContactBook.load(base / "robot"), settings=settings
            ) as robot,
            UserEndpoint(
                user_transport, user_id, KnownRobots.load(base / "user"), settings=settings
            ) as user,
        ):
            server.attach(robot)
            runner = asyncio.create_task(server.run(), name="robot-loop")
            try:
                call = await user.call(ROBOT)
                yield Rig(nav, server, RobotClient(call), audit)
                with contextlib.suppress(Exception):
                    await call.hangup()
            finally:
                runner.cancel()
                await asyncio.gather(runner, return_exceptions=True)


def relay_service(rig: Rig) -> RelayService:
    (opened,) = rig.server.open.values()
    service = opened.get("relay")
    assert isinstance(service, RelayService)
    return service


async def test_a_user_lists_the_simulators_topics_with_types_and_schemas(tmp_path: Path) -> None:
    async with robot_in_a_call(tmp_path) as rig:
        topics = {t.name: t for t in await rig.client.topics()}
        assert {"/scan", "/odom", "/amcl_pose", "/tf", "/plan", "/battery_state", "/map"} <= set(
            topics
        )
        assert "/navcam/image/compressed" in topics
        scan = topics["/scan"]
        assert scan.type == "sensor_msgs/msg/LaserScan" and scan.encoding == "cdr"
        assert scan.schema.startswith("std_msgs/Header header\n")
        assert "MSG: builtin_interfaces/Time" in scan.schema


async def test_a_relayed_scan_arrives_as_cdr_at_the_rate_asked_for(tmp_path: Path) -> None:
    async with robot_in_a_call(tmp_path) as rig:
        stamps: list[float] = []
        async with rig.client.relay("/odom", rate=2.0) as odom:
            assert odom.info.type == "nav_msgs/msg/Odometry"
            async for message in odom:
                msg = LIB.message(message.type).deserialize(message.data)
                assert msg.child_frame_id == "base_link" and message.topic == "/odom"
                stamps.append(message.stamp)
                if len(stamps) == 4:
                    break
            service = relay_service(rig)
            (relay,) = service.relays.values()
            # The simulator publishes odometry each step (50 Hz): the rest were dropped.
            await wait_until(lambda: relay.dropped > 10)
        gaps = [b - a for a, b in itertools.pairwise(stamps)]
        # 2/s, not the 50/s the robot has: on average (one gap may be short when a loaded
        # machine delays a message and the next one is due soon after).
        assert sum(gaps) / len(gaps) > 0.3, gaps
        await wait_until(lambda: not service.relays)  # leaving the block stopped it
        async with rig.client.relay("scan") as scans:  # a relative name is the root's
            message = await anext(aiter(scans))
            scan = LIB.message("sensor_msgs/msg/LaserScan").deserialize(message.data)
            assert len(scan.ranges) > 100 and message.data[:4] == b"\x00\x01\x00\x00"


async def test_latest_only_keeps_the_newest_message_for_a_slow_reader(tmp_path: Path) -> None:
    async with (
        robot_in_a_call(tmp_path) as rig,
        rig.client.relay("/odom", latest_only=True) as newest,
        rig.client.relay("/amcl_pose") as all_of_them,
    ):
        await wait_until(lambda: newest.received >= 5 and all_of_them.received >= 5)
        first = await anext(aiter(newest))
        # The slow reader skipped to the present; without latest only it reads the oldest.
        assert newest.dropped >= 4
        assert all_of_them.dropped == 0
        oldest = await anext(aiter(all_of_them))
        assert oldest.stamp < first.stamp


async def test_an_unknown_topic_is_refused_with_near_matches(tmp_path: Path) -> None:
    async with robot_in_a_call(tmp_path) as rig:
        with pytest.raises(UnknownTopic, match="/scan") as caught:
            async with rig.client.relay("/scna"):
                pass
        assert caught.value.near[0] == "/scan" and "did you mean" in str(caught.value)


async def test_an_observer_is_refused_a_topic_not_allowed_and_the_refusal_is_audited(
    tmp_path: Path,
) -> None:
    async with robot_in_a_call(tmp_path, role=Role.OBSERVER) as rig:
        listed = {t.name for t in await rig.client.topics()}
        assert "/scan" in listed and "/navcam/image/compressed" not in listed
        with pytest.raises(RelayRefused, match="observers may not relay") as caught:
            async with rig.client.relay("/navcam/image/compressed"):
                pass
        assert caught.value.code == "topic_not_allowed"
        async with rig.client.relay("/scan") as scans:  # a safe topic is fine
            assert (await anext(aiter(scans))).type == "sensor_msgs/msg/LaserScan"
        records = [json.loads(line) for line in rig.audit.read_text().splitlines()]
        refused = [r for r in records if r["what"] == "relay /navcam/image/compressed"]
        assert refused and refused[0]["outcome"] == "refused" and refused[0]["role"] == "observer"


async def test_a_relay_ends_with_the_call(tmp_path: Path) -> None:
    async with robot_in_a_call(tmp_path) as rig:
        async with rig.client.relay("/scan") as scans:
            await anext(aiter(scans))
            topics = rig.nav._topics
            assert topics is not None
            assert topics._topics["/scan"].subscribers
            await rig.client.call.hangup()
            async for _ in scans:  # drains what came, then ends
                pass
            assert scans.ended and scans.end_reason == "the call ended"
        await wait_until(lambda: not rig.server.open)
        assert not topics._topics["/scan"].subscribers  # the robot unsubscribed


async def test_a_relay_whose_topic_vanishes_ends_for_the_user(tmp_path: Path) -> None:
    VanishingSim.vanish = threading.Event()
    async with robot_in_a_call(tmp_path, nav_class=VanishingSim) as rig:
        async with rig.client.relay("/blip") as blips:
            await anext(aiter(blips))
            VanishingSim.vanish.set()  # the publisher is gone from the robot's network
            async with asyncio.timeout(30):  # a hang guard: without the end this never ends
                async for _ in blips:
                    pass
            assert blips.ended and "/blip is gone" in blips.end_reason
        await wait_until(lambda: not relay_service(rig).relays)


async def test_a_flooding_topic_is_rate_limited_and_counted_and_stops_still_go_through(
    tmp_path: Path,
) -> None:
    async with (
        robot_in_a_call(tmp_path, nav_class=FloodingSim) as rig,
        rig.client.relay("/flood") as flood,
        rig.client.relay("/scan") as scans,
    ):
        await wait_until(lambda: flood.received >= 2)
        for _ in range(5):  # every stop acknowledged while megabytes flood in
            ack = await rig.client.stop(timeout=5.0)
            assert ack.ok
        assert (await anext(aiter(scans))).type == "sensor_msgs/msg/LaserScan"
        service = relay_service(rig)
        relay = next(r for r in service.relays.values() if r.info.name == "/flood")
        nav = rig.nav
        assert isinstance(nav, FloodingSim)
        # Far more was offered than sent: the rest was dropped and counted.
        await wait_until(lambda: relay.dropped > 10)
        assert relay.sent < nav.flooded


# --------------------------------------------------------------------------- across processes


@pytest.mark.zenoh
@pytest.mark.timeout(180)
async def test_a_topic_on_the_ros2_robots_network_arrives_with_the_same_bytes(
    tmp_path: Path,
) -> None:
    """telebot-sim (its router), ``telebot-robot run --robot ros2``, and a ROS node of our
    own that publishes a point cloud (large: fragmented) the daemon has never heard of."""
    daemon = Daemon(tmp_path)
    sim, router = start_telebot_sim(daemon)
    node: Ros2Node | None = None
    stop = threading.Event()
    try:
        daemon.start()
        node = Ros2Node(name="lidar", connect=[router], library=LIB)
        cloud_type = LIB.message("sensor_msgs/msg/PointCloud2")
        publisher = node.publisher("/points", cloud_type)
        clouds = [
            cloud_type.serialize(
                cloud_type.make(
                    height=1,
                    width=20_000,
                    point_step=4,
                    row_step=80_000,
                    data=np.full(80_000, i, dtype=np.uint8),
                    is_dense=True,
                )
            )
            for i in range(3)
        ]

        def publish() -> None:
            i = 0
            while not stop.wait(0.1):
                publisher.publish_cdr(clouds[i % 3])
                i += 1

        threading.Thread(target=publish, daemon=True).start()
        async with daemon.connect() as user:

            async def listed() -> dict[str, TopicInfo]:
                return {t.name: t for t in await user.topics()}

            topics = await listed()
            for _ in range(50):  # the robot's node learns of ours through the graph
                if "/points" in topics:
                    break
                topics = await listed()
            assert topics["/points"].type == "sensor_msgs/msg/PointCloud2"
            assert "MSG: sensor_msgs/PointField" in topics["/points"].schema
            assert "/odom" in topics and "/scan" in topics  # telebot-sim's own
            got: list[bytes] = []
            async with user.relay("/points") as points:
                async for message in points:
                    got.append(message.data)
                    if len(got) == 3:
                        break
            assert all(data in clouds for data in got)  # byte for byte, fragmented and rebuilt
            assert len(got[0]) > 80_000
            async with user.relay("/scan", rate=5) as scans:
                scan = await anext(aiter(scans))
                assert LIB.message(scan.type).deserialize(scan.data).range_max > 0
    finally:
        stop.set()
        if node is not None:
            node.close()
        daemon.stop()
        sim.stop(graceful=True)


async def test_the_topics_chat_command_lists_what_the_caller_may_relay(tmp_path: Path) -> None:
    async with robot_in_a_call(tmp_path, role=Role.OBSERVER) as rig:
        result = await rig.client.chat("topics")
        assert result.ok and result.final_text.startswith("topics: ")
        assert "/scan (sensor_msgs/msg/LaserScan)" in result.final_text
        assert "/navcam/image/compressed" not in result.final_text  # not for observers
