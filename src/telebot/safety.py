"""The safety supervisor: a pure state machine that decides when the robot must stop.

:class:`SafetySupervisor` is sans-IO, like h11's connection: it is fed with events (a call
joined or left, a sign of life, a stop key, a motion or camera request, re-arm, hand-over,
obstacle, time) with the time passed in as ``now`` (seconds, monotonic), and it answers
with *actions*: frozen dataclasses, one per fact, that a thin driver carries out in order
with ``match`` (see :data:`Action`). It imports no clock, no event loop and no transport,
so every rule is tested with plain numbers.

Rules (fail safe: when in doubt, stop or refuse):

- **Any key stops.** Every participant, driver or observer, and the robot itself (``call_id
  None``: a signal handler, the daemon) may stop. A stop is never refused and is idempotent:
  a repeated stop stops again and changes nothing else.
- **Latch and re-arm** (ISO 13850; ISO 3691-4 §4.1.14, no automatic restart). After any stop
  the robot stays *disarmed*; the running goal is cancelled by :class:`Stop` (the
  NavStack's ``stop()`` cancels it), never resumed. Only :meth:`SafetySupervisor.rearm` by
  the drive holder arms it again (not one read while the robot stopped itself: its driver
  sent it before knowing), and re-arming starts nothing: a new motion command is needed.
  The supervisor starts disarmed, so a daemon that crashed and restarted comes back
  stopped, and its first actions are a :class:`Stop` and a zero speed cap.
- **Deadman.** While armed, the drive holder's last sign of life (any authentic frame of its
  call) must be younger than ``timeout``; at the timeout the supervisor stops and latches.
  The holder hanging up, dropping, releasing the drive, or losing it to an admin stops and
  latches too. A call that reappears after a drop joins as any call does: disarmed.
- **Speed cap** (a stale-data guard). The linear speed is capped at ``max_speed`` times a
  link factor in 0 … 1, and is 0 whenever the robot is disarmed. With ``age`` the time since
  the holder's last sign of life and ``rtt`` its latest round trip, the control loop through
  the operator is ``delay = age + rtt`` old (the newest command was sent ``rtt/2`` before it
  arrived, in answer to video ``rtt/2`` older still)::

      delay_factor = 1                                    if delay <= grace
                   = (timeout - delay) / (timeout - grace) if grace < delay < timeout
                   = 0                                    if delay >= timeout
      loss_factor  = max(0, 1 - loss / 0.5)               heartbeat loss 0 … 1
      factor       = min(delay_factor, loss_factor)       0 while rtt is not measured

  Every term only falls as the link gets worse, and the cap is exactly 0 when the holder's
  age reaches the timeout, whatever the round trip. The cap is announced through
  :class:`SetSpeedCap` in steps of :data:`CAP_STEP`, rounded down.
- **No driving blind** (stale video, ``stale_video`` s, 0 = off). A holder who watches the
  robot's video (:meth:`~SafetySupervisor.video_report`: its receiver reported within
  :data:`WATCHING_WINDOW`, no BYE) must keep getting new pictures. With ``age`` the time
  since its frames counter last grew, a fourth term of the factor is::

      video_factor = 1                                              if age <= stale_video/2
                   = (stale_video - age) / (stale_video / 2)       if stale_video/2 < age < stale_video
                   = 0                                              if age >= stale_video

  so the cap falls while the picture freezes, at rest too; and at ``stale_video``, if the
  robot moves (:meth:`~SafetySupervisor.motion`), it stops and latches (code
  ``video_stale``). A holder who does not watch video is not subject to this rule.
- **One driver, many observers.** Contacts with role driver or admin may hold the drive, one
  call at a time; the first such call to join while the drive is free takes it at once
  (still disarmed), the others are observers until the holder releases it
  (:meth:`~SafetySupervisor.take_drive` then) or an admin takes it over. Motion, camera and
  re-arm requests from any call but the holder are refused with the reason. A user's second
  call is one more call: it observes while the first holds the drive, and may take the
  drive from it (the robot stops and latches, as for an admin's takeover).
- **A call replaced by its user's next one** (``join(..., replaces=)``: the same client
  calling again before the robot noticed the old call drop) leaves at once; if it held the
  drive the robot stops and latches and the drive passes to the new call, disarmed. A
  replacement never arms, and the old call's end is then only noted.
- **Navcam while moving.** An allowed motion selects the navigation camera first; another
  camera is refused while the robot moves unless ``usercam_while_moving``.
- **Audit.** Every command, stop, re-arm and hand-over yields an :class:`AuditRecord` (who,
  when, what, outcome), as data inside an :class:`Audit` action; the driver writes them as
  JSON lines.

States, in words::

    DISARMED, nobody holds ──(driver/admin joins or takes)──► DISARMED, H holds
    DISARMED, H holds ──(H re-arms, link fresh)──► ARMED, H holds
    ARMED ──(any stop · deadman · frozen video while moving · H leaves/drops/releases ·
             admin takeover · clock fault)──►
        Stop, DISARMED (holder: none, or the admin after a takeover)
    DISARMED, H holds ──(H leaves/drops/releases)──► DISARMED, nobody holds
    any, H holds ──(H's user calls again: H replaced by H')──► Stop, DISARMED, H' holds

Only ARMED with a fresh link lets :meth:`~SafetySupervisor.request_motion` through.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from typing import Literal, TypeAlias

from telebot.errors import ConfigError
from telebot.identity import Role
from telebot.reasons import Reason
from telebot.rights import Right, may

__all__ = [
    "CAP_STEP",
    "LOCAL",
    "LOSS_LIMIT",
    "NAVCAM",
    "WATCHING_WINDOW",
    "Action",
    "Audit",
    "AuditRecord",
    "Decision",
    "Outcome",
    "Participant",
    "SafetyState",
    "SafetySupervisor",
    "SelectCamera",
    "SetSpeedCap",
    "StateChanged",
    "Stop",
]

#: The navigation camera, selected whenever motion is allowed.
NAVCAM = "navcam"
#: ``who`` of audit records for stops asked by the robot itself (``call_id`` None).
LOCAL = "robot"
#: Heartbeat loss at which the speed cap reaches 0.
LOSS_LIMIT = 0.5
#: Announced speed caps are rounded down to this step (m/s), so that a link whose quality
#: wobbles does not send a new limit to the NavStack on every tick.
CAP_STEP = 0.01
#: A holder watches video while its receiver's reports come at most this far apart (s):
#: the robot's video sender stops streaming as long after the last report (§17.2).
WATCHING_WINDOW = 2.0
#: Frame counters of receiver reports are u32 and wrap (serial arithmetic, §17.2).
_U32 = 2**32

#: What an audit record says happened: commands are allowed or refused; events (join,
#: leave, deadman, obstacle) stopped the robot or were only noted.
Outcome: TypeAlias = Literal["allowed", "refused", "stopped", "noted"]


# -- what the supervisor knows -------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Participant:
    """One call taking part: who it is, and the state of its link as last reported."""

    call_id: str
    user: str
    role: Role
    joined: float
    #: Time of the last authentic frame from the call.
    last_heard: float
    #: Latest round trip (s); None until measured (the cap is 0 until then).
    rtt: float | None = None
    #: Share of the call's recent heartbeats that were lost (0 … 1).
    loss: float = 0.0
    #: The frames counter of the call's latest video report; None while it does not watch
    #: the robot's video (no report yet, or a BYE).
    video_frames: int | None = None
    #: When its latest video report came.
    video_heard: float = -math.inf
    #: When its frames counter last grew (or it began watching): its newest picture's age
    #: is counted from here.
    video_fresh: float = -math.inf

    @property
    def may_drive(self) -> bool:
        """Whether the role lets this call hold the drive (driver or admin)."""
        return may(self.role, Right.DRIVE)


@dataclass(frozen=True, slots=True)
class SafetyState:
    """A snapshot of the supervisor, for telemetry and user interfaces."""

    armed: bool
    #: Why the robot was last stopped, in words (empty while armed).
    text: str
    #: The reason code of the latest stop (``ok`` while armed): ``link_silent`` for the
    #: deadman, ``video_stale``, ``stopped`` for a stop request, … (see ``docs/protocol.md``
    #: §18), so a user interface can tell the robot stopping itself from a STOP button.
    code: Reason
    #: The user holding the drive, its call and role; None when the drive is free.
    holder: str | None
    holder_call: str | None
    holder_role: Role | None
    #: When ``armed`` last changed.
    since: float
    #: The linear speed cap in force (m/s), 0 when the robot may not move.
    cap: float
    #: Whether the NavStack reports an obstacle ahead.
    blocked: bool


@dataclass(frozen=True, slots=True)
class AuditRecord:
    """One line of the audit log: who asked what, when, and what came of it."""

    t: float
    who: str
    role: str
    call: str | None
    what: str
    outcome: Outcome
    detail: str = ""
    #: How a stop was given (``"button"``, ``"key"``, ``"tab_closed"``, ``"chat"``, …);
    #: empty for other records, and then left out of the JSON line.
    how: str = ""

    def to_json(self) -> str:
        """The record as one line of JSON (no newline; the driver writes it)."""
        record = asdict(self)
        if not self.how:
            del record["how"]
        return json.dumps(record, ensure_ascii=False, separators=(",", ":"))


# -- actions: what the driver must do, in order --------------------------------------------


@dataclass(frozen=True, slots=True)
class Stop:
    """Stop now: ``NavStack.stop()`` (cancels the running goal and halts the base);
    ``text`` says why."""

    text: str


@dataclass(frozen=True, slots=True)
class SetSpeedCap:
    """Apply this linear speed cap: ``NavStack.set_speed_limit(linear)`` (m/s)."""

    linear: float


@dataclass(frozen=True, slots=True)
class SelectCamera:
    """Select this camera for the driver's video: ``NavStack.select_camera(name)``."""

    name: str


@dataclass(frozen=True, slots=True)
class StateChanged:
    """The armed state, the reason or the drive holder changed (tell the participants)."""

    state: SafetyState


@dataclass(frozen=True, slots=True)
class Audit:
    """Append this record to the audit log."""

    record: AuditRecord


#: Everything the supervisor may ask of its driver.
Action: TypeAlias = Stop | SetSpeedCap | SelectCamera | StateChanged | Audit


@dataclass(frozen=True, slots=True)
class Decision:
    """The answer to a command: allowed or refused (with why), and the actions to carry out.

    The driver carries out ``actions`` in order (a :class:`Stop` always comes first) and
    then, if ``allowed``, the command itself. ``actions`` already holds ``Audit(audit)``;
    ``audit`` is the same record, at hand for replies and tests. ``code`` is the reason
    code of the answer (:class:`~telebot.reasons.Reason`): ``ok`` when
    allowed, else why not (``not_armed``, ``not_holder``, ``rtt_unmeasured``, …).
    """

    allowed: bool
    #: Why, in words (what a refusal tells the user; the audit record's detail).
    text: str
    actions: tuple[Action, ...]
    audit: AuditRecord
    code: Reason = Reason.OK


# -- the supervisor ------------------------------------------------------------------------

#: A refusal: the text for people and its reason code.
_Refusal: TypeAlias = tuple[str, Reason]
_UNKNOWN_CALL: _Refusal = ("unknown call", Reason.UNKNOWN_CALL)
#: Replaced calls remembered until their end is reported (a bound: ends always come).
_REPLACED_KEPT = 256


@dataclass(slots=True)
class _Step:
    """Actions gathered while handling one event, sorted by kind when it finishes."""

    t: float
    key: tuple[object, ...]
    stops: list[Action]
    rest: list[Action]
    audits: list[Action]
    #: Whether the robot was armed when this step began.
    armed: bool


class SafetySupervisor:
    """The pure safety state machine (see the module docstring for its rules)."""

    def __init__(
        self,
        *,
        timeout: float = 0.5,
        max_speed: float = 0.5,
        usercam_while_moving: bool = False,
        grace: float = 0.1,
        stale_video: float = 1.0,
        now: float,
    ) -> None:
        """Start disarmed, with nobody holding the drive.

        ``timeout``: the deadman time (s); ``max_speed``: the hard linear cap (m/s);
        ``grace``: loop delay (s) below which the link costs no speed (two heartbeats at
        20 Hz); ``usercam_while_moving``: allow cameras other than the navcam while moving;
        ``stale_video``: the age of a watching holder's newest picture at which a moving
        robot stops (s; 0 turns the rule off).
        """
        for name, value in (
            ("timeout", timeout),
            ("max_speed", max_speed),
            ("grace", grace),
            ("stale_video", stale_video),
        ):
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ConfigError(f"safety {name} must be a finite number, not {value!r}")
        if timeout <= 0:
            raise ConfigError(f"safety timeout must be > 0, not {timeout}")
        if max_speed <= 0:
            raise ConfigError(f"safety max_speed must be > 0, not {max_speed}")
        if not 0 <= grace < timeout:
            raise ConfigError(f"safety grace must be ≥ 0 and below the timeout, not {grace}")
        if stale_video < 0:
            raise ConfigError(f"safety stale_video must be ≥ 0 (0: off), not {stale_video}")
        if not math.isfinite(now):
            raise ConfigError(f"the start time must be a finite number, not {now!r}")
        # Read-only after construction: a safety limit is not something to change in passing.
        self._timeout = float(timeout)
        self._max_speed = float(max_speed)
        self._grace = float(grace)
        self._stale_video = float(stale_video)
        self._usercam_while_moving = bool(usercam_while_moving)
        self._clock = float(now)
        self._armed = False
        # A restart after a crash lands here too: stopped, disarmed, waiting for a re-arm.
        self._reason = "not armed since start"
        self._code = Reason.STARTED
        self._since = self._clock
        self._holder: str | None = None
        self._participants: dict[str, Participant] = {}
        # Calls replaced by their user's next call (old id -> new id) until they end.
        self._replaced: dict[str, str] = {}
        self._camera: str | None = None  # unknown until the supervisor selects one
        self._blocked = False
        self._moving = False
        self._announced: float | None = None
        # Whatever the NavStack was doing before this process started, it stops now: the
        # first actions returned, by whichever call comes first, are these.
        self._boot: list[Action] = [
            Stop("safety supervisor started"),
            Audit(AuditRecord(self._clock, LOCAL, "", None, "start", "stopped", self._reason)),
        ]

    # -- state ---------------------------------------------------------------------------

    @property
    def timeout(self) -> float:
        """The deadman time (s): the holder's silence at which the robot stops."""
        return self._timeout

    @property
    def max_speed(self) -> float:
        """The hard linear speed cap (m/s), before the link factor."""
        return self._max_speed

    @property
    def grace(self) -> float:
        """Control-loop delay (s) up to which the link costs no speed."""
        return self._grace

    @property
    def stale_video(self) -> float:
        """The age (s) of a watching holder's newest picture at which a moving robot stops
        (0: the rule is off)."""
        return self._stale_video

    @property
    def usercam_while_moving(self) -> bool:
        """Whether cameras other than the navcam may be selected while moving."""
        return self._usercam_while_moving

    @property
    def armed(self) -> bool:
        """Whether the robot may move (on a fresh link); False after any stop until re-arm."""
        return self._armed

    @property
    def stop_reason(self) -> str:
        """Why the robot was last stopped (empty while armed)."""
        return "" if self._armed else self._reason

    @property
    def stop_code(self) -> Reason:
        """The reason code of the latest stop (``ok`` while armed)."""
        return Reason.OK if self._armed else self._code

    @property
    def holder(self) -> str | None:
        """The user holding the drive, if any."""
        p = self._holder_participant()
        return p.user if p else None

    @property
    def holder_call(self) -> str | None:
        """The call holding the drive, if any."""
        return self._holder

    def participant(self, call_id: str) -> Participant | None:
        """What the supervisor knows of a call, or None if it has not joined."""
        return self._participants.get(call_id)

    def participants(self) -> tuple[Participant, ...]:
        """Every call taking part, in the order they joined."""
        return tuple(self._participants.values())

    def state(self, now: float | None = None) -> SafetyState:
        """A snapshot; the cap is the one at ``now`` (default: the latest time seen)."""
        p = self._holder_participant()
        return SafetyState(
            armed=self._armed,
            text=self.stop_reason,
            code=self.stop_code,
            holder=p.user if p else None,
            holder_call=self._holder,
            holder_role=p.role if p else None,
            since=self._since,
            cap=self.speed_cap(self._clock if now is None else now),
            blocked=self._blocked,
        )

    def speed_cap(self, now: float) -> float:
        """The linear cap at ``now`` (m/s): ``max_speed`` × link factor, 0 when disarmed.

        A pure query: it changes nothing, so a holder whose link has gone stale has a cap
        of 0 here even before :meth:`tick` latches the stop.
        """
        if not math.isfinite(now):
            return 0.0
        t = max(now, self._clock)
        p = self._holder_participant()
        if not self._armed or p is None or not p.may_drive:
            return 0.0
        return self.max_speed * self._link_factor(p, t)

    # -- participants --------------------------------------------------------------------

    def join(
        self, call_id: str, user: str, role: Role, now: float, *, replaces: str | None = None
    ) -> list[Action]:
        """A call came up. The first driver or admin to join a free drive takes it.

        Taking the drive this way arms nothing: the robot stays stopped until the holder
        re-arms it, so a call that reappears after a drop does not restart motion.

        ``replaces``: the same user's earlier call that this one takes the place of (a
        client calling again while the robot has not yet noticed its old call drop). That
        call leaves the supervisor now; if it held the drive, the robot stops and latches
        (it may have been moving on a link that is gone) and the drive passes to this call,
        still disarmed. The old call's end is then only noted.
        """
        step = self._begin(now)
        if step is None:
            return self._fault(call_id, "join")
        self._replaced.pop(call_id, None)  # an id used again is a new call (not expected)
        old = self._participants.get(replaces) if replaces is not None else None
        if old is not None and old.user == user and call_id not in self._participants:
            return self._replace(step, old, call_id, role)
        if call_id in self._participants:
            # Two calls under one id is a bookkeeping fault: keep the first, and if it
            # was driving, stop rather than guess which one is real.
            detail = "call already joined"
            if call_id == self._holder:
                self._disarm(step, "call joined twice", Reason.INTERNAL_ERROR)
                detail += "; robot stopped"
            self._audit(step, call_id, "join", "refused", detail)
            return list(self._finish(step))
        self._participants[call_id] = Participant(call_id, user, role, step.t, step.t)
        detail = f"as {role.value}"
        if self._holder is None and may(role, Right.DRIVE):
            self._holder = call_id
            detail += "; holds the drive (robot stays stopped until re-armed)"
        elif may(role, Right.DRIVE):
            detail += f"; observing while {self.holder} holds the drive"
        self._audit(step, call_id, "join", "noted", detail)
        return list(self._finish(step))

    def _replace(self, step: _Step, old: Participant, call_id: str, role: Role) -> list[Action]:
        """``call_id`` takes the place of ``old``, the same user's earlier call."""
        del self._participants[old.call_id]
        self._replaced[old.call_id] = call_id
        while len(self._replaced) > _REPLACED_KEPT:  # ends that never came: forget the oldest
            del self._replaced[next(iter(self._replaced))]
        self._participants[call_id] = Participant(call_id, old.user, role, step.t, step.t)
        detail = f"as {role.value}; replaces call {old.call_id} ({old.user} called again)"
        outcome: Outcome = "noted"
        if self._holder == old.call_id:
            # Fail safe: what the old call started ran on a link that is gone.
            reason = f"driver {old.user} called again (the old call is replaced)"
            self._disarm(step, reason, Reason.DROPPED)
            outcome = "stopped"
            if may(role, Right.DRIVE):
                self._holder = call_id
                detail += "; holds the drive (robot stays stopped until re-armed)"
            else:
                self._holder = None
        elif self._holder is None and may(role, Right.DRIVE):
            self._holder = call_id
            detail += "; holds the drive (robot stays stopped until re-armed)"
        self._audit(step, call_id, "join", outcome, detail)
        return list(self._finish(step))

    def leave(self, call_id: str, how: Literal["hung_up", "dropped"], now: float) -> list[Action]:
        """A call ended. If it held the drive: stop, latch and free the drive."""
        step = self._begin(now)
        if step is None:
            return self._fault(call_id, "leave")
        what = "hang up" if how == "hung_up" else "drop"
        successor = self._replaced.pop(call_id, None)
        if successor is not None:
            self._audit(step, call_id, what, "noted", f"replaced by call {successor}")
            return list(self._finish(step))
        if call_id not in self._participants:
            self._audit(step, call_id, what, "refused", "unknown call")
            return list(self._finish(step))
        outcome: Outcome = "noted"
        if call_id == self._holder:
            user = self._participants[call_id].user
            words = "hung up" if how == "hung_up" else "dropped"
            code = Reason.HUNG_UP if how == "hung_up" else Reason.DROPPED
            self._disarm(step, f"driver {user} {words}", code)
            self._holder = None
            outcome = "stopped"
        self._audit(step, call_id, what, outcome, "")
        del self._participants[call_id]
        return list(self._finish(step))

    def heartbeat(
        self, call_id: str, now: float, *, rtt: float | None, loss: float
    ) -> list[Action]:
        """A sign of life (any authentic frame) from a call, with its link quality.

        ``rtt`` and ``loss`` are the call's latest figures; an ``rtt`` that is not a finite,
        non-negative number counts as unmeasured and a ``loss`` that is not finite as total.
        Unknown calls are ignored (no audit record: these arrive many times a second).
        """
        step = self._begin(now)
        if step is None:
            return self._fault(call_id, "heartbeat")
        p = self._participants.get(call_id)
        if p is not None:
            # A frame stamped before the latest event is as old as its stamp says: counting
            # it as heard "now" would make a stale link look fresh.
            heard = min(float(now), step.t)
            good_rtt = rtt is not None and math.isfinite(rtt) and rtt >= 0
            clean_loss = min(1.0, max(0.0, loss)) if math.isfinite(loss) else 1.0
            self._participants[call_id] = replace(
                p,
                last_heard=max(p.last_heard, heard),
                rtt=float(rtt) if good_rtt and rtt is not None else None,
                loss=clean_loss,
            )
        return list(self._finish(step))

    # -- commands ------------------------------------------------------------------------

    def request_stop(
        self, call_id: str | None, now: float, text: str = "stop requested", how: str = ""
    ) -> Decision:
        """Stop: from any participant, or the robot itself when ``call_id`` is None.

        ``how`` says how the stop was given (``"button"``, ``"key"``, ``"tab_closed"``,
        ``"chat"``, …): it goes into the stop reason and the audit record. Never refused,
        not even for an unknown call id: refusing a stop is never the safe answer.
        Idempotent: a repeated stop issues :class:`Stop` again and keeps the first reason.
        """
        step = self._begin(now)
        if step is None:
            return self._fault_decision(call_id, "stop")
        p = self._participants.get(call_id) if call_id is not None else None
        by = LOCAL if call_id is None else (p.user if p else f"unknown call {call_id}")
        was_armed = self._armed
        self._disarm(step, f"{text} by {by}" + (f" ({how})" if how else ""), Reason.STOPPED)
        detail = text if was_armed else f"{text} (already stopped)"
        return self._decide(step, call_id, "stop", True, detail, how=how)

    def request_motion(self, call_id: str, now: float, what: str) -> Decision:
        """May this call move the robot now (``what``: the command, for the audit log)?

        Allowed only when the robot is armed, the call holds the drive and its link is
        fresh enough for a cap above 0. On allow, the navcam is selected first and the cap
        in force is announced.
        """
        step = self._begin(now)
        if step is None:
            return self._fault_decision(call_id, f"motion: {what}")
        label = f"motion: {what}"
        refusal = self._holder_refusal(call_id, "drive")
        if refusal is None and not self._armed:
            refusal = (f"the robot is stopped ({self._reason}); re-arm it first", Reason.NOT_ARMED)
        if refusal is None:
            refusal = self._link_refusal(call_id, step.t)
        if refusal is not None:
            return self._decide(step, call_id, label, False, *refusal)
        if self._camera != NAVCAM:
            step.rest.append(SelectCamera(NAVCAM))
            self._camera = NAVCAM
        detail = "obstacle ahead" if self._blocked else ""
        return self._decide(step, call_id, label, True, detail)

    def request_camera(self, call_id: str, camera: str, moving: bool, now: float) -> Decision:
        """May this call select ``camera``? Only the holder; not the usercam while moving."""
        step = self._begin(now)
        if step is None:
            return self._fault_decision(call_id, f"camera: {camera}")
        label = f"camera: {camera}"
        refusal = self._holder_refusal(call_id, "select the camera", Right.CAMERA)
        if refusal is None and moving and camera != NAVCAM and not self.usercam_while_moving:
            refusal = (
                f"{camera} is refused while the robot moves: stop first, or use {NAVCAM}",
                Reason.CAMERA_WHILE_MOVING,
            )
        if refusal is not None:
            return self._decide(step, call_id, label, False, *refusal)
        step.rest.append(SelectCamera(camera))
        self._camera = camera
        return self._decide(step, call_id, label, True, "")

    def rearm(self, call_id: str, now: float, *, armed_when_received: bool = False) -> Decision:
        """Arm the robot again after a stop: only the drive holder, on a live link, and
        not if the robot stopped itself while this request was being read (in this step,
        or, with ``armed_when_received``, since the request arrived armed: its own frame,
        taken as a sign of life first, brought the deadman or a frozen picture due). Its
        driver sent it before they could know; that stop latches until a re-arm made
        after it.

        Re-arming starts nothing: the goal that was running was cancelled by the stop.
        """
        step = self._begin(now)
        if step is None:
            return self._fault_decision(call_id, "rearm")
        refusal = self._holder_refusal(call_id, "re-arm")
        if refusal is None:
            age = step.t - self._participants[call_id].last_heard
            if age >= self.timeout:
                refusal = (
                    f"your link is silent for {age:.2f} s; re-arm needs a live link",
                    Reason.LINK_SILENT,
                )
            elif (step.armed or armed_when_received) and not self._armed:
                refusal = (
                    f"the robot has just stopped: {self._reason}; arm again to drive on",
                    self._code,
                )
        if refusal is not None:
            return self._decide(step, call_id, "rearm", False, *refusal)
        if self._armed:
            return self._decide(step, call_id, "rearm", True, "already armed")
        detail = f"was stopped: {self._reason}"
        self._armed = True
        self._reason = ""
        self._since = step.t
        return self._decide(step, call_id, "rearm", True, detail)

    def take_drive(self, call_id: str, now: float) -> Decision:
        """Take the drive: a driver when it is free or held by another call of the same
        user, an admin always.

        Taking it from another call stops and latches the robot: the new holder must
        re-arm it, after seeing where it is.
        """
        step = self._begin(now)
        if step is None:
            return self._fault_decision(call_id, "take drive")
        p = self._participants.get(call_id)
        if p is None:
            return self._decide(step, call_id, "take drive", False, *_UNKNOWN_CALL)
        if not p.may_drive:
            refusal = f"{p.user} is an {p.role.value}: only drivers and admins may drive"
            return self._decide(step, call_id, "take drive", False, refusal, Reason.OBSERVER)
        previous = self._holder_participant()
        if previous is not None and previous.call_id == call_id:
            return self._decide(step, call_id, "take drive", True, "already yours")
        own = previous is not None and previous.user == p.user
        if previous is not None and not own and not may(p.role, Right.TAKE_OVER):
            refusal = f"the drive is held by {previous.user}; ask them to release it"
            return self._decide(step, call_id, "take drive", False, refusal, Reason.DRIVE_HELD)
        detail = ""
        if previous is not None and own:
            # A user moves the drive between their own calls (the page and the terminal):
            # the robot stops, and this call re-arms it once its user sees where it is.
            self._disarm(step, f"{p.user} took the drive to another call", Reason.HANDED_OVER)
            detail = f"taken from {p.user}'s call {previous.call_id}"
        elif previous is not None:
            reason = f"{p.user} (admin) took over the drive from {previous.user}"
            self._disarm(step, reason, Reason.HANDED_OVER)
            detail = f"taken over from {previous.user}"
        self._holder = call_id
        return self._decide(step, call_id, "take drive", True, detail)

    def release_drive(self, call_id: str, now: float) -> Decision:
        """Give up the drive: stop, latch, and let another driver take it."""
        step = self._begin(now)
        if step is None:
            return self._fault_decision(call_id, "release drive")
        refusal = self._holder_refusal(call_id, "release the drive")
        if refusal is not None:
            return self._decide(step, call_id, "release drive", False, *refusal)
        user = self._participants[call_id].user
        # Nobody would be watching the robot any more: it must not go on moving.
        self._disarm(step, f"{user} released the drive", Reason.HANDED_OVER)
        self._holder = None
        return self._decide(step, call_id, "release drive", True, "")

    # -- events --------------------------------------------------------------------------

    def obstacle(self, blocked: bool, now: float) -> list[Action]:
        """The NavStack reports an obstacle ahead (or its clearing).

        Noted, not latched: the NavStack already holds still before obstacles, and a driver
        must be able to turn away from one.
        """
        step = self._begin(now)
        if step is None:
            return self._fault(None, "obstacle")
        if blocked != self._blocked:
            self._blocked = blocked
            text = "obstacle ahead" if blocked else "obstacle cleared"
            self._audit(step, None, "obstacle", "noted", text)
        return list(self._finish(step))

    def motion(self, moving: bool, now: float) -> list[Action]:
        """The NavStack reports the robot moving (any velocity) or at rest.

        Only a moving robot is stopped for a frozen picture: at rest the cap alone keeps it
        from starting blind, and fresh pictures lift the cap again without a re-arm.
        """
        step = self._begin(now)
        if step is None:
            return self._fault(None, "motion")
        self._moving = bool(moving)
        self._video_lockout(step)
        return list(self._finish(step))

    def video_report(
        self, call_id: str, frames: int, now: float, *, bye: bool = False
    ) -> list[Action]:
        """A receiver report from ``call_id`` on the robot's ``video`` (§17.2), as the video
        sender accepted it (reordered reports already dropped): its ``frames`` counter (u32,
        wraps) and its BYE flag.

        The first report (or the first after a BYE or a 2 s lapse) starts the stale-video
        rule for the call with a fresh picture; a counter that grew freshens it; a BYE ends
        the rule for the call. Unknown calls are ignored (no audit record: these arrive five
        times a second).
        """
        step = self._begin(now)
        if step is None:
            return self._fault(call_id, "video report")
        p = self._participants.get(call_id)
        if p is not None and isinstance(frames, int):
            frames %= _U32
            t = step.t
            if bye:
                p = replace(p, video_frames=None)
            elif p.video_frames is None or t - p.video_heard >= WATCHING_WINDOW:
                p = replace(p, video_frames=frames, video_heard=t, video_fresh=t)
            else:
                # Serial arithmetic: a counter that moved forward by less than half the space.
                grew = 0 < (frames - p.video_frames) % _U32 < _U32 // 2
                p = replace(
                    p,
                    video_frames=frames if grew else p.video_frames,
                    video_heard=t,
                    video_fresh=t if grew else p.video_fresh,
                )
            self._participants[call_id] = p
        return list(self._finish(step))

    def tick(self, now: float) -> list[Action]:
        """Time passes: the deadman and the speed cap are brought up to ``now``.

        Call it at least as often as heartbeats arrive: between ticks the NavStack keeps
        the last cap announced.
        """
        step = self._begin(now)
        if step is None:
            return self._fault(None, "tick")
        return list(self._finish(step))

    # -- internals -----------------------------------------------------------------------

    def _holder_participant(self) -> Participant | None:
        return self._participants.get(self._holder) if self._holder is not None else None

    def _link_factor(self, p: Participant, t: float) -> float:
        """The link factor of the module docstring, 0 … 1."""
        if p.rtt is None:
            return 0.0
        delay = (t - p.last_heard) + p.rtt
        if delay >= self.timeout or t - p.last_heard >= self.timeout:
            return 0.0
        delay_factor = (
            1.0 if delay <= self.grace else (self.timeout - delay) / (self.timeout - self.grace)
        )
        loss_factor = max(0.0, 1.0 - p.loss / LOSS_LIMIT)
        return max(0.0, min(1.0, delay_factor, loss_factor, self._video_factor(p, t)))

    def _announced_cap(self, t: float) -> float:
        cap = self.speed_cap(t)
        if cap >= self.max_speed:
            return self.max_speed
        # min(): a quotient that rounds up must not lift the cap above the exact one.
        return min(cap, math.floor(cap / CAP_STEP) * CAP_STEP)

    def _key(self) -> tuple[object, ...]:
        return (self._armed, self._reason, self._code, self._holder, self._blocked)

    def _begin(self, now: float) -> _Step | None:
        """Bring the supervisor to ``now`` (the deadman first); None for a clock fault."""
        if not isinstance(now, int | float) or not math.isfinite(now):
            return None
        # Time never runs backwards in here: a late event is handled at the latest time
        # seen (only a sign of life keeps its own, older stamp).
        self._clock = max(self._clock, float(now))
        step = _Step(self._clock, self._key(), [], [], [], self._armed)
        boot, self._boot = self._boot, []
        for action in boot:
            (step.audits if isinstance(action, Audit) else step.stops).append(action)
        self._deadman(step)
        self._video_lockout(step)
        return step

    def _deadman(self, step: _Step) -> None:
        if not self._armed:
            return
        p = self._holder_participant()
        if p is None or not p.may_drive:  # cannot happen; if it does, nobody is in charge
            self._disarm(step, "armed without a driver", Reason.INTERNAL_ERROR)
            self._audit(step, None, "deadman", "stopped", "armed without a driver")
            return
        age = step.t - p.last_heard
        if age >= self.timeout:
            # The deadman time, not the age: a late tick must not make the rule look laxer.
            reason = f"driver {p.user}'s link lost: silent {self.timeout:.2f} s (deadman)"
            self._disarm(step, reason, Reason.LINK_SILENT)
            self._audit(step, p.call_id, "deadman", "stopped", f"silent for {age:.3f} s")

    def _watching(self, p: Participant, t: float) -> bool:
        """Whether the stale-video rule applies to ``p``: on, and its reports come."""
        return (
            self._stale_video > 0
            and p.video_frames is not None
            and t - p.video_heard < WATCHING_WINDOW
        )

    def _video_factor(self, p: Participant, t: float) -> float:
        """The video term of the link factor (module docstring), 0 … 1."""
        if not self._watching(p, t):
            return 1.0
        age = t - p.video_fresh
        half = self._stale_video / 2
        if age <= half:
            return 1.0
        if age >= self._stale_video:
            return 0.0
        return (self._stale_video - age) / half

    def _video_lockout(self, step: _Step) -> None:
        """No driving blind: stop and latch a moving robot whose holder's picture froze."""
        p = self._holder_participant()
        if not self._armed or not self._moving or p is None or not self._watching(p, step.t):
            return
        age = step.t - p.video_fresh
        if age >= self._stale_video:
            # The configured time, as the deadman's: the age may be a tick later.
            reason = f"video frozen for {self._stale_video:.1f} s: the robot stopped itself"
            self._disarm(step, reason, Reason.VIDEO_STALE)
            self._audit(
                step, p.call_id, "video_stale", "stopped", f"no new picture for {age:.3f} s"
            )

    def _disarm(self, step: _Step, reason: str, code: Reason) -> None:
        """Stop, and latch if armed; a stop while stopped keeps the first reason and code."""
        step.stops.append(Stop(reason))
        if self._armed:
            self._armed = False
            self._reason = reason
            self._code = code
            self._since = step.t

    def _holder_refusal(
        self, call_id: str, verb: str, right: Right = Right.DRIVE
    ) -> _Refusal | None:
        p = self._participants.get(call_id)
        if p is None:
            return _UNKNOWN_CALL
        if not may(p.role, right):
            return f"{p.user} is an {p.role.value}: observers may not {verb}", Reason.OBSERVER
        if self._holder != call_id:
            holder = self._holder_participant()
            if holder is None:
                text = f"you do not hold the drive (it is free: take it to {verb})"
                return text, Reason.NOT_HOLDER
            if holder.user == p.user:
                text = f"your other call holds the drive (take it to {verb} from this one)"
                return text, Reason.NOT_HOLDER
            return f"the drive is held by {holder.user}", Reason.NOT_HOLDER
        return None

    def _link_refusal(self, call_id: str, t: float) -> _Refusal | None:
        p = self._participants[call_id]
        age = t - p.last_heard
        if age >= self.timeout:
            return f"your link is silent for {age:.2f} s", Reason.LINK_SILENT
        if p.rtt is None:
            text = "your link's round trip is not measured yet; try again in a moment"
            return text, Reason.RTT_UNMEASURED
        if self._watching(p, t) and t - p.video_fresh >= self._stale_video:
            age = t - p.video_fresh
            text = f"your video is frozen (no new picture for {age:.1f} s): wait for it"
            return text, Reason.VIDEO_STALE
        if self.speed_cap(t) <= 0:
            text = f"your link is too poor to drive (rtt {p.rtt:.3f} s, loss {p.loss:.0%})"
            return text, Reason.LINK_POOR
        return None

    def _audit(
        self,
        step: _Step,
        call_id: str | None,
        what: str,
        outcome: Outcome,
        detail: str,
        how: str = "",
    ) -> AuditRecord:
        p = self._participants.get(call_id) if call_id is not None else None
        if call_id is None:
            who, role = LOCAL, ""
        elif p is None:
            who, role = f"unknown call {call_id}", ""
        else:
            who, role = p.user, p.role.value
        record = AuditRecord(step.t, who, role, call_id, what, outcome, detail, how)
        step.audits.append(Audit(record))
        return record

    def _finish(self, step: _Step) -> tuple[Action, ...]:
        """The step's actions in the order to carry them out: stops first."""
        cap: list[Action] = []
        announced = self._announced_cap(step.t)
        if announced != self._announced:
            self._announced = announced
            cap.append(SetSpeedCap(announced))
        state: list[Action] = []
        if self._key() != step.key:
            state.append(StateChanged(self.state(step.t)))
        return (*step.stops, *cap, *step.rest, *state, *step.audits)

    def _decide(
        self,
        step: _Step,
        call_id: str | None,
        what: str,
        allowed: bool,
        detail: str,
        code: Reason = Reason.OK,
        *,
        how: str = "",
    ) -> Decision:
        outcome: Outcome = "allowed" if allowed else "refused"
        record = self._audit(step, call_id, what, outcome, detail, how)
        return Decision(allowed, detail, self._finish(step), record, code)

    def _fault(self, call_id: str | None, what: str) -> list[Action]:
        """A ``now`` that is not a finite number: the clock cannot be trusted, so stop."""
        step = _Step(self._clock, self._key(), [], [], [], self._armed)
        boot, self._boot = self._boot, []
        for action in boot:
            (step.audits if isinstance(action, Audit) else step.stops).append(action)
        self._disarm(step, "clock fault", Reason.CLOCK_FAULT)
        self._audit(step, call_id, what, "refused", "time is not a finite number; stopped")
        return list(self._finish(step))

    def _fault_decision(self, call_id: str | None, what: str) -> Decision:
        actions = tuple(self._fault(call_id, what))
        record = next(a.record for a in reversed(actions) if isinstance(a, Audit))
        text = "time is not a finite number; stopped"
        return Decision(False, text, actions, record, Reason.CLOCK_FAULT)
