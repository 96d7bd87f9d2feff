"""``telebot-robot``: the robot's command line.

``telebot-robot run`` is the robot daemon (the robot adapter ``--robot`` or ``[robot] kind``
names, ``sim`` by default, ``ros2`` for a ROS 2 / Nav2 robot; chat, map, pose, goals, telemetry); it serves the browser gateway too when the config has ``[gateway]``. The other
commands manage the robot's key and contact list, write one-time invites for browsers
(``invite``), generate the default map, and run the echo robot, a network check.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from telebot.apps.common import (
    EXIT_OK,
    EXIT_USAGE,
    Parser,
    add_connection_options,
    add_home_option,
    add_log_level_option,
    home_of,
    keygen,
    load_app_config,
    name_arg,
    new_parser,
    run,
)
from telebot.config import RobotConfig
from telebot.errors import RobotError, excerpt
from telebot.identity import ContactBook, Identity, Role, encode_key, fingerprint, parse_public_key

PROG = "telebot-robot"


def build_parser() -> Parser:
    """The argument parser of telebot-robot."""
    parser = new_parser(PROG, "The telebot robot: answers calls from its contacts.")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    commands.required = True

    keygen = commands.add_parser("keygen", help="create this robot's key pair")
    keygen.add_argument(
        "name", type=name_arg, help="the robot's name, which users call (e.g. guiabot)"
    )
    keygen.add_argument("--force", action="store_true", help="replace an existing key")
    add_home_option(keygen, "robot")

    pubkey = commands.add_parser("pubkey", help="print this robot's public key line")
    add_home_option(pubkey, "robot")

    contacts = commands.add_parser("contacts", help="list or edit the users this robot answers")
    actions = contacts.add_subparsers(dest="action", metavar="ACTION", parser_class=Parser)
    actions.required = True
    listing = actions.add_parser("list", help="list contacts")
    add = actions.add_parser("add", help="add or replace a contact")
    add.add_argument("name", type=name_arg, help="the user's name")
    add.add_argument("public_key", help="the user's public key (or their whole .pub line)")
    add.add_argument("--role", choices=[r.value for r in Role], default=Role.OBSERVER.value)
    remove = actions.add_parser("remove", help="remove a contact")
    remove.add_argument("name", type=name_arg)
    for action in (listing, add, remove):
        add_home_option(action, "robot")

    invite = commands.add_parser(
        "invite",
        help="print a one-time link (and QR code) that lets a browser become a contact",
        description="Write a one-time invite for contact NAME with ROLE, valid 10 minutes, "
        "where the running daemon's browser gateway ([gateway] in its config) reads it, and "
        "print the link and its QR code. The browser that opens the link registers its own "
        "key as NAME (the link carries the robot's key, which the browser pins); the invite "
        "then is used up. 'contacts list/remove' show and remove the contact like any other. "
        "A NAME that is a contact already is refused unless --replace is given.",
    )
    invite.add_argument("name", type=name_arg, help="the contact's name (e.g. nurse1)")
    invite.add_argument(
        "--role",
        choices=[r.value for r in Role],
        default=Role.OBSERVER.value,
        help="what the contact may do (default: observer)",
    )
    invite.add_argument(
        "--url",
        default=None,
        metavar="URL",
        help="the robot gateway's address as the browser reaches it (default "
        "https://HOSTNAME:8443/)",
    )
    invite.add_argument(
        "--replace",
        action="store_true",
        help="let the browser replace the key and role of contact NAME if there is one",
    )
    invite.add_argument("--no-qr", action="store_true", help="print the link only")
    add_home_option(invite, "robot")

    daemon = commands.add_parser(
        "run",
        help="run the robot daemon: answer calls and serve chat, map, pose, goals, telemetry",
        description="Run the robot: start the robot adapter (the simulated robot on its map by "
        "default), answer calls from the contacts and serve them; with [gateway] in the "
        "config, also serve the web app and the browser gateway over HTTPS. Stops the robot, "
        "hangs up and exits on SIGINT/SIGTERM.",
    )
    add_home_option(daemon, "robot")
    add_connection_options(daemon)
    add_log_level_option(daemon)
    daemon.add_argument(
        "--robot",
        default=None,
        metavar="NAME",
        help="robot adapter to drive: 'sim' (the simulated robot, default), 'ros2' (a ROS 2 / "
        "Nav2 robot over rmw_zenoh, set up in [ros2] of the config) or an installed plug-in's "
        "name (entry-point group telebot.robots); overrides robot.kind of the config",
    )
    daemon.add_argument(
        "--map",
        default=None,
        metavar="MAP",
        help="map to drive on: 'building' (default), 'small' or a ROS map_server YAML file "
        "(overrides sim.map of the config)",
    )
    daemon.add_argument(
        "--events",
        action="store_true",
        help="print robot events as JSON lines on stdout: ready, call, chat, goal, safety, say, "
        "ended, stopping (each kind and its fields: docs/events.md)",
    )
    daemon.add_argument(
        "--screen",
        default=None,
        metavar="HOST:PORT|off",
        help="serve the robot's own screen (the remote user's video, name, call state and "
        "voice, for a browser on the robot's display) at http://HOST:PORT/ (default "
        "127.0.0.1:8090, [screen] of the config); 'off' serves none",
    )

    make_map = commands.add_parser(
        "make-map",
        help="generate a built-in map (ROS map_server YAML + PGM + places) into a folder",
    )
    make_map.add_argument("--name", choices=["building", "small"], default="building")
    make_map.add_argument("--out", type=Path, required=True, help="folder to write the map into")

    echo = commands.add_parser(
        "echo",
        help="answer calls and echo every datagram back (network check for 'telebot-user ping')",
    )
    add_home_option(echo, "robot")
    add_connection_options(echo)
    echo.add_argument(
        "--events",
        action="store_true",
        help="print call events as JSON lines on stdout: ready, call, ended, stopping "
        "(docs/events.md)",
    )
    return parser


def _print_event(event: dict[str, Any]) -> None:
    print(json.dumps(event), flush=True)


def main(argv: list[str] | None = None) -> int:
    """Entry point of telebot-robot."""
    args = build_parser().parse_args(argv)
    home = home_of(args, "robot")

    async def command() -> int:
        if args.command == "keygen":
            return keygen(args.name, home, overwrite=args.force, kind="robot")
        if args.command == "pubkey":
            print(Identity.load(home).public_line())
            return EXIT_OK
        if args.command == "contacts":
            return _contacts(args, home)
        if args.command == "invite":
            return _invite(args, home)
        if args.command == "make-map":
            from telebot.robot.sim.building import main as make_map

            return make_map(["--name", args.name, "--out", str(args.out)])
        if args.command == "run":
            return await _run_daemon(args, home)
        # echo
        from telebot.apps.echo import serve_echo

        identity = Identity.load(home)
        contacts = ContactBook.load(home)
        if not len(contacts):
            print(
                f"{PROG}: warning: no contacts in {home}; every call will be refused",
                file=sys.stderr,
            )
        emit = _print_event if args.events else (lambda event: None)
        await serve_echo(load_app_config(args, RobotConfig), identity, contacts, emit)
        return EXIT_OK

    return run(PROG, command, args.log_level)


async def _run_daemon(args: argparse.Namespace, home: Path) -> int:
    from telebot.apps.robot_daemon import serve_robot
    from telebot.robot import get_robot_class

    config = load_app_config(args, RobotConfig)
    base_dir = args.config.parent if args.config else None
    if args.robot is not None:
        config.robot.kind = args.robot
    try:
        get_robot_class(config.robot.kind)  # a bad name is a usage error, before anything starts
    except RobotError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.map is not None:
        config.sim.map = args.map
        base_dir = None  # a --map path is relative to where the command runs
    if args.screen is not None:
        from telebot.apps.web.screen import parse_screen_option

        try:
            config.screen = parse_screen_option(args.screen, config.screen)
        except ValueError as exc:
            print(f"{PROG}: error: --screen: {exc}", file=sys.stderr)
            return EXIT_USAGE
    identity = Identity.load(home)
    contacts = ContactBook.load(home)
    if not len(contacts):
        print(
            f"{PROG}: warning: no contacts in {home}; every call will be refused", file=sys.stderr
        )
    await serve_robot(
        config,
        identity,
        contacts,
        base_dir=base_dir,
        home=home,
        emit=_print_event if args.events else None,
    )
    return EXIT_OK


def _invite(args: argparse.Namespace, home: Path) -> int:
    import socket
    import time
    from urllib.parse import urlsplit

    from telebot.gateway.admission import contact_key, create_invite

    identity = Identity.load(home)
    url = args.url or f"https://{socket.gethostname()}:8443/"
    parts = urlsplit(url)
    if parts.scheme != "https" or not parts.netloc or parts.fragment or parts.query:
        print(
            f"{PROG}: error: --url {excerpt(url)}: expected https://HOST[:PORT]/ "
            "(browsers need HTTPS for the camera and the call)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    if not args.replace and contact_key(ContactBook.load(home), args.name) is not None:
        print(
            f"{PROG}: error: {args.name} is a contact already; --replace lets the invite "
            "replace its key and role",
            file=sys.stderr,
        )
        return EXIT_USAGE
    token, invite = create_invite(
        home, args.name, Role(args.role), time.time(), replace=args.replace
    )
    base = url if url.endswith("/") else url + "/"
    link = f"{base}#invite={token}&robot={identity.name}&key={encode_key(identity.public_key)}"
    minutes = round((invite.expires - time.time()) / 60)
    print(f"invite for {args.name} as {args.role}, valid {minutes} minutes, once:")
    print(link)
    if not args.no_qr:
        import segno

        segno.make(link, error="l").terminal(compact=True)
    return EXIT_OK


def _contacts(args: argparse.Namespace, home: Path) -> int:
    if args.action == "list":
        for contact in ContactBook.load(home):
            print(
                f"{contact.name}\t{contact.role.value}\t{encode_key(contact.public_key)}\t{fingerprint(contact.public_key)}"
            )
        return EXIT_OK
    from telebot.gateway.admission import locked

    # The lock a browser gateway's invite redemption holds: neither loses the other's change.
    with locked(home):
        return _edit_contacts(args, ContactBook.load(home))


def _edit_contacts(args: argparse.Namespace, book: ContactBook) -> int:
    if args.action == "add":
        try:
            key = parse_public_key(args.public_key)
        except ValueError as exc:
            print(f"{PROG}: error: bad public key for {args.name}: {exc}", file=sys.stderr)
            return EXIT_USAGE
        try:
            book.add(args.name, key, Role(args.role))
        except ValueError as exc:
            print(f"{PROG}: error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        book.save()
        print(f"{args.name} added as {args.role}")
        return EXIT_OK
    if not book.remove(args.name):
        print(f"{PROG}: error: no contact named {args.name!r}", file=sys.stderr)
        return EXIT_USAGE
    book.save()
    print(f"{args.name} removed")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
