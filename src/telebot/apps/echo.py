"""An echo robot: answers its contacts' calls and sends every datagram back.

It is the network check of telebot, like an echo server for ping: ``telebot-robot echo``
on the robot, ``telebot-user ping ROBOT`` on the user's side. A datagram on the channel
``_stats`` is answered with the call's counters as JSON on the same channel.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from typing import Any

from telebot.apps.common import stop_on_signals
from telebot.channels.call import Call, RobotEndpoint
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports import create_transport
from telebot.config import AppConfig
from telebot.identity import ContactBook, Identity

__all__ = ["STATS_CHANNEL", "call_stats", "echo_call", "serve_echo"]

STATS_CHANNEL = "_stats"

EventSink = Callable[[dict[str, Any]], None]


def call_stats(call: Call, endpoint: RobotEndpoint) -> dict[str, Any]:
    """The counters of a call and of its endpoint, as a JSON-ready dict."""
    return {
        "call": call.id,
        "frames_sent": call.stats.frames_sent,
        "frames_received": call.stats.frames_received,
        "rejected": dict(call.stats.rejected),
        "endpoint_rejected": dict(endpoint.stats.rejected),
        "rtt": call.stats.rtt,
        "loss": call.stats.loss,
        "unrouted": call.unrouted,
        "channels": {
            name: {
                "sent": ch.stats.sent,
                "received": ch.stats.received,
                "dropped": ch.stats.dropped,
            }
            for name, ch in call.channels.items()
        },
    }


def echo_call(call: Call, endpoint: RobotEndpoint, emit: EventSink) -> None:
    """Echo every datagram of ``call`` back on its channel; report its start and end."""

    def on_channel(name: str) -> None:
        channel = call.channel(name)

        def echo(datagram: ReceivedDatagram) -> None:
            if not call.active:
                return
            if name == STATS_CHANNEL:
                channel.send(json.dumps(call_stats(call, endpoint)))
            else:
                channel.send(datagram.payload)

        channel.set_callback(echo)

    call.on_unopened_channel = on_channel
    emit({"event": "call", "id": call.id, "peer": call.peer, "role": call.role})

    def on_end(task: asyncio.Future[Any]) -> None:
        end = call.end
        assert end is not None
        emit(
            {
                "event": "ended",
                "id": call.id,
                "peer": call.peer,
                "kind": end.kind,
                "by_peer": end.by_peer,
                "detail": end.detail,
            }
        )

    asyncio.ensure_future(call.wait_ended()).add_done_callback(on_end)


async def serve_echo(
    config: AppConfig,
    identity: Identity,
    contacts: ContactBook,
    emit: EventSink,
    stop: asyncio.Event | None = None,
) -> None:
    """Answer calls and echo datagrams until ``stop`` is set or SIGINT / SIGTERM arrives."""
    stop = stop or asyncio.Event()
    with stop_on_signals(stop):
        async with (
            create_transport(config.transport) as transport,
            RobotEndpoint(
                transport, identity, contacts, settings=config.call, namespace=config.namespace
            ) as robot,
        ):
            robot.on_call = lambda call: echo_call(call, robot, emit)
            emit({"event": "ready", "robot": identity.name, "inbox": robot.inbox})
            await stop.wait()
            emit({"event": "stopping", "calls": len(robot.calls)})
