"""The network emulator: replay Wi-Fi, 4G, an ocean or a bad link on loopback.

:mod:`telebot.netem.model` is the sans-IO link model (profiles, delay, jitter, random
and burst loss, a bandwidth cap with a queue, outages); :mod:`telebot.netem.proxy` puts it
between two zenoh endpoints (UDP and TCP); ``MemoryHub.set_profile`` puts it on the
in-process memory transport. README "Network emulator" has the profiles and the CLI.
"""

from telebot.netem.model import (
    PROFILES,
    Burst,
    InOrder,
    LinkModel,
    ModelStats,
    Outages,
    OutageSchedule,
    Profile,
    profile,
)
from telebot.netem.proxy import NetemProxy, ProxyStats, parse_endpoint

__all__ = [
    "PROFILES",
    "Burst",
    "InOrder",
    "LinkModel",
    "ModelStats",
    "NetemProxy",
    "OutageSchedule",
    "Outages",
    "Profile",
    "ProxyStats",
    "parse_endpoint",
    "profile",
]
