"""Contract suites and helpers shipped for people who extend telebot.

Each module is one contract a plug-in can run against itself (as httpx ships
``MockTransport``): a robot adapter runs :mod:`telebot.testing.navstack`, a transport
:mod:`telebot.testing.transport`. Nothing here is imported by ``import telebot``.
"""
