"""The ``video`` service: the robot's camera to the user (JPEG, H.264, VP8).

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.robot:RobotVideo", user="telebot.services.client:open_video"
)
