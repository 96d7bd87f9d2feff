"""``telebot-user``: the user's command line.

Talk to a robot (``chat``, ``send``), fetch its map (``getmap``), ask where it is
(``where``); manage your key and the robots you trust; list robots online; ping a robot;
show the robot in Foxglove (``foxglove``) and record its streams as MCAP (``record``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from telebot.apps.common import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    Parser,
    add_connection_options,
    add_home_option,
    app_config,
    home_of,
    keygen,
    name_arg,
    new_parser,
    run,
)
from telebot.identity import Identity, KnownRobots, encode_key, fingerprint, parse_public_key

PROG = "telebot-user"


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _port(text: str) -> int:
    value = int(text)
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port 0..65535, got {value}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def _teleop_topic(text: str) -> str:
    # As foxglove_bridge.TELEOP_TOPIC and GOAL_TOPIC (not imported here: the SDK is heavy).
    if not text.startswith("/") or len(text) < 2 or any(c.isspace() for c in text):
        raise argparse.ArgumentTypeError(f"must be a topic like /cmd_vel, got {text[:60]!r}")
    if text == "/goal_pose":
        raise argparse.ArgumentTypeError("/goal_pose is the goal topic, not a teleop topic")
    return text


def _teleop_rate(text: str) -> float:
    # The range of foxglove_bridge.TELEOP_RATES.
    value = float(text)
    if not 2.0 <= value <= 50.0:  # also refuses nan
        raise argparse.ArgumentTypeError(f"must be 2 to 50 Hz, got {text[:20]}")
    return value


def build_parser() -> Parser:
    """The argument parser of telebot-user."""
    parser = new_parser(PROG, "The telebot user client: call robots, talk and drive through them.")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    commands.required = True

    keygen = commands.add_parser("keygen", help="create your key pair")
    keygen.add_argument(
        "name", type=name_arg, help="your user name, as robots know you (e.g. alice)"
    )
    keygen.add_argument("--force", action="store_true", help="replace an existing key")
    add_home_option(keygen, "user")

    pubkey = commands.add_parser(
        "pubkey", help="print your public key line (give it to robot admins)"
    )
    add_home_option(pubkey, "user")

    known = commands.add_parser("known", help="list or edit the robots whose keys you trust")
    actions = known.add_subparsers(dest="action", metavar="ACTION", parser_class=Parser)
    actions.required = True
    listing = actions.add_parser("list", help="list known robots")
    add = actions.add_parser("add", help="trust a robot's key")
    add.add_argument("name", type=name_arg, help="the robot's name")
    add.add_argument("public_key", help="the robot's public key (or its whole .pub line)")
    remove = actions.add_parser("remove", help="forget a robot")
    remove.add_argument("name", type=name_arg)
    for action in (listing, add, remove):
        add_home_option(action, "user")

    robots = commands.add_parser("robots", help="list the robots online")
    add_home_option(robots, "user")
    add_connection_options(robots)
    robots.add_argument(
        "--wait", type=_positive_float, default=2.0, help="seconds to listen (default 2)"
    )

    ping = commands.add_parser(
        "ping", help="call a robot running 'telebot-robot echo' and measure the link"
    )
    ping.add_argument("robot", type=name_arg, help="the robot's name")
    add_home_option(ping, "user")
    add_connection_options(ping)
    ping.add_argument(
        "--count", type=_positive_int, default=20, help="datagrams to send (default 20)"
    )
    ping.add_argument(
        "--size", type=_positive_int, default=64, help="bytes per datagram, 12..32768 (default 64)"
    )
    ping.add_argument(
        "--interval",
        type=_positive_float,
        default=0.05,
        help="seconds between datagrams (default 0.05)",
    )
    ping.add_argument(
        "--timeout",
        type=_positive_float,
        default=None,
        help="seconds to wait for the robot to answer",
    )

    chat = commands.add_parser(
        "chat",
        help="chat with a robot (Table I commands, 'say TEXT' to everyone in its calls); reads "
        "commands from stdin when piped",
        description="Chat with a robot. On a terminal, commands run as you type them and, "
        "while the robot moves, any key stops it (Escape always does). Piped, one command "
        "per line runs to its end before the next, and the command exits after the last one; "
        "all of it, pauses in the input included, within --timeout (else exit 2). While chat "
        "waits for input its call stays up. The robot starts stopped: send 'arm' before moving it. If the "
        "call drops, chat calls the robot again by itself and says so on stderr ([reconnect] "
        "in the config); the robot stays stopped until you send 'arm' again. "
        "When the robot stops itself (the driver's link silent for the deadman time, its "
        "video frozen, its call dropped) chat says so in one line on stderr: 'arm' drives on. "
        "Everyone in the "
        "robot's calls is a conference: 'say TEXT' reaches all of them with your name; their "
        "messages, the robot's announcements and who is in the call show on stderr. 'follow' "
        "makes the robot follow the person in front of it (any key stops that too); 'help' "
        "lists every command. Driving by hand, on a terminal: Tab turns drive mode on; hold "
        "the arrow keys or WASD to drive (each key event drives for 0.6 s: the robot stops "
        "within about 0.9 s of letting go); Escape or Enter leaves drive mode (the robot "
        "stops, still armed); space or any other key stops the robot (it latches: 'arm' "
        "again) and leaves drive mode. Piped input has no drive mode.",
    )
    send = commands.add_parser(
        "send",
        help="send one chat command and print the replies until it completes",
        description="Send one chat command. Exit status: 0 success, 1 the robot reports "
        "failure, 2 usage or connection error (robot offline, not a contact, timed out).",
    )
    send.add_argument("robot", type=name_arg, help="the robot's name")
    send.add_argument(
        "--arm",
        action="store_true",
        help="re-arm the robot first, in the same call (needed to move it: the robot latches "
        "stopped whenever its driver's call ends)",
    )
    send.add_argument("words", nargs="+", metavar="COMMAND", help="the command, e.g. fwd 2")
    chat.add_argument("robot", type=name_arg, help="the robot's name")
    _add_record_option(chat)
    for parser_ in (chat, send):
        add_home_option(parser_, "user")
        add_connection_options(parser_)
        parser_.add_argument(
            "--timeout",
            type=_positive_float,
            default=300.0,
            help="seconds the command may take (piped chat: all commands, pauses in the input "
            "included; default 300)",
        )
        parser_.add_argument(
            "--map-dir",
            type=Path,
            default=Path("."),
            help="where 'getmap' saves ROBOT-map.png and its YAML (default: current folder)",
        )

    getmap = commands.add_parser(
        "getmap", help="download the robot's map as PNG plus a ROS map_server YAML"
    )
    getmap.add_argument("robot", type=name_arg, help="the robot's name")
    getmap.add_argument(
        "-o", "--output", type=Path, required=True, help="PNG file to write (YAML goes beside it)"
    )
    getmap.add_argument(
        "--timeout", type=_positive_float, default=60.0, help="seconds the transfer may take"
    )
    add_home_option(getmap, "user")
    add_connection_options(getmap)

    video = commands.add_parser(
        "video",
        help="receive the robot's video: show codec, fps, bit rate and loss; record it, share it in memory",
    )
    video.add_argument("robot", type=name_arg, help="the robot's name")
    video.add_argument(
        "--record", type=Path, metavar="FILE.mp4", help="record to this MP4 file (OpenCV mp4v)"
    )
    video.add_argument(
        "--shm",
        metavar="NAME",
        help="publish frames in the shared-memory ring NAME for local programs",
    )
    video.add_argument(
        "--duration",
        type=_positive_float,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C)",
    )
    add_home_option(video, "user")
    add_connection_options(video)

    talk = commands.add_parser(
        "talk",
        help="a voice call: send a microphone (and a test camera) to the robot, hear its mic",
    )
    talk.add_argument("robot", type=name_arg, help="the robot's name")
    talk.add_argument(
        "--mic",
        default="default",
        metavar="FILE|default",
        help="a WAV file (looped), 'default' (sound card: pip install 'telebot[audio]'), "
        "tone:HZ or none (default: default)",
    )
    talk.add_argument(
        "--speaker",
        default="default",
        metavar="FILE|default",
        help="where the robot's audio goes: a WAV file, 'default' or none (default: default)",
    )
    talk.add_argument("--camera", action="store_true", help="also send a test camera pattern")
    talk.add_argument(
        "--duration", type=_positive_float, metavar="S", help="hang up after S seconds"
    )
    add_home_option(talk, "user")
    add_connection_options(talk)

    video_log = commands.add_parser(
        "video-log", help="record the frames another telebot-user shares in memory (video --shm)"
    )
    video_log.add_argument("name", help="the shared-memory ring's name (as given to video --shm)")
    video_log.add_argument("-o", "--output", type=Path, required=True, help="MP4 file to write")
    video_log.add_argument(
        "--duration",
        type=_positive_float,
        metavar="S",
        help="stop after S seconds (default: until the ring closes or Ctrl-C)",
    )
    video_log.add_argument(
        "--fps", type=_positive_float, default=30.0, help="frame rate of the recording (default 30)"
    )
    video_log.add_argument(
        "--wait", type=_positive_float, default=10.0, help="seconds to wait for the ring to appear"
    )

    ui = commands.add_parser(
        "ui",
        help="serve a local web page to drive a robot (map, click-to-goal, stop, video, voice, "
        "chat), or without a robot name the fleet page",
        description="Call the robot and serve its web UI at http://HOST:PORT/ (open it in a "
        "browser). The page shows and plays the robot's camera and microphone and sends yours "
        "(the browser asks for them; mute, camera off and push to talk on the page; this "
        "process relays the encoded media, it never re-encodes). "
        "Any key on the page stops the robot; closing the page while it moves "
        "stops it too. The robot starts stopped: re-arm it on the page. If the call drops, the "
        "client calls the robot again by itself ([reconnect] in the config) and the page "
        "carries on; the robot stays stopped until re-armed. 'say TEXT' in the chat box speaks "
        "to everyone in the robot's calls. Without a robot name: the fleet page, every robot "
        "online with its battery, state, driver and link (each trusted robot is called to "
        "learn them; a robot that refuses says why); open robots to drive them side by side "
        "(each its own call and STOP, at /robot/NAME/); STOP ALL stops every robot you have "
        "a call with and says which did not answer.",
    )
    ui.add_argument(
        "robot",
        type=name_arg,
        nargs="?",
        default=None,
        help="the robot's name (none: the fleet page)",
    )
    _add_record_option(ui)
    ui.add_argument(
        "--port",
        type=_port,
        default=8080,
        help="TCP port of the page (default 8080; 0: any free port)",
    )
    ui.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to serve on (default 127.0.0.1: this machine only)",
    )
    add_home_option(ui, "user")
    add_connection_options(ui)

    fox = commands.add_parser(
        "foxglove",
        help="serve the robot to the Foxglove app (ws://HOST:PORT): map, pose, plan, video, goals",
        description="Call the robot and serve a Foxglove WebSocket server (open a connection "
        "to ws://HOST:PORT in the Foxglove app). Topics: /map (foxglove.Grid: the known part of "
        "the map, as getmap sends it), /pose "
        "(foxglove.PoseInFrame), /tf, /plan (foxglove.PosesInFrame), /camera "
        "(foxglove.CompressedImage), /telebot/* (JSON: telemetry, safety, goal, chat, "
        "commands, connection) and the robot topics given with --topic (ros2msg, cdr). A pose "
        "published on /goal_pose (the 3D panel's publish tool) is a goal: it goes through the "
        "robot's supervisor as a click on the web page does (drivers only; the robot must be "
        "armed). The services /telebot/arm, /telebot/stop, /telebot/take, /telebot/release and "
        "/telebot/cancel (the Service Call panel; request {}) are the web page's buttons. "
        "A geometry_msgs/Twist published on /cmd_vel (the Teleop panel; --teleop-topic) "
        "drives the robot by hand: linear.x and angular.z, while the panel publishes "
        "(set the panel's publish rate to 10 Hz, or to --teleop-rate).",
    )
    fox.add_argument("robot", type=_robot_after_topics, help="the robot's name")
    fox.add_argument(
        "--teleop-topic",
        type=_teleop_topic,
        default="/cmd_vel",
        metavar="TOPIC",
        help="the topic Foxglove's Teleop panel publishes Twist on (default /cmd_vel)",
    )
    fox.add_argument(
        "--teleop-rate",
        type=_teleop_rate,
        default=10.0,
        metavar="HZ",
        help="the Teleop panel's publish rate, 2 to 50 (default 10; set the panel to the "
        "same): each message drives for 1.5 periods, so letting go stops the robot within "
        "1.5 periods plus the robot's [drive] stale_after (0.15 + 0.3 s at 10 Hz)",
    )
    fox.add_argument(
        "--port", type=_port, default=8765, help="TCP port to serve on (default 8765; 0: any)"
    )
    fox.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to serve on (default 127.0.0.1: this machine only)",
    )
    _add_topics_option(fox)
    _add_record_option(fox)
    add_home_option(fox, "user")
    add_connection_options(fox)

    record = commands.add_parser(
        "record",
        help="record the robot's streams to an MCAP file (readable by Foxglove and mcap)",
        description="Call the robot and write what reaches you to an MCAP file: map, pose, "
        "plan, video, telemetry, safety events, goals, chat and the commands you give (the "
        "same channels as 'telebot-user foxglove'). A progress line shows on stderr; Ctrl-C "
        "or --duration ends the recording and finishes the file.",
    )
    record.add_argument("robot", type=_robot_after_topics, help="the robot's name")
    record.add_argument(
        "-o", "--output", type=Path, required=True, metavar="FILE.mcap", help="MCAP file to write"
    )
    record.add_argument(
        "--duration",
        type=_positive_float,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C or the call ends)",
    )
    _add_topics_option(record)
    add_home_option(record, "user")
    add_connection_options(record)

    where = commands.add_parser("where", help="print the robot's pose in the map frame")
    where.add_argument("robot", type=name_arg, help="the robot's name")
    where.add_argument(
        "--timeout", type=_positive_float, default=5.0, help="seconds to wait for a pose"
    )
    add_home_option(where, "user")
    add_connection_options(where)
    return parser


def _add_record_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="also record the call to this MCAP file (as 'telebot-user record' does)",
    )


def _robot_after_topics(text: str) -> str:
    """argparse type of the robot of ``foxglove`` and ``record``: a name, and a topic there
    (``--topics /scan /odom ROBOT``, the old list form) said to be one."""
    if text.startswith("/"):
        raise argparse.ArgumentTypeError(
            f"{text[:80]!r} is a topic, not a robot name: give one topic per --topic "
            "(--topic /scan --topic /odom ROBOT)"
        )
    return name_arg(text)


def _topic_list(text: str) -> list[str]:
    """argparse type of ``--topic``: one topic, or several separated by commas."""
    topics = [topic.strip() for topic in text.split(",")]
    if not all(topics):
        raise argparse.ArgumentTypeError(f"an empty topic name in {text[:80]!r}")
    return topics


def _add_topics_option(parser: argparse.ArgumentParser) -> None:
    # One value per flag (repeatable): a list flag would swallow the robot's name after it.
    parser.add_argument(
        "--topic",
        "--topics",
        dest="topics",
        action="extend",
        type=_topic_list,
        default=[],
        metavar="TOPIC",
        help="a robot topic to relay as well (e.g. /scan; needs the robot's relay service); "
        "repeat for more (--topic /scan --topic /odom) or separate them with commas",
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point of telebot-user."""
    args = build_parser().parse_args(argv)
    home = home_of(args, "user")

    async def command() -> int:
        if args.command == "keygen":
            return keygen(args.name, home, overwrite=args.force, kind="user")
        if args.command == "pubkey":
            print(Identity.load(home).public_line())
            return EXIT_OK
        if args.command == "known":
            return _known(args, home)
        if args.command == "robots":
            return await _robots(args, home)
        if args.command == "ping":
            return await _ping(args, home)
        if args.command == "video":
            from telebot.apps.video_cli import video

            return await video(
                args.robot,
                home=home,
                config=app_config(args),
                record=args.record,
                shm=args.shm,
                duration=args.duration,
            )
        if args.command == "talk":
            from telebot.apps.talk_cli import talk

            return await talk(
                args.robot,
                home=home,
                config=app_config(args),
                mic=args.mic,
                speaker=args.speaker,
                camera=args.camera,
                duration=args.duration,
            )
        if args.command == "ui":
            from telebot.apps.foxglove_cli import check_output_file
            from telebot.apps.web.server import serve_ui

            if args.record is not None and (problem := check_output_file(args.record)):
                print(f"{PROG}: error: {problem}", file=sys.stderr)
                return EXIT_USAGE
            if args.robot is None and args.record is not None:
                print(f"{PROG}: error: --record needs a robot name", file=sys.stderr)
                return EXIT_USAGE
            try:
                if args.robot is None:
                    from telebot.apps.web.fleet import serve_fleet

                    return await serve_fleet(
                        home=home, config=app_config(args), host=args.host, port=args.port
                    )
                return await serve_ui(
                    args.robot,
                    home=home,
                    config=app_config(args),
                    host=args.host,
                    port=args.port,
                    record=args.record,
                )
            except OSError as exc:
                print(
                    f"{PROG}: error: cannot serve on {args.host}:{args.port}: {exc.strerror or exc}",
                    file=sys.stderr,
                )
                return EXIT_USAGE
        if args.command == "foxglove":
            from telebot.apps.foxglove_cli import serve_foxglove

            return await serve_foxglove(
                args.robot,
                home=home,
                config=app_config(args),
                host=args.host,
                port=args.port,
                topics=args.topics,
                record=args.record,
                teleop_topic=args.teleop_topic,
                teleop_rate=args.teleop_rate,
            )
        if args.command == "record":
            from telebot.apps.foxglove_cli import record_session

            return await record_session(
                args.robot,
                args.output,
                home=home,
                config=app_config(args),
                duration=args.duration,
                topics=args.topics,
            )
        if args.command == "video-log":
            from telebot.apps.video_cli import video_log

            return video_log(
                args.name, args.output, duration=args.duration, fps=args.fps, wait=args.wait
            )
        return await _talk(args, home)

    return run(PROG, command, args.log_level)


async def _talk(args: argparse.Namespace, home: Path) -> int:
    from telebot.apps import user_client

    config = app_config(args)
    if args.command == "send":
        return await user_client.send_command(
            args.robot,
            " ".join(args.words),
            home=home,
            config=config,
            timeout=args.timeout,
            map_dir=args.map_dir,
            arm=args.arm,
        )
    if args.command == "chat":
        from telebot.apps.foxglove_cli import check_output_file

        if args.record is not None and (problem := check_output_file(args.record)):
            print(f"{PROG}: error: {problem}", file=sys.stderr)
            return EXIT_USAGE
        return await user_client.chat_session(
            args.robot,
            home=home,
            config=config,
            timeout=args.timeout,
            map_dir=args.map_dir,
            record=args.record,
        )
    if args.command == "getmap":
        return await user_client.get_map(
            args.robot, args.output, home=home, config=config, timeout=args.timeout
        )
    return await user_client.where(args.robot, home=home, config=config, timeout=args.timeout)


def _known(args: argparse.Namespace, home: Path) -> int:
    known = KnownRobots.load(home)
    if args.action == "list":
        for name in known.names():
            key = known.get(name) or b""
            print(f"{name}\t{encode_key(key)}\t{fingerprint(key)}")
        return EXIT_OK
    if args.action == "add":
        try:
            known.add(args.name, parse_public_key(args.public_key))
        except ValueError as exc:
            print(f"{PROG}: error: bad robot name or key for {args.name}: {exc}", file=sys.stderr)
            return EXIT_USAGE
        known.save()
        print(f"{args.name} is now a known robot")
        return EXIT_OK
    if not known.remove(args.name):
        print(f"{PROG}: error: no known robot named {args.name!r}", file=sys.stderr)
        return EXIT_USAGE
    known.save()
    print(f"{args.name} forgotten")
    return EXIT_OK


async def _robots(args: argparse.Namespace, home: Path) -> int:
    from telebot.channels.call import UserEndpoint
    from telebot.channels.transports import create_transport

    config = app_config(args)
    identity = Identity.load(home)
    known = KnownRobots.load(home)
    async with (
        create_transport(config.transport) as transport,
        UserEndpoint(
            transport, identity, known, settings=config.call, namespace=config.namespace
        ) as user,
    ):
        online = await user.robots_online(wait=args.wait)
    for robot in online:
        trust = (
            "known" if robot.trusted else ("KEY MISMATCH" if known.get(robot.name) else "unknown")
        )
        print(f"{robot.name}\t{trust}\t{encode_key(robot.public_key)}")
    if not online:
        print("no robots online", file=sys.stderr)
    return EXIT_OK


async def _ping(args: argparse.Namespace, home: Path) -> int:
    from telebot.apps.ping import ping
    from telebot.channels.call import UserEndpoint
    from telebot.channels.transports import create_transport

    if not 12 <= args.size <= 32768:
        print(f"{PROG}: error: --size must be between 12 and 32768 bytes", file=sys.stderr)
        return EXIT_USAGE
    config = app_config(args)
    identity = Identity.load(home)
    known = KnownRobots.load(home)
    async with (
        create_transport(config.transport) as transport,
        UserEndpoint(
            transport, identity, known, settings=config.call, namespace=config.namespace
        ) as user,
    ):
        call = await user.call(args.robot, timeout=args.timeout)
        print(f"call {call.id} with {call.peer} answered (role {call.role})")
        result = await ping(call, count=args.count, size=args.size, interval=args.interval)
        await call.hangup("ping done")
    print(result.summary())
    return EXIT_OK if result.received else EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
