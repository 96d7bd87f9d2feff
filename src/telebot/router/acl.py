"""Sans-IO: the zenoh configs of a telebot router and of its clients, with the ACL.

Everything here returns plain dicts (JSON-serialisable, also valid JSON5) built from
names and paths; nothing is opened or read. ``apps/router_cli.py`` loads them into
zenoh-python, and ``telebot-router config`` prints the router's one for ``zenohd -c``.

The access-control list follows the key layout of docs/protocol.md §2.1, where every
key a peer publishes on names that peer; per common name (``robot:R``, ``user:U``,
``admin:A``), on what the client *sends* to the router (ingress; what the router
forwards to it is whatever it was allowed to subscribe to):

=========================  ==============================================================
robot R may                keys
=========================  ==============================================================
subscribe                  ``{ns}/robot/R/**`` (its inbox and its calls' keys)
publish (put)              ``{ns}/user/*/*/in/R``, ``{ns}/user/*/*/call/R/*/ctl|data``;
                           ``{ns}/user/*/*/in`` (version 1's inbox: the refusal that
                           tells an older client to upgrade)
liveliness token           ``{ns}/presence/robot/R/*``
watch liveliness           ``{ns}/presence/user/*/*``
user U may
subscribe                  ``{ns}/user/U/**``
publish (put)              ``{ns}/robot/*/in/U``, ``{ns}/robot/*/call/U/*/ctl|data``;
                           ``{ns}/robot/*/in`` (version 1's HELLO key, so that an older
                           client is told to upgrade rather than left unanswered)
liveliness token           ``{ns}/presence/user/U/*``
watch liveliness           ``{ns}/presence/robot/*/*``
admin A may                everything
a linked router may        everything under ``{ns}/**`` (common name ``telebot-router``:
                           every router certificate of the CA, ``certs.ROUTER_CN``)
=========================  ==============================================================

Everything else is denied (``default_permission: deny``): a robot cannot publish to or
read any robot's keys, its own included (nobody calls a robot from a robot), nor publish
on a call key that names another robot; a user cannot read another user's keys, pose as
another user's presence, or publish on a robot's handshake or call keys under another
user's name (so not into another user's call); and no certificate outside the list (or
on ``revoked.txt``) can do anything at all.

Two routers (docs/protocol.md §22.5): a router that shares this router's CA may link to
it (``RouterPlan.peers``: the endpoints it connects to). Each router enforces the rules
above for its *own* clients on their ingress; what a linked router forwards was checked by
that router, so a linked router is trusted with the namespace (it could not be told apart
from its clients' traffic anyway: one link carries them all).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Final

from telebot.channels.proto.frames import validate_name

__all__ = [
    "DEFAULT_PORT",
    "MIXED_RELIABILITY",
    "ROUTER_CN",
    "Member",
    "RouterPlan",
    "acl_config",
    "client_tls_options",
    "router_config",
    "with_quic_datagrams",
]

DEFAULT_PORT: Final = 7447
#: The common name of every router's certificate (``telebot-router init``): the subject a
#: linked router (one made from the same CA) is matched by.
ROUTER_CN: Final = "telebot-router"
_ALL_MESSAGES: Final = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


@dataclass(frozen=True, slots=True)
class Member:
    """One certificate holder the router lets in: its kind, name and common name."""

    kind: str  # "robot", "user" or "admin"
    name: str

    def __post_init__(self) -> None:
        if self.kind not in ("robot", "user", "admin"):
            raise ValueError(f"invalid member kind {self.kind!r}: robot, user or admin")
        validate_name(self.name, self.kind)

    @property
    def common_name(self) -> str:
        """The certificate common name the ACL matches: ``kind:name``."""
        return f"{self.kind}:{self.name}"


@dataclass(frozen=True, slots=True)
class RouterPlan:
    """What a router config is made of: where it listens, its files, who may connect."""

    ca: str
    cert: str
    key: str
    members: tuple[Member, ...] = ()
    namespace: str = "telebot"
    listen_tls: tuple[str, ...] = (f"tls/127.0.0.1:{DEFAULT_PORT}",)
    #: QUIC endpoints (UDP): the same certificates, mutual TLS and ACL as ``listen_tls``.
    listen_quic: tuple[str, ...] = ()
    #: Plain TCP endpoints (no certificates, hence no ACL subject: denied everything
    #: unless ``acl`` is off). Off unless asked.
    listen_tcp: tuple[str, ...] = ()
    acl: bool = True
    #: Other routers to link to (``tls/HOST:PORT``, connected to as a router: zenoh's
    #: router mesh); they must share this router's CA (§22.5).
    peers: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for endpoint in self.peers:
            if not endpoint.startswith("tls/"):
                raise ValueError(f"peer router {endpoint}: not a tls/ endpoint")


def _rule(rid: str, messages: list[str], keys: Iterable[str]) -> dict[str, Any]:
    return {
        "id": rid,
        "messages": messages,
        "flows": ["ingress"],
        "permission": "allow",
        "key_exprs": list(keys),
    }


def _member_rules(member: Member, ns: str) -> list[dict[str, Any]]:
    tag, name = f"{member.kind}-{member.name}", member.name
    # The keys a peer publishes on name it (the last chunk of the handshake key, the
    # chunk after "call"); "in" alone is protocol version 1's handshake key.
    put_keys = ("in", f"in/{name}", f"call/{name}/*/ctl", f"call/{name}/*/data")
    if member.kind == "robot":
        return [
            _rule(f"{tag}-sub", ["declare_subscriber"], [f"{ns}/robot/{name}/**"]),
            _rule(f"{tag}-put", ["put"], [f"{ns}/user/*/*/{k}" for k in put_keys]),
            _rule(
                f"{tag}-token",
                ["liveliness_token", "liveliness_query"],
                [f"{ns}/presence/robot/{name}/*"],
            ),
            _rule(
                f"{tag}-watch",
                ["declare_liveliness_subscriber", "liveliness_query"],
                [f"{ns}/presence/user/*/*"],
            ),
        ]
    if member.kind == "user":
        return [
            _rule(f"{tag}-sub", ["declare_subscriber"], [f"{ns}/user/{name}/**"]),
            _rule(f"{tag}-put", ["put"], [f"{ns}/robot/*/{k}" for k in put_keys]),
            _rule(
                f"{tag}-token",
                ["liveliness_token", "liveliness_query"],
                [f"{ns}/presence/user/{name}/*"],
            ),
            _rule(
                f"{tag}-watch",
                ["declare_liveliness_subscriber", "liveliness_query"],
                [f"{ns}/presence/robot/*/*"],
            ),
        ]
    return [_rule(f"{tag}-all", _ALL_MESSAGES, ["**"])]


def acl_config(members: Iterable[Member], namespace: str = "telebot") -> dict[str, Any]:
    """zenoh's ``access_control`` section: deny by default, allow each member its keys.

    Egress (what the router sends to a client) is allowed for every message: a client
    only gets what it was allowed to subscribe to.
    """
    validate_name(namespace, "namespace")
    members = list(members)
    rules: list[dict[str, Any]] = [
        {
            "id": "egress",
            "messages": _ALL_MESSAGES,
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": ["**"],
        }
    ]
    subjects: list[dict[str, Any]] = [{"id": "anyone"}]
    policies: list[dict[str, Any]] = [{"id": "egress", "rules": ["egress"], "subjects": ["anyone"]}]
    # A linked router: it checked its own clients' ingress by its own ACL (§22.5).
    rules.append(_rule("router", _ALL_MESSAGES, [f"{namespace}/**"]))
    subjects.append({"id": "router", "cert_common_names": [ROUTER_CN]})
    policies.append({"id": "router", "rules": ["router"], "subjects": ["router"]})
    for member in members:
        tag = f"{member.kind}-{member.name}"
        mine = _member_rules(member, namespace)
        rules.extend(mine)
        subjects.append({"id": tag, "cert_common_names": [member.common_name]})
        policies.append({"id": tag, "rules": [r["id"] for r in mine], "subjects": [tag]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


#: The QUIC endpoint metadata key of zenoh's mixed-reliability links.
MIXED_RELIABILITY: Final = "mixed_rel"


def with_quic_datagrams(endpoint: str) -> str:
    """``endpoint``, with ``mixed_rel=auto`` added if it is a ``quic/`` endpoint that does
    not choose for itself.

    On a mixed-reliability QUIC link zenoh sends best-effort frames (telebot's CONTROL
    and DATA lanes: see ``LANE_QOS``) as QUIC datagrams, so a lost packet costs only its
    own frame: no retransmission holds a stop or a heartbeat up. ``auto`` uses it
    when both ends offer it and falls back to QUIC streams with a zenoh that does not.
    Other endpoints are returned as they are.
    """
    if not endpoint.startswith("quic/"):
        return endpoint
    head, hash_, config = endpoint.partition("#")
    address, question, metadata = head.partition("?")
    params = [p for p in metadata.split(";") if p] if question else []
    if any(p.split("=", 1)[0] == MIXED_RELIABILITY for p in params):
        return endpoint
    params.append(f"{MIXED_RELIABILITY}=auto")
    return f"{address}?{';'.join(params)}{hash_}{config}"


def router_config(plan: RouterPlan) -> dict[str, Any]:
    """The whole zenoh config of the router (``zenohd -c`` reads it as it is)."""
    config: dict[str, Any] = {
        "mode": "router",
        # QUIC carries best-effort frames as datagrams (with_quic_datagrams says why).
        "listen": {
            "endpoints": [
                *plan.listen_tls,
                *(with_quic_datagrams(e) for e in plan.listen_quic),
                *plan.listen_tcp,
            ]
        },
        # Linked routers (§22.5): retried in the background for as long as the router
        # runs, so either side may start first or restart.
        "connect": {"endpoints": list(plan.peers), "exit_on_failure": False},
        # Across networks nothing is found by multicast, and answering it on a LAN would
        # only advertise the router to strangers.
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {
                # zenoh's QUIC links take their certificates from this section too.
                "tls": {
                    "root_ca_certificate": plan.ca,
                    "listen_certificate": plan.cert,
                    "listen_private_key": plan.key,
                    # Mutual TLS: no client certificate from this CA, no connection.
                    "enable_mtls": True,
                    "connect_certificate": plan.cert,
                    "connect_private_key": plan.key,
                }
            }
        },
        # zenoh's admin space and REST plugin stay off: the ACL is the only door.
        "adminspace": {"enabled": False},
    }
    if plan.acl:
        config["access_control"] = acl_config(plan.members, plan.namespace)
    return config


def client_tls_options(ca: str, cert: str, key: str) -> dict[str, Any]:
    """The zenoh config paths a client sets to reach the router over mutual TLS."""
    return {
        "transport/link/tls/root_ca_certificate": ca,
        "transport/link/tls/connect_certificate": cert,
        "transport/link/tls/connect_private_key": key,
        "transport/link/tls/enable_mtls": True,
    }
