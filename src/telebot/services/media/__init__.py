"""The ``media`` service: two-way audio and the user's camera (PyAV, loaded when used).

Its robot side is installed with its settings by
:func:`~telebot.services.media.robot.install_robot_media`.

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(robot=None, user="telebot.services.media.user:open_user_media")
