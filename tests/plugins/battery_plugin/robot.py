"""The robot side: one gauge per robot, read by every call twice a second."""

from __future__ import annotations

from battery_plugin.wire import BATTERY, encode_level
from telebot.channels.call import Call
from telebot.channels.transports.base import Lane
from telebot.services.base import HostService, RobotHost

#: How often (s) each call hears the level.
EVERY = 0.5


class Battery(HostService[RobotHost]):
    """The robot's battery (per robot): drains 1 % a second from 100 % (a stand-in)."""

    def start(self) -> None:
        self.started = self.host.now()

    def percent(self) -> float:
        return max(0.0, 100.0 - (self.host.now() - self.started))

    def open(self, call: Call) -> BatteryCall:
        return BatteryCall(self, call)


class BatteryCall:
    """The level on one call."""

    def __init__(self, battery: Battery, call: Call) -> None:
        self.battery = battery
        self.channel = call.channel(BATTERY, lane=Lane.DATA, latest_only=True)
        self.due = -1.0

    def tick(self, now: float) -> None:
        if now >= self.due:
            self.due = now + EVERY
            self.channel.send(encode_level(self.battery.percent()))

    def close(self) -> None:
        pass
