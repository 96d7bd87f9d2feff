"""The robot's services on a call's channels: chat (Table I), map, pose, goals, telemetry, ...

One folder per service (``chat``, ``mapxfer``, ``video``, ``relay``, ...): ``wire.py`` is
its sans-IO wire format, ``robot.py`` its robot side, ``user.py`` its user side. The hosts
(:mod:`telebot.services.robot`, :mod:`telebot.services.client`) open them on every call
through :mod:`telebot.services.registry`; :mod:`telebot.services.base` is the seam between
them. Channel names and payloads are in ``docs/protocol.md``.
"""
