"""``telebot-user ui``: a local web page bridged to a call (map, click-to-goal, stop, video, chat).

See :mod:`telebot.apps.web.server` for the server and the websocket protocol.
"""

from __future__ import annotations

from telebot.apps.web.server import WebUI, serve_ui

__all__ = ["WebUI", "serve_ui"]
