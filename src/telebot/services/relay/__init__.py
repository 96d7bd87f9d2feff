"""The ``relay`` service: robot topics to the user as CDR.

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.relay.robot:RelayService", user="telebot.services.client:open_relay"
)
