"""Reason codes: the stable, machine-readable *why* beside every reply's text.

People read the text; programs decide on the code. Chat replies, goal updates and safety
acks carry one in their ``code`` field (``docs/protocol.md`` §13.1 lists them)::

    {"id": 7, "seq": 0, "text": "refused: the robot is stopped (…); re-arm it first",
     "final": true, "ok": false, "code": "not_armed"}

The wording of a text may change from one release to the next; a code never does. A
receiver keeps a code it does not know as it is (a newer robot may add codes) and treats
a missing one as ``""`` (an older robot sends none).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

from telebot.errors import ProtocolError

__all__ = ["DESCRIPTIONS", "MAX_CODE", "Reason", "Refusal", "decode_code"]

#: Longest code a receiver accepts (characters).
MAX_CODE = 64


class Reason(enum.StrEnum):
    """Every reason code the robot sends (a ``str``: compare with ``==`` to plain text)."""

    OK = "ok"
    ACCEPTED = "accepted"
    FINISHED = "finished"
    # Who may do what, and the safety supervisor's refusals.
    OBSERVER = "observer"
    NOT_HOLDER = "not_holder"
    DRIVE_HELD = "drive_held"
    NOT_ARMED = "not_armed"
    RTT_UNMEASURED = "rtt_unmeasured"
    LINK_SILENT = "link_silent"
    LINK_POOR = "link_poor"
    CAMERA_WHILE_MOVING = "camera_while_moving"
    NO_SUPERVISOR = "no_supervisor"
    UNKNOWN_CALL = "unknown_call"
    CLOCK_FAULT = "clock_fault"
    # Why the robot is stopped (the safety state's code, §18), beside ``stopped``,
    # ``link_silent`` (the deadman), ``clock_fault`` and ``internal_error``.
    VIDEO_STALE = "video_stale"
    STARTED = "started"
    HUNG_UP = "hung_up"
    DROPPED = "dropped"
    HANDED_OVER = "handed_over"
    # Commands the robot could not make sense of.
    UNKNOWN_COMMAND = "unknown_command"
    USAGE = "usage"
    INVALID = "invalid"
    UNKNOWN_PLACE = "unknown_place"
    UNKNOWN_CAMERA = "unknown_camera"
    UNKNOWN_GOAL = "unknown_goal"
    UNKNOWN_TOPIC = "unknown_topic"
    TOPIC_NOT_ALLOWED = "topic_not_allowed"
    TOO_MANY_RELAYS = "too_many_relays"
    INTERNAL_ERROR = "internal_error"
    # How a motion ended, or why it could not start.
    NO_PATH = "no_path"
    OBSTACLE = "obstacle"
    STOPPED = "stopped"
    CANCELLED = "cancelled"
    REPLACED = "replaced"
    BATTERY_EMPTY = "battery_empty"
    FAILED = "failed"
    # Conference messages (``say``) refused.
    EMPTY = "empty"
    TOO_LONG = "too_long"
    TOO_FAST = "too_fast"
    # Follow-me (the ``follow`` command): whom to follow, and why a follow ended.
    NO_PERSON = "no_person"
    UNKNOWN_TRACK = "unknown_track"
    NO_PEOPLE_SOURCE = "no_people_source"
    LOST_PERSON = "lost_person"
    PERSON_TOO_CLOSE = "person_too_close"
    # Driving by hand (the ``drive`` channel): why it ended.
    RELEASED = "released"
    STALE = "stale"


#: What each code means (the table of docs/protocol.md §13.1 says the same).
DESCRIPTIONS: dict[Reason, str] = {
    Reason.OK: "done, or answered (queries, stop, cancel, arm, take, release)",
    Reason.ACCEPTED: "a motion started (the non-final acknowledgement, or a goal running)",
    Reason.FINISHED: "a motion reached its goal",
    Reason.OBSERVER: "the caller's role (observer) may not do this",
    Reason.NOT_HOLDER: "another call holds the drive, or nobody does: take it first",
    Reason.DRIVE_HELD: "take refused: another driver holds the drive",
    Reason.NOT_ARMED: "the robot is stopped (latched): the drive holder must arm it first",
    Reason.RTT_UNMEASURED: "the call's round trip is not measured yet: retry in ~0.1 s",
    Reason.LINK_SILENT: "the caller's link has been silent for the deadman time",
    Reason.LINK_POOR: "the caller's link is too slow or lossy to drive (speed cap 0)",
    Reason.CAMERA_WHILE_MOVING: "only the navcam may be selected while the robot moves",
    Reason.NO_SUPERVISOR: "the robot runs no safety supervisor: nothing to arm or hand over",
    Reason.UNKNOWN_CALL: "the safety supervisor does not know the call",
    Reason.CLOCK_FAULT: "the robot's clock failed: it stopped",
    Reason.VIDEO_STALE: (
        "the drive holder's video froze (no new picture for `[safety] stale_video`) "
        "while the robot moved: it stopped itself; a motion refused while it stays frozen"
    ),
    Reason.STARTED: "the robot (re)started: it comes up stopped until armed",
    Reason.HUNG_UP: "the drive holder's call hung up: the robot stopped",
    Reason.DROPPED: "the drive holder's call dropped (or was replaced by its client's next call)",
    Reason.HANDED_OVER: "the drive changed hands (taken over, taken to another call, released)",
    Reason.UNKNOWN_COMMAND: "not a command (or an empty line): see help",
    Reason.USAGE: "bad arguments: the text is the command's usage line",
    Reason.INVALID: (
        "a number that is not finite, or another invalid argument; "
        "a `safety` request that does not decode (§18)"
    ),
    Reason.UNKNOWN_PLACE: "no place of that name (the text lists the known ones)",
    Reason.UNKNOWN_CAMERA: "the robot has no camera of that name",
    Reason.UNKNOWN_GOAL: "a goal query for an id the robot does not know: send the goal again",
    Reason.UNKNOWN_TOPIC: "no relayable topic of that name (the text lists near matches)",
    Reason.TOPIC_NOT_ALLOWED: "the robot's [relay] config does not let the caller's role relay it",
    Reason.TOO_MANY_RELAYS: "the call already has as many relays as the robot allows",
    Reason.INTERNAL_ERROR: "the robot failed to run the command",
    Reason.NO_PATH: "no path to the goal (inside an obstacle, outside the map, unreachable)",
    Reason.OBSTACLE: "an obstacle holds the robot up (notice) or stopped the motion (final)",
    Reason.STOPPED: "someone stopped the robot",
    Reason.CANCELLED: "someone cancelled the motion",
    Reason.REPLACED: "a newer goal or manual driving replaced the motion",
    Reason.BATTERY_EMPTY: "the battery is empty",
    Reason.FAILED: "the motion failed for another reason (the text says which)",
    Reason.EMPTY: "a conference message with no text",
    Reason.TOO_LONG: "a conference message longer than 1000 characters",
    Reason.TOO_FAST: "more than 10 conference messages in 10 s from one call: wait",
    Reason.NO_PERSON: "follow refused: nobody is tracked in front of the robot",
    Reason.UNKNOWN_TRACK: "follow refused: no tracked person has that id (the text lists them)",
    Reason.NO_PEOPLE_SOURCE: "follow refused: this robot tracks no people",
    Reason.LOST_PERSON: "a follow ended: the person was lost (unseen, or only jumping tracks)",
    Reason.PERSON_TOO_CLOSE: "a follow ended: the person came closer than the minimum distance",
    Reason.RELEASED: "driving by hand ended: the user let go (a zero command); the robot stopped",
    Reason.STALE: "driving by hand ended: no fresh command for `[drive] stale_after`; the robot stopped",
}


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why something was refused: the text for people and the code for programs."""

    text: str
    code: Reason

    def __str__(self) -> str:
        return self.text


def decode_code(message: dict[str, Any], *, what: str) -> str:
    """The ``code`` of a decoded message: ``""`` when absent, kept as-is when unknown."""
    code = message.get("code", "")
    if not isinstance(code, str) or len(code) > MAX_CODE:
        raise ProtocolError(f"{what}: 'code' must be text of at most {MAX_CODE} characters")
    return code
