"""The ``people`` service: tracked people and alerts.

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.people.robot:RobotPeople", user="telebot.services.client:open_people"
)
