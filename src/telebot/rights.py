"""What each contact role may do on a robot: the one table every service asks.

=============  =========  ========  =====
right          observer   driver    admin
=============  =========  ========  =====
``observe``    yes        yes       yes     chat queries, map, pose, telemetry, video
``stop``       yes        yes       yes     stop the robot (never depends on anything else)
``drive``      no         yes       yes     hold the drive: motions, goals, cancel, arm,
                                            take a free drive, release
``camera``     no         yes       yes     switch cameras (the drive holder, §18)
``take_over``  no         no        yes     take the drive from another holder
=============  =========  ========  =====

A role grants the right to ask; the safety supervisor (:mod:`telebot.safety`) then decides
whether now is the moment (armed, holding the drive, a fresh link). An unknown role (a
robot that sent a role this client does not know) has the observer's rights.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping

from telebot.identity import Role

__all__ = ["RIGHTS", "Right", "may", "rights_of"]


class Right(enum.StrEnum):
    """One thing a role may do (see the module docstring's table)."""

    OBSERVE = "observe"
    STOP = "stop"
    DRIVE = "drive"
    CAMERA = "camera"
    TAKE_OVER = "take_over"


#: Every role's rights.
RIGHTS: Mapping[Role, frozenset[Right]] = {
    Role.OBSERVER: frozenset({Right.OBSERVE, Right.STOP}),
    Role.DRIVER: frozenset({Right.OBSERVE, Right.STOP, Right.DRIVE, Right.CAMERA}),
    Role.ADMIN: frozenset(Right),
}


def rights_of(role: Role | str | None) -> frozenset[Right]:
    """The rights of ``role`` (a :class:`Role`, its name, or None: an observer's)."""
    try:
        return RIGHTS[Role(role)] if role is not None else RIGHTS[Role.OBSERVER]
    except ValueError:
        return RIGHTS[Role.OBSERVER]


def may(role: Role | str | None, right: Right) -> bool:
    """Whether ``role`` has ``right``."""
    return right in rights_of(role)
