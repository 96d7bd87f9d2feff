"""Driving by hand on the robot: the ``drive`` channel (``docs/protocol.md`` §27).

:class:`RobotDrive` is the service on a robot (a :class:`~telebot.services.base.HostService`,
registered as ``drive``): it holds the robot's follow-me and direct driving, reads their
``[follow]`` and ``[drive]`` sections of the config, ticks them on every control cycle
(follow first, then driving; a failing tick stops the robot and latches the stop) and
opens one :class:`CallDrive` per call. One :class:`DriveService` per robot (one call drives
at a time) and one :class:`CallDrive` per call (its channel, its newest ``seq``, what it
was last told). The user's client sends
velocity commands at 20 Hz while a key, stick or button is held; the robot obeys only while
fresh ones arrive.

Direct driving rides the same safety path as follow-me (:mod:`telebot.services.drive.follow`):

- its first command is a motion request to the safety supervisor (observers, non-holders,
  a disarmed robot, an unmeasured or poor link are refused with the supervisor's code, and
  the request is audited); the end of driving is audited too, never each command;
- each control cycle, *after* the supervisor's tick (and the follow's), it checks that the
  robot is still armed, that the call still holds the drive, that no goal or follow took
  over (``replaced``) and that a command came within ``[drive] stale_after`` (``stale``),
  then commands the wanted velocity clamped to the robot's limits, the supervisor's speed
  cap and the free distance the laser sees (``obstacle``: it brakes to a stop before
  anything ahead, or behind when reversing; turning on the spot stays allowed);
- a zero command (the user let go) stops the robot at once, not latched (``released``);
  any stop, a hand-over or the call's end ends driving (``stopped``); a command that does
  not decode stops it too (``invalid``) and is answered;
- after a takeover (``replaced``) or a stop (``stopped``) a held key does not drive again:
  the user lets go first (a release, or a gap of ``stale_after``), so a goal wins over the
  tail of a key press and a re-arm starts nothing by itself.

Velocities go to the robot's own velocity interface (:class:`~telebot.robot.nav.Drivable`:
the simulator's base, ``cmd_vel`` as Twist or TwistStamped on a ROS 2 robot), which keeps
its acceleration limits, obstacle guard and cmd_vel timeout.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from telebot.channels.transports.base import Lane
from telebot.config import DriveSettings, FollowSettings
from telebot.errors import TelebotError
from telebot.identity import Role
from telebot.reasons import Reason, Refusal
from telebot.rights import Right, may
from telebot.robot.follow import (
    BRAKING_MARGIN,
    clearance_ahead,
    clearance_behind,
)
from telebot.robot.nav import (
    Drivable,
    GoalStatus,
    LaserSource,
    MotionLimits,
    NavStack,
    NavState,
)
from telebot.safety import SafetyState
from telebot.services.base import HostService, RobotHost
from telebot.services.drive.follow import FollowService, TrackSource
from telebot.services.drive.wire import (
    DRIVE,
    DriveCommand,
    DriveState,
    InvalidDriveCommand,
    NotADriveCommand,
    decode_drive_command,
    seq_newer,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call
    from telebot.channels.channel import ReceivedDatagram

__all__ = ["DRIVE_WHAT", "STATE_EVERY", "CallDrive", "DriveService", "RobotDrive"]

log = logging.getLogger(__name__)

#: While a call drives, its state is repeated this often (s): 5 Hz.
STATE_EVERY = 0.2
#: An inactive state (driving ended, or refused) is sent this many more times when it changes,
#: STATE_EVERY apart: the lane is lossy, and nothing else would repeat it (a lost
#: ``released`` left a page saying "driving").
END_REPEATS = 2
#: A refused command is asked of the supervisor again after this long (s) while the key
#: stays held (at once when the safety state changes, or after the user lets go): a held
#: key must not write 20 audit records a second.
REFUSAL_RETRY = 1.0
#: … but a round trip not measured yet (the call just came up) is asked again this soon.
UNMEASURED_RETRY = 0.1
#: Below this speed (m/s) the room left before an obstacle counts as none: the robot stops.
CRAWL = 0.03
#: What the supervisor's audit log calls driving by hand.
DRIVE_WHAT = "drive by hand"
_OBSERVER = "observers may not drive: ask the driver"


class MotionGate(Protocol):
    """A call's gate of the safety supervisor: may this call move the robot now?"""

    def motion(self, what: str) -> Refusal | None:
        """None if the call may move the robot; else why not (refusals are audited)."""
        ...


class DriveSafety(Protocol):
    """What driving by hand uses of the safety supervisor (its driver is one)."""

    watchdog_stops: int

    def gate(self, call_id: str) -> MotionGate:
        """The gate of call ``call_id``."""
        ...

    def state(self) -> SafetyState:
        """The supervisor's state now."""
        ...

    def note(self, call_id: str | None, what: str, detail: str = "") -> None:
        """Write an audit record."""
        ...


class RobotDrive(HostService[RobotHost]):
    """The ``drive`` service on a robot: its follow-me and its driving by hand.

    A :class:`~telebot.services.base.MotionService`: the robot halts it before an emergency
    stop and tells it each safety change. Follow-me follows the tracks of the robot's
    ``people`` service (None without one: ``follow`` is then refused).
    """

    def __init__(self, host: RobotHost) -> None:
        super().__init__(host)
        safety = host.safety
        #: Follow-me (the ``follow`` command, ``[follow]``).
        self.follow = FollowService(
            host.nav,
            host.config.get("follow", FollowSettings),
            safety_state=safety.state if safety is not None else None,
            watchdog_stops=(lambda: safety.watchdog_stops) if safety is not None else None,
        )
        #: Driving by hand (the ``drive`` channel, ``[drive]``), ticked after the follow.
        self.drive = DriveService(
            host.nav, host.config.get("drive", DriveSettings), safety=safety, follow=self.follow
        )

    def start(self) -> None:
        """Follow the people the robot's ``people`` service tracks (if it has one)."""
        people = self.host.service("people")
        if isinstance(people, TrackSource):
            self.follow.people = people

    def tick(self, now: float) -> None:
        """One control cycle, after the supervisor's tick and the people tracker's step:
        the follow first, then driving (a follow just started wins); a failure stops the
        robot and latches the stop."""
        try:
            self.follow.tick(now)
        except Exception:
            log.exception("follow-me failed: stopping the robot")
            self.host.emergency_stop("follow-me failed")
        try:
            self.drive.tick(now)
        except Exception:
            log.exception("driving by hand failed: stopping the robot")
            self.host.emergency_stop("driving by hand failed")

    def open(self, call: Call) -> CallDrive:
        """The ``drive`` channel of ``call``."""
        return CallDrive(self.drive, call, self.host.now)

    def halt(self, text: str) -> None:
        """End a follow (first: it must not drive again after the stop), then driving."""
        with contextlib.suppress(Exception):
            self.follow.unfollow()
        with contextlib.suppress(Exception):
            self.drive.end(Reason.STOPPED, text, self.host.now())

    def safety_changed(self, state: Any) -> None:
        """A stop or a hand-over ends a follow and driving before anyone hears of it."""
        try:
            self.follow.safety_changed(state)
        except Exception:
            log.exception("follow-me: safety change failed")
        try:
            self.drive.safety_changed(state, self.host.now())
        except Exception:
            log.exception("driving by hand: safety change failed")


class CallDrive:
    """The ``drive`` service of one call: decodes its commands, sends its drive states."""

    def __init__(self, service: DriveService, call: Call, clock: Callable[[], float]) -> None:
        self.service = service
        self.call = call
        self.call_id = call.id
        self.role = call.role
        self._clock = clock
        self.channel = call.channel(DRIVE, lane=Lane.CONTROL)
        #: The newest ``seq`` taken from this call (None before the first command).
        self.seq: int | None = None
        #: When the newest command arrived (robot clock).
        self.last_command = -math.inf
        #: After ``replaced`` or ``stopped``: the user must let go before driving again.
        self.wait_for_release = False
        #: A refused start: the refusal, the safety state it was refused in, and when.
        self.refused: tuple[DriveState, object, float] | None = None
        #: Datagrams dropped (not commands, or older than the newest taken).
        self.dropped = 0
        self._sent: DriveState | None = None
        self._next_state = math.inf
        self._end_repeats = 0
        self.channel.set_callback(self._on_datagram)
        self.service.attach(self)

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        now = self._clock()
        try:
            command = decode_drive_command(datagram.payload)
        except NotADriveCommand:
            self.dropped += 1
            self.channel.stats.rejected += 1
            return
        except InvalidDriveCommand as exc:
            self.channel.stats.rejected += 1
            self.service.invalid(self, str(exc), now)
            return
        if self.seq is not None and not seq_newer(command.seq, self.seq):
            self.dropped += 1  # reordered or repeated: a newer command was taken already
            return
        self.seq = command.seq
        self.service.command(self, command, now)

    def report(self, state: DriveState, now: float, *, force: bool = False) -> None:
        """Send ``state`` if ``active`` or ``code`` changed (or ``force``); while active,
        :meth:`tick` repeats it at 5 Hz, and a changed inactive one END_REPEATS times."""
        sent = self._sent
        changed = sent is None or (sent.active, sent.code) != (state.active, state.code)
        self._sent = state
        if changed:
            self._next_state = now + STATE_EVERY
            self._end_repeats = 0 if state.active else END_REPEATS
        if changed or force:
            self._send(state)

    def tick(self, now: float) -> None:
        """Repeat the state: at 5 Hz while this call drives, END_REPEATS times when it stopped
        (each with the newest ``seq`` taken)."""
        sent = self._sent
        if sent is None or now < self._next_state:
            return
        if sent.active:
            self._next_state = max(self._next_state + STATE_EVERY, now)
            self._send(self.service.state_of(self))
        elif self._end_repeats > 0:
            self._end_repeats -= 1
            self._next_state = now + STATE_EVERY if self._end_repeats else math.inf
            self._send(_with_seq(sent, self))
        else:
            self._next_state = math.inf

    def close(self) -> None:
        """The call ended: its follow and its driving end (the robot stops)."""
        self.channel.set_callback(None)
        follow = self.service.follow
        if follow is not None:
            try:
                follow.call_ended(self.call_id)
            except Exception:
                log.exception("follow-me: ending the call's follow failed")
        self.service.detach(self, self._clock())

    def _send(self, state: DriveState) -> None:
        if not self.call.active:
            return
        try:
            self.channel.send(state.encode())
        except TelebotError as exc:  # the call ended under us
            log.debug("call %s: drive state not sent: %s", self.call_id, exc)


class DriveService:
    """The robot's direct driving (module docstring); ``tick`` it after the follow's."""

    def __init__(
        self,
        nav: NavStack,
        settings: DriveSettings | None = None,
        *,
        safety: DriveSafety | None = None,
        follow: FollowService | None = None,
        limits: MotionLimits | None = None,
    ) -> None:
        """``safety``: the supervisor's driver (None: roles alone decide, nothing is
        audited); ``follow``: the robot's follow-me, ended when driving starts."""
        self.nav = nav
        self.settings = settings if settings is not None else DriveSettings()
        self.safety = safety
        self.follow = follow
        self.limits = limits if limits is not None else nav.motion_limits
        self._calls: dict[str, CallDrive] = {}
        #: The call driving now (None: nobody).
        self.driver: CallDrive | None = None
        self._wanted = (0.0, 0.0)
        self._last = -math.inf
        #: What the robot commands now (after clamps).
        self.commanded = (0.0, 0.0)
        self._code = Reason.OK
        self._watchdog_mark = 0

    # -- calls ------------------------------------------------------------------------

    def attach(self, call: CallDrive) -> None:
        """A call opened its ``drive`` channel."""
        self._calls[call.call_id] = call

    def detach(self, call: CallDrive, now: float) -> None:
        """A call closed: if it drove, the robot stops."""
        self._calls.pop(call.call_id, None)
        if self.driver is call:
            self.end(Reason.STOPPED, "stopped: the call ended", now)

    def state_of(self, call: CallDrive) -> DriveState:
        """What ``call`` is told now."""
        seq = call.seq if call.seq is not None else 0
        cap = self._cap()
        if self.driver is call:
            linear, angular = self.commanded
            return DriveState(seq, True, self._code, "", linear, angular, cap)
        return DriveState(seq, False, Reason.OK, "", 0.0, 0.0, cap)

    # -- commands ---------------------------------------------------------------------

    def command(self, call: CallDrive, command: DriveCommand, now: float) -> None:
        """A new command (newer ``seq``) from ``call``."""
        gap = now - call.last_command
        call.last_command = now
        if command.release:
            call.wait_for_release = False
            call.refused = None
            if self.driver is call:
                self._end_unless_taken_over(Reason.RELEASED, "released", now)
            else:
                self._tell(call, Reason.RELEASED, "", now)
            return
        if call.wait_for_release:
            if gap < self.settings.stale_after:
                return  # still the key held through a takeover or a stop: ignored
            call.wait_for_release = False
        if self.driver is call:
            self._wanted = (command.linear, command.angular)
            self._last = now
            self._cycle(now)
            return
        # A new start: what a goal needs.
        if call.refused is not None and gap < self.settings.stale_after:
            state, key, when = call.refused
            retry = UNMEASURED_RETRY if state.code == Reason.RTT_UNMEASURED else REFUSAL_RETRY
            if key == self._safety_key() and now - when < retry:
                call.report(_with_seq(state, call), now)
                return
        refusal = self._may_start(call)
        if refusal is not None:
            state = DriveState(0, False, refusal.code, refusal.text, 0.0, 0.0, self._cap())
            call.refused = (state, self._safety_key(), now)
            call.report(_with_seq(state, call), now, force=True)
            return
        call.refused = None
        if self.driver is not None:  # no supervisor: the newest driver takes over
            self.end(Reason.REPLACED, "replaced: another call drives", now, stop=False)
        if self.follow is not None and (follow := self.follow.goal) is not None:
            why = "replaced by driving by hand"
            self.follow.end_follow(follow, GoalStatus.CANCELLED, why, Reason.REPLACED, stop=False)
        # A running goal is ended by the robot's drive() itself (code ``replaced``).
        self.driver = call
        self._wanted = (command.linear, command.angular)
        self._last = now
        self._code = Reason.OK
        self._watchdog_mark = self.safety.watchdog_stops if self.safety is not None else 0
        log.info("call %s drives by hand", call.call_id)
        self._cycle(now, starting=True)

    def invalid(self, call: CallDrive, text: str, now: float) -> None:
        """``call`` sent a command that does not decode: stop its driving, answer it."""
        log.debug("call %s: invalid drive command: %s", call.call_id, text)
        if self.driver is call:
            self._end_unless_taken_over(Reason.INVALID, text, now)
        state = DriveState(call.seq or 0, False, Reason.INVALID, text, 0.0, 0.0, self._cap())
        call.report(state, now, force=True)

    # -- events -----------------------------------------------------------------------

    def safety_changed(self, state: SafetyState, now: float) -> None:
        """The supervisor's state changed: a stop or a hand-over ends driving at once."""
        driver = self.driver
        if driver is not None and (why := self._safety_refusal(state, driver)) is not None:
            self.end(Reason.STOPPED, f"stopped: {why}", now)

    def tick(self, now: float) -> None:
        """One control cycle (after the supervisor's tick and the follow's)."""
        if self.driver is not None:
            self._cycle(now)

    def end(self, code: Reason, text: str, now: float, *, stop: bool = True) -> None:
        """End direct driving with ``code`` (audited); ``stop``: stop the robot too."""
        driver = self.driver
        if driver is None:
            return
        self.driver = None
        self._wanted = self.commanded = (0.0, 0.0)
        if stop:
            try:
                self.nav.stop()
            except Exception:
                log.exception("stopping after driving by hand failed")
        if code in (Reason.REPLACED, Reason.STOPPED):
            driver.wait_for_release = True
        log.info("call %s: driving by hand ended: %s (%s)", driver.call_id, code, text)
        if self.safety is not None:
            with contextlib.suppress(Exception):  # the audit log must not keep it driving
                self.safety.note(driver.call_id, f"{DRIVE_WHAT}: end", f"{code}: {text}")
        self._tell(driver, code, "" if code is Reason.RELEASED else text, now)

    # -- internals --------------------------------------------------------------------

    def _cycle(self, now: float, *, starting: bool = False) -> None:
        driver = self.driver
        assert driver is not None
        if self.safety is not None:
            if self.safety.watchdog_stops != self._watchdog_mark:
                silent = "stopped: the driver's link was silent (safety watchdog)"
                self.end(Reason.STOPPED, silent, now)
                return
            state = self.safety.state()
            if (why := self._safety_refusal(state, driver)) is not None:
                self.end(Reason.STOPPED, f"stopped: {why}", now)
                return
        if not starting and (took_over := self._taken_over()) is not None:
            self.end(Reason.REPLACED, took_over, now, stop=False)
            return
        if now - self._last > self.settings.stale_after:
            text = f"no command for {self.settings.stale_after:g} s: stopped"
            self.end(Reason.STALE, text, now)
            return
        cap = self._cap()
        linear = _clamp(self._wanted[0], cap)
        angular = _clamp(self._wanted[1], self.limits.max_angular_speed)
        room = self._room(linear)
        code = Reason.OK
        if linear != 0.0:
            allowed = math.sqrt(2.0 * self.limits.linear_accel * max(room - BRAKING_MARGIN, 0.0))
            if allowed < CRAWL:
                linear, code = 0.0, Reason.OBSTACLE
            elif allowed < abs(linear):
                linear = math.copysign(allowed, linear)
            if self.nav.status().state is NavState.BLOCKED:
                code = Reason.OBSTACLE  # the base's own guard holds it
        assert isinstance(self.nav, Drivable)
        try:
            self.nav.drive(linear, angular)
        except Exception:
            log.exception("drive command failed: stopping")
            self.end(Reason.FAILED, "the robot's velocity command failed", now)
            return
        self.commanded = (linear, angular)
        self._code = code
        driver.report(self.state_of(driver), now)

    def _taken_over(self) -> str | None:
        """Why another motion (a goal, a follow) has replaced driving, if one has."""
        if self.follow is not None and self.follow.goal is not None:
            return "replaced by a follow"
        goal = self.nav.current_goal()
        if goal is not None and not goal.status.done:
            return "replaced by a goal"
        return None

    def _end_unless_taken_over(self, code: Reason, text: str, now: float) -> None:
        """End driving with ``code`` and stop, unless a goal or follow took over since the
        last cycle: then it ends ``replaced`` and the new motion is left running."""
        took_over = self._taken_over()
        if took_over is not None:
            self.end(Reason.REPLACED, took_over, now, stop=False)
        else:
            self.end(code, text, now)

    def _may_start(self, call: CallDrive) -> Refusal | None:
        if self.safety is not None:
            refusal = self.safety.gate(call.call_id).motion(DRIVE_WHAT)
        elif not may(call.role or Role.OBSERVER, Right.DRIVE):
            refusal = Refusal(_OBSERVER, Reason.OBSERVER)
        else:
            refusal = None
        if refusal is None and not isinstance(self.nav, Drivable):
            refusal = Refusal("this robot takes no velocity commands", Reason.FAILED)
        return refusal

    def _safety_key(self) -> object:
        if self.safety is None:
            return None
        state = self.safety.state()
        return (state.armed, state.holder_call)

    def _safety_refusal(self, state: SafetyState, driver: CallDrive) -> str | None:
        if not state.armed:
            return state.text or "the robot was stopped"
        if state.holder_call != driver.call_id:
            return "the drive changed hands"
        return None

    def _cap(self) -> float:
        cap = min(self.nav.speed_limit, self.limits.max_linear_speed)
        if self.safety is not None:
            cap = min(cap, self.safety.state().cap)
        return max(cap, 0.0)

    def _room(self, linear: float) -> float:
        """Free distance the laser sees in the direction of ``linear`` (inf: no laser)."""
        nav = self.nav
        if linear == 0.0 or not isinstance(nav, LaserSource):
            return math.inf  # a base without a laser here guards itself (collision monitor)
        try:
            scan = nav.laser_scan()
            if scan is None:
                return 0.0  # fail safe: no scan yet, no driving
            angles = np.asarray(scan.angles, dtype=np.float64)
            ranges = np.asarray(scan.ranges, dtype=np.float64)
            hit = np.isfinite(ranges) & (ranges < scan.range_max)
            points = np.column_stack(
                (ranges[hit] * np.cos(angles[hit]), ranges[hit] * np.sin(angles[hit]))
            )
        except Exception:
            log.exception("laser scan unavailable")
            return 0.0  # fail safe: no scan, no driving
        radius = nav.motion_limits.robot_radius
        if linear > 0:
            return clearance_ahead(points, radius)
        return clearance_behind(points, radius, angles, hit)

    def _tell(self, call: CallDrive, code: Reason, text: str, now: float) -> None:
        seq = call.seq if call.seq is not None else 0
        call.report(DriveState(seq, False, code, text, 0.0, 0.0, self._cap()), now)


def _with_seq(state: DriveState, call: CallDrive) -> DriveState:
    """``state`` with the newest ``seq`` taken from ``call``."""
    seq = call.seq if call.seq is not None else 0
    return DriveState(
        seq, state.active, state.code, state.text, state.linear, state.angular, state.cap
    )


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))
