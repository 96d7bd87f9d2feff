"""Messages of the ``pose``, ``goals`` and ``telemetry`` channels (JSON text datagrams).

``pose`` (robot → user, latest only, ``pose_hz``)::

    {"t": 12.5, "x": 1.0, "y": 2.0, "yaw": 0.5, "cov": [xx, yy, yawyaw],
     "v": 0.3, "w": 0.0, "state": "moving", "detail": "goto lab", "goal": 7}

``goals`` (user → robot)::

    {"type": "goal", "id": 7, "x": 1.0, "y": 2.0, "yaw": 0.5}    yaw optional
    {"type": "cancel", "id": 7}
    {"type": "query", "id": 7}

``goals`` (robot → user): ``{"type": "status", "id": 7, "status": S, "progress": 0.4,
"reason": "...", "code": "..."}`` (``reason``: the text for people, ``code``: the reason code
of :mod:`~telebot.reasons`) with S one of ``active``, ``succeeded``, ``failed``, ``cancelled``,
``refused`` (not started: a caller that may not drive, or numbers that are not finite),
``unknown`` (a query for an id the robot does not remember).

``telemetry`` (robot → user, latest only, ``telemetry_hz``): one object, see
:class:`Telemetry`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from telebot.errors import ProtocolError
from telebot.reasons import decode_code
from telebot.services.messages import (
    decode_object,
    encode_object,
    finite_number,
    require_int,
)

__all__ = [
    "GOALS",
    "GOAL_STATES",
    "POSE",
    "TELEMETRY",
    "GoalCommand",
    "GoalUpdate",
    "PoseUpdate",
    "Telemetry",
    "decode_goal_command",
    "decode_goal_update",
    "decode_pose",
    "decode_telemetry",
]

#: Channel names of the robot's status (both ends open them by these names).
POSE = "pose"
GOALS = "goals"
TELEMETRY = "telemetry"

GOAL_STATES = ("active", "succeeded", "failed", "cancelled", "refused", "unknown")
FINAL_GOAL_STATES = frozenset(GOAL_STATES) - {"active"}


@dataclass(frozen=True, slots=True)
class PoseUpdate:
    """The robot's pose estimate, velocity and state at time ``t`` (robot clock)."""

    t: float
    x: float
    y: float
    yaw: float
    cov: tuple[float, float, float]
    v: float
    w: float
    state: str
    detail: str = ""
    goal: int | None = None

    def encode(self) -> str:
        """The datagram text."""
        data = asdict(self)
        data["cov"] = list(self.cov)
        return encode_object(data)


def decode_pose(payload: str | bytes) -> PoseUpdate:
    """Parse a ``pose`` datagram; ProtocolError when malformed."""
    what = "pose"
    msg = decode_object(payload, what=what)
    cov = msg.get("cov")
    if not isinstance(cov, list) or len(cov) != 3:
        raise ProtocolError("pose: 'cov' must be a list of 3 numbers")
    cov_values = tuple(finite_number({"c": c}, "c", what=what) for c in cov)
    goal = msg.get("goal")
    if goal is not None:
        goal = require_int(msg, "goal", what=what)
    return PoseUpdate(
        t=finite_number(msg, "t", what=what),
        x=finite_number(msg, "x", what=what),
        y=finite_number(msg, "y", what=what),
        yaw=finite_number(msg, "yaw", what=what),
        cov=(cov_values[0], cov_values[1], cov_values[2]),
        v=finite_number(msg, "v", what=what),
        w=finite_number(msg, "w", what=what),
        state=_text(msg, "state", what),
        detail=_text(msg, "detail", what, default=""),
        goal=goal,
    )


@dataclass(frozen=True, slots=True)
class GoalCommand:
    """A request on the ``goals`` channel: start, cancel or ask about goal ``id``."""

    type: Literal["goal", "cancel", "query"]
    id: int
    x: float = 0.0
    y: float = 0.0
    yaw: float | None = None

    def encode(self) -> str:
        """The datagram text."""
        if self.type != "goal":
            return encode_object({"type": self.type, "id": self.id})
        data: dict[str, Any] = {"type": "goal", "id": self.id, "x": self.x, "y": self.y}
        if self.yaw is not None:
            data["yaw"] = self.yaw
        return encode_object(data)


def decode_goal_command(payload: str | bytes) -> GoalCommand:
    """Parse a user → robot ``goals`` datagram; ProtocolError when malformed."""
    what = "goals"
    msg = decode_object(payload, what=what)
    kind = msg.get("type")
    goal_id = require_int(msg, "id", what=what)
    if kind in ("cancel", "query"):
        return GoalCommand(kind, goal_id)
    if kind != "goal":
        raise ProtocolError(f"goals: unknown type {kind!r}")
    yaw = finite_number(msg, "yaw", what=what) if msg.get("yaw") is not None else None
    return GoalCommand(
        "goal",
        goal_id,
        finite_number(msg, "x", what=what),
        finite_number(msg, "y", what=what),
        yaw,
    )


@dataclass(frozen=True, slots=True)
class GoalUpdate:
    """Where goal ``id`` stands (robot → user).

    ``text`` says why in words (the wire's ``reason`` field: ``"no path to (1.00, 2.00):
    inside an obstacle"``); ``code`` is the stable code to decide on (the wire's ``code``:
    ``"no_path"``, see :class:`~telebot.reasons.Reason`).
    """

    id: int
    status: str
    progress: float = 0.0
    text: str = ""
    code: str = ""

    @property
    def final(self) -> bool:
        """Whether the goal has ended (or never started)."""
        return self.status in FINAL_GOAL_STATES

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "status",
                "id": self.id,
                "status": self.status,
                "progress": round(self.progress, 4),
                "reason": self.text,
                "code": self.code,
            }
        )


def decode_goal_update(payload: str | bytes) -> GoalUpdate:
    """Parse a robot → user ``goals`` datagram; ProtocolError when malformed."""
    what = "goals"
    msg = decode_object(payload, what=what)
    if msg.get("type") != "status":
        raise ProtocolError(f"goals: unknown type {msg.get('type')!r}")
    status = _text(msg, "status", what)
    if status not in GOAL_STATES:
        raise ProtocolError(f"goals: unknown status {status!r}")
    return GoalUpdate(
        id=require_int(msg, "id", what=what),
        status=status,
        progress=finite_number(msg, "progress", what=what),
        text=_text(msg, "reason", what, default=""),
        code=decode_code(msg, what=what),
    )


@dataclass(frozen=True, slots=True)
class Telemetry:
    """The robot's slow-changing state, sent at ``telemetry_hz``."""

    t: float
    battery: float
    battery_low: bool
    state: str
    detail: str
    goal: str | None
    progress: float | None
    camera: str
    speed_limit: float
    rtt: float | None
    loss: float
    role: str
    diagnostics: dict[str, str] = field(default_factory=dict)
    #: The safety supervisor: armed or not (and why not), and who holds the drive.
    armed: bool = False
    stop_reason: str = ""
    holder: str | None = None
    #: The video sent to this call now: frame rate, size and JPEG quality (0: none).
    video_fps: float = 0.0
    video_width: int = 0
    video_height: int = 0
    video_quality: int = 0
    #: The robot's map version: when it differs from the map you downloaded
    #: (``MapDownload.version``), the map changed (SLAM) and a new download shows it.
    map_version: int = 0
    #: Frames of this call the robot dropped unread: over the call's receive queue
    #: (sent faster than the robot serves them) or larger than any frame.
    rx_dropped: int = 0

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(asdict(self))


def decode_telemetry(payload: str | bytes) -> Telemetry:
    """Parse a ``telemetry`` datagram; ProtocolError when malformed."""
    what = "telemetry"
    msg = decode_object(payload, what=what)
    diagnostics = msg.get("diagnostics", {})
    if not isinstance(diagnostics, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in diagnostics.items()
    ):
        raise ProtocolError("telemetry: 'diagnostics' must map names to text")
    goal = _optional_text(msg, "goal", what)
    battery_low = _flag(msg, "battery_low", what)
    return Telemetry(
        t=finite_number(msg, "t", what=what),
        battery=finite_number(msg, "battery", what=what),
        battery_low=battery_low,
        state=_text(msg, "state", what),
        detail=_text(msg, "detail", what, default=""),
        goal=goal,
        progress=_optional_number(msg, "progress", what),
        camera=_text(msg, "camera", what),
        speed_limit=finite_number(msg, "speed_limit", what=what),
        rtt=_optional_number(msg, "rtt", what),
        loss=finite_number(msg, "loss", what=what),
        role=_text(msg, "role", what),
        diagnostics=dict(diagnostics),
        armed=_flag(msg, "armed", what),
        stop_reason=_text(msg, "stop_reason", what, default=""),
        holder=_optional_text(msg, "holder", what),
        video_fps=finite_number(msg, "video_fps", what=what) if "video_fps" in msg else 0.0,
        video_width=require_int(msg, "video_width", what=what, high=65535)
        if "video_width" in msg
        else 0,
        video_height=require_int(msg, "video_height", what=what, high=65535)
        if "video_height" in msg
        else 0,
        video_quality=require_int(msg, "video_quality", what=what, high=100)
        if "video_quality" in msg
        else 0,
        map_version=require_int(msg, "map_version", what=what, high=2**53 - 1)
        if "map_version" in msg
        else 0,
        rx_dropped=require_int(msg, "rx_dropped", what=what, high=2**53 - 1)
        if "rx_dropped" in msg
        else 0,
    )


def _text(msg: dict[str, Any], key: str, what: str, default: str | None = None) -> str:
    value = msg.get(key, default)
    if not isinstance(value, str):
        raise ProtocolError(f"{what}: {key!r} must be text")
    return value


def _optional_number(msg: dict[str, Any], key: str, what: str) -> float | None:
    if msg.get(key) is None:
        return None
    return finite_number(msg, key, what=what)


def _flag(msg: dict[str, Any], key: str, what: str) -> bool:
    value = msg.get(key)
    if not isinstance(value, bool):
        raise ProtocolError(f"{what}: {key!r} must be true or false")
    return value


def _optional_text(msg: dict[str, Any], key: str, what: str) -> str | None:
    value = msg.get(key)
    if value is not None and not isinstance(value, str):
        raise ProtocolError(f"{what}: {key!r} must be text or null")
    return value
