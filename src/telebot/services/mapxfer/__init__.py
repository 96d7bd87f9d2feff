"""Map transfer over a call's "map" channel: the robot's :class:`MapService`, the user's
:func:`fetch_map`.

The protocol itself (PNG encoding, offer, chunks, resends, hash) is sans-IO in
:mod:`telebot.services.mapxfer.wire`; its two sides only move its datagrams and keep time
with the event loop. Neither side starts a task: the robot is driven by the channel's
callback and loop timers, the user by the awaiting coroutine, so nothing is left running
behind a call.

Robot::

    service = MapService.attach(call, lambda: encoded)   # cache-friendly provider

User::

    download = await fetch_map(map_channel(call), progress=bar.update)
    download.save(Path("map.png"))                        # map.png + map.yaml

A map that changes (SLAM) is followed: every transfer sends the map as it is at the
request, ``download.version`` says which version that was, and the robot's telemetry
carries the current ``map_version``; when the two differ, fetch again.

The map transfer (part of every call's core): ``wire.py`` (sans-IO: PNG encoding and both
state machines), ``robot.py`` (serving it), ``user.py`` (fetching it).
"""

#: The map channel's name (both ends open it by this name). Here, not in ``wire.py``: the
#: hosts open the channel without loading the map codec (numpy, OpenCV, YAML).
MAP = "map"
