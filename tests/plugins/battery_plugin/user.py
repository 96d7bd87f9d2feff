"""The user side: ``client.battery.percent``, the newest level heard (None before one)."""

from __future__ import annotations

from battery_plugin.wire import BATTERY, decode_level
from telebot.channels.call import Call
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import ProtocolError
from telebot.services.base import ClientHost, HostService


class BatteryGauge(HostService[ClientHost]):
    """The robot's battery level as this client last heard it (across reconnections)."""

    def __init__(self, client: ClientHost) -> None:
        super().__init__(client)
        self.percent: float | None = None

    def open(self, call: Call) -> BatteryChannel:
        return BatteryChannel(self, call)


class BatteryChannel:
    """The battery channel of one call."""

    def __init__(self, gauge: BatteryGauge, call: Call) -> None:
        self.gauge = gauge
        self.channel = call.channel(BATTERY, lane=Lane.DATA, latest_only=True)
        self.channel.set_callback(self._on_level)

    def _on_level(self, datagram: ReceivedDatagram) -> None:
        try:
            self.gauge.percent = decode_level(datagram.payload)
        except ProtocolError:
            self.gauge.host.rejected += 1

    def tick(self, now: float) -> None:
        pass

    def close(self) -> None:
        self.channel.set_callback(None)
