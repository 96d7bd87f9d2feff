"""The robot's services on a call's channels: chat (Table I), map, pose, goals, telemetry.

Sans-IO logic (command parsing, map transfer, message formats) lives in
:mod:`telebot.services.proto`; the modules here drive it with a call's channels and the
robot's :class:`~telebot.robot.nav.NavStack`. Channel names and payloads are in
``docs/protocol.md``.
"""
