"""The one error tree of telebot.

Every error telebot raises on purpose derives from :class:`TelebotError`; errors from
foreign libraries (zenoh, cryptography, pydantic) are mapped at the boundary with
``raise ... from exc``. Where an error resembles a builtin it inherits that too, so
``except TimeoutError`` or ``except ValueError`` keep working::

    TelebotError
    ├── ConfigError(ValueError)           bad config file, key, flag or home directory
    ├── IdentityError                     missing / unreadable / malformed key files
    ├── TransportError                    a transport failed to open, publish or close
    │   ├── UnknownTransport(LookupError) no transport registered under that name
    │   └── TransportTimeout(TimeoutError)
    ├── ProtocolError(ValueError)         a frame or message that does not decode (sans-IO)
    │   └── AuthenticationError           a frame that fails AEAD / handshake verification
    ├── DatagramTooLarge(ValueError)      payload over 32,768 bytes, raised before any I/O
    └── CallError                         a call could not be set up, or it ended
        ├── CallRejected                  the robot refused the call (reason given by it)
        ├── CallTimeout(TimeoutError)     nobody answered in time
        └── CallEnded                     using a call that was hung up or dropped
"""

from __future__ import annotations

__all__ = [
    "AuthenticationError",
    "CallEnded",
    "CallError",
    "CallRejected",
    "CallTimeout",
    "ConfigError",
    "DatagramTooLarge",
    "IdentityError",
    "ProtocolError",
    "TelebotError",
    "TransportError",
    "TransportTimeout",
    "UnknownTransport",
]


class TelebotError(Exception):
    """Base of every error telebot raises on purpose."""


class ConfigError(TelebotError, ValueError):
    """A config file, config key, command-line flag or home directory is invalid."""


class IdentityError(TelebotError):
    """A key file is missing, unreadable or malformed."""


class TransportError(TelebotError):
    """A transport could not open, publish, subscribe or close."""


class UnknownTransport(TransportError, LookupError):
    """No transport is registered under the requested name."""


class TransportTimeout(TransportError, TimeoutError):
    """A transport operation did not finish in its time bound."""


class ProtocolError(TelebotError, ValueError):
    """Bytes that do not decode as a telebot frame or message."""


class AuthenticationError(ProtocolError):
    """A frame that fails authentication: forged, tampered, replayed or wrongly keyed."""


class DatagramTooLarge(TelebotError, ValueError):
    """A datagram payload is larger than the 32,768 bytes a channel carries."""


class CallError(TelebotError):
    """A call could not be set up, or was used after it ended."""


class CallRejected(CallError):
    """The robot refused the call; ``str(exc)`` is the robot's reason."""


class CallTimeout(CallError, TimeoutError):
    """The called robot did not answer in time."""


class CallEnded(CallError):
    """The call was hung up or dropped; ``reason`` says which."""

    def __init__(self, message: str, reason: str = "") -> None:
        super().__init__(message)
        self.reason = reason
