"""The browser gateway (docs/protocol.md §26): WebSocket ⇄ zenoh, sealed frames only.

A browser holds its own key and does the protocol itself; the gateway admits it after a
proof of that key (:mod:`~telebot.gateway.admission`: the router's gateway users, or the
robot's contacts and invites), then relays its frames under the key rules of §22.2 and
per-connection budgets (:mod:`~telebot.gateway.core`, sans-IO), over one transport
(:mod:`~telebot.gateway.server`). It holds no key that opens a frame.
"""
