"""The map transfer (part of every call's core): ``wire.py`` (sans-IO: PNG encoding and both
state machines), ``robot.py`` (serving it), ``user.py`` (fetching it)."""

#: The map channel's name (both ends open it by this name). Here, not in ``wire.py``: the
#: hosts open the channel without loading the map codec (numpy, OpenCV, YAML).
MAP = "map"
