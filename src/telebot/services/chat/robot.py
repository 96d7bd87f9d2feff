"""The chat service: the paper's text commands (Table I) run on a :class:`NavStack`.

One :class:`ChatSession` serves one caller on the ``chat`` channel. The daemon hands it
every datagram (:meth:`ChatSession.on_payload`) and calls :meth:`ChatSession.poll` from its
loop at 10 Hz or more; the session answers through ``send``. It needs no event loop and no
clock of its own: a motion's end is noticed by polling the goal's handle, exactly as the
paper's server monitored the pose until "finished moving".

A motion command is answered twice, as in the paper::

    fwd 2   →  "Forward command received"   (final: false)
            →  "finished moving"            (final: true, ok: true)
            or "stopped: obstacle ahead"    (final: true, ok: false)

Callers whose role may not drive (observers) may still ask questions and ``stop``: a stop
button that depends on one's role is not a safety feature.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from telebot.config import RelaySettings
from telebot.errors import (
    InvalidCommand,
    NoPath,
    ProtocolError,
    RobotError,
    UnknownCamera,
    UnknownPlace,
)
from telebot.identity import Role
from telebot.reasons import Reason, Refusal
from telebot.rights import Right as Privilege
from telebot.rights import rights_of
from telebot.robot.nav import GoalHandle, GoalStatus, NavStack, NavState, TopicSource
from telebot.services.chat.wire import (
    HELP_TEXT,
    USAGE,
    Arm,
    BatteryQuery,
    Cancel,
    ChatReply,
    Command,
    CommandError,
    Follow,
    Forward,
    GetMap,
    GotoPlace,
    GotoPoint,
    Help,
    Left,
    NavCam,
    Places,
    ReleaseDrive,
    Right,
    Status,
    Stop,
    TakeDrive,
    Topics,
    Turn,
    Unfollow,
    UserCam,
    Where,
    decode_request,
    parse_command,
)
from telebot.services.mapxfer.wire import EncodedMap, encode_map
from telebot.services.relay.wire import allowed_topic
from telebot.services.safety.wire import latched_text

__all__ = [
    "FINISHED",
    "NO_FOLLOW",
    "NO_SUPERVISOR",
    "OBSERVER_REFUSAL",
    "UNBLOCK_POLLS",
    "ChatSession",
    "DriveGate",
    "FollowHook",
    "error_reason",
    "goal_reason",
]

logger = logging.getLogger(__name__)

#: The final reply of a motion that reached its goal (the paper's words).
FINISHED = "finished moving"
#: The reply to an observer's motion or camera command.
OBSERVER_REFUSAL = "refused: observers may not drive or switch cameras — ask a driver"
#: Polls a blocked goal must stay clear before a new blockage earns a new notice; a robot
#: edging past an obstacle flickers between blocked and moving, and one notice is enough.
UNBLOCK_POLLS = 10

_ACK_GOTO = "Goto command received"
_ACK_FORWARD = "Forward command received"
_ACK_TURN = "Turn command received"

# The right each command needs beyond observing (table: telebot.rights).
_NEEDS: dict[type, Privilege] = {
    **dict.fromkeys(
        (
            GotoPlace,
            GotoPoint,
            Forward,
            Turn,
            Left,
            Right,
            Cancel,
            Arm,
            TakeDrive,
            ReleaseDrive,
            Follow,
            Unfollow,
        ),
        Privilege.DRIVE,
    ),
    NavCam: Privilege.CAMERA,
    UserCam: Privilege.CAMERA,
    Stop: Privilege.STOP,
}
# Commands that move the robot or change what it shows: logged at INFO.
_DRIVING = tuple(command for command, right in _NEEDS.items() if right is not Privilege.STOP)
# Commands that start a motion: the safety supervisor must allow each.
_MOVING = (GotoPlace, GotoPoint, Forward, Turn, Left, Right, Follow)


def _describe(command: Command) -> str:
    """A command as the audit log names it (``Forward(metres=2.0)`` → ``fwd 2``)."""
    match command:
        case GotoPlace(name):
            return f"goto {name}"
        case GotoPoint(x, y, yaw):
            return f"goto {x:g} {y:g}" + ("" if yaw is None else f" {yaw:g}")
        case Forward(metres):
            return f"fwd {metres:g}"
        case Turn(degrees):
            return f"turn {degrees:g}"
        case Follow(target):
            return "follow" if target is None else f"follow {target}"
        case _:
            return type(command).__name__.lower()


class DriveGate(Protocol):
    """The safety supervisor's say over one caller (see :mod:`telebot.services.safety.robot`).

    Each method returns None when allowed, or the refusal (text and code) to reply with.
    """

    def motion(self, what: str) -> Refusal | None:
        """May the caller start this motion now?"""
        ...

    def camera(self, name: str) -> Refusal | None:
        """May the caller select this camera now?"""
        ...

    def stop(self, text: str = "stop requested", how: str = "") -> None:
        """Stop the robot and latch (never refused); ``text`` says why, ``how`` it was given,
        for the audit."""
        ...

    def rearm(self) -> Refusal | None:
        """Re-arm after a stop."""
        ...

    def take(self) -> Refusal | None:
        """Take the drive."""
        ...

    def release(self) -> Refusal | None:
        """Give the drive up."""
        ...

    def latched(self) -> str | None:
        """Why the robot is stopped and latched (who or what stopped it); None while armed."""
        ...


class FollowHook(Protocol):
    """The robot's follow-me for one caller (see :mod:`telebot.services.drive.follow`)."""

    def start(self, target: int | None) -> GoalHandle | Refusal:
        """Follow ``target`` (None: the nearest person in front): the follow, or why not."""
        ...

    def unfollow(self) -> bool:
        """End the running follow (the robot stops); False when there was none."""
        ...


#: The reply to ``follow`` on a robot without follow-me.
NO_FOLLOW = "this robot cannot follow people"

#: Replies to the drive-holding commands when the robot runs no supervisor.
NO_SUPERVISOR = "this robot has no safety supervisor: nothing to arm or hand over"


@dataclass(slots=True)
class _Motion:
    """A motion request still waiting for its final reply."""

    request_id: int
    handle: GoalHandle
    notified_blocked: bool = False
    clear_polls: int = 0


class ChatSession:
    """Runs one caller's chat commands on ``nav`` and sends the replies (module docstring).

    ``role`` is the caller's contact role: its rights (:mod:`telebot.rights`) say which
    commands it may give; ``send`` delivers one reply on the chat channel; ``user`` names
    the caller in logs; ``map_offer`` gives the map the ``map`` channel sends (default:
    ``nav``'s map, cropped and encoded on each ``getmap``). Neither :meth:`on_payload` nor
    :meth:`poll` ever raises.
    """

    def __init__(
        self,
        nav: NavStack,
        *,
        role: Role | None,
        send: Callable[[ChatReply], None],
        user: str = "",
        gate: DriveGate | None = None,
        map_offer: Callable[[], EncodedMap] | None = None,
        relay: RelaySettings | None = None,
        follow: FollowHook | None = None,
    ) -> None:
        self._nav = nav
        self._follow = follow
        self._role = role
        # Which topics the caller may relay (``topics``): the robot's [relay] config.
        self._relay = relay if relay is not None else RelaySettings()
        # What getmap announces must be what the map channel sends: the cropped map.
        self._map_offer = map_offer or (lambda: encode_map(nav.map()))
        self._rights = rights_of(role)
        self._gate = gate
        self._send = send
        self._user = user or "caller"
        self._motions: list[_Motion] = []
        # Next reply number of each request that has not had its final reply.
        self._seq: dict[int, int] = {}
        #: Datagrams dropped because they were not chat requests.
        self.rejected = 0
        #: Replies that ``send`` failed to deliver (logged, then dropped).
        self.send_errors = 0

    @property
    def may_drive(self) -> bool:
        """Whether this caller's role may move the robot."""
        return Privilege.DRIVE in self._rights

    @property
    def pending(self) -> int:
        """Motion requests that have not had their final reply yet."""
        return len(self._motions)

    # ------------------------------------------------------------------ entry points

    def on_payload(self, payload: str | bytes) -> None:
        """Handle one datagram from the chat channel; garbage is counted and dropped."""
        try:
            request = decode_request(payload)
        except ProtocolError as exc:
            # No reply: without a valid id there is nothing to answer to, and answering
            # garbage would let any sender make the robot talk.
            self.rejected += 1
            logger.debug("chat from %s: dropped a datagram: %s", self._user, exc)
            return
        self.handle_text(request.id, request.text)

    def handle_text(self, request_id: int, text: str) -> None:
        """Parse and run one chat line as request ``request_id`` (never raises)."""
        try:
            command = parse_command(text)
        except CommandError as exc:
            self._reply(request_id, str(exc), exc.code, ok=False)
            return
        # Who moved the robot belongs in the log; a web UI polling "status" does not.
        level = logging.INFO if isinstance(command, (*_DRIVING, Stop)) else logging.DEBUG
        logger.log(level, "chat from %s: %s", self._user, command)
        try:
            self._execute(request_id, command)
        except RobotError as exc:
            # InvalidCommand, UnknownPlace (lists the known ones), UnknownCamera, NoPath:
            # the adapter's own message is the clearest answer.
            self._finish_done_motions()
            self._reply(request_id, str(exc), error_reason(exc), ok=False)
        except Exception:
            logger.exception("chat from %s: %r failed", self._user, text)
            text = "internal error: the robot could not run that"
            self._reply(request_id, text, Reason.INTERNAL_ERROR, ok=False)

    def poll(self) -> None:
        """Send the final replies of finished motions and notices of blocked ones."""
        try:
            self._finish_done_motions()
            self._notice_blockages()
        except Exception:
            # A broken adapter must not take the daemon's loop down with it.
            logger.exception("chat poll for %s failed", self._user)

    # ------------------------------------------------------------------ commands

    def _execute(self, request_id: int, command: Command) -> None:
        nav = self._nav
        gate = self._gate
        needs = _NEEDS.get(type(command), Privilege.OBSERVE)
        if needs not in self._rights:
            logger.info("chat from %s: refused %s (no %s right)", self._user, command, needs)
            text = OBSERVER_REFUSAL
            if gate is not None:
                # The supervisor refuses observers too, and writes the refusal to the audit
                # log: who tried what matters most when it was refused.
                refusal = gate.motion(_describe(command))
                text = f"refused: {refusal}" if refusal is not None else text
            self._reply(request_id, text, Reason.OBSERVER, ok=False)
            return
        if gate is not None and isinstance(command, _MOVING):
            refusal = gate.motion(_describe(command))
            if refusal is not None:
                self._refused(request_id, refusal)
                return
        match command:
            case GotoPlace(name):
                self._start_motion(request_id, nav.navigate_to_place(name), _ACK_GOTO)
            case GotoPoint(x, y, yaw_deg):
                yaw = None if yaw_deg is None else math.radians(yaw_deg)
                self._start_motion(request_id, nav.navigate_to(x, y, yaw), _ACK_GOTO)
            case Forward(metres):
                self._start_motion(request_id, nav.forward(metres), _ACK_FORWARD)
            case Turn(degrees_right):
                # The paper's turn is positive to the right; REP-103 is counter-clockwise.
                self._start_motion(request_id, nav.turn(-math.radians(degrees_right)), _ACK_TURN)
            case Left():
                self._start_motion(request_id, nav.turn(math.pi / 2), _ACK_TURN)
            case Right():
                self._start_motion(request_id, nav.turn(-math.pi / 2), _ACK_TURN)
            case Stop():
                if gate is not None:
                    gate.stop(how="chat")  # latches: the robot stays stopped until re-armed
                else:
                    # No supervisor to end a follow-me: end it here, or it drives on.
                    if self._follow is not None:
                        self._follow.unfollow()
                    nav.stop()
                self._finish_done_motions()  # the stopped request hears "stopped" first
                self._reply(request_id, "stopped")
            case Arm() | TakeDrive() | ReleaseDrive():
                self._drive_command(request_id, command)
            case Cancel():
                goal = nav.current_goal()
                if goal is None or goal.status.done:
                    # A follow-me is not the navigation stack's goal: cancel ends it too.
                    if self._follow is not None and self._follow.unfollow():
                        self._finish_done_motions()
                        self._reply(request_id, "cancelled")
                        return
                    self._reply(request_id, "nothing to cancel")
                    return
                goal.cancel()
                self._finish_done_motions()
                self._reply(request_id, "cancelled")
            case NavCam() | UserCam():
                camera = "navcam" if isinstance(command, NavCam) else "usercam"
                refusal = gate.camera(camera) if gate is not None else None
                if refusal is not None:
                    self._refused(request_id, refusal)
                    return
                nav.select_camera(camera)
                self._reply(request_id, f"{nav.active_camera} selected")
            case Follow(target):
                if self._follow is None:
                    self._reply(request_id, NO_FOLLOW, Reason.NO_PEOPLE_SOURCE, ok=False)
                    return
                started = self._follow.start(target)
                if isinstance(started, Refusal):
                    self._refused(request_id, started)
                    return
                self._start_motion(request_id, started, _following(started))
            case Unfollow():
                stopped = self._follow is not None and self._follow.unfollow()
                self._finish_done_motions()  # the follow's final reply goes first
                self._reply(request_id, "stopped following" if stopped else "not following anyone")
            case Where():
                self._reply(request_id, self._where())
            case Places():
                self._reply(request_id, self._places())
            case Topics():
                self._reply(request_id, self._topics())
            case Status():
                self._reply(request_id, self._status())
            case BatteryQuery():
                battery = nav.battery()
                text = f"battery {battery.percent:.0f}%"
                if battery.low:
                    text += " (low)"
                if battery.charging:
                    text += ", charging"
                self._reply(request_id, text)
            case GetMap():
                offer = self._map_offer()
                self._reply(
                    request_id,
                    f"sending map: {offer.width} x {offer.height} cells at {offer.resolution:g} m",
                    attachment="map",
                )
            case Help(topic):
                self._reply(request_id, HELP_TEXT if topic is None else USAGE[topic])

    def _drive_command(self, request_id: int, command: Arm | TakeDrive | ReleaseDrive) -> None:
        gate = self._gate
        if gate is None:
            self._reply(request_id, NO_SUPERVISOR, Reason.NO_SUPERVISOR, ok=False)
            return
        if isinstance(command, Arm):
            refusal, done = gate.rearm(), "armed: send a motion command to move"
        elif isinstance(command, TakeDrive):
            refusal, done = gate.take(), "you hold the drive (send arm to re-arm)"
        else:
            refusal, done = gate.release(), "drive released; the robot is stopped"
            self._finish_done_motions()  # the stopped motion's final reply goes first
        if refusal is not None:
            self._refused(request_id, refusal)
        else:
            self._reply(request_id, done)

    def _start_motion(self, request_id: int, handle: GoalHandle, ack: str) -> None:
        # The new goal may have replaced one of ours: its final reply goes out first.
        self._finish_done_motions()
        if handle.status.done:
            # Refused at once (no path, battery empty): the reason is the whole answer.
            self._final_reply(request_id, handle)
            return
        self._reply(request_id, ack, Reason.ACCEPTED, final=False)
        self._motions.append(_Motion(request_id, handle))

    def _where(self) -> str:
        pose = self._nav.pose().pose
        heading = round(math.degrees(pose.yaw)) + 0  # "+ 0": no "-0°"
        return f"x {_metres(pose.x)} m, y {_metres(pose.y)} m, heading {heading}°"

    def _topics(self) -> str:
        nav = self._nav
        if not isinstance(nav, TopicSource):
            return "this robot relays no topics"
        topics = sorted(
            (t for t in nav.topics() if allowed_topic(self._relay, self._role, t.name)),
            key=lambda t: t.name,
        )
        if not topics:
            return "no topics you may relay"
        return "topics: " + ", ".join(f"{t.name} ({t.type})" for t in topics)

    def _places(self) -> str:
        places = self._nav.places()
        if not places:
            return "no named places on this map"
        listed = ", ".join(
            f"{name} ({_metres(pose.x)}, {_metres(pose.y)})"
            for name, pose in sorted(places.items())
        )
        return f"places: {listed}"

    def _status(self) -> str:
        # Stopped and latched is not "idle": the robot will not move until re-armed.
        latched = self._gate.latched() if self._gate is not None else None
        if latched is not None:
            return latched_text(latched)
        status = self._nav.status()
        goal = self._nav.current_goal()
        text = str(status.state)
        # The simulated robot's detail while moving is the goal's description: say it once.
        if status.detail and (goal is None or status.detail != goal.description):
            text += f": {status.detail}"
        if goal is not None and not goal.status.done:
            text += f" — {goal.description}, {goal.progress:.0%} done"
        return text

    # ------------------------------------------------------------------ goal tracking

    def _finish_done_motions(self) -> None:
        still_running: list[_Motion] = []
        finished: list[_Motion] = []
        for motion in self._motions:
            (finished if motion.handle.status.done else still_running).append(motion)
        self._motions = still_running
        for motion in finished:
            self._final_reply(motion.request_id, motion.handle)

    def _notice_blockages(self) -> None:
        if not self._motions:
            return
        status = self._nav.status()
        current = self._nav.current_goal()
        for motion in self._motions:
            blocked = (
                status.state is NavState.BLOCKED
                and current is not None
                and current.goal_id == motion.handle.goal_id
            )
            if blocked:
                motion.clear_polls = 0
                if not motion.notified_blocked:
                    motion.notified_blocked = True
                    detail = status.detail or "obstacle ahead"
                    text = f"blocked: {detail}"
                    self._reply(motion.request_id, text, Reason.OBSTACLE, final=False, ok=False)
            elif motion.notified_blocked:
                motion.clear_polls += 1
                if motion.clear_polls >= UNBLOCK_POLLS:
                    motion.notified_blocked = False

    # ------------------------------------------------------------------ output

    def _refused(self, request_id: int, refusal: Refusal) -> None:
        self._reply(request_id, f"refused: {refusal}", refusal.code, ok=False)

    def _final_reply(self, request_id: int, handle: GoalHandle) -> None:
        ok = handle.status is GoalStatus.SUCCEEDED
        self._reply(request_id, _final_text(handle), goal_reason(handle), ok=ok)

    def _reply(
        self,
        request_id: int,
        text: str,
        code: str = Reason.OK,
        *,
        final: bool = True,
        ok: bool = True,
        attachment: str | None = None,
    ) -> None:
        seq = self._seq.pop(request_id, 0) if final else self._seq.get(request_id, 0)
        if not final:
            self._seq[request_id] = seq + 1
        reply = ChatReply(
            request_id, text, final=final, ok=ok, attachment=attachment, seq=seq, code=code
        )
        try:
            self._send(reply)
        except Exception:
            # A lost reply is what a lossy channel does anyway; the daemon must go on.
            self.send_errors += 1
            logger.warning("chat reply to %s could not be sent", self._user, exc_info=True)


def goal_reason(handle: GoalHandle) -> str:
    """The reason code of a finished goal (its NavStack's code, else one from its status)."""
    # A plug-in robot's goal handles may predate codes: then the status says it.
    code = getattr(handle, "code", "")
    if isinstance(code, str) and code:
        return code
    match handle.status:
        case GoalStatus.SUCCEEDED:
            return Reason.FINISHED
        case GoalStatus.CANCELLED:
            return Reason.CANCELLED
        case GoalStatus.FAILED:
            return Reason.FAILED
    return Reason.ACCEPTED


def error_reason(exc: Exception) -> Reason:
    """The reason code of an error the NavStack raised for a command."""
    match exc:
        case UnknownPlace():
            return Reason.UNKNOWN_PLACE
        case UnknownCamera():
            return Reason.UNKNOWN_CAMERA
        case NoPath():
            return Reason.NO_PATH
        case InvalidCommand():
            return Reason.INVALID
    return Reason.FAILED


def _final_text(handle: GoalHandle) -> str:
    """The final reply for a finished goal: the paper's words, or why it did not get there."""
    status, reason = handle.status, handle.reason
    if status is GoalStatus.SUCCEEDED:
        return FINISHED
    if status is GoalStatus.FAILED:
        return reason or "failed"
    # Cancelled: "stopped" and "cancelled" speak for themselves, other reasons need the
    # word ("cancelled: replaced by a new goal").
    if not reason:
        return "cancelled"
    if reason.startswith(("stopped", "cancelled")):
        return reason
    return f"cancelled: {reason}"


def _following(handle: GoalHandle) -> str:
    """The acknowledgement of a follow: "following person 3"."""
    return handle.description.replace("follow", "following", 1)


def _metres(value: float) -> str:
    text = f"{value:.2f}"
    return "0.00" if text == "-0.00" else text
