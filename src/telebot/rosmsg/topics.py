"""The simulator's own streams as ROS 2 topics (CDR), for the ``relay`` service.

:class:`SimTopics` is the :class:`~telebot.robot.nav.TopicSource` of a simulated robot
(:class:`~telebot.robot.sim.stack.SimNavStack`, or anything with the members of
:class:`SimulatedRobot`): ``/map``, ``/amcl_pose``, ``/odom``, ``/tf``,
``/plan``, ``/scan``, ``/battery_state`` and ``/<camera>/image/compressed``, the names and
types ``telebot-sim`` serves them under, built by the same code
(:class:`~telebot.rosmsg.messages.SimMessages`). A topic is only built while something
subscribes to it; the stack calls :meth:`SimTopics.step` after each of its steps (the
callbacks then run on the stepping thread, the event loop under the daemon).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from telebot.robot.nav import (
    Battery,
    CameraFrame,
    CameraInfo,
    LaserScanLike,
    Pose2D,
    PoseEstimate,
    SourceTopic,
    Velocity,
)
from telebot.rosmsg.messages import BATTERY_HZ, CAMERA_HZ, SCAN_HZ, SimMessages
from telebot.rosmsg.types import TypeLibrary

if TYPE_CHECKING:
    from telebot.robot.grid import OccupancyGrid

__all__ = ["SimTopics", "SimulatedRobot"]

log = logging.getLogger(__name__)

Callback = Callable[[bytes, float], None]


@dataclass(slots=True)
class _Topic:
    name: str
    type: str
    #: Seconds between messages; 0: every step; inf: on change only.
    period: float
    build: Callable[[float], Any | None]
    #: For on-change topics: what the message was built from last (None: send now).
    changed: Callable[[], object] | None = None
    subscribers: list[Callback] = field(default_factory=list)
    next_at: float = -math.inf
    last_key: object = None


class SimulatedRobot(Protocol):
    """What :class:`SimTopics` reads of a simulated robot (the NavStack members it
    publishes, and the true pose for ``/odom``)."""

    def map(self) -> OccupancyGrid:
        """As :meth:`telebot.robot.nav.NavStack.map`."""
        ...

    def map_version(self) -> int:
        """As :meth:`telebot.robot.nav.NavStack.map_version`."""
        ...

    def pose(self) -> PoseEstimate:
        """As :meth:`telebot.robot.nav.NavStack.pose`."""
        ...

    def velocity(self) -> Velocity:
        """As :meth:`telebot.robot.nav.NavStack.velocity`."""
        ...

    def planned_path(self) -> tuple[Pose2D, ...]:
        """As :meth:`telebot.robot.nav.NavStack.planned_path`."""
        ...

    def battery(self) -> Battery:
        """As :meth:`telebot.robot.nav.NavStack.battery`."""
        ...

    def cameras(self) -> tuple[CameraInfo, ...]:
        """As :meth:`telebot.robot.nav.NavStack.cameras`."""
        ...

    def get_frame(self, camera: str | None = None) -> CameraFrame:
        """As :meth:`telebot.robot.nav.NavStack.get_frame`."""
        ...

    def laser_scan(self) -> LaserScanLike:
        """The latest laser scan (:class:`~telebot.robot.nav.LaserSource`)."""
        ...

    @property
    def true_pose(self) -> Pose2D:
        """Where the robot really is (odometry's pose)."""
        ...


class _Subscription:
    def __init__(self, topics: SimTopics, topic: _Topic, callback: Callback) -> None:
        self._topics = topics
        self._topic = topic
        self._callback = callback

    def close(self) -> None:
        """Deliver nothing more."""
        self._topics._unsubscribe(self._topic, self._callback)


class SimTopics:
    """The topic source of one simulated robot (see the module docstring)."""

    def __init__(self, stack: SimulatedRobot, *, distro: str = "jazzy") -> None:
        self._stack = stack
        self._distro = distro
        self._msgs: SimMessages | None = None
        self._lock = threading.Lock()
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, str] = {}
        for topic in self._declare():
            self._topics[topic.name] = topic

    def _declare(self) -> list[_Topic]:
        stack = self._stack
        topics = [
            _Topic(
                "/map",
                "nav_msgs/msg/OccupancyGrid",
                math.inf,
                lambda wall: self.msgs.map(stack.map(), wall),
                changed=stack.map_version,
            ),
            _Topic(
                "/amcl_pose",
                "geometry_msgs/msg/PoseWithCovarianceStamped",
                0.0,
                lambda wall: self.msgs.amcl_pose(stack.pose(), wall),
            ),
            _Topic(
                "/odom",
                "nav_msgs/msg/Odometry",
                0.0,
                lambda wall: self.msgs.odom(stack.true_pose, stack.velocity(), wall),
            ),
            _Topic(
                "/tf",
                "tf2_msgs/msg/TFMessage",
                0.0,
                lambda wall: self.msgs.tf(stack.pose().pose, wall),
            ),
            _Topic(
                "/plan",
                "nav_msgs/msg/Path",
                math.inf,
                lambda wall: self.msgs.path(stack.planned_path(), wall),
                changed=lambda: id(stack.planned_path()),
            ),
            _Topic(
                "/scan",
                "sensor_msgs/msg/LaserScan",
                1.0 / SCAN_HZ,
                lambda wall: self.msgs.scan(stack.laser_scan(), wall),
            ),
            _Topic(
                "/battery_state",
                "sensor_msgs/msg/BatteryState",
                1.0 / BATTERY_HZ,
                lambda wall: self.msgs.battery(stack.battery(), wall),
            ),
        ]
        for camera in stack.cameras():

            def build(wall: float, name: str = camera.name) -> Any | None:
                return self.msgs.image(name, stack.get_frame(name).image, wall)

            topics.append(
                _Topic(
                    f"/{camera.name}/image/compressed",
                    "sensor_msgs/msg/CompressedImage",
                    1.0 / CAMERA_HZ,
                    build,
                )
            )
        return topics

    @property
    def msgs(self) -> SimMessages:
        """The message builder (made on first use: it loads the ROS type store)."""
        if self._msgs is None:
            self._msgs = SimMessages(TypeLibrary("kilted" if self._distro == "kilted" else "jazzy"))
        return self._msgs

    def topics(self) -> list[SourceTopic]:
        """Every stream of the simulator, with its ROS type and schema."""
        return [SourceTopic(t.name, t.type, self._schema(t.type)) for t in self._topics.values()]

    def _schema(self, type_name: str) -> str:
        schema = self._schemas.get(type_name)
        if schema is None:
            schema = self._schemas[type_name] = self.msgs.lib.schema_text(type_name)
        return schema

    def subscribe_topic(self, name: str, callback: Callback) -> _Subscription:
        """Call ``callback(cdr, stamp)`` with each message of ``name`` from now on (the next
        step sends the newest one at once). LookupError for a topic the simulator lacks."""
        topic = self._topics.get(name)
        if topic is None:
            raise LookupError(f"the simulator has no topic {name!r}")
        self.msgs  # noqa: B018 (load the types now, not in the control loop's step)
        with self._lock:
            topic.subscribers.append(callback)
            topic.next_at = -math.inf
            topic.last_key = None
        return _Subscription(self, topic, callback)

    def _unsubscribe(self, topic: _Topic, callback: Callback) -> None:
        with self._lock:
            if callback in topic.subscribers:
                topic.subscribers.remove(callback)

    def step(self, now: float) -> None:
        """Build and hand out the messages due at ``now`` (only topics with subscribers)."""
        with self._lock:
            due: list[tuple[_Topic, list[Callback]]] = []
            for topic in self._topics.values():
                if not topic.subscribers:
                    continue
                if topic.changed is not None:
                    key = topic.changed()
                    if key == topic.last_key:
                        continue
                    topic.last_key = key
                elif now < topic.next_at:
                    continue
                else:
                    following = topic.next_at + topic.period
                    topic.next_at = following if following > now else now + topic.period
                due.append((topic, list(topic.subscribers)))
        if not due:
            return
        wall = time.time()
        for topic, subscribers in due:
            try:
                msg = topic.build(wall)
                if msg is None:
                    continue
                data = bytes(self.msgs.lib.message(topic.type).serialize(msg))
            except Exception:
                log.exception("simulated topic %s could not be built", topic.name)
                continue
            for callback in subscribers:
                try:
                    callback(data, wall)
                except Exception:
                    log.exception("a subscriber of %s failed", topic.name)
