"""The user's commands that talk to a robot: ``chat``, ``send``, ``getmap``, ``where``."""

from __future__ import annotations

import asyncio
import codecs
import contextlib
import math
import os
import sys
import time
from collections.abc import AsyncGenerator, AsyncIterator, Callable, Coroutine, Iterator
from pathlib import Path
from typing import Any, TextIO

from telebot.apps.common import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from telebot.config import AppConfig
from telebot.errors import CallEnded, ProtocolError
from telebot.services.chat.wire import ChatReply
from telebot.services.client import ConnectionEvent, RobotClient, connect
from telebot.services.conference.wire import MAX_TEXT as MAX_SAY_TEXT
from telebot.services.conference.wire import Message, Roster, say_text
from telebot.services.people.wire import PeopleAlertMessage
from telebot.services.safety.wire import SafetyStatus, latched_text
from telebot.services.status.wire import PoseUpdate

__all__ = [
    "DRIVE_HOLD",
    "DRIVE_MODE_KEY",
    "chat_session",
    "drive_keys",
    "format_pose",
    "get_map",
    "read_lines",
    "send_command",
    "where",
]

#: The key that turns the terminal chat's drive mode on (Tab).
DRIVE_MODE_KEY = "\t"
#: How long one key event drives (s): longer than a terminal's key-repeat delay (about
#: 0.25 … 0.5 s), so a held key drives without a gap; a key let go stops the robot this
#: long plus ``[drive] stale_after`` later (a terminal says nothing when a key is let go).
DRIVE_HOLD = 0.6
#: Velocities of the drive keys: forward and back (m/s), turning (rad/s); the robot caps them.
DRIVE_FORWARD = 0.3
DRIVE_BACK = 0.15
DRIVE_TURN = 0.8
#: Each drive key's velocity (linear, angular): arrows (their last escape byte) and WASD.
_ARROWS = {
    "A": (DRIVE_FORWARD, 0.0),
    "B": (-DRIVE_BACK, 0.0),
    "C": (0.0, -DRIVE_TURN),
    "D": (0.0, DRIVE_TURN),
}
_WASD = {"w": _ARROWS["A"], "s": _ARROWS["B"], "d": _ARROWS["C"], "a": _ARROWS["D"]}
_DRIVE_HELP = (
    "[drive mode: hold the arrow keys or WASD to drive; space (any other key) stops "
    "the robot; Escape or Enter leaves drive mode]"
)


def drive_keys(chunk: str) -> list[tuple[str, float, float]]:
    """What the keys read in drive mode mean: ``("drive", linear, angular)`` for an arrow
    key or WASD, ``("leave", 0, 0)`` for Escape or Enter, ``("stop", 0, 0)`` for any
    other key (space, a letter, a function key …)."""
    events: list[tuple[str, float, float]] = []
    i = 0
    while i < len(chunk):
        char = chunk[i]
        if char == "\x1b" and i + 1 < len(chunk) and chunk[i + 1] in "[O":
            # An escape sequence: CSI/SS3 parameters, then one final byte (@ … ~).
            j = i + 2
            while j < len(chunk) and not "@" <= chunk[j] <= "~":
                j += 1
            final = chunk[j] if j < len(chunk) else ""
            if final in _ARROWS and final:
                events.append(("drive", *_ARROWS[final]))
            else:
                events.append(("stop", 0.0, 0.0))
            i = j + 1
            continue
        if char in ("\x1b", "\r", "\n"):
            events.append(("leave", 0.0, 0.0))
        elif char.lower() in _WASD:
            events.append(("drive", *_WASD[char.lower()]))
        else:
            events.append(("stop", 0.0, 0.0))
        i += 1
    return events


def _is_arrow(chunk: str) -> bool:
    """Whether ``chunk`` is only arrow keys (in line mode: a hint, not a stop)."""
    events = drive_keys(chunk)
    return bool(events) and chunk.startswith("\x1b") and all(e[0] == "drive" for e in events)


def format_pose(x: float, y: float, yaw: float) -> str:
    """A pose as people read it: metres and degrees (map frame, heading CCW from +x)."""
    return f"x {x:.2f} m, y {y:.2f} m, heading {math.degrees(yaw):.0f}°"


@contextlib.asynccontextmanager
async def _robot(
    robot: str,
    home: Path,
    config: AppConfig,
    timeout: float | None,
    *,
    reconnect: bool | None = False,
) -> AsyncIterator[RobotClient]:
    # One-shot commands do not reconnect (what was in flight fails: exit status 2);
    # chat follows config.reconnect.
    async with connect(
        robot, home=home, config=config, timeout=timeout, reconnect=reconnect
    ) as client:
        yield client


def _say_connection(event: ConnectionEvent) -> None:
    """Tell the chat user the call dropped / came back (stderr: stdout is the replies)."""
    print(f"[{event}]", file=sys.stderr, flush=True)


def stopped_itself_line(state: SafetyStatus, me: str | None) -> str:
    """The one line the chat prints after the robot stopped itself (``state.stopped_itself``:
    a silent link, a frozen picture, a dropped call): what happened and that ``arm`` drives
    on (said to the drive holder; others learn who may)."""
    what = state.text.removesuffix(": the robot stopped itself")  # said once is enough
    if me is None or state.holder in (None, me):
        way = "Type 'arm' to drive on."
    else:
        way = f"{state.holder} holds the drive and may re-arm it."
    return f"the robot stopped itself: {what}. {way}"


def _say_self_stops(client: RobotClient) -> None:
    """After the robot stopped itself, say so once on stderr (with connection news), with
    the re-arm that undoes it: a brief blip of the link costs one word, ``arm``."""
    first = client.latest_safety.value
    seen: list[SafetyStatus] = [first] if first is not None else []

    def on_state(state: SafetyStatus) -> None:
        previous = seen[-1] if seen else None
        seen[:] = [state]
        # Only stops seen happening (the state repeats once a second; an old stop found
        # on connecting is what `status` is for), and across reconnections too.
        if previous is None or not state.stopped_itself:
            return
        if not previous.armed and previous.text == state.text:
            return
        roster = client.conference.roster
        me = next((m.name for m in roster.users if m.you), None) if roster else None
        print(f"[{stopped_itself_line(state, me)}]", file=sys.stderr, flush=True)

    client.on_safety.append(on_state)


def _say_people_alert(alert: PeopleAlertMessage) -> None:
    """Tell the chat user about someone near the robot (stderr, like connection news)."""
    print(f"[{alert.text}]", file=sys.stderr, flush=True)


class _Progress:
    """A progress bar on a terminal; a single summary line otherwise."""

    def __init__(self, label: str, stream: TextIO = sys.stderr) -> None:
        self.label = label
        self.stream = stream
        self.tty = stream.isatty()

    def __call__(self, done: int, total: int) -> None:
        if not self.tty or total <= 0:
            return
        width = 30
        filled = int(width * done / total)
        self.stream.write(
            f"\r{self.label} [{'#' * filled}{' ' * (width - filled)}] {done}/{total} chunks"
        )
        self.stream.flush()

    def finish(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r\033[K")
        print(text, file=self.stream)


async def _fetch_and_save(client: RobotClient, png_path: Path, timeout: float) -> Path:
    progress = _Progress(f"map from {client.robot}")
    download = await client.get_map(timeout=timeout, progress=progress)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    yaml_path = download.save(png_path)
    progress.finish(
        f"map saved to {png_path} ({len(download.png) // 1024} KB, "
        f"{download.width} x {download.height} cells at {download.resolution:g} m, "
        f"{download.resent} chunks resent) and {yaml_path.name}"
    )
    return yaml_path


def format_roster(roster: Roster) -> str:
    """Who is in the robot's calls, as the chat shows it: ``alice (driver, driving), …``;
    a user's further calls (a page beside a terminal) say ``another call``."""
    people = []
    seen: set[str] = set()
    for member in roster.users:
        notes = [member.role] + (["driving"] if member.driving else [])
        if member.name in seen:
            notes.append("another call")
        seen.add(member.name)
        people.append(f"{member.name}{' (you)' if member.you else ''} ({', '.join(notes)})")
    return ", ".join(people) or "nobody"


def format_message(message: Message) -> str:
    """A conference message as the chat shows it: ``[alice] hello`` or ``[bot1: …]``."""
    if message.kind == "robot":
        return f"[{message.sender}: {message.text}]"
    return f"[{message.sender}] {message.text}"


def _show_conference(client: RobotClient) -> None:
    """Print other users' messages, the robot's announcements and roster changes (stderr:
    stdout is the replies to this user's commands)."""
    shown: list[str] = []

    def on_message(message: Message) -> None:
        roster = client.conference.roster
        me = next((m.name for m in roster.users if m.you), None) if roster else None
        if message.kind == "user" and message.sender == me:
            return  # what this user typed: already on the screen
        print(format_message(message), file=sys.stderr, flush=True)

    def on_roster(roster: Roster) -> None:
        text = format_roster(roster)
        if shown != [text]:
            shown[:] = [text]
            print(f"[in the call: {text}]", file=sys.stderr, flush=True)

    client.conference.on_message.append(on_message)
    client.conference.on_roster.append(on_roster)
    if client.conference.roster is not None:
        on_roster(client.conference.roster)


def _print_reply(reply: ChatReply) -> None:
    print(f"{'' if reply.ok or not reply.final else '! '}{reply.text}", flush=True)


#: How much of a command the chat shows when it echoes or names it.
SHOWN_CHARS = 80


def shown(command: str) -> str:
    """``command`` as the chat echoes it: cut at :data:`SHOWN_CHARS` (a line of a megabyte
    is not printed back)."""
    return command if len(command) <= SHOWN_CHARS else command[:SHOWN_CHARS] + "…"


async def _run_command(
    client: RobotClient,
    command: str,
    timeout: float | None,
    map_dir: Path,
    *,
    survive_drop: bool = False,
    motions: _Motions | None = None,
) -> bool:
    """One chat command: print its replies; fetch the map for getmap. True if it succeeded.

    ``survive_drop``: a call that drops under the command fails the command (never sent
    again on the next call) instead of raising, unless no call will come any more.
    ``motions``: told when the command's motion starts and ends (the terminal chat).
    """
    ok = False
    attachment = None
    moving = False
    try:
        if (message := say_text(command)) is not None:
            # "say TEXT": to everyone in the robot's calls (the conference), not a command.
            if len(message) > MAX_SAY_TEXT:  # what the robot refuses, and may not fit a datagram
                print(f"! say refused: message longer than {MAX_SAY_TEXT} characters", flush=True)
                return False
            said = await client.say(message, timeout=timeout or 5.0)
            if not said.ok:
                print(f"! say refused: {said.text}", flush=True)
            return said.ok
        async for reply in client.chat_replies(command, timeout=timeout):
            # A motion runs from its acknowledgement to its final reply: noted before the
            # reply shows, so that a key typed on seeing "finished moving" is a command.
            if motions is not None and not reply.final and not moving:
                moving = True
                motions.started()
            elif motions is not None and reply.final and moving:
                moving = False
                motions.ended()
            _print_reply(reply)
            if reply.final:
                ok, attachment = reply.ok, reply.attachment
        if ok and attachment == "map":
            await _fetch_and_save(client, map_dir / f"{client.robot}-map.png", timeout or 60.0)
    except ProtocolError as exc:  # a command no robot would take (too long): not sent
        print(f"! {exc}", flush=True)
        return False
    except CallEnded:
        if not survive_drop:
            raise
        what = "the call ended" if client.finished else "the call dropped (not resent)"
        print(f"! {shown(command)}: interrupted, {what}", flush=True)
        return False
    finally:
        if moving and motions is not None:  # no final reply will come for it
            motions.ended()
    return ok


async def send_command(
    robot: str,
    command: str,
    *,
    home: Path,
    config: AppConfig,
    timeout: float,
    map_dir: Path,
    arm: bool = False,
) -> int:
    """``telebot-user send``: exit 0 on success, 1 when the robot reports failure.

    ``arm`` re-arms the robot first, in the same call (a robot latches stopped whenever
    its driver's call ends, so a one-shot motion needs it).
    """
    async with _robot(robot, home, config, config.call.connect_timeout) as client:
        if arm:
            ack = await client.arm()
            if not ack.ok:
                print(f"! refused to arm: {ack.text}", flush=True)
                return EXIT_FAILURE
        try:
            ok = await _run_command(client, command, timeout, map_dir)
        except TimeoutError:
            print(
                f"telebot-user: error: {robot} did not finish {shown(command)!r} within {timeout:g} s",
                file=sys.stderr,
            )
            return EXIT_USAGE
    return EXIT_OK if ok else EXIT_FAILURE


async def chat_session(
    robot: str,
    *,
    home: Path,
    config: AppConfig,
    timeout: float,
    map_dir: Path,
    stdin: TextIO = sys.stdin,
    record: Path | None = None,
) -> int:
    """``telebot-user chat``: interactive on a terminal, one command per line otherwise.

    Piped input runs the commands one after the other, each to its end (a script of
    moves), and ends after the last one, all within ``timeout``: stdin is read without
    blocking the event loop, so while the script pauses the call stays up, the conference
    shows and the timeout runs. On a terminal commands run at once, and while the robot
    moves any key stops it (Escape always does). ``record``: an MCAP file of the call
    (``--record``).
    """
    from telebot.apps.foxglove_bridge import recording

    async with (
        _robot(robot, home, config, config.call.connect_timeout, reconnect=None) as client,
        recording(client, record),
    ):
        client.on_connection.append(_say_connection)
        _show_conference(client)
        client.on_people_alert.append(_say_people_alert)
        _say_self_stops(client)
        print(
            f"connected to {robot} (role {client.call.role}); type help, Ctrl-D to leave",
            file=sys.stderr,
        )
        if stdin.isatty():
            return await _interactive(client, map_dir)
        try:
            async with asyncio.timeout(timeout):
                return await _until_no_call(client, _piped(client, stdin, map_dir))
        except TimeoutError:
            pass  # said once the call is closed: the error is the last line on stderr
    # Pauses in the script count: --timeout bounds the whole chat.
    print(
        f"telebot-user: error: chat did not finish within {timeout:g} s (--timeout)",
        file=sys.stderr,
    )
    return EXIT_USAGE


async def _piped(client: RobotClient, stdin: TextIO, map_dir: Path) -> int:
    """Piped chat: one command per line, each to its end before the next."""
    failures = 0
    async with contextlib.aclosing(read_lines(stdin)) as lines:
        async for line in lines:
            command = line.strip()
            if not command:
                continue
            print(f"> {shown(command)}", flush=True)
            if not await _run_command(client, command, None, map_dir, survive_drop=True):
                failures += 1
    return EXIT_OK if failures == 0 else EXIT_FAILURE


async def _until_no_call(client: RobotClient, work: Coroutine[Any, Any, int]) -> int:
    """``work``'s exit status, or 1 as soon as no call will come any more (the client has
    said why on stderr): a chat waiting for input must not outlive its robot."""
    task = asyncio.ensure_future(work)
    finished = asyncio.ensure_future(client.wait_finished())
    try:
        await asyncio.wait({task, finished}, return_when=asyncio.FIRST_COMPLETED)
        if task.done():
            return task.result()
        return EXIT_FAILURE
    finally:
        for future in (task, finished):
            future.cancel()
        await asyncio.gather(task, finished, return_exceptions=True)


async def read_lines(stream: TextIO) -> AsyncGenerator[str, None]:
    """The lines of ``stream`` (stdin), read without blocking the event loop.

    While a piped chat waits for its next line the loop must go on: the call's heartbeats
    keep the robot's deadman quiet, alerts and roster changes show, ``--timeout`` runs. A
    pipe, terminal or socket is read when the loop says it is readable; a regular file or
    an in-memory text (never waiting on anyone) is read as it is.
    """
    loop = asyncio.get_running_loop()
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is both
        fd = -1
    chunks: asyncio.Queue[bytes] = asyncio.Queue()

    def readable() -> None:
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""  # a read error ends the input like an end of file
        if not data:
            loop.remove_reader(fd)
        chunks.put_nowait(data)

    watched = fd >= 0
    if watched:
        try:
            loop.add_reader(fd, readable)
        except OSError:  # epoll refuses regular files (and /dev/null)
            watched = False
    if not watched:
        for line in stream:
            yield line
        return
    decoder = codecs.getincrementaldecoder("utf-8")(errors="replace")
    pending = ""
    try:
        while True:
            data = await chunks.get()
            pending += decoder.decode(data, final=not data)
            *complete, pending = pending.split("\n")
            for line in complete:
                yield line + "\n"
            if not data:
                break
        if pending:
            yield pending
    finally:
        loop.remove_reader(fd)


async def _interactive(client: RobotClient, map_dir: Path) -> int:
    """A terminal chat: line editing, and while the robot moves any key stops it."""
    loop = asyncio.get_running_loop()
    keys: asyncio.Queue[str] = asyncio.Queue()
    fd = sys.stdin.fileno()
    with _cbreak(fd):
        loop.add_reader(fd, lambda: keys.put_nowait(os.read(fd, 64).decode(errors="replace")))
        try:
            return await _edit_lines(client, map_dir, keys)
        finally:
            loop.remove_reader(fd)


@contextlib.contextmanager
def _cbreak(fd: int) -> Iterator[None]:
    """Keys arrive one by one, without echo (we echo what is typed ourselves)."""
    import termios
    import tty

    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd, termios.TCSANOW)  # not TCSAFLUSH: keys typed while connecting count
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


class _Motions:
    """Whether the robot moves, as the terminal chat decides what a key means.

    Decided from the goals' own state, not from the pose's velocity, which lags a goal's
    end (one pose every 0.1 s, and the base still rolls to rest after "finished moving"):
    a key typed just after the final reply is a command, not a stop.

    - This chat's motions run from their acknowledgement to their final reply: while one
      runs, any key stops the robot.
    - Otherwise a pose that names a running goal (someone else's) means moving; so does a
      pose that says the robot moves without a goal (a follow, manual driving), except
      while the base comes to rest after one of this chat's motions ended.
    - The pose that was the newest when one of this chat's motions ended was sent before
      that end: it says nothing about what runs now.

    Both exceptions are bounded in time (:data:`SETTLE_AT_MOST`, :data:`STALE_AT_MOST`), so
    that odometry that never reads exactly zero, or poses that stopped coming, can never
    make a key a command while the robot moves: in doubt, a key stops it.
    """

    #: After this chat's motion ended, the base comes to rest within this (s); motion the
    #: poses show later is someone else's.
    SETTLE_AT_MOST = 1.0
    #: The newest pose at a motion's end is taken as sent before it for this long (s).
    STALE_AT_MOST = 0.3

    def __init__(self, client: RobotClient, clock: Callable[[], float] = time.monotonic) -> None:
        self._client = client
        self._clock = clock
        self._running = 0
        self._stale: PoseUpdate | None = None
        self._settling = False
        self._ended_at = -math.inf

    def started(self) -> None:
        """One of this chat's motions was acknowledged: it runs."""
        self._running += 1

    def ended(self) -> None:
        """One of this chat's motions had its final reply (or its call dropped)."""
        self._running -= 1
        self._stale = self._client.latest_pose.value
        self._settling = True
        self._ended_at = self._clock()

    def on_pose(self, pose: PoseUpdate) -> None:
        """A pose came: once the base is at rest after this chat's motion, it has settled."""
        if self._settling and pose is not self._stale and _at_rest(pose):
            self._settling = False

    async def watch(self) -> None:
        """Follow the poses as they come (until cancelled)."""
        async for pose in self._client.poses():
            self.on_pose(pose)

    def moving(self) -> bool:
        """Whether a key now stops the robot."""
        if self._running:
            return True
        since_end = self._clock() - self._ended_at
        pose = self._client.latest_pose.value
        if pose is None or (pose is self._stale and since_end < self.STALE_AT_MOST):
            return False
        if pose.goal is not None:  # a goal runs, and not one of ours
            return True
        settling = self._settling and since_end < self.SETTLE_AT_MOST
        return not settling and not _at_rest(pose)


def _at_rest(pose: PoseUpdate) -> bool:
    return pose.v == 0.0 and pose.w == 0.0 and pose.state != "moving"


async def _edit_lines(client: RobotClient, map_dir: Path, keys: asyncio.Queue[str]) -> int:
    prompt = f"{client.robot}> "
    print(prompt, end="", flush=True)
    finished = asyncio.ensure_future(client.wait_finished())
    motions = _Motions(client)
    driving = _DriveMode(client, motions)
    watch = asyncio.ensure_future(motions.watch())
    drive_watch = asyncio.ensure_future(driving.watch())
    try:
        return await _read_keys(client, map_dir, keys, prompt, finished, motions, driving)
    finally:
        for future in (finished, watch, drive_watch):
            future.cancel()
        await asyncio.gather(finished, watch, drive_watch, return_exceptions=True)


async def _read_keys(
    client: RobotClient,
    map_dir: Path,
    keys: asyncio.Queue[str],
    prompt: str,
    finished: asyncio.Future[Any],
    motions: _Motions,
    driving: _DriveMode,
) -> int:
    line = ""
    async with asyncio.TaskGroup() as tasks:
        while True:
            key = asyncio.ensure_future(keys.get())
            await asyncio.wait({key, finished}, return_when=asyncio.FIRST_COMPLETED)
            if not key.done():  # no more calls: the chat is over
                key.cancel()
                print(file=sys.stderr)
                return EXIT_FAILURE
            chunk = key.result()
            if not chunk:
                break
            if driving.on:
                if driving.keys(chunk, tasks):
                    print(prompt + line, end="", flush=True)
                continue
            if motions.moving():
                # The paper's rule: any key while the robot moves stops it, at once.
                tasks.create_task(client.stop(how="key"))
                print("\r\033[K[key pressed: stopping]", flush=True)
                line = ""
                print(prompt, end="", flush=True)
                continue
            if _is_arrow(chunk):  # the robot is at rest: say how to drive, stop nothing
                print(f"\r\033[K[to drive with the arrow keys, press Tab]\n{prompt}{line}", end="")
                continue
            for index, char in enumerate(chunk):
                if char == DRIVE_MODE_KEY:
                    driving.enter()
                    if driving.keys(chunk[index + 1 :], tasks):
                        print(prompt + line, end="", flush=True)
                    break
                if char in ("\x04",) and not line:  # Ctrl-D on an empty line: leave
                    print()
                    return EXIT_OK
                if char in ("\r", "\n"):
                    print()
                    command = line.strip()
                    line = ""
                    if command in ("quit", "exit"):
                        return EXIT_OK
                    if command:
                        tasks.create_task(
                            _run_command(
                                client, command, None, map_dir, survive_drop=True, motions=motions
                            )
                        )
                    print(prompt, end="", flush=True)
                elif char in ("\x7f", "\b"):
                    if line:
                        line = line[:-1]
                        print("\b \b", end="", flush=True)
                elif char == "\x1b":  # Escape: stop (as in the web UI's chat box)
                    tasks.create_task(client.stop(how="key"))
                elif char.isprintable():
                    line += char
                    print(char, end="", flush=True)
    return EXIT_OK


class _DriveMode:
    """The terminal chat's drive mode (Tab): arrow keys and WASD drive the robot by hand.

    Each drive key event calls :meth:`RobotClient.drive` with :data:`DRIVE_HOLD`; a held
    key's auto-repeat keeps it driving, and a key let go stops the robot within
    ``DRIVE_HOLD`` plus the robot's ``stale_after``. Any other key stops the robot (a safety
    stop, ``how`` ``key``: it latches) and leaves drive mode; Escape or Enter releases (the
    robot stops at once, armed) and leaves it. What the robot makes of it (refusals, an
    obstacle, a takeover) is printed as it changes.
    """

    def __init__(self, client: RobotClient, motions: _Motions) -> None:
        self.client = client
        # Drive mode counts as one of this chat's motions: keys typed just after it ends
        # (the robot at rest, the poses not yet saying so) are commands, not stops.
        self._motions = motions
        self.on = False
        self._said: tuple[bool, str] | None = None

    def enter(self) -> None:
        """Turn drive mode on."""
        self.on = True
        self._said = None
        self._motions.started()
        print(f"\r\033[K{_DRIVE_HELP}", flush=True)

    def leave(self, text: str) -> None:
        """Turn drive mode off, saying why."""
        self.on = False
        self._motions.ended()
        print(f"\r\033[K[{text}]", flush=True)

    def keys(self, chunk: str, tasks: asyncio.TaskGroup) -> bool:
        """Act on keys read in drive mode; True when drive mode ended (show the prompt)."""
        for kind, linear, angular in drive_keys(chunk):
            if kind == "drive":
                self.client.drive(linear, angular, hold=DRIVE_HOLD)
            elif kind == "leave":
                self.client.drive(0.0, 0.0)
                self.leave("drive mode off")
                return True
            else:
                tasks.create_task(self.client.stop(how="key"))
                self.leave("key pressed: stopping; drive mode off")
                return True
        return False

    async def watch(self) -> None:
        """Say what the robot makes of the driving while in drive mode (until cancelled)."""
        while True:
            state = await self.client.latest_drive.next()
            said = (state.active, state.code)
            if not self.on or said == self._said:
                continue
            self._said = said
            if state.active and state.code == "ok":
                text = f"driving (speed cap {state.cap:.2f} m/s)"
            else:
                text = state.code + (f": {state.text}" if state.text else "")
            print(f"\r\033[K[drive: {text}]", flush=True)


async def get_map(
    robot: str, output: Path, *, home: Path, config: AppConfig, timeout: float
) -> int:
    """``telebot-user getmap``: write the PNG and its map_server YAML."""
    async with _robot(robot, home, config, config.call.connect_timeout) as client:
        await _fetch_and_save(client, output, timeout)
    return EXIT_OK


async def where(robot: str, *, home: Path, config: AppConfig, timeout: float) -> int:
    """``telebot-user where``: the robot's pose in the map frame and what it is doing."""
    async with _robot(robot, home, config, config.call.connect_timeout) as client:
        try:
            pose = await client.pose(timeout=timeout)
            # Every robot sends its safety state with its first pose, and on every change.
            safety = client.latest_safety.value
            if safety is None:
                async with asyncio.timeout(timeout):
                    safety = await client.latest_safety.next()
        except TimeoutError:
            print(
                f"telebot-user: error: {robot} sent no pose and state within {timeout:g} s",
                file=sys.stderr,
            )
            return EXIT_USAGE
    state = pose.state + (f" ({pose.detail})" if pose.detail else "")
    if not safety.armed:  # stopped and latched is not "idle": it will not move until re-armed
        state = latched_text(safety.text)
    print(f"{format_pose(pose.x, pose.y, pose.yaw)}; {state}")
    return EXIT_OK
