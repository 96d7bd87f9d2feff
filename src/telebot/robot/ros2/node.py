"""A ROS 2 node on its own zenoh session, speaking rmw_zenoh's wire format (no ROS installed).

:class:`Ros2Node` opens a zenoh session (a client of rmw_zenoh's router by default), declares
its node's liveliness token (so ``ros2 node list`` shows it) and makes publishers,
subscriptions, service clients and servers, action clients and servers on it, each with the
liveliness token rmw_zenoh would declare (see :mod:`.keys` for the formats).

Threads: zenoh calls our callbacks on its own threads. Every callback here catches
everything: a peer's garbage (bad CDR, a missing or short attachment, another type on the
topic's name) is dropped, counted in the endpoint's ``stats`` and logged as one line naming
the topic (at most one line per endpoint and reason every :data:`LOG_EVERY` seconds); an
exception in a user callback is counted and logged the same way. Nothing raises into zenoh.

Liveliness tokens are kept referenced by their endpoint for as long as it lives: zenoh-python
undeclares a token when its Python object is garbage-collected.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeVar

import numpy as np
import zenoh
import zenoh.ext

from telebot.errors import CdrError, RobotUnreachable, Ros2Error
from telebot.robot.ros2.keys import (
    Attachment,
    EntityKind,
    GraphEntity,
    QoS,
    Reliability,
    action_names,
    graph_selector,
    parse_liveliness,
    resolve_name,
    topic_key,
)

if TYPE_CHECKING:
    from telebot.rosmsg.types import ActionType, MessageType, ServiceType, TypeLibrary

__all__ = [
    "GOAL_ABORTED",
    "GOAL_ACCEPTED",
    "GOAL_CANCELED",
    "GOAL_CANCELING",
    "GOAL_EXECUTING",
    "GOAL_SUCCEEDED",
    "GOAL_UNKNOWN",
    "ActionClient",
    "ActionServer",
    "EndpointStats",
    "Publisher",
    "Responder",
    "Ros2Node",
    "ServiceClient",
    "ServiceServer",
    "Subscription",
]

logger = logging.getLogger(__name__)

_E = TypeVar("_E", bound="_Endpoint")

#: QoS of an endpoint declared without one (rclcpp's default: reliable, volatile, depth 10).
DEFAULT_QOS = QoS()


class _Undeclarable(Protocol):
    # zenoh's stubs leave undeclare()/close() unannotated; this gives our calls a type.
    def undeclare(self) -> None: ...


class _Closable(Protocol):
    def close(self) -> None: ...


def _undeclare(raw: _Undeclarable) -> None:
    # zenoh-python's objects are Rust cells: while another thread is inside one of the
    # object's methods (a put from an executor, a cache query on an advanced publisher),
    # undeclare() raises "Already borrowed" instead of waiting. That method returns within
    # microseconds, so wait for it (up to ~50 ms) rather than leak the declaration.
    for attempt in range(50):
        try:
            raw.undeclare()
            return
        except RuntimeError as exc:
            if "Already borrowed" not in str(exc) or attempt == 49:
                raise
            time.sleep(0.001)


def _close(raw: _Closable) -> None:
    raw.close()


#: Seconds between two log lines about the same endpoint and reason.
LOG_EVERY = 5.0
#: rmw_zenoh's heartbeat period (s) for reliable transient-local publishers.
HEARTBEAT_PERIOD = 0.5
#: A request that reached no server goes again after this many seconds (until its timeout).
RETRY_GAP = 0.05
#: A GetResult request waits this long (s): rmw_zenoh waits forever, we wait a day.
RESULT_TIMEOUT = 86_400.0

# action_msgs/msg/GoalStatus codes.
GOAL_UNKNOWN = 0
GOAL_ACCEPTED = 1
GOAL_EXECUTING = 2
GOAL_CANCELING = 3
GOAL_SUCCEEDED = 4
GOAL_CANCELED = 5
GOAL_ABORTED = 6
_TERMINAL = frozenset({GOAL_SUCCEEDED, GOAL_CANCELED, GOAL_ABORTED})

# action_msgs/srv/CancelGoal return codes.
CANCEL_NONE = 0
CANCEL_REJECTED = 1
CANCEL_UNKNOWN_GOAL = 2
CANCEL_TERMINATED = 3


@dataclass
class EndpointStats:
    """What one endpoint received, delivered and dropped (and why)."""

    received: int = 0  # samples, requests or replies that arrived
    delivered: int = 0  # handed to the callback / handler
    sent: int = 0  # samples published, requests sent, replies sent
    bad_cdr: int = 0  # payload that is not CDR of the expected type
    bad_attachment: int = 0  # attachment missing or not rmw_zenoh's 33 bytes
    wrong_type: int = 0  # a sample on our topic name with another type name or hash
    too_large: int = 0  # over the subscription's max_bytes
    callback_errors: int = 0  # our user's callback raised

    @property
    def dropped(self) -> int:
        """Everything that arrived and was not delivered."""
        return self.bad_cdr + self.bad_attachment + self.wrong_type + self.too_large


class _LogLimiter:
    """One log line per (endpoint, reason) every :data:`LOG_EVERY` seconds."""

    def __init__(self) -> None:
        self._last: dict[str, float] = {}
        self._lock = threading.Lock()

    def warn(self, reason: str, message: str, *args: object) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._last.get(reason)
            if last is not None and now - last < LOG_EVERY:
                return
            self._last[reason] = now
        logger.warning(message, *args)


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text.split(" at /")[0]  # zenoh appends the Rust source location


def _payload(data: Any) -> bytes:
    return b"" if data is None else bytes(data.to_bytes())


def _uuid_bytes(uuid_msg: Any) -> bytes:
    return bytes(np.asarray(uuid_msg.uuid, dtype=np.uint8).tobytes())


class Ros2Node:
    """One ROS 2 node on its own zenoh session. Thread-safe. Callbacks run on zenoh's threads.

    ``connect`` lists zenoh endpoints of rmw_zenoh's router (``tcp/host:7447``); a router that
    does not answer within ``connect_timeout`` seconds raises :class:`RobotUnreachable`.
    ``zenoh_options`` (config path -> value) are inserted into the zenoh config last.
    Names not starting with ``/`` are relative to ``namespace``.
    """

    def __init__(
        self,
        *,
        name: str,
        namespace: str = "",
        domain_id: int = 0,
        connect: Sequence[str] = (),
        mode: Literal["client", "peer"] = "client",
        listen: Sequence[str] = (),
        library: TypeLibrary | None = None,
        zenoh_options: Mapping[str, Any] | None = None,
        connect_timeout: float = 5.0,
        enclave: str = "/",
    ) -> None:
        if library is None:
            from telebot.rosmsg.types import TypeLibrary

            library = TypeLibrary()
        self.library = library
        self.name = name
        self.namespace = "/" + namespace.strip("/") if namespace.strip("/") else "/"
        self.domain_id = domain_id
        self.enclave = enclave
        self._lock = threading.RLock()
        self._ids = itertools.count()
        self._closed = False
        self._endpoints: list[_Endpoint] = []
        self._graph: dict[str, GraphEntity] = {}
        self._graph_listeners: list[Callable[[GraphEntity, bool], None]] = []
        self._log = _LogLimiter()
        #: Liveliness tokens that are not rmw_zenoh's (counted, never raised).
        self.bad_tokens = 0
        config = self._config(mode, connect, listen, connect_timeout, zenoh_options or {})
        where = ", ".join(connect) if connect else "(zenoh's default endpoints)"
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as exc:
            raise RobotUnreachable(f"no zenoh router at {where}: {_reason(exc)}") from exc
        self.zid = str(self._session.info.zid())
        self._node_id = str(next(self._ids))
        try:
            self._graph_sub = self._session.liveliness().declare_subscriber(
                graph_selector(domain_id), self._on_token, history=True
            )
            self.entity = GraphEntity(
                kind=EntityKind.NODE,
                domain_id=domain_id,
                zid=self.zid,
                node_id=self._node_id,
                entity_id=self._node_id,
                namespace=self.namespace,
                node_name=name,
                enclave=enclave,
            )
            self._token = self._session.liveliness().declare_token(self.entity.key)
        except zenoh.ZError as exc:
            _close(self._session)
            raise Ros2Error(f"cannot declare node {name!r}: {_reason(exc)}") from exc

    @staticmethod
    def _config(
        mode: str,
        connect: Sequence[str],
        listen: Sequence[str],
        connect_timeout: float,
        options: Mapping[str, Any],
    ) -> zenoh.Config:
        config = zenoh.Config()
        values: dict[str, Any] = {
            "mode": mode,
            "scouting/multicast/enabled": False,
            # A client gives up after connect_timeout (zenoh.open raises); rmw_zenoh's
            # client default is to exit on failure too.
            "connect/timeout_ms": {"client": int(connect_timeout * 1000), "peer": -1},
            "connect/exit_on_failure": {"client": True, "peer": False},
            # As rmw_zenoh's session config: samples carry HLC timestamps.
            "timestamping/enabled": {"router": True, "peer": True, "client": True},
        }
        if connect:
            values["connect/endpoints"] = list(connect)
        if listen:
            values["listen/endpoints"] = list(listen)
        values.update(options)
        for path, value in values.items():
            try:
                config.insert_json5(path, json.dumps(value))
            except zenoh.ZError as exc:
                raise Ros2Error(f"bad zenoh option {path} = {value!r}: {_reason(exc)}") from exc
        return config

    # ----------------------------------------------------------------- lifecycle

    @property
    def session(self) -> zenoh.Session:
        """The zenoh session (for what this class does not cover)."""
        return self._session

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` ran."""
        return self._closed

    def close(self) -> None:
        """Undeclare every endpoint and token and close the session. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            endpoints, self._endpoints = self._endpoints, []
        for endpoint in reversed(endpoints):
            endpoint.close()
        steps: tuple[Callable[[], None], ...] = (
            lambda: _undeclare(self._token),
            lambda: _undeclare(self._graph_sub),
            lambda: _close(self._session),
        )
        for step in steps:
            try:
                step()
            except zenoh.ZError as exc:  # closing must not raise: log and go on
                logger.debug("closing ROS node %s: %s", self.name, _reason(exc))

    def __enter__(self) -> Ros2Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def resolve(self, name: str) -> str:
        """``name`` fully qualified (relative names are under the node's namespace)."""
        return resolve_name(name, self.namespace)

    # ----------------------------------------------------------------- endpoints

    def publisher(self, topic: str, mtype: MessageType, *, qos: QoS = DEFAULT_QOS) -> Publisher:
        """Declare a publisher (transient local: zenoh's advanced publisher with a cache)."""
        return self._add(Publisher(self, self.resolve(topic), mtype, qos))

    def subscribe(
        self,
        topic: str,
        mtype: MessageType,
        callback: Callable[[Any, Attachment], None],
        *,
        qos: QoS = DEFAULT_QOS,
        max_bytes: int | None = None,
    ) -> Subscription:
        """Subscribe to ``topic``; ``callback(msg, attachment)`` runs on a zenoh thread.

        Transient local: an advanced subscriber that asks late-joined publishers for their
        cache, so ``/map`` published before we joined arrives. Samples over ``max_bytes``
        are dropped (counted, logged) before they are decoded.
        """
        sub = Subscription(self, self.resolve(topic), mtype, callback, qos, max_bytes)
        return self._add(sub)

    def subscribe_raw(
        self,
        topic: str,
        dds_type: str,
        type_hash: str,
        callback: Callable[[bytes, Attachment], None],
        *,
        qos: QoS = DEFAULT_QOS,
        max_bytes: int | None = None,
    ) -> Subscription:
        """Subscribe to ``topic`` without decoding: ``callback(cdr, attachment)`` gets each
        sample's bytes unchanged (encapsulation header included), on a zenoh thread.

        For any type on the graph, known to the type library or not (the topic relay).
        """
        from telebot.rosmsg.types import MessageType, ros_type_name

        mtype = MessageType(ros_type_name(dds_type), dds_type, type_hash, self.library)
        sub = Subscription(self, self.resolve(topic), mtype, callback, qos, max_bytes, raw=True)
        return self._add(sub)

    def service_client(self, name: str, stype: ServiceType) -> ServiceClient:
        """A client of the service ``name``."""
        return self._add(ServiceClient(self, self.resolve(name), stype))

    def service_server(
        self, name: str, stype: ServiceType, handler: Callable[[Any, Responder], None]
    ) -> ServiceServer:
        """Serve ``name``: ``handler(request, responder)``; reply now or later."""
        return self._add(ServiceServer(self, self.resolve(name), stype, handler))

    def action_client(self, name: str, atype: ActionType) -> ActionClient:
        """A client of the action ``name`` (three services, two topics)."""
        return ActionClient(self, name, atype)

    def action_server(
        self,
        name: str,
        atype: ActionType,
        *,
        on_goal: Callable[[bytes, Any], bool],
        on_cancel: Callable[[bytes], bool] = lambda goal_id: True,
    ) -> ActionServer:
        """Serve the action ``name`` (see :class:`ActionServer`)."""
        return ActionServer(self, name, atype, on_goal=on_goal, on_cancel=on_cancel)

    def _add(self, endpoint: _E) -> _E:
        with self._lock:
            if self._closed:
                endpoint.close()
                raise Ros2Error(f"ROS node {self.name} is closed")
            self._endpoints.append(endpoint)
        return endpoint

    def _remove(self, endpoint: _Endpoint) -> None:
        with self._lock:
            if endpoint in self._endpoints:
                self._endpoints.remove(endpoint)

    def _declare_token(
        self, kind: EntityKind, topic: str, dds_type: str, type_hash: str, qos: QoS
    ) -> tuple[GraphEntity, zenoh.LivelinessToken]:
        entity = GraphEntity(
            kind=kind,
            domain_id=self.domain_id,
            zid=self.zid,
            node_id=self._node_id,
            entity_id=str(next(self._ids)),
            namespace=self.namespace,
            node_name=self.name,
            enclave=self.enclave,
            topic=topic,
            dds_type=dds_type,
            type_hash=type_hash,
            qos=qos,
        )
        try:
            token = self._session.liveliness().declare_token(entity.key)
        except zenoh.ZError as exc:
            raise Ros2Error(f"cannot declare {kind} token for {topic}: {_reason(exc)}") from exc
        return entity, token

    # ----------------------------------------------------------------- graph

    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            key = str(sample.key_expr)
            if sample.kind == zenoh.SampleKind.DELETE:
                with self._lock:
                    gone = self._graph.pop(key, None)
                if gone is not None:
                    self._notify(gone, False)
                return
            entity = parse_liveliness(key)
            if entity is None:
                self.bad_tokens += 1
                self._log.warn("token", "ROS graph: ignoring a liveliness token %r", key[:200])
                return
            with self._lock:
                known = key in self._graph
                self._graph[key] = entity
            if not known:
                self._notify(entity, True)
        except Exception as exc:  # never raise into zenoh
            self._log.warn("token-error", "ROS graph: token dropped: %s", _reason(exc))

    def _notify(self, entity: GraphEntity, alive: bool) -> None:
        with self._lock:
            listeners = list(self._graph_listeners)
        for listener in listeners:
            try:
                listener(entity, alive)
            except Exception as exc:
                self._log.warn("graph-cb", "ROS graph callback failed: %s", _reason(exc))

    def graph(self, *, refresh: bool = False, timeout: float = 2.0) -> list[GraphEntity]:
        """The entities of the ROS graph now (this node's own included).

        From the liveliness subscription kept up to date since the node opened; with
        ``refresh``, first a liveliness query (up to ``timeout`` s) for what is there now.
        """
        if refresh:
            found: dict[str, GraphEntity] = {}
            try:
                replies = self._session.liveliness().get(
                    graph_selector(self.domain_id), timeout=timeout
                )
                for reply in replies:
                    if reply.ok is not None:
                        key = str(reply.ok.key_expr)
                        entity = parse_liveliness(key)
                        if entity is not None:
                            found[key] = entity
            except zenoh.ZError as exc:
                raise Ros2Error(f"ROS graph query failed: {_reason(exc)}") from exc
            with self._lock:
                self._graph.update(found)
        with self._lock:
            return list(self._graph.values())

    def on_graph_change(self, callback: Callable[[GraphEntity, bool], None]) -> Callable[[], None]:
        """Call ``callback(entity, alive)`` as tokens appear and disappear; returns an
        unregister function. Runs on a zenoh thread."""
        with self._lock:
            self._graph_listeners.append(callback)

        def unregister() -> None:
            with self._lock:
                if callback in self._graph_listeners:
                    self._graph_listeners.remove(callback)

        return unregister

    def find(self, kind: EntityKind, name: str, dds_type: str | None = None) -> list[GraphEntity]:
        """Entities of ``kind`` on topic/service ``name`` (and of ``dds_type`` if given)."""
        full = self.resolve(name)
        with self._lock:
            return [
                e
                for e in self._graph.values()
                if e.kind == kind
                and e.topic == full
                and (dds_type is None or e.dds_type == dds_type)
            ]

    def entity_by_gid(self, gid: bytes) -> GraphEntity | None:
        """The live entity whose GID (XXH3 of its token) is ``gid``, if any."""
        with self._lock:
            for entity in self._graph.values():
                if entity.kind != EntityKind.NODE and entity.gid == gid:
                    return entity
        return None

    def topic_types(self, topic: str) -> list[tuple[str, str]]:
        """The (dds type, type hash) pairs the graph's endpoints use on ``topic``."""
        full = self.resolve(topic)
        with self._lock:
            return sorted(
                {
                    (e.dds_type, e.type_hash)
                    for e in self._graph.values()
                    if e.topic == full and e.dds_type is not None and e.type_hash is not None
                }
            )


class _Endpoint:
    """Something declared on a node, with a liveliness token and stats."""

    kind: EntityKind

    def __init__(self, node: Ros2Node, name: str, dds_type: str, type_hash: str, qos: QoS):
        self.node = node
        self.name = name
        self.qos = qos
        self.key = topic_key(node.domain_id, name, dds_type, type_hash)
        self.stats = EndpointStats()
        self._lock = threading.Lock()
        self._closed = False
        self.entity, self._token = node._declare_token(self.kind, name, dds_type, type_hash, qos)
        self.gid = self.entity.gid

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` ran (or the node closed)."""
        return self._closed

    def close(self) -> None:
        """Undeclare this endpoint and its token. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self.node._remove(self)
        for undeclare in self._undeclarers():
            try:
                undeclare()
            except zenoh.ZError as exc:
                logger.debug("closing %s: %s", self.name, _reason(exc))

    def _undeclarers(self) -> list[Callable[[], Any]]:
        return [lambda: _undeclare(self._token)]

    def _drop(self, counter: str, what: str) -> None:
        setattr(self.stats, counter, getattr(self.stats, counter) + 1)
        self.node._log.warn(
            f"{self.key}:{counter}",
            "ROS %s %s: dropped %s (%d dropped so far)",
            self.kind.name.lower(),
            self.name,
            what,
            self.stats.dropped,
        )


class Publisher(_Endpoint):
    """Publishes messages of one type on one topic, with rmw_zenoh's attachment."""

    kind = EntityKind.PUBLISHER

    def __init__(self, node: Ros2Node, topic: str, mtype: MessageType, qos: QoS) -> None:
        super().__init__(node, topic, mtype.dds_name, mtype.type_hash, qos)
        self.mtype = mtype
        self._seq = 1
        reliability = (
            zenoh.Reliability.RELIABLE if qos.is_reliable else zenoh.Reliability.BEST_EFFORT
        )
        congestion = zenoh.CongestionControl.DROP
        try:
            if qos.is_transient_local:
                # As rmw_zenoh: a cache of `depth` samples that late joiners query, detectable
                # publishers, and (reliable) sporadic heartbeats for last-sample recovery.
                miss = (
                    zenoh.ext.MissDetectionConfig(
                        heartbeat=None, sporadic_heartbeat=HEARTBEAT_PERIOD
                    )
                    if qos.is_reliable
                    else None
                )
                self._raw: Any = zenoh.ext.declare_advanced_publisher(
                    node.session,
                    self.key,
                    congestion_control=congestion,
                    reliability=reliability,
                    cache=zenoh.ext.CacheConfig(max(1, qos.depth)),
                    sample_miss_detection=miss,
                    publisher_detection=True,
                )
            else:
                self._raw = node.session.declare_publisher(
                    self.key, congestion_control=congestion, reliability=reliability
                )
        except zenoh.ZError as exc:
            _undeclare(self._token)
            raise Ros2Error(f"cannot publish on {topic}: {_reason(exc)}") from exc

    def _undeclarers(self) -> list[Callable[[], Any]]:
        return [lambda: _undeclare(self._raw), lambda: _undeclare(self._token)]

    def publish(self, msg: Any) -> None:
        """Serialize ``msg`` (CdrError if it is not a valid message of the type) and publish."""
        self.publish_cdr(self.mtype.serialize(msg))

    def publish_cdr(self, data: bytes) -> None:
        """Publish already-serialized CDR (with its 4-byte encapsulation header)."""
        with self._lock:
            if self._closed:
                raise Ros2Error(f"publisher on {self.name} is closed")
            seq = self._seq
            self._seq += 1
        attachment = Attachment(seq, time.time_ns(), self.gid).encode()
        try:
            self._raw.put(data, attachment=attachment)
        except zenoh.ZError as exc:
            raise Ros2Error(f"cannot publish on {self.name}: {_reason(exc)}") from exc
        self.stats.sent += 1

    def subscriber_count(self) -> int:
        """How many subscriptions of this topic and type the ROS graph has (ours included)."""
        return len(self.node.find(EntityKind.SUBSCRIPTION, self.name, self.mtype.dds_name))


class Subscription(_Endpoint):
    """Delivers decoded messages of one type on one topic to a callback."""

    kind = EntityKind.SUBSCRIPTION

    def __init__(
        self,
        node: Ros2Node,
        topic: str,
        mtype: MessageType,
        callback: Callable[[Any, Attachment], None],
        qos: QoS,
        max_bytes: int | None,
        *,
        raw: bool = False,
    ) -> None:
        super().__init__(node, topic, mtype.dds_name, mtype.type_hash, qos)
        self.mtype = mtype
        #: Deliver the CDR bytes as they came (no decoding).
        self.raw = raw
        self.max_bytes = max_bytes
        self._callback = callback
        # Any type name and hash on this topic's name: a peer's wrong type is then seen,
        # counted and logged instead of silently never arriving.
        selector = f"{node.domain_id}/{topic.strip('/')}/*/*"
        try:
            if qos.is_transient_local:
                recovery = zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True)
                self._raw: Any = zenoh.ext.declare_advanced_subscriber(
                    node.session,
                    selector,
                    self._on_sample,
                    history=zenoh.ext.HistoryConfig(
                        detect_late_publishers=True, max_samples=max(1, qos.depth)
                    ),
                    recovery=recovery if qos.reliability == Reliability.RELIABLE else None,
                    subscriber_detection=True,
                )
            else:
                self._raw = node.session.declare_subscriber(selector, self._on_sample)
        except zenoh.ZError as exc:
            _undeclare(self._token)
            raise Ros2Error(f"cannot subscribe to {topic}: {_reason(exc)}") from exc

    def _undeclarers(self) -> list[Callable[[], Any]]:
        return [lambda: _undeclare(self._raw), lambda: _undeclare(self._token)]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self._handle(sample)
        except Exception as exc:  # never raise into zenoh
            self._drop("callback_errors", f"a sample: {_reason(exc)}")

    def _handle(self, sample: zenoh.Sample) -> None:
        if self._closed or sample.kind != zenoh.SampleKind.PUT:
            return
        self.stats.received += 1
        _, dds_type, type_hash = str(sample.key_expr).rsplit("/", 2)
        if dds_type != self.mtype.dds_name or type_hash != self.mtype.type_hash:
            self._drop(
                "wrong_type",
                f"a sample of type {dds_type} {type_hash[:19]}… "
                f"(expected {self.mtype.dds_name} {self.mtype.type_hash[:19]}…)",
            )
            return
        if sample.attachment is None:
            self._drop("bad_attachment", "a sample without attachment")
            return
        try:
            attachment = Attachment.decode(_payload(sample.attachment))
        except CdrError as exc:
            self._drop("bad_attachment", f"a sample: {exc}")
            return
        data = _payload(sample.payload)
        if self.max_bytes is not None and len(data) > self.max_bytes:
            self._drop("too_large", f"a {len(data)}-byte sample (limit {self.max_bytes})")
            return
        try:
            msg = data if self.raw else self.mtype.deserialize(data)
        except Exception as exc:  # CdrError, and whatever a broken decoder raises
            self._drop("bad_cdr", f"a sample that is not {self.mtype.name}: {_reason(exc)}")
            return
        self.stats.delivered += 1
        try:
            self._callback(msg, attachment)
        except Exception as exc:
            self.stats.callback_errors += 1
            self.node._log.warn(
                f"{self.key}:callback",
                "ROS subscription %s: callback failed: %s",
                self.name,
                _reason(exc),
            )


class ServiceClient(_Endpoint):
    """Calls one service; replies arrive on a zenoh thread."""

    kind = EntityKind.CLIENT

    def __init__(self, node: Ros2Node, name: str, stype: ServiceType) -> None:
        super().__init__(node, name, stype.dds_name, stype.type_hash, QoS())
        self.stype = stype
        self._seq = 1

    def available(self) -> bool:
        """Whether a server of this service (same type and hash) is in the ROS graph."""
        return any(
            e.type_hash == self.stype.type_hash
            for e in self.node.find(EntityKind.SERVICE, self.name, self.stype.dds_name)
        )

    def call(
        self,
        request: Any,
        on_done: Callable[[Any | None, str], None],
        timeout: float = 5.0,
    ) -> int:
        """Send ``request`` without blocking; returns its sequence number.

        ``on_done(response, "")`` or ``on_done(None, why)`` runs exactly once, on a zenoh
        thread (or on this one when the request could not be sent). A request that is not a
        valid message of the request type raises CdrError here.
        """
        payload = self.stype.request.serialize(request)
        with self._lock:
            seq = self._seq
            self._seq += 1
        call = _PendingCall(self, seq, payload, on_done, timeout)
        call.send()
        self.stats.sent += 1
        return seq

    def call_sync(self, request: Any, timeout: float = 5.0) -> Any:
        """Call and wait: the response, TimeoutError, or Ros2Error with the reason."""
        done = threading.Event()
        result: list[tuple[Any | None, str]] = []

        def on_done(response: Any | None, why: str) -> None:
            result.append((response, why))
            done.set()

        self.call(request, on_done, timeout)
        if not done.wait(timeout + 2.0):
            raise TimeoutError(f"no reply from {self.name} within {timeout:g} s")
        response, why = result[0]
        if response is None:
            if "within" in why:
                raise TimeoutError(why)
            raise Ros2Error(why)
        return response


class _PendingCall:
    """One request in flight: ``on_done`` runs exactly once."""

    def __init__(
        self,
        client: ServiceClient,
        seq: int,
        payload: bytes,
        on_done: Callable[[Any | None, str], None],
        timeout: float,
    ) -> None:
        self.client = client
        self.seq = seq
        self.payload = payload
        self.on_done = on_done
        self.timeout = timeout
        self.deadline = time.monotonic() + timeout
        self._done = False
        self._lock = threading.Lock()

    def send(self) -> None:
        """Send (or resend) the query with the time left."""
        client = self.client
        if client.closed or client.node.closed:
            self.finish(None, f"service client {client.name} is closed")
            return
        left = self.deadline - time.monotonic()
        attachment = Attachment(self.seq, time.time_ns(), client.gid).encode()
        try:
            client.node.session.get(
                client.key,
                zenoh.handlers.Callback(self.on_reply, self.on_end),
                target=zenoh.QueryTarget.ALL_COMPLETE,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=max(left, 0.001),
                payload=self.payload,
                attachment=attachment,
            )
        except zenoh.ZError as exc:
            self.finish(None, f"cannot call {client.name}: {_reason(exc)}")

    def finish(self, response: Any | None, why: str) -> None:
        with self._lock:
            if self._done:
                return
            self._done = True
        try:
            self.on_done(response, why)
        except Exception as exc:
            self.client.node._log.warn(
                f"{self.client.key}:on_done",
                "ROS service %s: on_done failed: %s",
                self.client.name,
                _reason(exc),
            )

    def on_reply(self, reply: zenoh.Reply) -> None:
        try:
            self._on_reply(reply)
        except Exception as exc:  # never raise into zenoh
            self.finish(None, f"bad reply from {self.client.name}: {_reason(exc)}")

    def _on_reply(self, reply: zenoh.Reply) -> None:
        client = self.client
        client.stats.received += 1
        sample = reply.ok
        if sample is None:
            err = reply.err
            text = _payload(err.payload).decode("utf-8", "replace") if err is not None else ""
            self.finish(None, f"service {client.name} failed: {text[:200] or 'error reply'}")
            return
        if sample.attachment is None:
            client._drop("bad_attachment", "a reply without attachment")
            self.finish(None, f"service {client.name} replied without attachment")
            return
        try:
            Attachment.decode(_payload(sample.attachment))
            response = client.stype.response.deserialize(_payload(sample.payload))
        except CdrError as exc:
            client._drop("bad_cdr", f"a reply: {exc}")
            self.finish(None, f"service {client.name} sent a bad reply: {exc}")
            return
        client.stats.delivered += 1
        self.finish(response, "")

    def on_end(self) -> None:
        """The query ended; without a reply, resend it while time is left.

        A query that reached no queryable ends at once. That happens while the client's
        zenoh session has not yet learnt of a server that has just appeared (its liveliness
        token can arrive first), so the request goes again, as a ROS client would wait.
        """
        with self._lock:
            if self._done:
                return
        if self.deadline - time.monotonic() > RETRY_GAP and not self.client.closed:
            timer = threading.Timer(RETRY_GAP, self.send)
            timer.daemon = True
            timer.start()
            return
        why = f"no reply from service {self.client.name} within {self.timeout:g} s"
        if not self.client.available():
            why += " (no server in the ROS graph)"
        self.finish(None, why)


class Responder:
    """Answers one service request, now or later, from any thread (once)."""

    def __init__(self, server: ServiceServer, query: zenoh.Query, attachment: Attachment) -> None:
        self.server = server
        self.attachment = attachment
        self._query: zenoh.Query | None = query
        self._lock = threading.Lock()

    @property
    def client_gid(self) -> bytes:
        """The GID of the calling client (rmw_zenoh's: XXH3 of its liveliness key)."""
        return self.attachment.gid

    @property
    def replied(self) -> bool:
        """Whether :meth:`reply` or :meth:`fail` ran."""
        return self._query is None

    def _take(self) -> zenoh.Query | None:
        with self._lock:
            query, self._query = self._query, None
        return query

    def reply(self, response: Any) -> None:
        """Send ``response`` (a message of the response type). Later calls do nothing."""
        query = self._take()
        if query is None:
            return
        server = self.server
        try:
            data = server.stype.response.serialize(response)
            attachment = Attachment(
                self.attachment.sequence_number, time.time_ns(), self.attachment.gid
            ).encode()
            query.reply(server.key, data, attachment=attachment)
            server.stats.sent += 1
        except Exception as exc:  # a bad response or a closed session: log, fail the call
            server.node._log.warn(
                f"{server.key}:reply",
                "ROS service %s: cannot reply: %s",
                server.name,
                _reason(exc),
            )
            _refuse(query, f"cannot reply: {_reason(exc)}")
            return
        _quietly(query.drop)

    def fail(self, why: str) -> None:
        """Answer with a zenoh error reply (rmw_zenoh clients log it and get no response)."""
        query = self._take()
        if query is None:
            return
        _refuse(query, why)


def _quietly(action: Callable[[], Any]) -> None:
    try:
        action()
    except Exception as exc:  # a best-effort answer to a peer that may be gone
        logger.debug("ignored: %s", _reason(exc))


class ServiceServer(_Endpoint):
    """Serves one service; ``handler(request, responder)`` runs on a zenoh thread."""

    kind = EntityKind.SERVICE

    def __init__(
        self,
        node: Ros2Node,
        name: str,
        stype: ServiceType,
        handler: Callable[[Any, Responder], None],
    ) -> None:
        super().__init__(node, name, stype.dds_name, stype.type_hash, QoS())
        self.stype = stype
        self._handler = handler
        try:
            self._raw = node.session.declare_queryable(self.key, self._on_query, complete=True)
        except zenoh.ZError as exc:
            _undeclare(self._token)
            raise Ros2Error(f"cannot serve {name}: {_reason(exc)}") from exc

    def _undeclarers(self) -> list[Callable[[], Any]]:
        return [lambda: _undeclare(self._raw), lambda: _undeclare(self._token)]

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            self._handle(query)
        except Exception as exc:  # never raise into zenoh
            self._drop("callback_errors", f"a request: {_reason(exc)}")
            _refuse(query, "request failed")

    def _handle(self, query: zenoh.Query) -> None:
        self.stats.received += 1
        try:
            if query.attachment is None:
                raise CdrError("request without attachment")
            attachment = Attachment.decode(_payload(query.attachment))
        except CdrError as exc:
            self._drop("bad_attachment", f"a request: {exc}")
            _refuse(query, f"bad request attachment: {exc}")
            return
        try:
            request = self.stype.request.deserialize(_payload(query.payload))
        except Exception as exc:
            self._drop("bad_cdr", f"a request that is not {self.stype.name}: {_reason(exc)}")
            _refuse(query, f"bad request: {_reason(exc)}")
            return
        self.stats.delivered += 1
        responder = Responder(self, query, attachment)
        try:
            self._handler(request, responder)
        except Exception as exc:
            self.stats.callback_errors += 1
            self.node._log.warn(
                f"{self.key}:handler",
                "ROS service %s: handler failed: %s",
                self.name,
                _reason(exc),
            )
            responder.fail(f"service handler failed: {_reason(exc)}")


def _refuse(query: zenoh.Query, why: str) -> None:
    """Answer a request we cannot serve with an error reply, then finalize it."""
    _quietly(lambda: query.reply_err(why))
    _quietly(query.drop)


# ===================================================================== actions


def _now_stamp() -> tuple[int, int]:
    now = time.time_ns()
    return now // 1_000_000_000, now % 1_000_000_000


class _ActionParts:
    """The message types an action client and server both need."""

    def __init__(self, node: Ros2Node, atype: ActionType) -> None:
        lib = node.library
        self.atype = atype
        self.uuid = lib.message("unique_identifier_msgs/msg/UUID")
        self.time = lib.message("builtin_interfaces/msg/Time")
        self.goal_info = lib.message("action_msgs/msg/GoalInfo")
        self.goal_status = lib.message("action_msgs/msg/GoalStatus")

    def uuid_msg(self, goal_id: bytes) -> Any:
        return self.uuid.make(uuid=np.frombuffer(goal_id, dtype=np.uint8).copy())

    def stamp(self, sec_nsec: tuple[int, int]) -> Any:
        return self.time.make(sec=sec_nsec[0], nanosec=sec_nsec[1])


class ActionClient:
    """The client side of an rclcpp_action action over rmw_zenoh.

    ``<name>/_action/send_goal|get_result|cancel_goal`` are services,
    ``<name>/_action/feedback|status`` topics (status transient local). Callbacks run on
    zenoh threads; exceptions in them are logged, never raised into zenoh.
    """

    def __init__(self, node: Ros2Node, name: str, atype: ActionType) -> None:
        self.node = node
        self.name = node.resolve(name)
        self.atype = atype
        self._parts = _ActionParts(node, atype)
        names = action_names(self.name)
        self._lock = threading.Lock()
        self._goals: dict[bytes, _ClientGoal] = {}
        self._statuses: dict[bytes, int] = {}
        self.send_goal_client = node.service_client(names["send_goal"], atype.send_goal)
        self.get_result_client = node.service_client(names["get_result"], atype.get_result)
        self.cancel_client = node.service_client(names["cancel_goal"], atype.cancel_goal)
        self.feedback_sub = node.subscribe(names["feedback"], atype.feedback, self._on_feedback)
        self.status_sub = node.subscribe(
            names["status"], atype.status, self._on_status, qos=QoS.transient_local()
        )

    def server_ready(self) -> bool:
        """Whether the action's three services are served (same types and hashes)."""
        return all(
            client.available()
            for client in (self.send_goal_client, self.get_result_client, self.cancel_client)
        )

    def close(self) -> None:
        """Undeclare the action's endpoints. Idempotent."""
        for endpoint in (
            self.send_goal_client,
            self.get_result_client,
            self.cancel_client,
            self.feedback_sub,
            self.status_sub,
        ):
            endpoint.close()

    def status(self, goal_id: bytes) -> int | None:
        """The goal's last status from the server's status topic (None: not seen)."""
        with self._lock:
            return self._statuses.get(goal_id)

    def send_goal(
        self,
        goal: Any,
        *,
        on_accepted: Callable[[bytes, bool], None] | None = None,
        on_feedback: Callable[[Any], None] | None = None,
        on_result: Callable[[int, Any | None, str], None] | None = None,
        timeout: float = 5.0,
    ) -> bytes:
        """Send ``goal`` (an ``atype.goal`` message); returns its 16-byte goal id.

        ``on_accepted(goal_id, accepted)`` once the server answers; then, if accepted,
        ``on_feedback(feedback_body)`` per feedback and ``on_result(status, result, "")``
        once. If the goal request fails or is rejected, ``on_result(GOAL_UNKNOWN or
        GOAL_ABORTED, None, why)`` says why.
        """
        goal_id = os.urandom(16)
        entry = _ClientGoal(goal_id, on_accepted, on_feedback, on_result)
        with self._lock:
            self._goals[goal_id] = entry
        request = self.atype.send_goal.request.make(
            goal_id=self._parts.uuid_msg(goal_id), goal=goal
        )

        def accepted(response: Any | None, why: str) -> None:
            if response is None:
                self._finish(goal_id, GOAL_UNKNOWN, None, f"goal request failed: {why}")
                return
            ok = bool(response.accepted)
            _call_logged(self.node, self.name, entry.on_accepted, goal_id, ok)
            if not ok:
                self._finish(goal_id, GOAL_UNKNOWN, None, f"goal rejected by {self.name}")
                return
            self.get_result_client.call(
                self.atype.get_result.request.make(goal_id=self._parts.uuid_msg(goal_id)),
                lambda resp, why: self._on_result(goal_id, resp, why),
                RESULT_TIMEOUT,
            )

        self.send_goal_client.call(request, accepted, timeout)
        return goal_id

    def _on_result(self, goal_id: bytes, response: Any | None, why: str) -> None:
        if response is None:
            self._finish(goal_id, GOAL_UNKNOWN, None, f"no result: {why}")
        else:
            self._finish(goal_id, int(response.status), response.result, "")

    def _finish(self, goal_id: bytes, status: int, result: Any | None, why: str) -> None:
        with self._lock:
            entry = self._goals.pop(goal_id, None)
        if entry is not None:
            _call_logged(self.node, self.name, entry.on_result, status, result, why)

    def _on_feedback(self, msg: Any, attachment: Attachment) -> None:
        with self._lock:
            entry = self._goals.get(_uuid_bytes(msg.goal_id))
        if entry is not None:
            _call_logged(self.node, self.name, entry.on_feedback, msg.feedback)

    def _on_status(self, msg: Any, attachment: Attachment) -> None:
        statuses = {_uuid_bytes(s.goal_info.goal_id): int(s.status) for s in msg.status_list}
        with self._lock:
            self._statuses = statuses

    def cancel(
        self,
        goal_id: bytes,
        on_done: Callable[[int, list[bytes], str], None] | None = None,
        timeout: float = 5.0,
    ) -> None:
        """Ask the server to cancel ``goal_id`` (all goals: 16 zero bytes).

        ``on_done(return_code, goal ids now canceling, why)``: CancelGoal's return code
        (0 none, 1 rejected, 2 unknown goal, 3 terminated) or -1 when the call failed.
        """
        info = self._parts.goal_info.make(
            goal_id=self._parts.uuid_msg(goal_id), stamp=self._parts.stamp((0, 0))
        )

        def done(response: Any | None, why: str) -> None:
            if response is None:
                _call_logged(self.node, self.name, on_done, -1, [], why)
                return
            canceling = [_uuid_bytes(g.goal_id) for g in response.goals_canceling]
            _call_logged(self.node, self.name, on_done, int(response.return_code), canceling, "")

        self.cancel_client.call(self.atype.cancel_goal.request.make(goal_info=info), done, timeout)

    def cancel_all(
        self,
        on_done: Callable[[int, list[bytes], str], None] | None = None,
        timeout: float = 5.0,
    ) -> None:
        """Cancel every goal of the server (zero goal id and zero stamp, per CancelGoal)."""
        self.cancel(bytes(16), on_done, timeout)


@dataclass
class _ClientGoal:
    goal_id: bytes
    on_accepted: Callable[[bytes, bool], None] | None
    on_feedback: Callable[[Any], None] | None
    on_result: Callable[[int, Any | None, str], None] | None


def _call_logged(
    node: Ros2Node, name: str, callback: Callable[..., Any] | None, *args: Any
) -> None:
    if callback is None:
        return
    try:
        callback(*args)
    except Exception as exc:
        node._log.warn(
            f"{name}:action-cb", "ROS action %s: callback failed: %s", name, _reason(exc)
        )


@dataclass
class _ServerGoal:
    goal_id: bytes
    stamp: tuple[int, int]
    client_gid: bytes
    status: int = GOAL_ACCEPTED
    result: Any | None = None
    ended: float = 0.0
    waiting: list[Responder] | None = None


class ActionServer:
    """The server side of an rclcpp_action action over rmw_zenoh (for ``telebot-sim``).

    ``on_goal(goal_id, goal) -> bool`` accepts or rejects a goal (on a zenoh thread; an
    exception rejects); ``on_cancel(goal_id) -> bool`` accepts a cancel request (the goal
    then is CANCELING until :meth:`cancel` ends it). The owner then calls
    :meth:`publish_feedback`, and ends each goal with :meth:`succeed`, :meth:`abort` or
    :meth:`cancel`, which answer its GetResult requests and publish the status (transient
    local). Ended goals are remembered for :data:`KEEP_ENDED` seconds.
    """

    KEEP_ENDED = 60.0

    def __init__(
        self,
        node: Ros2Node,
        name: str,
        atype: ActionType,
        *,
        on_goal: Callable[[bytes, Any], bool],
        on_cancel: Callable[[bytes], bool] = lambda goal_id: True,
    ) -> None:
        self.node = node
        self.name = node.resolve(name)
        self.atype = atype
        self._parts = _ActionParts(node, atype)
        self._on_goal = on_goal
        self._on_cancel = on_cancel
        self._lock = threading.RLock()
        self._goals: dict[bytes, _ServerGoal] = {}
        names = action_names(self.name)
        self.feedback_pub = node.publisher(names["feedback"], atype.feedback)
        self.status_pub = node.publisher(names["status"], atype.status, qos=QoS.transient_local())
        self.send_goal_server = node.service_server(
            names["send_goal"], atype.send_goal, self._handle_goal
        )
        self.get_result_server = node.service_server(
            names["get_result"], atype.get_result, self._handle_result
        )
        self.cancel_server = node.service_server(
            names["cancel_goal"], atype.cancel_goal, self._handle_cancel
        )

    def close(self) -> None:
        """Undeclare the action's endpoints. Idempotent."""
        for endpoint in (
            self.send_goal_server,
            self.get_result_server,
            self.cancel_server,
            self.feedback_pub,
            self.status_pub,
        ):
            endpoint.close()

    # -- what the owner calls

    def status(self, goal_id: bytes) -> int:
        """The goal's status (GOAL_UNKNOWN for a goal this server does not know)."""
        with self._lock:
            goal = self._goals.get(goal_id)
            return goal.status if goal is not None else GOAL_UNKNOWN

    def active_goals(self) -> list[bytes]:
        """Ids of the goals not yet ended."""
        with self._lock:
            return [g.goal_id for g in self._goals.values() if g.status not in _TERMINAL]

    def client_gid(self, goal_id: bytes) -> bytes | None:
        """The GID of the action client that sent the goal (its send_goal client)."""
        with self._lock:
            goal = self._goals.get(goal_id)
            return goal.client_gid if goal is not None else None

    def client_alive(self, goal_id: bytes) -> bool | None:
        """Whether the goal's client still has its liveliness token (None: unknown goal)."""
        gid = self.client_gid(goal_id)
        return None if gid is None else self.node.entity_by_gid(gid) is not None

    def execute(self, goal_id: bytes) -> None:
        """Mark an accepted goal EXECUTING (publish_feedback does it too)."""
        self._set_status(goal_id, GOAL_EXECUTING, only_from=(GOAL_ACCEPTED,))

    def publish_feedback(self, goal_id: bytes, feedback: Any) -> None:
        """Publish ``feedback`` (an ``atype.feedback_body`` message) for the goal."""
        self.execute(goal_id)
        self.feedback_pub.publish(
            self.atype.feedback.make(goal_id=self._parts.uuid_msg(goal_id), feedback=feedback)
        )

    def succeed(self, goal_id: bytes, result: Any | None = None) -> None:
        """End the goal SUCCEEDED with ``result`` (default: an empty result)."""
        self._end(goal_id, GOAL_SUCCEEDED, result)

    def abort(self, goal_id: bytes, result: Any | None = None) -> None:
        """End the goal ABORTED."""
        self._end(goal_id, GOAL_ABORTED, result)

    def cancel(self, goal_id: bytes, result: Any | None = None) -> None:
        """End the goal CANCELED (after on_cancel accepted it, or on the server's own)."""
        self._end(goal_id, GOAL_CANCELED, result)

    # -- internals

    def _set_status(self, goal_id: bytes, status: int, only_from: tuple[int, ...]) -> None:
        with self._lock:
            goal = self._goals.get(goal_id)
            if goal is None or goal.status not in only_from:
                return
            goal.status = status
        self._publish_status()

    def _end(self, goal_id: bytes, status: int, result: Any | None) -> None:
        if result is None:
            result = self.atype.result.make()
        with self._lock:
            goal = self._goals.get(goal_id)
            if goal is None or goal.status in _TERMINAL:
                return
            goal.status, goal.result, goal.ended = status, result, time.monotonic()
            waiting, goal.waiting = goal.waiting or [], None
        response = self.atype.get_result.response.make(status=status, result=result)
        for responder in waiting:
            responder.reply(response)
        self._publish_status()

    def _publish_status(self) -> None:
        now = time.monotonic()
        with self._lock:
            for goal_id in [
                g.goal_id
                for g in self._goals.values()
                if g.status in _TERMINAL and now - g.ended > self.KEEP_ENDED
            ]:
                del self._goals[goal_id]
            goals = list(self._goals.values())
        parts = self._parts
        status_list = [
            parts.goal_status.make(
                goal_info=parts.goal_info.make(
                    goal_id=parts.uuid_msg(g.goal_id), stamp=parts.stamp(g.stamp)
                ),
                status=g.status,
            )
            for g in goals
        ]
        try:
            self.status_pub.publish(self.atype.status.make(status_list=status_list))
        except Ros2Error as exc:
            self.node._log.warn(f"{self.name}:status", "ROS action %s: %s", self.name, exc)

    def _handle_goal(self, request: Any, responder: Responder) -> None:
        goal_id = _uuid_bytes(request.goal_id)
        stamp = _now_stamp()
        with self._lock:
            known = goal_id in self._goals
        accepted = False
        if not known:
            try:
                accepted = bool(self._on_goal(goal_id, request.goal))
            except Exception as exc:
                self.node._log.warn(
                    f"{self.name}:on_goal",
                    "ROS action %s: on_goal failed: %s",
                    self.name,
                    _reason(exc),
                )
        if accepted:
            with self._lock:
                self._goals[goal_id] = _ServerGoal(goal_id, stamp, responder.client_gid)
        responder.reply(
            self.atype.send_goal.response.make(accepted=accepted, stamp=self._parts.stamp(stamp))
        )
        if accepted:
            self._publish_status()

    def _handle_result(self, request: Any, responder: Responder) -> None:
        goal_id = _uuid_bytes(request.goal_id)
        with self._lock:
            goal = self._goals.get(goal_id)
            if goal is not None and goal.status not in _TERMINAL:
                if goal.waiting is None:
                    goal.waiting = []
                goal.waiting.append(responder)
                return
        if goal is None:
            response = self.atype.get_result.response.make(status=GOAL_UNKNOWN)
        else:
            response = self.atype.get_result.response.make(status=goal.status, result=goal.result)
        responder.reply(response)

    def _handle_cancel(self, request: Any, responder: Responder) -> None:
        info = request.goal_info
        goal_id = _uuid_bytes(info.goal_id)
        stamp = (int(info.stamp.sec), int(info.stamp.nanosec))
        everything = goal_id == bytes(16)
        with self._lock:
            target = self._goals.get(goal_id)
            candidates = [
                g
                for g in self._goals.values()
                if g.status in (GOAL_ACCEPTED, GOAL_EXECUTING)
                and (
                    (everything and stamp == (0, 0))
                    or g.goal_id == goal_id
                    or (stamp != (0, 0) and g.stamp <= stamp)
                )
            ]
        canceling: list[_ServerGoal] = []
        for goal in candidates:
            try:
                ok = bool(self._on_cancel(goal.goal_id))
            except Exception as exc:
                ok = False
                self.node._log.warn(
                    f"{self.name}:on_cancel",
                    "ROS action %s: on_cancel failed: %s",
                    self.name,
                    _reason(exc),
                )
            if ok:
                with self._lock:
                    if goal.status in (GOAL_ACCEPTED, GOAL_EXECUTING):
                        goal.status = GOAL_CANCELING
                        canceling.append(goal)
        if canceling:
            code = CANCEL_NONE
        elif not everything and target is None:
            code = CANCEL_UNKNOWN_GOAL
        elif not everything and target is not None and target.status in _TERMINAL:
            code = CANCEL_TERMINATED
        else:
            code = CANCEL_REJECTED
        parts = self._parts
        responder.reply(
            self.atype.cancel_goal.response.make(
                return_code=code,
                goals_canceling=[
                    parts.goal_info.make(
                        goal_id=parts.uuid_msg(g.goal_id), stamp=parts.stamp(g.stamp)
                    )
                    for g in canceling
                ],
            )
        )
        if canceling:
            self._publish_status()
