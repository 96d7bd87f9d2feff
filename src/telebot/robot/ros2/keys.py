"""rmw_zenoh's wire names, sans-IO: key expressions, QoS text, liveliness tokens, attachments.

Everything here follows rmw_zenoh_cpp's released sources (Jazzy 0.2.10, Kilted 0.6.7: the two
write these formats identically) and its ``docs/design.md``:

- A topic or service is the key ``<domain>/<name without leading/trailing '/'>/<dds type>/
  <RIHS01 type hash>``, e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66…``.
- Every node and endpoint holds a liveliness token
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/
  <node>[/<topic>/<dds type>/<type hash>/<qos>]`` where every ``/`` inside a name is written
  ``%`` (so the root namespace and enclave ``/`` become ``%``).
- The QoS chunk is ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:
  <lifespan s>,<ns>:<liveliness>,<lease s>,<ns>`` with each value left empty where it equals
  rmw_zenoh's default (reliable, volatile, keep last 42, infinite durations, automatic).
- Every sample, query and reply carries a 33-byte attachment: sequence number (int64 LE),
  source timestamp in ns since the epoch (int64 LE), the GID's length (1 byte, 16) and the
  16-byte GID of the publisher or client.
- An entity's GID is the XXH3-128 hash of its liveliness key (low 64 bits first, each little
  endian), which lets a peer tie a request's GID to the client's liveliness token.
"""

from __future__ import annotations

import enum
import os
import struct
from dataclasses import dataclass, field, replace

import xxhash

from telebot.errors import CdrError

__all__ = [
    "ADMIN_SPACE",
    "ATTACHMENT_SIZE",
    "Attachment",
    "Durability",
    "EntityKind",
    "GraphEntity",
    "History",
    "Liveliness",
    "QoS",
    "Reliability",
    "action_names",
    "demangle",
    "entity_gid",
    "graph_selector",
    "mangle",
    "new_gid",
    "parse_liveliness",
    "resolve_name",
    "topic_key",
]

#: The hermetic first chunk of every rmw_zenoh liveliness token.
ADMIN_SPACE = "@ros2_lv"
#: Bytes in an rmw_zenoh attachment: int64 + int64 + 1-byte length + 16-byte GID.
ATTACHMENT_SIZE = 33
GID_SIZE = 16

_ATTACHMENT = struct.Struct("<qqB")
#: rmw's RMW_DURATION_INFINITE as (seconds, nanoseconds).
INFINITE_S = 9_223_372_036
INFINITE_NS = 854_775_807


class EntityKind(enum.StrEnum):
    """The entity chunk of a liveliness token."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class Reliability(enum.IntEnum):
    """rmw_qos_reliability_policy_e."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(enum.IntEnum):
    """rmw_qos_durability_policy_e."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class History(enum.IntEnum):
    """rmw_qos_history_policy_e."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Liveliness(enum.IntEnum):
    """rmw_qos_liveliness_policy_e."""

    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_NODE = 2
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


#: rmw_zenoh's defaults: a field equal to these is written as an empty string.
_DEFAULT_DEPTH = 42


@dataclass(frozen=True)
class QoS:
    """A ROS 2 QoS profile as rmw_zenoh carries it in liveliness tokens.

    The default is rclcpp's default profile (reliable, volatile, keep last 10).
    """

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10
    deadline: tuple[int, int] = (INFINITE_S, INFINITE_NS)
    lifespan: tuple[int, int] = (INFINITE_S, INFINITE_NS)
    liveliness: Liveliness = Liveliness.AUTOMATIC
    liveliness_lease: tuple[int, int] = (INFINITE_S, INFINITE_NS)

    @classmethod
    def transient_local(cls, depth: int = 1) -> QoS:
        """Reliable, transient local, keep last ``depth`` (``/map``, action status)."""
        return cls(durability=Durability.TRANSIENT_LOCAL, depth=depth)

    @classmethod
    def sensor_data(cls, depth: int = 5) -> QoS:
        """rclcpp's SensorDataQoS: best effort, volatile, keep last 5."""
        return cls(reliability=Reliability.BEST_EFFORT, depth=depth)

    @property
    def is_transient_local(self) -> bool:
        """Whether late joiners get the last ``depth`` samples."""
        return self.durability == Durability.TRANSIENT_LOCAL

    @property
    def is_reliable(self) -> bool:
        """Whether samples are sent reliably (best effort otherwise)."""
        return self.reliability != Reliability.BEST_EFFORT

    def with_depth(self, depth: int) -> QoS:
        """This profile with another history depth."""
        return replace(self, depth=depth)

    def keyexpr(self) -> str:
        """The QoS chunk of a liveliness token, exactly as rmw_zenoh writes it."""

        def val(value: int, default: int) -> str:
            return "" if value == default else str(int(value))

        inf = (INFINITE_S, INFINITE_NS)
        return (
            f"{val(self.reliability, Reliability.RELIABLE)}:"
            f"{val(self.durability, Durability.VOLATILE)}:"
            f"{val(self.history, History.KEEP_LAST)},{val(self.depth, _DEFAULT_DEPTH)}:"
            f"{val(self.deadline[0], inf[0])},{val(self.deadline[1], inf[1])}:"
            f"{val(self.lifespan[0], inf[0])},{val(self.lifespan[1], inf[1])}:"
            f"{val(self.liveliness, Liveliness.AUTOMATIC)},"
            f"{val(self.liveliness_lease[0], inf[0])},{val(self.liveliness_lease[1], inf[1])}"
        )

    @classmethod
    def parse(cls, text: str) -> QoS | None:
        """The QoS a token's QoS chunk describes; None when it is not one."""
        parts = text.split(":")
        if len(parts) < 6:
            return None
        history, deadline, lifespan, live = (parts[i].split(",") for i in (2, 3, 4, 5))
        if len(history) < 2 or len(deadline) < 2 or len(lifespan) < 2 or len(live) < 3:
            return None

        def num(chunk: str, default: int, limit: int = 2**64 - 1) -> int:
            if chunk == "":
                return default
            if not chunk.isdigit() or int(chunk) > limit:
                raise ValueError(chunk)
            return int(chunk)

        inf = (INFINITE_S, INFINITE_NS)
        try:
            return cls(
                reliability=Reliability(num(parts[0], Reliability.RELIABLE)),
                durability=Durability(num(parts[1], Durability.VOLATILE)),
                history=History(num(history[0], History.KEEP_LAST)),
                depth=num(history[1], _DEFAULT_DEPTH),
                deadline=(num(deadline[0], inf[0]), num(deadline[1], inf[1])),
                lifespan=(num(lifespan[0], inf[0]), num(lifespan[1], inf[1])),
                liveliness=Liveliness(num(live[0], Liveliness.AUTOMATIC)),
                liveliness_lease=(num(live[1], inf[0]), num(live[2], inf[1])),
            )
        except ValueError:
            return None


def resolve_name(name: str, namespace: str = "") -> str:
    """The fully qualified ROS name: ``name`` if absolute, else under ``namespace``.

    ``resolve_name("map", "/robot1") == "/robot1/map"``; ``resolve_name("/map", "/r") ==
    "/map"``. Raises ValueError (one line) for an empty name or one with ``//``.
    """
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    full = name if name.startswith("/") else f"{ns}/{name}"
    full = full.rstrip("/") if len(full) > 1 else full
    if not name or not full.strip("/") or "//" in full:
        raise ValueError(f"invalid ROS name {name!r} (namespace {namespace!r})")
    return full


def topic_key(domain_id: int, name: str, dds_name: str, type_hash: str) -> str:
    """The zenoh key of a topic or service: ``<domain>/<name>/<dds type>/<hash>``."""
    return f"{domain_id}/{name.strip('/')}/{dds_name}/{type_hash}"


def action_names(name: str) -> dict[str, str]:
    """The three services and two topics an action ``name`` is made of (rclcpp_action's)."""
    base = name.rstrip("/")
    return {
        part: f"{base}/_action/{part}"
        for part in ("send_goal", "get_result", "cancel_goal", "feedback", "status")
    }


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` becomes ``%`` (rmw_zenoh's mangle_name)."""
    return name.replace("/", "%")


def demangle(chunk: str) -> str:
    """The inverse of :func:`mangle`."""
    return chunk.replace("%", "/")


def graph_selector(domain_id: int) -> str:
    """The key expression matching every liveliness token of a ROS domain."""
    return f"{ADMIN_SPACE}/{domain_id}/**"


def entity_gid(liveliness_key: str) -> bytes:
    """An entity's 16-byte GID as rmw_zenoh computes it: XXH3-128 of its liveliness key."""
    digest = xxhash.xxh3_128_intdigest(liveliness_key.encode())
    # rmw_zenoh copies low64 then high64, each in the machine's (little-endian) order.
    return digest.to_bytes(GID_SIZE, "little")


def new_gid() -> bytes:
    """16 random bytes: a GID for something that has no liveliness token."""
    return os.urandom(GID_SIZE)


@dataclass(frozen=True)
class GraphEntity:
    """One node or endpoint of the ROS graph, as its liveliness token describes it.

    ``namespace`` and ``topic`` are fully qualified (``"/"`` is the root namespace);
    ``topic``, ``dds_type``, ``type_hash`` and ``qos`` are None for a node.
    """

    kind: EntityKind
    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    namespace: str
    node_name: str
    enclave: str = "/"
    topic: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: QoS | None = None
    key: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if not self.key:
            object.__setattr__(self, "key", self._compose())

    def _compose(self) -> str:
        parts = [
            ADMIN_SPACE,
            str(self.domain_id),
            self.zid,
            self.node_id,
            self.entity_id,
            str(self.kind),
            mangle(self.enclave),
            mangle(self.namespace),
            mangle(self.node_name),
        ]
        if self.kind != EntityKind.NODE:
            if self.topic is None or self.dds_type is None or self.type_hash is None:
                raise ValueError(f"a {self.kind} token needs a topic, type and hash")
            qos = self.qos if self.qos is not None else QoS()
            parts += [mangle(self.topic), mangle(self.dds_type), mangle(self.type_hash)]
            parts.append(qos.keyexpr())
        return "/".join(parts)

    @property
    def gid(self) -> bytes:
        """This entity's GID (see :func:`entity_gid`)."""
        return entity_gid(self.key)

    @property
    def node_fqn(self) -> str:
        """The node's fully qualified name, ``/ns/name``."""
        return resolve_name(self.node_name, self.namespace)


_ENTITY_KINDS = {kind.value: kind for kind in EntityKind}


def parse_liveliness(key: str) -> GraphEntity | None:
    """The entity a liveliness key describes; None for anything that is not an rmw_zenoh token."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(not part for part in parts):
        return None
    kind = _ENTITY_KINDS.get(parts[5])
    if kind is None or not parts[1].isdigit():
        return None
    common = {
        "kind": kind,
        "domain_id": int(parts[1]),
        "zid": parts[2],
        "node_id": parts[3],
        "entity_id": parts[4],
        "enclave": demangle(parts[6]),
        "namespace": demangle(parts[7]),
        "node_name": demangle(parts[8]),
        "key": key,
    }
    if kind == EntityKind.NODE:
        return GraphEntity(**common) if len(parts) == 9 else None  # type: ignore[arg-type]
    if len(parts) != 13:
        return None
    qos = QoS.parse(parts[12])
    if qos is None:
        return None
    return GraphEntity(
        **common,  # type: ignore[arg-type]
        topic=demangle(parts[9]),
        dds_type=demangle(parts[10]),
        type_hash=demangle(parts[11]),
        qos=qos,
    )


@dataclass(frozen=True)
class Attachment:
    """The attachment rmw_zenoh puts on every sample, query and reply."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        """The 33 bytes on the wire."""
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(self.gid)}")
        head = _ATTACHMENT.pack(self.sequence_number, self.source_timestamp_ns, GID_SIZE)
        return head + bytes(self.gid)

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """Parse an attachment; CdrError (one line) for anything but the 33-byte layout."""
        if len(data) != ATTACHMENT_SIZE:
            raise CdrError(f"attachment is {len(data)} bytes, expected {ATTACHMENT_SIZE}")
        seq, stamp, gid_len = _ATTACHMENT.unpack_from(data)
        if gid_len != GID_SIZE:
            raise CdrError(f"attachment GID length is {gid_len}, expected {GID_SIZE}")
        return cls(seq, stamp, bytes(data[_ATTACHMENT.size :]))
