"""What a page sends to its server, typed: one frozen dataclass per message (sans-IO).

The three local pages (the robot's page, docs/protocol.md §19; the fleet page, §21; the
robot's screen, §19.2) send JSON text messages ``{"type": TYPE, ...}`` over their
websocket. :func:`parse_page_message` reads one once, into the dataclass of its ``type``,
so a server handles it with ``match``; a message that is not one of those is a
:class:`PageMessageError` whose text is one line naming the fault (never a traceback,
never the page's input echoed at length). The browser client (``web/src/session.js``,
``RobotSession``) takes the same §19 messages as JavaScript objects.

The tables of docs/protocol.md §19, §19.2 and §21 are :func:`message_table` of
:data:`ROBOT_PAGE`, :data:`SCREEN_PAGE` and :data:`FLEET_PAGE` (a test checks the document
says the same).
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final, Literal, Self, TypeAlias, TypeVar, cast

from telebot.errors import excerpt

__all__ = [
    "FLEET_PAGE",
    "PAGE_CODECS",
    "PAGE_DECODES",
    "ROBOT_PAGE",
    "SCREEN_PAGE",
    "Arm",
    "Camera",
    "Chat",
    "CloseRobot",
    "Drive",
    "FleetPageMessage",
    "Goal",
    "Keyframe",
    "MediaCaps",
    "OpenRobot",
    "PageMessage",
    "PageMessageError",
    "Ping",
    "ReleaseDrive",
    "RequestId",
    "RobotPageMessage",
    "Say",
    "ScreenPageMessage",
    "Stop",
    "StopAll",
    "TakeDrive",
    "message_table",
    "parse_page_message",
]

#: A page's request id, echoed in the answers: a number, a short text or null.
RequestId: TypeAlias = int | float | str | None
#: Longest text id a page may use (characters).
MAX_ID = 64
#: The ``how`` of a page's stop (docs/protocol.md §18); anything else is a ``button``.
PAGE_STOP_HOWS: Final = ("button", "key", "touch", "page_hidden")
#: Video codecs a page may say it decodes.
PAGE_DECODES: Final = ("h264", "vp8", "jpeg")
#: Codecs a page may send its camera in (what WebCodecs encodes; never JPEG).
PAGE_CODECS: Final = ("vp8", "h264")


class PageMessageError(ValueError):
    """A page's message that is not one of its page's; ``str()`` is one line for the page.

    ``kind`` is the message's ``type`` when it had a known one (a server may fail safe on
    it: a bad ``drive`` releases the page's drive).
    """

    def __init__(self, text: str, kind: str = "") -> None:
        super().__init__(text)
        self.kind = kind


def _finite(obj: Mapping[str, Any], name: str) -> float | None:
    value = obj.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def _request_id(obj: Mapping[str, Any], kind: str) -> RequestId:
    value = obj.get("id")
    if value is None or _finite(obj, "id") is not None:
        return value  # as it came (an int stays an int)
    if isinstance(value, str) and len(value) <= MAX_ID:
        return value
    raise PageMessageError(
        f"{kind}: 'id' must be a number, a text of at most {MAX_ID} characters or null", kind
    )


def _codec_names(value: Any, known: tuple[str, ...]) -> tuple[str, ...]:
    """The known codec names of a page's list, in its order, once each (others ignored:
    a newer browser may know more)."""
    if not isinstance(value, list):
        return ()
    return tuple(dict.fromkeys(v for v in value if isinstance(v, str) and v in known))


@dataclass(frozen=True, slots=True)
class _Message:
    """Base of the page messages: ``TYPE`` is the JSON ``type``."""

    TYPE: ClassVar[str] = ""

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        """The message from its JSON object (its ``type`` already checked); a
        :class:`PageMessageError` if a field is wrong. Messages without fields take none."""
        return cls()


# --------------------------------------------------------------------- the robot's page


@dataclass(frozen=True, slots=True)
class Stop(_Message):
    """Stop now: anyone may, never refused (another `how` is a `button`)."""

    TYPE: ClassVar[str] = "stop"
    how: Literal["button", "key", "touch", "page_hidden"] = "button"

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        how = obj.get("how")
        return cls(how if how in PAGE_STOP_HOWS else "button")


@dataclass(frozen=True, slots=True)
class Arm(_Message):
    """Re-arm a stopped robot."""

    TYPE: ClassVar[str] = "arm"


@dataclass(frozen=True, slots=True)
class TakeDrive(_Message):
    """Take the drive."""

    TYPE: ClassVar[str] = "take"


@dataclass(frozen=True, slots=True)
class ReleaseDrive(_Message):
    """Give the drive up."""

    TYPE: ClassVar[str] = "release"


@dataclass(frozen=True, slots=True)
class Goal(_Message):
    """Go to a place: map frame, metres, radians (`yaw` null: any heading)."""

    TYPE: ClassVar[str] = "goal"
    x: float
    y: float
    yaw: float | None = None

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        try:
            x, y = float(obj["x"]), float(obj["y"])
            yaw = None if obj.get("yaw") is None else float(obj["yaw"])
        except (KeyError, TypeError, ValueError):
            raise PageMessageError("a goal needs numbers x, y (and yaw)", cls.TYPE) from None
        if not all(math.isfinite(v) for v in (x, y, yaw or 0.0)):
            raise PageMessageError("a goal needs finite numbers", cls.TYPE)
        return cls(x, y, yaw)


@dataclass(frozen=True, slots=True)
class Drive(_Message):
    """Drive by hand (§27): m/s, rad/s; sent at 20 Hz while held, zeros once on release."""

    TYPE: ClassVar[str] = "drive"
    linear: float
    angular: float

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        linear, angular = _finite(obj, "linear"), _finite(obj, "angular")
        if linear is None or angular is None:
            raise PageMessageError("a drive needs finite numbers linear, angular", cls.TYPE)
        return cls(linear, angular)


@dataclass(frozen=True, slots=True)
class _TextRequest(_Message):
    """A line of text the page wants answered under its request ``id``."""

    id: RequestId
    text: str

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        return cls(_request_id(obj, cls.TYPE), str(obj.get("text", "")))


@dataclass(frozen=True, slots=True)
class Chat(_TextRequest):
    """A chat command (§14; `say TEXT` goes to the conference, §20)."""

    TYPE: ClassVar[str] = "chat"


@dataclass(frozen=True, slots=True)
class Say(_TextRequest):
    """A line to everyone in the robot's calls (§20)."""

    TYPE: ClassVar[str] = "say"


@dataclass(frozen=True, slots=True)
class Camera(_Message):
    """Switch the robot's camera (sent as the chat command `name`)."""

    TYPE: ClassVar[str] = "camera"
    id: RequestId
    name: Literal["navcam", "usercam"]

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        name = obj.get("name")
        if name == "navcam" or name == "usercam":
            return cls(_request_id(obj, cls.TYPE), name)
        raise PageMessageError("camera: 'name' must be navcam or usercam", cls.TYPE)


@dataclass(frozen=True, slots=True)
class Ping(_Message):
    """Answered with `pong` and the same `t`."""

    TYPE: ClassVar[str] = "ping"
    t: float | None = None

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        t = _finite(obj, "t")
        if t is None and obj.get("t") is not None:
            raise PageMessageError("ping: 't' must be a finite number or null", cls.TYPE)
        return cls(t)


@dataclass(frozen=True, slots=True)
class MediaCaps(_Message):
    """What the browser decodes and encodes, in preference order (§19.1; on every open)."""

    TYPE: ClassVar[str] = "media"
    decode: tuple[Literal["h264", "vp8", "jpeg"], ...] = ()
    encode: tuple[Literal["vp8", "h264"], ...] = ()

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        return cls(
            _codec_names(obj.get("decode"), PAGE_DECODES),  # type: ignore[arg-type]
            _codec_names(obj.get("encode"), PAGE_CODECS),  # type: ignore[arg-type]
        )


@dataclass(frozen=True, slots=True)
class Keyframe(_Message):
    """The page lost a picture (or just opened): a keyframe, please (§19.1)."""

    TYPE: ClassVar[str] = "keyframe"


# --------------------------------------------------------------------- the fleet page


def _robot(obj: Mapping[str, Any], kind: str) -> str:
    name = obj.get("robot")
    if not isinstance(name, str):
        raise PageMessageError(f"{kind}: 'robot' must be a name", kind)
    return name


@dataclass(frozen=True, slots=True)
class _RobotRequest(_Message):
    """Something the fleet page asks of one robot, by name."""

    robot: str

    @classmethod
    def parse(cls, obj: Mapping[str, Any]) -> Self:
        return cls(_robot(obj, cls.TYPE))


@dataclass(frozen=True, slots=True)
class OpenRobot(_RobotRequest):
    """Open a robot's page (at `robot/NAME/`)."""

    TYPE: ClassVar[str] = "open"


@dataclass(frozen=True, slots=True)
class CloseRobot(_RobotRequest):
    """Close a robot's page (its call stays)."""

    TYPE: ClassVar[str] = "close"


@dataclass(frozen=True, slots=True)
class StopAll(_Message):
    """Stop every robot with a call, all at once."""

    TYPE: ClassVar[str] = "stop_all"


#: What the robot's page sends.
RobotPageMessage: TypeAlias = (
    Stop
    | Arm
    | TakeDrive
    | ReleaseDrive
    | Goal
    | Drive
    | Chat
    | Say
    | Camera
    | Ping
    | MediaCaps
    | Keyframe
)
#: What the fleet page sends.
FleetPageMessage: TypeAlias = OpenRobot | CloseRobot | StopAll
#: What the robot's screen sends.
ScreenPageMessage: TypeAlias = Keyframe
#: Any page message.
PageMessage: TypeAlias = RobotPageMessage | FleetPageMessage
#: A type of page message (parse_page_message gives one of the kinds it is asked for).
M = TypeVar("M", bound=PageMessage)
#: What the robot's page sends (§19, §19.1).
ROBOT_PAGE: Final[tuple[type[RobotPageMessage], ...]] = (
    Stop,
    Arm,
    TakeDrive,
    ReleaseDrive,
    Goal,
    Drive,
    Chat,
    Say,
    Camera,
    Ping,
    MediaCaps,
    Keyframe,
)
#: What the fleet page sends (§21).
FLEET_PAGE: Final[tuple[type[FleetPageMessage], ...]] = (OpenRobot, CloseRobot, StopAll)
#: What the robot's screen sends (§19.2).
SCREEN_PAGE: Final[tuple[type[ScreenPageMessage], ...]] = (Keyframe,)


def parse_page_message(text: str, kinds: tuple[type[M], ...]) -> M:
    """One websocket text message of a page that sends ``kinds``; a
    :class:`PageMessageError` (one line) if it is not one of them."""
    try:
        obj = json.loads(text)
        kind = obj["type"]
    except (ValueError, KeyError, TypeError, RecursionError):
        raise PageMessageError("not a JSON message with a type") from None
    for cls in kinds:
        if kind == cls.TYPE:
            return cast(M, cls.parse(obj))  # cls is one of kinds: its parse gives an M
    shown = excerpt(kind, 40) if isinstance(kind, str) else excerpt(repr(kind), 40)
    raise PageMessageError(f"unknown message type {shown!r}")


# --------------------------------------------------------------------- documentation


def _type_text(hint: Any) -> str:
    """A field's type for people: `number`, `text`, `null`, literal values, lists."""
    origin = typing.get_origin(hint)
    if hint is float or hint is int:
        return "number"
    if hint is str:
        return "text"
    if hint is type(None):
        return "null"
    if origin is Literal:
        return " \\| ".join(f'`"{value}"`' for value in typing.get_args(hint))
    if origin is tuple:
        return f"[{_type_text(typing.get_args(hint)[0])}, …]"
    if origin in (typing.Union, types.UnionType):
        parts = dict.fromkeys(_type_text(arg) for arg in typing.get_args(hint))
        return " \\| ".join(parts)
    raise TypeError(f"no text for the type {hint!r}")


def message_table(kinds: tuple[type[PageMessage], ...]) -> str:
    """The markdown table of ``kinds`` (docs/protocol.md quotes it): type, fields, meaning."""
    rows = ["| `type` | fields | meaning |", "|---|---|---|"]
    for cls in kinds:
        hints = typing.get_type_hints(cls)
        fields = ", ".join(
            f"`{f.name}`: {_type_text(hints[f.name])}" for f in dataclasses.fields(cls)
        )
        meaning = (cls.__doc__ or "").strip().splitlines()[0]
        rows.append(f"| `{cls.TYPE}` | {fields or '—'} | {meaning} |")
    return "\n".join(rows) + "\n"
