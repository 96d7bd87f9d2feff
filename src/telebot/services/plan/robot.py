"""The robot's side of ``plan``: :class:`PlanService` and :class:`PlanSource` (see the service's
overview in :mod:`telebot.services.plan`).
"""

from __future__ import annotations

import logging
import math
import weakref
from typing import TYPE_CHECKING, Any

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import TelebotError
from telebot.robot.nav import NavStack, Pose2D
from telebot.services.base import RobotHost
from telebot.services.plan.wire import (
    MAX_SEQ,
    PLAN,
    Place,
    PlacesUpdate,
    PlanUpdate,
    simplify_path,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["PLACES_EVERY", "PLAN_EVERY", "PlanService", "PlanSource"]

log = logging.getLogger(__name__)

#: An unchanged plan is sent again this often (s): a lost one heals within it.
PLAN_EVERY = 1.0
#: Unchanged places are sent again this often (s).
PLACES_EVERY = 2.0
#: The NavStack's places are looked at this often (s): they change rarely, if ever.
PLACES_CHECK_EVERY = 1.0


class PlanSource:
    """The NavStack's plan and places as messages, made once per change for every call."""

    def __init__(self) -> None:
        self._checked_at = -math.inf
        self._failed = False
        self._path: tuple[Pose2D, ...] = ()
        self._seq = 0
        self.plan = PlanUpdate(0, None, ())
        self.plan_text = self.plan.encode()
        self._places: dict[str, Pose2D] | None = None
        self._places_checked_at = -math.inf
        #: The places message, and a number that changes with it.
        self.places_text = ""
        self.places_version = 0

    def update(self, nav: NavStack, now: float) -> None:
        """Read the plan and places from ``nav`` (once per ``now``: calls share the work)."""
        if now == self._checked_at:
            return
        self._checked_at = now
        try:
            path = nav.planned_path()
            if path is not self._path and path != self._path:
                points = simplify_path([(pose.x, pose.y) for pose in path])
                goal = nav.current_goal() if points else None
                self._new_plan(path, points, goal.goal_id if goal is not None else None)
        except Exception:
            # Only a picture for the user: show no plan rather than fail every tick, and
            # say so once (the robot's control loop runs at tens of hertz).
            if not self._failed:
                log.exception("the robot's planned path cannot be read: none is shown")
            self._failed = True
            if self._path:
                self._new_plan((), (), None)
        if now - self._places_checked_at < PLACES_CHECK_EVERY:
            return
        self._places_checked_at = now
        places = nav.places()
        if self._places is None or dict(places) != self._places:
            self._places = dict(places)
            update = PlacesUpdate(
                tuple(Place(name, pose.x, pose.y, pose.yaw) for name, pose in places.items())
            )
            self.places_text = update.encode()
            self.places_version += 1

    def _new_plan(
        self, path: tuple[Pose2D, ...], points: tuple[tuple[float, float], ...], goal: int | None
    ) -> None:
        self._path = path
        self._seq = self._seq % MAX_SEQ + 1
        self.plan = PlanUpdate(self._seq, goal, points)
        self.plan_text = self.plan.encode()


# Keyed weakly by the NavStack: the source goes with it. Values must not refer to the nav.
_SOURCES: weakref.WeakKeyDictionary[Any, PlanSource] = weakref.WeakKeyDictionary()


def shared_source(nav: NavStack) -> PlanSource:
    """The :class:`PlanSource` of ``nav`` (one per NavStack, shared by its calls)."""
    try:
        source = _SOURCES.get(nav)
        if source is None:
            source = _SOURCES[nav] = PlanSource()
        return source
    except TypeError:  # not weakly referenceable: this call reads the plan on its own
        return PlanSource()


class PlanService:
    """The robot's ``plan`` service on one call (see the module docstring)."""

    def __init__(self, server: RobotHost, call: Call) -> None:
        self.nav = server.nav
        self.call = call
        self.channel = call.channel(PLAN, lane=Lane.DATA)
        self.channel.set_callback(self._on_datagram)
        self.source = shared_source(server.nav)
        self._sent_seq: int | None = None
        self._next_plan = -math.inf
        self._sent_places: int | None = None
        self._next_places = -math.inf
        #: Datagrams from the user (nothing is expected of it): dropped.
        self.rejected = 0

    def tick(self, now: float) -> None:
        """Send the plan (and places) when changed or due."""
        self.source.update(self.nav, now)
        source = self.source
        due = source.plan.seq != self._sent_seq or now >= self._next_plan
        if due and self._send(source.plan_text):
            self._sent_seq = source.plan.seq
            self._next_plan = now + PLAN_EVERY
        due = source.places_version != self._sent_places or now >= self._next_places
        if due and self._send(source.places_text):
            self._sent_places = source.places_version
            self._next_places = now + PLACES_EVERY

    def close(self) -> None:
        """Nothing to end: the call's channels go with it."""
        self.channel.set_callback(None)

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        self.rejected += 1
        self.channel.stats.rejected += 1

    def _send(self, text: str) -> bool:
        if not self.call.active:
            return False
        try:
            self.channel.send(text)
        except TelebotError as exc:  # the call ended under us: its end is reported apart
            log.debug("call %s: plan not sent: %s", self.call.id, exc)
            return False
        return True
