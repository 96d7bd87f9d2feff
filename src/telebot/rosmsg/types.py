"""ROS 2 message, service and action types: CDR (through rosbags) and RIHS01 type hashes.

A :class:`TypeLibrary` knows the types of one ROS 2 distro (``"jazzy"`` or ``"kilted"``):
rosbags' type store for that distro, plus the service and action types telebot needs, written
here as ``.srv`` / ``.action`` text (``nav2_msgs`` actions differ between the distros).
Services and actions get their derived types the way ``rosidl_parser`` builds them
(``_Request``/``_Response``/``_Event``; ``_Goal``/``_Result``/``_Feedback``,
``_SendGoal``, ``_GetResult``, ``_FeedbackMessage``).

Type hashes follow REP 2011 as ``rosidl_generator_type_description`` computes them: the
type description (fields only, no constants or default values) of the type and of every
type it references (sorted by name), as compact JSON, SHA-256. In ``.msg`` files ``char``
is ``uint8`` and ``byte`` is ``octet`` (``rosidl_adapter``), so they hash as such; rosbags'
own ``hash_rihs01`` uses the IDL ``char`` id and gets every service hash wrong (the service
event carries ``service_msgs/ServiceEventInfo``'s ``char[16] client_gid``).

Everything is built lazily and cached: constructing a library is cheap; the rosbags store
is loaded on first use. A library is safe to use from several threads.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import re
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, cast

from telebot.errors import CdrError, ConfigError, Ros2Error, UnknownRosType

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

    from rosbags.typesys.store import Typestore

__all__ = [
    "ActionType",
    "MessageType",
    "ServiceType",
    "TypeLibrary",
    "dds_type_name",
    "rihs01_hash",
    "ros_type_name",
]

Distro = Literal["jazzy", "kilted"]

# rosbags' parse-tree node kinds (rosbags.interfaces.Nodetype); literal ints keep the import
# of rosbags (~150 ms) out of TypeLibrary's constructor.
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4

# type_description_interfaces/msg/FieldType ids of .msg primitive types (after rosidl_adapter
# maps them to IDL: char -> uint8, byte -> octet, bool -> boolean, float32 -> float, ...).
_FIELD_TYPE_ID = {
    "int8": 2,
    "uint8": 3,
    "char": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "bool": 15,
    "byte": 16,
    "octet": 16,
    "string": 17,
}
_NESTED_TYPE_ID = 1
_BOUNDED_STRING_ID = 21
_ARRAY_OFFSET, _BOUNDED_SEQUENCE_OFFSET, _UNBOUNDED_SEQUENCE_OFFSET = 48, 96, 144

# numpy dtypes rosbags uses for primitive arrays and sequences (make() fills these).
_NUMPY_DTYPE = {
    "int8": "int8",
    "uint8": "uint8",
    "char": "uint8",
    "byte": "uint8",
    "octet": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
    "bool": "bool",
}

_TYPE_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*/(msg|srv|action)/[A-Za-z][A-Za-z0-9_]*$")
_SEPARATOR = re.compile(r"^---[ \t]*$", re.MULTILINE)

# Services and actions telebot uses that rosbags' message-only stores lack. Texts are the
# fields of the upstream .srv/.action files (comments dropped; constants kept).
_SRV_TEXTS: dict[str, str] = {
    "action_msgs/srv/CancelGoal": """\
action_msgs/GoalInfo goal_info
---
int8 ERROR_NONE=0
int8 ERROR_REJECTED=1
int8 ERROR_UNKNOWN_GOAL_ID=2
int8 ERROR_GOAL_TERMINATED=3
int8 return_code
action_msgs/GoalInfo[] goals_canceling
""",
    "std_srvs/srv/SetBool": """\
bool data
---
bool success
string message
""",
    "std_srvs/srv/Trigger": """\
---
bool success
string message
""",
    "std_srvs/srv/Empty": """\
---
""",
    "example_interfaces/srv/AddTwoInts": """\
int64 a
int64 b
---
int64 sum
""",
}

# Messages beyond rosbags' stores, registered with the store when it is built:
# nav2_msgs/msg/SpeedLimit.msg (the same on jazzy and kilted), which Nav2's controller
# server takes on /speed_limit.
_MSG_TEXTS: dict[str, str] = {
    "nav2_msgs/msg/SpeedLimit": """\
std_msgs/Header header
bool percentage
float64 speed_limit
""",
}

# nav2_msgs/action/*.action of navigation2's jazzy branch (f4108e5b) ...
_NAV2_JAZZY: dict[str, str] = {
    "nav2_msgs/action/NavigateToPose": """\
geometry_msgs/PoseStamped pose
string behavior_tree
---
uint16 NONE=0
uint16 error_code
string error_msg
---
geometry_msgs/PoseStamped current_pose
builtin_interfaces/Duration navigation_time
builtin_interfaces/Duration estimated_time_remaining
int16 number_of_recoveries
float32 distance_remaining
""",
    "nav2_msgs/action/DriveOnHeading": """\
geometry_msgs/Point target
float32 speed
builtin_interfaces/Duration time_allowance
---
uint16 NONE=0
uint16 UNKNOWN=720
uint16 TIMEOUT=721
uint16 TF_ERROR=722
uint16 COLLISION_AHEAD=723
uint16 INVALID_INPUT=724
builtin_interfaces/Duration total_elapsed_time
uint16 error_code
string error_msg
---
float32 distance_traveled
""",
    "nav2_msgs/action/Spin": """\
float32 target_yaw
builtin_interfaces/Duration time_allowance
---
uint16 NONE=0
uint16 UNKNOWN=700
uint16 TIMEOUT=701
uint16 TF_ERROR=702
uint16 COLLISION_AHEAD=703
builtin_interfaces/Duration total_elapsed_time
uint16 error_code
string error_msg
---
float32 angular_distance_traveled
""",
    "nav2_msgs/action/BackUp": """\
geometry_msgs/Point target
float32 speed
builtin_interfaces/Duration time_allowance
---
uint16 NONE=0
uint16 UNKNOWN=710
uint16 TIMEOUT=711
uint16 TF_ERROR=712
uint16 INVALID_INPUT=713
uint16 COLLISION_AHEAD=714
builtin_interfaces/Duration total_elapsed_time
uint16 error_code
string error_msg
---
float32 distance_traveled
""",
}

# ... and of its kilted branch (71a1d84f): NavigateToPose gained error constants only (same
# fields, same hash); DriveOnHeading, Spin and BackUp gained ``disable_collision_checks``.
_NAV2_KILTED: dict[str, str] = {
    "nav2_msgs/action/NavigateToPose": _NAV2_JAZZY["nav2_msgs/action/NavigateToPose"].replace(
        "uint16 NONE=0\n",
        "uint16 NONE=0\nuint16 UNKNOWN=9000\nuint16 FAILED_TO_LOAD_BEHAVIOR_TREE=9001\n"
        "uint16 TF_ERROR=9002\nuint16 TIMEOUT=9003\n",
    ),
    **{
        name: text.replace(
            "builtin_interfaces/Duration time_allowance\n---",
            "builtin_interfaces/Duration time_allowance\nbool disable_collision_checks False\n---",
            1,
        )
        for name, text in _NAV2_JAZZY.items()
        if name != "nav2_msgs/action/NavigateToPose"
    },
}

_ACTION_TEXTS: dict[str, dict[str, str]] = {"jazzy": _NAV2_JAZZY, "kilted": _NAV2_KILTED}

_GOAL_ID = "unique_identifier_msgs/msg/UUID"
_TIME = "builtin_interfaces/msg/Time"
_SERVICE_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"
_CANCEL_GOAL = "action_msgs/srv/CancelGoal"
_GOAL_STATUS_ARRAY = "action_msgs/msg/GoalStatusArray"


def dds_type_name(name: str) -> str:
    """The type name rmw_zenoh puts in key expressions and liveliness tokens.

    ``"geometry_msgs/msg/Twist"`` -> ``"geometry_msgs::msg::dds_::Twist_"``; for a service
    (or an action's service) the name without its ``_Request``/``_Response`` suffix:
    ``"nav2_msgs/action/NavigateToPose_SendGoal"`` ->
    ``"nav2_msgs::action::dds_::NavigateToPose_SendGoal_"``.
    """
    pkg, kind, base = name.split("/")
    return f"{pkg}::{kind}::dds_::{base}_"


def ros_type_name(dds_name: str) -> str:
    """Inverse of :func:`dds_type_name`; raises :class:`UnknownRosType` on other text."""
    match = re.fullmatch(r"([A-Za-z][A-Za-z0-9_]*)::(msg|srv|action)::dds_::(\w+)_", dds_name)
    if match is None:
        raise UnknownRosType(f"not an rmw_zenoh type name: {dds_name[:80]!r}")
    return "/".join(match.groups())


def rihs01_hash(description: dict[str, Any]) -> str:
    """The REP 2011 hash ``RIHS01_<sha256 hex>`` of a full type description.

    ``description`` is ``{"type_description": {...}, "referenced_type_descriptions": [...]}``
    as :meth:`TypeLibrary.type_description` returns it: each individual description is
    ``{"type_name", "fields": [{"name", "type": {"type_id", "capacity", "string_capacity",
    "nested_type_name"}}]}`` (default values, if present, are not hashed).
    """

    def strip(td: dict[str, Any]) -> dict[str, Any]:
        return {
            "type_name": td["type_name"],
            "fields": [{"name": f["name"], "type": f["type"]} for f in td["fields"]],
        }

    hashable = {
        "type_description": strip(description["type_description"]),
        "referenced_type_descriptions": [
            strip(td) for td in description["referenced_type_descriptions"]
        ],
    }
    # The exact JSON rosidl_generator_type_description hashes (separators as libyaml's).
    text = json.dumps(hashable, ensure_ascii=True, allow_nan=False, separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class MessageType:
    """A ROS 2 message type: its names, its RIHS01 hash, and CDR (de)serialization."""

    name: str
    """ROS name, e.g. ``"geometry_msgs/msg/Twist"``."""
    dds_name: str
    """Type name in rmw_zenoh's keys, e.g. ``"geometry_msgs::msg::dds_::Twist_"``."""
    type_hash: str
    """``"RIHS01_<64 lowercase hex>"`` (REP 2011)."""
    _library: TypeLibrary = field(repr=False, compare=False)

    def serialize(self, msg: Any) -> bytes:
        """CDR little endian, with the 4-byte encapsulation header (as rmw_zenoh sends it).

        Raises :class:`CdrError` if ``msg`` is not a well-formed message of this type.
        """
        return self._library._serialize(self.name, msg)

    def deserialize(self, data: bytes | bytearray | memoryview) -> Any:
        """A message object from CDR bytes (header included).

        Anything that is not a complete message of this type (short, truncated, unknown
        encapsulation, absurd lengths, trailing junk) raises :class:`CdrError`, one line,
        naming the type. Primitive arrays come back as read-only numpy arrays over the
        (copied, if mutable) input.
        """
        return self._library._deserialize(self.name, data)

    def make(self, **fields: Any) -> Any:
        """A message object; omitted fields get defaults (0, ``""``, empty, nested defaults,
        zero-filled fixed arrays).

        Primitive arrays may be given as numpy arrays, bytes, lists or tuples; nested
        messages as message objects or dicts of their fields. Raises :class:`Ros2Error`
        naming an unknown field, bad array values or a wrong fixed array length.
        """
        return self._library._make(self.name, fields)

    @property
    def cls(self) -> type[Any]:
        """The rosbags dataclass of this type (for ``isinstance`` checks)."""
        return self._library._store().types[self.name]


@dataclass(frozen=True)
class ServiceType:
    """A ROS 2 service type: its request/response messages and the service's own hash."""

    name: str
    """ROS name, e.g. ``"std_srvs/srv/SetBool"``."""
    dds_name: str
    """rmw_zenoh's name, e.g. ``"std_srvs::srv::dds_::SetBool_"``."""
    type_hash: str
    """RIHS01 hash of the service type description (request, response and event)."""
    request: MessageType
    response: MessageType


@dataclass(frozen=True)
class ActionType:
    """A ROS 2 action type with the services and topics rclcpp_action builds from it."""

    name: str
    """ROS name, e.g. ``"nav2_msgs/action/NavigateToPose"``."""
    send_goal: ServiceType
    """``<name>_SendGoal``: request (goal_id: unique_identifier_msgs/UUID, goal),
    response (accepted, stamp)."""
    get_result: ServiceType
    """``<name>_GetResult``: request (goal_id), response (status, result)."""
    cancel_goal: ServiceType
    """``action_msgs/srv/CancelGoal``."""
    feedback: MessageType
    """``<name>_FeedbackMessage`` (goal_id, feedback), on the ``_action/feedback`` topic."""
    status: MessageType
    """``action_msgs/msg/GoalStatusArray``, on the ``_action/status`` topic."""
    goal: MessageType
    result: MessageType
    feedback_body: MessageType
    """``<name>_Feedback``, the feedback without its goal id."""
    type_hash: str
    """RIHS01 hash of the action type description itself (not used in rmw_zenoh keys)."""


def _split(text: str, parts: int, name: str) -> list[str]:
    chunks = _SEPARATOR.split(text)
    if len(chunks) != parts:
        raise Ros2Error(f"{name}: expected {parts} sections separated by '---', got {len(chunks)}")
    return chunks


class TypeLibrary:
    """The ROS 2 types of one distro, by name, with CDR and REP 2011 hashes.

    Knows rosbags' message store for the distro (std_msgs, geometry_msgs, nav_msgs,
    sensor_msgs, tf2_msgs, builtin_interfaces, action_msgs, unique_identifier_msgs,
    rcl_interfaces, ...) plus ``std_srvs`` SetBool/Trigger/Empty, ``example_interfaces``
    AddTwoInts, ``action_msgs/srv/CancelGoal``, ``nav2_msgs/msg/SpeedLimit`` and the nav2
    actions NavigateToPose, DriveOnHeading, Spin and BackUp. More can be added with the ``register_*_text`` methods.
    """

    def __init__(self, distro: Distro = "jazzy") -> None:
        """Cheap: the rosbags store and every type are built on first use."""
        if distro not in _ACTION_TEXTS:
            raise ConfigError(f"unknown ROS 2 distro {distro!r}; known: jazzy, kilted")
        self.distro: Distro = distro
        self._lock = threading.RLock()
        self._typestore: Typestore | None = None
        self._srv_texts = dict(_SRV_TEXTS)
        self._action_texts = dict(_ACTION_TEXTS[distro])
        self._services: set[str] = set()  # registered in the store (request/response/event)
        self._actions: set[str] = set()
        self._individual: dict[str, dict[str, Any]] = {}
        self._messages: dict[str, MessageType] = {}
        self._service_types: dict[str, ServiceType] = {}
        self._action_types: dict[str, ActionType] = {}
        self._hashes: dict[str, str] = {}

    # -- lookup ------------------------------------------------------------------------------

    def message(self, name: str) -> MessageType:
        """The message type ``pkg/msg/Name`` (``pkg/Name`` works too).

        Raises :class:`UnknownRosType` listing similar known names.
        """
        name = self._normalize(name, "msg")
        with self._lock:
            found = self._messages.get(name)
            if found is None:
                self._ensure_parent(name)
                if name not in self._store().fielddefs:
                    raise self._unknown(name, self._store().fielddefs)
                self._store().get_msgdef(name)  # generate the (de)serializers now, once
                found = MessageType(name, dds_type_name(name), self.type_hash(name), self)
                self._messages[name] = found
            return found

    def schema_text(self, name: str) -> str:
        """The ``.msg`` text of message type ``name`` with its dependencies, as MCAP's
        ``ros2msg`` schema encoding and rosbag2 want it (each dependency after a line of 80
        ``=`` and ``MSG: pkg/Type``). Raises :class:`UnknownRosType`."""
        name = self.message(name).name
        with self._lock:
            text, _ = self._store().generate_msgdef(name, ros_version=2)
        return text

    def service(self, name: str) -> ServiceType:
        """The service type ``pkg/srv/Name`` (or an action's ``..._SendGoal``/``_GetResult``)."""
        name = self._normalize(name, "srv")
        with self._lock:
            found = self._service_types.get(name)
            if found is None:
                self._ensure_service(name)
                found = ServiceType(
                    name=name,
                    dds_name=dds_type_name(name),
                    type_hash=self.type_hash(name),
                    request=self.message(name + "_Request"),
                    response=self.message(name + "_Response"),
                )
                self._service_types[name] = found
            return found

    def action(self, name: str) -> ActionType:
        """The action type ``pkg/action/Name`` with all its derived services and messages."""
        name = self._normalize(name, "action")
        with self._lock:
            found = self._action_types.get(name)
            if found is None:
                self._ensure_action(name)
                found = ActionType(
                    name=name,
                    type_hash=self.type_hash(name),
                    send_goal=self.service(name + "_SendGoal"),
                    get_result=self.service(name + "_GetResult"),
                    cancel_goal=self.service(_CANCEL_GOAL),
                    feedback=self.message(name + "_FeedbackMessage"),
                    status=self.message(_GOAL_STATUS_ARRAY),
                    goal=self.message(name + "_Goal"),
                    result=self.message(name + "_Result"),
                    feedback_body=self.message(name + "_Feedback"),
                )
                self._action_types[name] = found
            return found

    def type_hash(self, name: str) -> str:
        """RIHS01 hash of any known message, service or action type (full ROS name)."""
        with self._lock:
            found = self._hashes.get(name)
            if found is None:
                found = rihs01_hash(self.type_description(name))
                self._hashes[name] = found
            return found

    def type_description(self, name: str) -> dict[str, Any]:
        """The full REP 2011 type description (no default values) of a known type."""
        with self._lock:
            top = self._describe(name)
            seen: set[str] = set()
            queue = [f["type"]["nested_type_name"] for f in top["fields"]]
            while queue:
                ref = queue.pop()
                if ref and ref not in seen:
                    seen.add(ref)
                    queue.extend(
                        f["type"]["nested_type_name"] for f in self._describe(ref)["fields"]
                    )
            return {
                "type_description": top,
                "referenced_type_descriptions": [self._describe(n) for n in sorted(seen)],
            }

    def known(self) -> list[str]:
        """Every message, service and action name this library can build (sorted)."""
        with self._lock:
            names = set(self._store().fielddefs) | set(self._srv_texts) | set(self._action_texts)
            return sorted(names | self._services | self._actions)

    # -- registration ------------------------------------------------------------------------

    def register_msg_text(self, name: str, text: str) -> None:
        """Add a message type from ``.msg`` text (relative names resolve in its package)."""
        name = self._normalize(name, "msg")
        self._register(self._parse(name, text))

    def register_srv_text(self, name: str, text: str) -> None:
        """Add a service type from ``.srv`` text (request ``---`` response)."""
        name = self._normalize(name, "srv")
        _split(text, 2, name)
        with self._lock:
            if name in self._services:
                raise Ros2Error(f"service type {name} is already registered")
            self._srv_texts[name] = text

    def register_action_text(self, name: str, text: str) -> None:
        """Add an action type from ``.action`` text (goal ``---`` result ``---`` feedback)."""
        name = self._normalize(name, "action")
        _split(text, 3, name)
        with self._lock:
            if name in self._actions:
                raise Ros2Error(f"action type {name} is already registered")
            self._action_texts[name] = text

    # -- internals ---------------------------------------------------------------------------

    def _store(self) -> Typestore:
        store = self._typestore
        if store is None:
            with self._lock:
                if self._typestore is None:
                    from rosbags.typesys import Stores, get_typestore

                    which = Stores.ROS2_JAZZY if self.distro == "jazzy" else Stores.ROS2_KILTED
                    typestore = get_typestore(which)
                    for name, text in _MSG_TEXTS.items():
                        typestore.register(self._parse(name, text))
                    self._typestore = typestore
                store = self._typestore
        return store

    @staticmethod
    def _normalize(name: str, kind: str) -> str:
        if not isinstance(name, str):
            raise UnknownRosType(f"a ROS type name must be a string, not {type(name).__name__}")
        parts = name.strip("/").split("/")
        if len(parts) == 2:
            parts.insert(1, kind)
        full = "/".join(parts)
        if not _TYPE_NAME.match(full):
            raise UnknownRosType(f"not a ROS type name: {name[:80]!r} (like pkg/{kind}/Name)")
        return full

    def _unknown(self, name: str, pool: Iterable[str]) -> UnknownRosType:
        near = difflib.get_close_matches(name, list(pool), n=4, cutoff=0.6)
        hint = f"; did you mean {', '.join(near)}?" if near else ""
        return UnknownRosType(f"unknown ROS type {name}{hint}")

    def _parse(self, name: str, text: str) -> dict[str, Any]:
        from rosbags.typesys import get_types_from_msg

        pkg, _, base = name.split("/")
        # Parse under the msg namespace so relative names resolve to pkg/msg/X, as in ROS.
        try:
            parsed = get_types_from_msg(text, f"{pkg}/msg/{base}")
        except Exception as exc:  # rosbags raises its own parse errors
            raise Ros2Error(f"{name}: bad message text: {exc}".splitlines()[0]) from exc
        tree = parsed.pop(f"{pkg}/msg/{base}")
        return {name: tree, **parsed}

    def _register(self, types: dict[str, Any]) -> None:
        from rosbags.typesys.base import TypesysError

        with self._lock:
            try:
                self._store().register(types)
            except TypesysError as exc:
                raise Ros2Error(str(exc)) from exc

    def _ensure_parent(self, name: str) -> None:
        """Register the service/action a derived message name belongs to, if any."""
        kind = name.split("/")[1]
        if kind == "msg" or name in self._store().fielddefs:
            return
        for suffix in ("_Request", "_Response", "_Event"):
            if name.endswith(suffix) and name.removesuffix(suffix) in self._srv_like():
                self._ensure_service(name.removesuffix(suffix))
                return
        for suffix in ("_Goal", "_Result", "_Feedback", "_FeedbackMessage"):
            if name.endswith(suffix) and name.removesuffix(suffix) in self._action_texts:
                self._ensure_action(name.removesuffix(suffix))
                return

    def _srv_like(self) -> set[str]:
        derived = {a + s for a in self._action_texts for s in ("_SendGoal", "_GetResult")}
        return set(self._srv_texts) | derived

    def _ensure_service(self, name: str) -> None:
        if name in self._services:
            return
        if name in self._srv_texts:
            request, response = _split(self._srv_texts[name], 2, name)
            types = {**self._parse(name + "_Request", request)}
            types.update(self._parse(name + "_Response", response))
            self._register(types)
        elif name.endswith(("_SendGoal", "_GetResult")):
            action = name.rsplit("_", 1)[0]
            if action not in self._action_texts:
                raise self._unknown(name, self._srv_like())
            self._ensure_action(action)
            return
        else:
            raise self._unknown(name, self._srv_like())
        self._add_service_event(name)

    def _add_service_event(self, name: str) -> None:
        event: tuple[list[Any], list[Any]] = (
            [],
            [
                ("info", (_NAME, _SERVICE_EVENT_INFO)),
                ("request", (_SEQUENCE, ((_NAME, name + "_Request"), 1))),
                ("response", (_SEQUENCE, ((_NAME, name + "_Response"), 1))),
            ],
        )
        self._register({name + "_Event": event})
        self._individual[name] = {
            "type_name": name,
            "fields": [
                _field(fname, _NESTED_TYPE_ID, nested=name + suffix)
                for fname, suffix in (
                    ("request_message", "_Request"),
                    ("response_message", "_Response"),
                    ("event_message", "_Event"),
                )
            ],
        }
        self._services.add(name)

    def _ensure_action(self, name: str) -> None:
        if name in self._actions:
            return
        if name not in self._action_texts:
            raise self._unknown(name, self._action_texts)
        goal, result, feedback = _split(self._action_texts[name], 3, name)
        types: dict[str, Any] = {}
        types.update(self._parse(name + "_Goal", goal))
        types.update(self._parse(name + "_Result", result))
        types.update(self._parse(name + "_Feedback", feedback))
        send, get = name + "_SendGoal", name + "_GetResult"
        types[send + "_Request"] = (
            [],
            [("goal_id", (_NAME, _GOAL_ID)), ("goal", (_NAME, name + "_Goal"))],
        )
        types[send + "_Response"] = (
            [],
            [("accepted", (_BASE, ("bool", 0))), ("stamp", (_NAME, _TIME))],
        )
        types[get + "_Request"] = ([], [("goal_id", (_NAME, _GOAL_ID))])
        types[get + "_Response"] = (
            [],
            [("status", (_BASE, ("int8", 0))), ("result", (_NAME, name + "_Result"))],
        )
        types[name + "_FeedbackMessage"] = (
            [],
            [("goal_id", (_NAME, _GOAL_ID)), ("feedback", (_NAME, name + "_Feedback"))],
        )
        self._register(types)
        self._add_service_event(send)
        self._add_service_event(get)
        self._individual[name] = {
            "type_name": name,
            "fields": [
                _field(fname, _NESTED_TYPE_ID, nested=name + suffix)
                for fname, suffix in (
                    ("goal", "_Goal"),
                    ("result", "_Result"),
                    ("feedback", "_Feedback"),
                    ("send_goal_service", "_SendGoal"),
                    ("get_result_service", "_GetResult"),
                    ("feedback_message", "_FeedbackMessage"),
                )
            ],
        }
        self._actions.add(name)

    def _describe(self, name: str) -> dict[str, Any]:
        """The individual type description of one type (fields only)."""
        found = self._individual.get(name)
        if found is not None:
            return found
        kind = name.split("/")[1] if name.count("/") == 2 else ""
        if kind == "srv" or name.endswith(("_SendGoal", "_GetResult")):
            if name in self._srv_like():
                self._ensure_service(name)
        elif kind == "action" and name in self._action_texts:
            self._ensure_action(name)
        else:
            self._ensure_parent(name)
        found = self._individual.get(name)
        if found is not None:
            return found
        store = self._store()
        if name not in store.fielddefs:
            raise self._unknown(name, self.known())
        fields = [_describe_field(fname, desc) for fname, desc in store.fielddefs[name][1]]
        if not fields:  # rosidl gives empty structures one dummy member
            fields = [_field("structure_needs_at_least_one_member", _FIELD_TYPE_ID["uint8"])]
        found = {"type_name": name, "fields": fields}
        self._individual[name] = found
        return found

    # -- CDR ---------------------------------------------------------------------------------

    def _serialize(self, name: str, msg: Any) -> bytes:
        store = self._store()
        try:
            return bytes(store.serialize_cdr(msg, name, little_endian=True))
        except Exception as exc:  # rosbags raises whatever the generated code hits
            raise CdrError(_one_line(f"cannot serialize {name}: {exc}")) from exc

    def _deserialize(self, name: str, data: bytes | bytearray | memoryview) -> Any:
        store = self._store()
        if isinstance(data, (bytearray, memoryview)):
            # Decoded arrays are views of the input: keep them off a buffer that may change.
            try:
                data = bytes(data)
            except (TypeError, ValueError) as exc:
                raise CdrError(f"{name}: unreadable buffer: {exc}") from exc
        if not isinstance(data, bytes):
            raise CdrError(f"{name}: CDR must be bytes, not {type(data).__name__}")
        raw = memoryview(data)
        if len(raw) < 4:
            raise CdrError(f"{name}: {len(raw)} bytes, shorter than the CDR header")
        header = bytes(raw[:2])
        if header not in (b"\x00\x00", b"\x00\x01"):
            raise CdrError(f"{name}: unsupported CDR encapsulation {header.hex()}")
        msgdef = store.get_msgdef(name)
        func = msgdef.deserialize_cdr_le if header[1] else msgdef.deserialize_cdr_be
        body = raw[4:]
        try:
            message, pos = cast("Callable[..., tuple[Any, int]]", func)(body, 0, msgdef.cls, store)
        except Exception as exc:  # truncated, bad lengths, bad UTF-8, ...: all garbage
            raise CdrError(_one_line(f"bad CDR for {name}: {exc}")) from exc
        if pos > len(body):
            raise CdrError(f"bad CDR for {name}: truncated ({len(body)} of {pos} bytes)")
        if len(body) - pos > 3:  # at most alignment padding may follow
            raise CdrError(f"bad CDR for {name}: {len(body) - pos} bytes of trailing junk")
        return message

    def _make(self, name: str, values: dict[str, Any]) -> Any:
        from rosbags.typesys.base import normalize_fieldname

        store = self._store()
        fielddefs = store.fielddefs[name][1]
        known = {fname for fname, _ in fielddefs}
        unknown = sorted(set(values) - known)
        if unknown:
            raise Ros2Error(
                f"{name} has no field {', '.join(unknown)}; fields: {', '.join(sorted(known))}"
            )
        kwargs = {
            normalize_fieldname(fname): self._coerce(name, fname, desc, values[fname])
            if fname in values
            else self._default(desc)
            for fname, desc in fielddefs
        }
        return store.types[name](**kwargs)

    def _coerce(self, name: str, fname: str, desc: Any, value: Any) -> Any:
        """Accept the obvious Python forms: a dict for a nested message; bytes, lists or
        tuples for primitive arrays (rosbags serializes numpy arrays only)."""
        import numpy as np

        kind, arg = desc
        if kind == _NAME:
            return self._make(arg, value) if isinstance(value, dict) else value
        if kind not in (_ARRAY, _SEQUENCE):
            return value
        (sub_kind, sub_arg), count = arg
        if sub_kind == _BASE and sub_arg[0] in _NUMPY_DTYPE:
            dtype = _NUMPY_DTYPE[sub_arg[0]]
            try:
                if isinstance(value, (bytes, bytearray, memoryview)):
                    value = np.frombuffer(value, dtype=dtype)
                else:
                    value = np.asarray(value, dtype=dtype)
            except (TypeError, ValueError) as exc:
                raise Ros2Error(_one_line(f"{name}.{fname}: not {dtype} values: {exc}")) from exc
            if value.ndim != 1:
                raise Ros2Error(f"{name}.{fname}: needs a flat array, got shape {value.shape}")
        elif sub_kind == _NAME and isinstance(value, (list, tuple)):
            value = [self._make(sub_arg, v) if isinstance(v, dict) else v for v in value]
        if kind == _ARRAY and len(value) != count:
            raise Ros2Error(f"{name}.{fname}: needs exactly {count} elements, got {len(value)}")
        if kind == _SEQUENCE and count and len(value) > count:
            raise Ros2Error(f"{name}.{fname}: at most {count} elements, got {len(value)}")
        return value

    def _default(self, desc: Any) -> Any:
        import numpy as np

        kind, arg = desc
        if kind == _BASE:
            return _scalar_default(arg[0])
        if kind == _NAME:
            return self._make(arg, {})
        (sub_kind, sub_arg), count = arg
        if sub_kind == _BASE and sub_arg[0] in _NUMPY_DTYPE:
            length = count if kind == _ARRAY else 0
            return np.zeros(length, dtype=_NUMPY_DTYPE[sub_arg[0]])
        if kind == _SEQUENCE:
            return []
        return [self._default((sub_kind, sub_arg)) for _ in range(count)]


def _scalar_default(typ: str) -> Any:
    if typ == "string":
        return ""
    if typ == "bool":
        return False
    if typ.startswith("float"):
        return 0.0
    return 0


def _one_line(text: str) -> str:
    return " ".join(text.split())[:300]


def _field(
    name: str, type_id: int, *, capacity: int = 0, string_capacity: int = 0, nested: str = ""
) -> dict[str, Any]:
    return {
        "name": name,
        "type": {
            "type_id": type_id,
            "capacity": capacity,
            "string_capacity": string_capacity,
            "nested_type_name": nested,
        },
    }


def _describe_field(name: str, desc: Any) -> dict[str, Any]:
    """REP 2011 description of one field from its rosbags parse tree."""
    kind, arg = desc
    offset, capacity = 0, 0
    if kind in (_ARRAY, _SEQUENCE):
        (kind_inner, arg_inner), count = arg
        if kind == _ARRAY:
            offset, capacity = _ARRAY_OFFSET, count
        elif count:
            offset, capacity = _BOUNDED_SEQUENCE_OFFSET, count
        else:
            offset = _UNBOUNDED_SEQUENCE_OFFSET
        kind, arg = kind_inner, arg_inner
    if kind == _NAME:
        return _field(name, offset + _NESTED_TYPE_ID, capacity=capacity, nested=arg)
    typ, string_capacity = arg
    if typ == "string" and string_capacity:
        return _field(
            name, offset + _BOUNDED_STRING_ID, capacity=capacity, string_capacity=string_capacity
        )
    if typ not in _FIELD_TYPE_ID:
        raise Ros2Error(f"field {name}: type {typ} has no REP 2011 type id")
    return _field(name, offset + _FIELD_TYPE_ID[typ], capacity=capacity)
