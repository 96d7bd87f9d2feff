"""A tiny plug-in service: the robot's battery level, read as ``client.battery.percent``.

The whole service is this folder plus one registration line (an entry point)::

    [project.entry-points."telebot.services"]
    battery = "battery_plugin:SERVICE"
"""

from telebot.services.base import ServiceSpec

SERVICE = ServiceSpec(robot="battery_plugin.robot:Battery", user="battery_plugin.user:BatteryGauge")
