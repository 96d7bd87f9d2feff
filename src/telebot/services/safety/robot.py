"""The thin driver of the safety supervisor: calls and the NavStack on one side, rules on the other.

:class:`SafetyDriver` feeds :class:`~telebot.safety.SafetySupervisor` with what happens
(calls joining and leaving, their signs of life and link quality, commands, obstacles,
time) and carries out its actions on the NavStack (stop, speed cap, camera), writes the
audit log and tells every call when the safety state changes.

The deadman does not depend on the event loop: a watchdog thread compares the drive
holder's last sign of life (a float the call updates on every authentic frame) with the
monotonic clock every :data:`WATCHDOG_PERIOD`, and if it is older than the timeout it asks
the NavStack for an emergency stop, which needs no loop to act. A stuck handler therefore
cannot keep the robot moving; the loop latches the stop as soon as it runs again.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Literal

from telebot.channels.call import Call
from telebot.identity import Role
from telebot.reasons import Refusal
from telebot.robot.nav import EmergencyStoppable, NavState, Velocity
from telebot.safety import (
    LOCAL,
    Action,
    Audit,
    AuditRecord,
    Decision,
    SafetyState,
    SafetySupervisor,
    SelectCamera,
    SetSpeedCap,
    StateChanged,
    Stop,
)
from telebot.services.video.wire import Report

__all__ = ["WATCHDOG_PERIOD", "CallGate", "SafetyDriver"]

log = logging.getLogger(__name__)

#: How often the watchdog thread looks at the drive holder's link (s).
WATCHDOG_PERIOD = 0.01


class SafetyDriver:
    """Connects the supervisor to calls, the NavStack, the audit log and the watchdog."""

    def __init__(
        self,
        nav: EmergencyStoppable,
        *,
        timeout: float,
        max_speed: float,
        usercam_while_moving: bool = False,
        stale_video: float = 1.0,
        audit_path: Path | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.nav = nav
        self._clock = clock
        self.supervisor = SafetySupervisor(
            timeout=timeout,
            max_speed=max_speed,
            usercam_while_moving=usercam_while_moving,
            stale_video=stale_video,
            now=clock(),
        )
        self._audit_file: IO[str] | None = None
        if audit_path is not None:
            audit_path.parent.mkdir(parents=True, exist_ok=True)
            self._audit_file = audit_path.open("a", encoding="utf-8", buffering=1)
        self._calls: dict[str, Call] = {}
        #: Called with each new safety state (the services send it to every call).
        self.on_state: Callable[[SafetyState], None] = lambda state: None
        #: Called with each audit record as it is written (the call recorder keeps them).
        self.on_audit: Callable[[AuditRecord], None] = lambda record: None
        # What the watchdog thread watches: the holder's call while armed, else None.
        # Written by the loop, read by the thread; a tuple swap is atomic under the GIL.
        self._watch: tuple[Call, float] | None = None
        self._stop_thread = threading.Event()
        self._thread: threading.Thread | None = None
        self.watchdog_stops = 0
        self._blocked = False
        self._moving = False
        self.apply(self.supervisor.tick(clock()))  # the start-up stop and zero cap

    # -- lifecycle ------------------------------------------------------------------------

    def start(self) -> None:
        """Start the watchdog thread."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._watchdog, name="telebot-safety-watchdog", daemon=True
            )
            self._thread.start()

    def close(self) -> None:
        """Stop the watchdog thread and close the audit log."""
        self._stop_thread.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._audit_file is not None:
            with contextlib.suppress(OSError):
                self._audit_file.close()
            self._audit_file = None

    def __enter__(self) -> SafetyDriver:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- events ---------------------------------------------------------------------------

    def join(self, call: Call, *, replaces: Call | None = None) -> None:
        """A call came up; ``replaces``: the same user's earlier call it takes the place
        of (it leaves the supervisor now, handing over its drive, disarmed)."""
        self._calls[call.id] = call
        role = call.role if call.role is not None else Role.OBSERVER
        old = None
        if replaces is not None:
            self._calls.pop(replaces.id, None)  # no more signs of life from it count
            old = replaces.id
        self.apply(self.supervisor.join(call.id, call.peer, role, self._clock(), replaces=old))

    def leave(self, call: Call) -> None:
        """A call ended (hung up or dropped)."""
        self._calls.pop(call.id, None)
        hung_up = call.end is not None and call.end.kind == "hung_up"
        how: Literal["hung_up", "dropped"] = "hung_up" if hung_up else "dropped"
        self.apply(self.supervisor.leave(call.id, how, self._clock()))

    def tick(self) -> None:
        """Each control step: signs of life and link quality of every call, obstacles, time."""
        now = self._clock()
        for call_id in list(self._calls):
            self.heard(call_id)
        blocked = self.nav.status().state is NavState.BLOCKED
        if blocked != self._blocked:
            self._blocked = blocked
            self.apply(self.supervisor.obstacle(blocked, now))
        moving = self.nav.velocity() != Velocity()
        if moving != self._moving:
            self._moving = moving
            self.apply(self.supervisor.motion(moving, now))
        self.apply(self.supervisor.tick(now))

    def video_report(self, call: Call, report: Report) -> None:
        """A receiver report on ``call``'s ``video`` that its sender took (§17.2)."""
        if call.id in self._calls:
            now = self._clock()
            self.apply(self.supervisor.video_report(call.id, report.frames, now, bye=report.bye))

    def stop(self, call_id: str | None, text: str = "stop requested", how: str = "") -> Decision:
        """Stop (anyone may; ``call_id`` None: the robot itself); ``how``: see ``STOP_HOWS``."""
        return self.carry_out(self.supervisor.request_stop(call_id, self._clock(), text, how))

    def heard(self, call_id: str) -> None:
        """Tell the supervisor ``call_id``'s latest sign of life and link quality now, not
        at the next control step: a request that just arrived is itself one, and a re-arm
        right after the link came back must not be refused on the step-old view."""
        call = self._calls.get(call_id)
        if call is not None:
            stats = call.stats
            self.apply(
                self.supervisor.heartbeat(call.id, call.last_heard, rtt=stats.rtt, loss=stats.loss)
            )

    def gate(self, call_id: str) -> CallGate:
        """What ``call_id`` may do, for the chat and goals services."""
        return CallGate(self, call_id)

    def state(self) -> SafetyState:
        """The supervisor's state now."""
        return self.supervisor.state(self._clock())

    def note(self, call_id: str | None, what: str, detail: str = "") -> None:
        """Write an audit record of something the supervisor did not decide (the end of
        driving by hand): outcome ``noted``, who from the call (``call_id`` None: the robot)."""
        p = self.supervisor.participant(call_id) if call_id is not None else None
        if call_id is None:
            who, role = LOCAL, ""
        elif p is None:
            who, role = f"unknown call {call_id}", ""
        else:
            who, role = p.user, p.role.value
        self.apply([Audit(AuditRecord(self._clock(), who, role, call_id, what, "noted", detail))])

    # -- actions --------------------------------------------------------------------------

    def carry_out(self, decision: Decision) -> Decision:
        """Carry out a decision's actions; the caller then runs the command if allowed."""
        self.apply(decision.actions)
        return decision

    def apply(self, actions: Iterable[Action]) -> None:
        """Carry out the supervisor's actions in order."""
        for action in actions:
            match action:
                case Stop(text):
                    log.warning("safety stop: %s", text)
                    self.nav.stop()
                case SetSpeedCap(linear):
                    self.nav.set_speed_limit(linear)
                case SelectCamera(name):
                    self.nav.select_camera(name)
                case StateChanged(state):
                    self.on_state(state)
                case Audit(record):
                    if self._audit_file is not None:
                        try:
                            self._audit_file.write(record.to_json() + "\n")
                        except OSError as exc:  # a full disk must not stop the robot's loop
                            log.error("audit log not written: %s", exc)
                    try:
                        self.on_audit(record)
                    except Exception:  # a recorder's trouble must not stop a stop
                        log.exception("audit listener failed")
        self._update_watch()

    def _update_watch(self) -> None:
        sup = self.supervisor
        holder = sup.holder_call
        call = self._calls.get(holder) if holder is not None else None
        self._watch = (call, sup.timeout) if sup.armed and call is not None else None

    def _watchdog(self) -> None:
        while not self._stop_thread.wait(WATCHDOG_PERIOD):
            try:
                self._watch_once()
            except Exception:  # the watchdog must outlive any one failure
                log.exception("safety watchdog check failed")

    def _watch_once(self) -> None:
        watch = self._watch
        if watch is None:
            return
        call, timeout = watch
        if time.monotonic() - call.last_heard > timeout:
            self._watch = None
            self.watchdog_stops += 1
            self.nav.emergency_stop(f"driver {call.peer} silent for {timeout:g} s")


class CallGate:
    """One call's rights, as the supervisor decides them (used by chat and goals).

    Each method returns None when allowed, or the refusal (text and code) to send back.
    """

    def __init__(self, driver: SafetyDriver, call_id: str) -> None:
        self._driver = driver
        self.call_id = call_id

    def _decide(self, decision: Decision) -> Refusal | None:
        self._driver.carry_out(decision)
        return None if decision.allowed else Refusal(decision.text, decision.code)

    def motion(self, what: str) -> Refusal | None:
        """May this call start ``what`` (a motion command) now?"""
        self._driver.heard(self.call_id)
        sup = self._driver.supervisor
        return self._decide(sup.request_motion(self.call_id, self._driver._clock(), what))

    def camera(self, name: str) -> Refusal | None:
        """May this call select camera ``name`` now?"""
        nav = self._driver.nav
        # A goal just accepted, or held up by an obstacle, stands still but is about to move.
        moving = nav.velocity() != Velocity() or nav.current_goal() is not None
        sup = self._driver.supervisor
        return self._decide(sup.request_camera(self.call_id, name, moving, self._driver._clock()))

    def stop(self, text: str = "stop requested", how: str = "") -> None:
        """Stop the robot (never refused); ``text`` says why, ``how`` it was given goes to
        the audit log."""
        self._driver.stop(self.call_id, text, how)

    def rearm(self) -> Refusal | None:
        """Re-arm the robot (the drive holder only; not if it stopped itself while the
        request was read: :meth:`SafetySupervisor.rearm`)."""
        sup = self._driver.supervisor
        armed = sup.armed
        self._driver.heard(self.call_id)
        now = self._driver._clock()
        return self._decide(sup.rearm(self.call_id, now, armed_when_received=armed))

    def take(self) -> Refusal | None:
        """Take the drive."""
        return self._decide(self._driver.supervisor.take_drive(self.call_id, self._driver._clock()))

    def release(self) -> Refusal | None:
        """Give the drive up (the robot stops)."""
        sup = self._driver.supervisor
        return self._decide(sup.release_drive(self.call_id, self._driver._clock()))

    def latched(self) -> str | None:
        """Why the robot is stopped and latched (who or what stopped it); None while armed."""
        sup = self._driver.supervisor
        return None if sup.armed else sup.stop_reason
