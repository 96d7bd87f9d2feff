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
    │   ├── AuthenticationError           a frame that fails AEAD / handshake verification
    │   └── IncompatiblePeer              a peer of another protocol version or cipher suites
    ├── DatagramTooLarge(ValueError)      payload over 32,768 bytes, raised before any I/O
    ├── CallError                         a call could not be set up, or it ended
    │   ├── CallRejected                  the robot refused the call (reason given by it)
    │   ├── CallTimeout(TimeoutError)     nobody answered in time
    │   └── CallEnded                     using a call that was hung up or dropped
    └── RobotError                        the robot adapter refused or could not do something
        ├── UnknownRobot(LookupError)     no robot adapter registered under that name
        ├── MapError(ValueError)          a missing or malformed map file (names the file)
        ├── UnknownPlace(LookupError)     a place name the robot does not know (lists known ones)
        ├── UnknownCamera(LookupError)    a camera name the robot does not have
        ├── UnknownTopic(LookupError)     a topic the robot cannot relay (lists near matches)
        ├── RelayRefused(PermissionError) a relay the caller's role may not have (with a code)
        ├── NoPath                        no path to a goal (outside the map, in a wall, cut off)
        ├── InvalidCommand(ValueError)    a motion request with bad numbers (NaN, infinite, …)
        └── Ros2Error                     the ROS 2 robot (rmw_zenoh) failed or misbehaved
            ├── RobotUnreachable(ConnectionError)  no router, or Nav2 not there, at start-up
            ├── UnknownRosType(LookupError)  a message/service/action type telebot does not know
            └── CdrError(ValueError)      bytes that are not a valid CDR message of that type
"""

from __future__ import annotations

__all__ = [
    "AuthenticationError",
    "CallEnded",
    "CallError",
    "CallRejected",
    "CallTimeout",
    "CdrError",
    "ConfigError",
    "DatagramTooLarge",
    "IdentityError",
    "IncompatiblePeer",
    "InvalidCommand",
    "MapError",
    "NoPath",
    "ProtocolError",
    "RelayRefused",
    "RobotError",
    "RobotUnreachable",
    "Ros2Error",
    "TelebotError",
    "TransportError",
    "TransportTimeout",
    "UnknownCamera",
    "UnknownPlace",
    "UnknownRobot",
    "UnknownRosType",
    "UnknownTopic",
    "UnknownTransport",
    "excerpt",
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


class IncompatiblePeer(ProtocolError):
    """A well-formed frame from a peer that speaks another version of the protocol
    (an older or newer telebot) or has no cipher suite in common with this end."""


class CallError(TelebotError):
    """A call could not be set up, or was used after it ended."""


class CallRejected(CallError):
    """The robot refused the call; ``str(exc)`` is the robot's reason."""


class CallTimeout(CallError, TimeoutError):
    """The called robot did not answer in time."""


class CallEnded(CallError):
    """The call was hung up or dropped; ``code`` says which (the end's kind)."""

    def __init__(self, message: str, code: str = "") -> None:
        super().__init__(message)
        self.code = code


class RobotError(TelebotError):
    """The robot adapter refused a request or could not carry it out."""


class UnknownRobot(RobotError, LookupError):
    """No robot adapter is registered under the requested name; the message lists the known ones."""


class MapError(RobotError, ValueError):
    """A map file is missing or malformed; the message names the file."""


class UnknownPlace(RobotError, LookupError):
    """A place name the robot does not know; the message lists the known ones."""


class UnknownCamera(RobotError, LookupError):
    """A camera name the robot does not have; the message lists its cameras."""


class UnknownTopic(RobotError, LookupError):
    """A topic the robot cannot relay; the message lists near matches (also in ``near``)."""

    def __init__(self, message: str, near: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.near = near


class RelayRefused(RobotError, PermissionError):
    """The robot refused a topic relay; ``code`` is its reason code (``"topic_not_allowed"``, …)."""

    def __init__(self, message: str, code: str = "") -> None:
        super().__init__(message)
        self.code = code


class NoPath(RobotError):
    """The planner found no path; the message says why (``"inside an obstacle"``)."""


class InvalidCommand(RobotError, ValueError):
    """A motion request with numbers the robot cannot act on (not finite, out of range)."""


class Ros2Error(RobotError):
    """The ROS 2 robot (over rmw_zenoh) failed or misbehaved."""


class RobotUnreachable(Ros2Error, ConnectionError):
    """The robot is not there at start-up: no router, or a Nav2 server missing (named)."""


class UnknownRosType(Ros2Error, LookupError):
    """A ROS message, service or action type that telebot does not know."""


class CdrError(Ros2Error, ValueError):
    """Bytes that are not a valid CDR-encoded message of the expected type."""


#: What an error message or a log line quotes of someone's input, at most (characters).
EXCERPT = 200


def excerpt(text: str, limit: int = EXCERPT) -> str:
    """``text`` on one line and at most about ``limit`` characters, for error messages and
    log lines that quote what someone sent: a megabyte of garbage is never echoed back, only
    its start and its size (``'AAAA… (1048576 characters)'``)."""
    line = " ".join(text[: 2 * limit].split())
    if len(line) <= limit and len(text) <= 2 * limit:
        return line
    return f"{line[: limit - 1]}… ({len(text)} characters)"
