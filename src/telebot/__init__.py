"""telebot: robot telepresence over authenticated App2App-style datagram channels."""

__version__ = "0.1.0"
