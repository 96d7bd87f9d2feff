"""The ``video`` service: the robot's camera to the user (JPEG, H.264, VP8).

``wire.py``: the wire format; ``sender.py`` (the camera's encoder and pacing) and
``receiver.py`` (reassembly, decoding, the feed) are the stream machinery both hosts' video
sides use, and the media service reuses for the user's camera; ``stream.py`` what both share.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.robot:RobotVideo", user="telebot.services.client:open_video"
)
