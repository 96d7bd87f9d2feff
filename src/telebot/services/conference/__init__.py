"""The ``conference`` service: many users, one robot (roster and messages).

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.conference.robot:ConferenceRoom",
    user="telebot.services.conference.user:ConferenceState",
)
