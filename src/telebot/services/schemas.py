"""The JSON schemas of telebot's JSON messages in MCAP files and on Foxglove channels.

One home for both writers: the robot's call recordings (:mod:`telebot.services.recording`)
and the user's Foxglove bridge (:mod:`telebot.apps.foxglove_bridge`, live and ``record``) name
their JSON channels' schemas from here, ``telebot.*``, so that a stream that both carry (the
robot's telemetry) has one schema, and a Foxglove layout made on one works on the other.
Properties only (the protocol adds fields over time): Foxglove uses them to offer fields in
its plots and panels.
"""

from __future__ import annotations

import json
from typing import Any

__all__ = [
    "AUDIT_SCHEMA",
    "BRIDGE_SCHEMAS",
    "CALLS_SCHEMA",
    "SCHEMAS",
    "TRIGGER_REQUEST",
    "TRIGGER_RESULT",
    "json_schema",
    "schema_bytes",
]

_NUMBER = {"type": "number"}
_INT = {"type": "integer"}
_TEXT = {"type": "string"}
_BOOL = {"type": "boolean"}


def json_schema(title: str, properties: dict[str, Any]) -> dict[str, Any]:
    """A JSON schema of an object named ``title`` (the schema name MCAP and Foxglove show)."""
    return {"title": title, "type": "object", "properties": properties}


#: The JSON schema of each recorded stream, by (channel, direction): "out" is what the
#: robot sent, "in" what the user sent. Properties only (the protocol adds fields over
#: time): Foxglove uses them to offer fields in its plots and panels.
SCHEMAS: dict[tuple[str, str], dict[str, Any]] = {
    ("pose", "out"): json_schema(
        "telebot.PoseUpdate",
        {
            "t": _NUMBER,
            "x": _NUMBER,
            "y": _NUMBER,
            "yaw": _NUMBER,
            "cov": {"type": "array", "items": _NUMBER},
            "v": _NUMBER,
            "w": _NUMBER,
            "state": _TEXT,
            "detail": _TEXT,
            "goal": {"type": ["integer", "null"]},
        },
    ),
    ("telemetry", "out"): json_schema(
        "telebot.Telemetry",
        {
            "t": _NUMBER,
            "battery": _NUMBER,
            "battery_low": _BOOL,
            "state": _TEXT,
            "detail": _TEXT,
            "goal": {"type": ["string", "null"]},
            "progress": {"type": ["number", "null"]},
            "camera": _TEXT,
            "speed_limit": _NUMBER,
            "rtt": {"type": ["number", "null"]},
            "loss": _NUMBER,
            "role": _TEXT,
            "diagnostics": {"type": "object", "additionalProperties": _TEXT},
            "armed": _BOOL,
            "stop_reason": _TEXT,
            "holder": {"type": ["string", "null"]},
            "video_fps": _NUMBER,
            "video_width": _INT,
            "video_height": _INT,
            "video_quality": _INT,
            "map_version": _INT,
            "rx_dropped": _INT,
        },
    ),
    ("plan", "out"): json_schema(
        "telebot.PlanUpdate",
        {
            "type": _TEXT,
            "seq": _INT,
            "goal": {"type": ["integer", "null"]},
            "points": {"type": "array", "items": {"type": "array", "items": _NUMBER}},
        },
    ),
    ("goals", "out"): json_schema(
        "telebot.GoalUpdate",
        {
            "type": _TEXT,
            "id": _INT,
            "status": _TEXT,
            "progress": _NUMBER,
            "reason": _TEXT,
            "code": _TEXT,
        },
    ),
    ("goals", "in"): json_schema(
        "telebot.GoalCommand",
        {"type": _TEXT, "id": _INT, "x": _NUMBER, "y": _NUMBER, "yaw": _NUMBER},
    ),
    ("chat", "out"): json_schema(
        "telebot.ChatReply",
        {
            "id": _INT,
            "seq": _INT,
            "text": _TEXT,
            "final": _BOOL,
            "ok": _BOOL,
            "attachment": _TEXT,
            "code": _TEXT,
        },
    ),
    ("chat", "in"): json_schema("telebot.ChatRequest", {"id": _INT, "text": _TEXT}),
    ("safety", "out"): json_schema(
        "telebot.SafetyMessage",
        {
            "type": _TEXT,
            "id": _INT,
            "ok": _BOOL,
            "reason": _TEXT,
            "code": _TEXT,
            "armed": _BOOL,
            "holder": {"type": ["string", "null"]},
            "cap": _NUMBER,
            "blocked": _BOOL,
        },
    ),
    ("safety", "in"): json_schema(
        "telebot.SafetyRequest", {"type": _TEXT, "id": _INT, "how": _TEXT}
    ),
}
CALLS_SCHEMA = json_schema(
    "telebot.CallEvent",
    {
        "event": {"type": "string", "enum": ["start", "end"]},
        "call": _TEXT,
        "peer": _TEXT,
        "role": _TEXT,
        "kind": _TEXT,
        "detail": _TEXT,
    },
)
AUDIT_SCHEMA = json_schema(
    "telebot.AuditRecord",
    {
        "t": _NUMBER,
        "who": _TEXT,
        "role": _TEXT,
        "call": {"type": ["string", "null"]},
        "what": _TEXT,
        "outcome": _TEXT,
        "detail": _TEXT,
        "how": _TEXT,
    },
)


def schema_bytes(schema: dict[str, Any]) -> bytes:
    """``schema`` as the ``jsonschema`` data of an MCAP or Foxglove schema record."""
    return json.dumps(schema).encode()


_CODE = _TEXT  # a reason code (``telebot.reasons.Reason``)
_SAFETY_FIELDS = {
    "request": _TEXT,
    "how": _TEXT,
    "ok": _BOOL,
    "text": _TEXT,
    "code": _CODE,
    "armed": _BOOL,
    "reason": _TEXT,
    "holder": {"type": ["string", "null"]},
    "cap": _NUMBER,
    "blocked": _BOOL,
}
_GOAL_FIELDS = {
    "id": _INT,
    "x": _NUMBER,
    "y": _NUMBER,
    "yaw": {"type": ["number", "null"]},
    "status": _TEXT,
    "progress": _NUMBER,
    "text": _TEXT,
    "code": _CODE,
}
_CHAT_FIELDS = {
    "command": _TEXT,
    "text": _TEXT,
    "ok": _BOOL,
    "final": _BOOL,
    "code": _CODE,
}

#: The schema of each ``/telebot/NAME`` JSON channel of the Foxglove bridge, by NAME: what
#: this user's client saw and did (the robot's own telemetry has the recorder's schema).
BRIDGE_SCHEMAS: dict[str, dict[str, Any]] = {
    "telemetry": SCHEMAS[("telemetry", "out")],
    "safety": json_schema(
        "telebot.SafetyEvent",
        {"event": {"type": "string", "enum": ["state", "safety", "safety_ack"]}, **_SAFETY_FIELDS},
    ),
    "goal": json_schema(
        "telebot.GoalEvent",
        {"kind": {"type": "string", "enum": ["goal", "goal_update", "refused"]}, **_GOAL_FIELDS},
    ),
    "chat": json_schema(
        "telebot.ChatEvent",
        {"kind": {"type": "string", "enum": ["chat", "chat_reply"]}, **_CHAT_FIELDS},
    ),
    "commands": json_schema(
        "telebot.Command",
        {"kind": {"type": "string", "enum": ["chat", "goal", "safety"]}}
        | _SAFETY_FIELDS
        | _GOAL_FIELDS
        | _CHAT_FIELDS,
    ),
    "connection": json_schema(
        "telebot.ConnectionEvent",
        {
            "state": _TEXT,  # connected, reconnecting, reconnected, ended, relay_refused
            "detail": _TEXT,
            "seconds": _NUMBER,
        },
    ),
}

#: The request of the Foxglove bridge's command services (``/telebot/arm`` …): no fields.
TRIGGER_REQUEST = json_schema("telebot.TriggerRequest", {})
#: Their response: whether the robot did it, and why not in words and as a reason code.
TRIGGER_RESULT = json_schema("telebot.TriggerResult", {"ok": _BOOL, "text": _TEXT, "code": _CODE})
