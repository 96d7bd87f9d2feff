"""The ``drive`` service: driving by hand, and follow-me.

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.drive.robot:RobotDrive", user="telebot.services.client:ClientDrive"
)
