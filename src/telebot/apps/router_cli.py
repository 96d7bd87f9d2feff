"""``telebot-router``: a zenoh router with TLS, client certificates and access control.

``init`` makes a router directory (a CA and the router's certificate), ``cert`` issues a
client certificate for a robot, a user or an admin (or imports one signed elsewhere by the
same CA), ``revoke`` takes a name out of the access-control list, ``gateway-user`` lists the users
the browser gateway admits, ``config`` prints the zenoh config (``zenohd -c`` runs the
same router), and ``run`` runs the router in this process (zenoh-python, router mode),
with the browser gateway over HTTPS beside it (docs/protocol.md §26), until SIGINT or
SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from telebot.apps.common import (
    EXIT_OK,
    EXIT_USAGE,
    Parser,
    name_arg,
    new_parser,
    run,
    stop_on_signals,
)
from telebot.errors import ConfigError, TransportError
from telebot.router import certs
from telebot.router.acl import DEFAULT_PORT, Member, RouterPlan, router_config

PROG = "telebot-router"
DEFAULT_LISTEN = f"tls/0.0.0.0:{DEFAULT_PORT}"
#: QUIC beside TLS on the same port number (UDP): the link to use across the internet
#: (README "Networks"; bench/wan.py measures why).
DEFAULT_QUIC = f"quic/0.0.0.0:{DEFAULT_PORT}"
DEFAULT_GATEWAY = "0.0.0.0:8443"


def _add_who(parser: argparse.ArgumentParser) -> None:
    who = parser.add_mutually_exclusive_group(required=True)
    for kind in certs.KINDS:
        who.add_argument(
            f"--{kind}", type=name_arg, metavar="NAME", help=f"a certificate for {kind} NAME"
        )


def _who(args: argparse.Namespace) -> tuple[certs.Kind, str]:
    for kind in certs.KINDS:
        name = getattr(args, kind)
        if name is not None:
            return kind, name
    raise AssertionError("argparse requires one of --robot, --user, --admin")


def _add_router_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", type=Path, help="the router directory made by 'init'")
    parser.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"TLS endpoint to listen on (repeatable; default {DEFAULT_LISTEN} and "
        f"{DEFAULT_QUIC} when neither --listen nor --quic is given)",
    )
    parser.add_argument(
        "--quic",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="also listen on this QUIC endpoint (UDP; the same certificates and access "
        "control as TLS), e.g. quic/0.0.0.0:7447: the link to use across the internet, "
        "stops and heartbeats as QUIC datagrams (mixed_rel=auto is added unless the "
        "endpoint sets mixed_rel; README 'Networks'; repeatable)",
    )
    parser.add_argument(
        "--tcp",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="also listen on this plain TCP endpoint, e.g. tcp/127.0.0.1:7448 (no "
        "certificate, so the ACL lets it do nothing unless --no-acl; off by default)",
    )
    parser.add_argument(
        "--peer-router",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="link to another telebot router at this TLS endpoint, e.g. "
        "tls/cloud.example.com:7447 (repeatable): clients of either reach clients of the "
        "other; it must share this router's CA (init --ca --ca-key; docs/protocol.md §22.5)",
    )
    parser.add_argument(
        "--namespace", default="telebot", help="the telebot namespace (default: telebot)"
    )
    parser.add_argument(
        "--no-acl",
        action="store_true",
        help="no access control: any client with a certificate from the CA may do anything",
    )


def build_parser() -> Parser:
    """The argument parser of telebot-router."""
    parser = new_parser(
        PROG,
        "A zenoh router for telebot across networks: TLS with client certificates from its "
        "own CA, and an access-control list that keeps each robot and user to its own keys.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    commands.required = True

    init = commands.add_parser(
        "init", help="make a router directory: a CA and the router's certificate"
    )
    init.add_argument("dir", type=Path, help="the directory to create")
    init.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="HOST",
        help="an address or DNS name clients use to reach the router (repeatable; "
        "127.0.0.1, ::1 and localhost are always in)",
    )
    init.add_argument("--ca", type=Path, default=None, help="use this existing CA certificate")
    init.add_argument("--ca-key", type=Path, default=None, help="...and its private key (PEM)")
    init.add_argument("--force", action="store_true", help="replace an existing CA")

    cert = commands.add_parser(
        "cert", help="issue a client certificate (prints the client's [transport.zenoh] settings)"
    )
    cert.add_argument("dir", type=Path, help="the router directory")
    _add_who(cert)
    cert.add_argument(
        "--import",
        dest="import_cert",
        type=Path,
        default=None,
        metavar="CERT",
        help="register an existing certificate signed by this CA (its common name must be "
        "KIND:NAME) instead of issuing one",
    )
    cert.add_argument(
        "--router",
        default=f"quic/127.0.0.1:{DEFAULT_PORT}",
        metavar="ENDPOINT",
        help="the router endpoint to print in the client settings (default "
        f"quic/127.0.0.1:{DEFAULT_PORT}, the link to use across the internet; a tls/ "
        "endpoint where UDP is blocked)",
    )
    cert.add_argument("--force", action="store_true", help="replace an existing certificate")

    revoke = commands.add_parser(
        "revoke",
        help="take a name out of the ACL (takes effect when the router restarts; the browser "
        "gateway refuses a revoked user at once and cuts its open connections within 5 s)",
    )
    revoke.add_argument("dir", type=Path, help="the router directory")
    _add_who(revoke)

    listing = commands.add_parser("list", help="list the client certificates and revocations")
    listing.add_argument("dir", type=Path, help="the router directory")

    config = commands.add_parser(
        "config", help="print the router's zenoh config (JSON5; 'zenohd -c FILE' runs it)"
    )
    _add_router_options(config)

    users = commands.add_parser(
        "gateway-user",
        help="list or edit the users the router's browser gateway admits",
        description="The browser gateway ('run' serves it at https://HOST:8443/ once this "
        "list has a user) admits a browser that proves it holds the key listed for its name "
        "(and is not revoked). Changes take effect at the next admission, without a restart; "
        "an open connection whose user was removed is cut within 5 s.",
    )
    actions = users.add_subparsers(dest="action", metavar="ACTION", parser_class=Parser)
    actions.required = True
    add = actions.add_parser("add", help="add or replace a gateway user")
    add.add_argument("dir", type=Path, help="the router directory")
    add.add_argument("name", type=name_arg, help="the user's name")
    add.add_argument("public_key", help="the user's public key (43 characters, or its .pub line)")
    listing_users = actions.add_parser("list", help="list the gateway users")
    listing_users.add_argument("dir", type=Path, help="the router directory")
    remove = actions.add_parser("remove", help="remove a gateway user")
    remove.add_argument("dir", type=Path, help="the router directory")
    remove.add_argument("name", type=name_arg, help="the user's name")

    runp = commands.add_parser("run", help="run the router until SIGINT/SIGTERM")
    _add_router_options(runp)
    runp.add_argument(
        "--gateway",
        default=None,
        metavar="HOST:PORT|off",
        help="serve the browser gateway and the web app over HTTPS with the router's "
        f"certificate at https://HOST:PORT/ (default {DEFAULT_GATEWAY} once "
        "'gateway-user add' has listed a user; 'off': never)",
    )
    runp.add_argument(
        "--gateway-cert",
        type=Path,
        default=None,
        metavar="PEM",
        help="serve the gateway with this certificate (chain) instead of the router's, e.g. "
        "a publicly trusted one for the router's DNS name; with --gateway-key",
    )
    runp.add_argument(
        "--gateway-key", type=Path, default=None, metavar="PEM", help="its private key"
    )
    runp.add_argument(
        "--events",
        action="store_true",
        help="print a JSON 'ready' line on stdout when listening (docs/events.md)",
    )
    return parser


def plan_of(args: argparse.Namespace) -> RouterPlan:
    """The router plan of ``config``/``run``: its files, endpoints and allowed members."""
    root: Path = args.dir
    for name in ("ca.pem", "router.pem", "router.key"):
        if not (root / name).is_file():
            raise ConfigError(f"{root / name}: no such file (run '{PROG} init {root}' first)")
    revoked = certs.read_revoked(root)
    members = tuple(
        Member(c.kind, c.name) for c in certs.list_clients(root) if c.common_name not in revoked
    )
    for endpoint in args.listen:
        if not endpoint.startswith("tls/"):
            raise ConfigError(
                f"--listen {endpoint}: not a tls/ endpoint (QUIC: --quic; plain TCP: --tcp)"
            )
    for endpoint in args.quic:
        if not endpoint.startswith("quic/"):
            raise ConfigError(f"--quic {endpoint}: not a quic/ endpoint")
    defaults = not args.listen and not args.quic
    for endpoint in args.tcp:
        if not endpoint.startswith("tcp/"):
            raise ConfigError(f"--tcp {endpoint}: not a tcp/ endpoint")
    try:
        return RouterPlan(
            ca=str((root / "ca.pem").resolve()),
            cert=str((root / "router.pem").resolve()),
            key=str((root / "router.key").resolve()),
            members=members,
            namespace=args.namespace,
            listen_tls=(DEFAULT_LISTEN,) if defaults else tuple(args.listen),
            listen_quic=(DEFAULT_QUIC,) if defaults else tuple(args.quic),
            listen_tcp=tuple(args.tcp),
            acl=not args.no_acl,
            peers=tuple(args.peer_router),
        )
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc


def _client_settings(client: certs.ClientCert, router: str, key: str | None = None) -> str:
    scheme, sep, address = router.partition("/")
    fallback = (
        [f"# where UDP is blocked: connect = [{json.dumps(f'tls/{address}')}]"]
        if scheme == "quic" and sep
        else []
    )
    return "\n".join(
        [
            "[transport.zenoh]",
            'mode = "client"',
            f"connect = [{json.dumps(router)}]",
            *fallback,
            "multicast_scouting = false",
            "[transport.zenoh.tls]",
            f"ca = {json.dumps(str(client.ca.resolve()))}",
            f"cert = {json.dumps(str(client.cert.resolve()))}",
            f"key = {json.dumps(key or str(client.key.resolve()))}",
        ]
    )


def _cmd_init(args: argparse.Namespace) -> int:
    if (args.ca is None) != (args.ca_key is None):
        raise ConfigError("--ca and --ca-key go together")
    certs.init_ca(args.dir, args.host, force=args.force, ca=args.ca, ca_key=args.ca_key)
    print(f"CA and router certificate written to {args.dir}")
    print(f"next: {PROG} cert {args.dir} --robot NAME, then {PROG} run {args.dir}")
    return EXIT_OK


def _cmd_cert(args: argparse.Namespace) -> int:
    kind, name = _who(args)
    if args.import_cert is not None:
        client = certs.import_client(args.dir, kind, name, args.import_cert, force=args.force)
        print(f"{client.common_name}: registered {client.cert}; its key stays with its owner")
        key = "PATH/TO/ITS/KEY.pem"
    else:
        client = certs.issue_client(args.dir, kind, name, force=args.force)
        print(f"{client.common_name}: certificate in {client.directory}")
        key = None
    print(f"# the {kind}'s config (TOML):")
    print(_client_settings(client, args.router, key))
    return EXIT_OK


def _cmd_revoke(args: argparse.Namespace) -> int:
    kind, name = _who(args)
    cn = certs.revoke(args.dir, kind, name)
    print(f"{cn} revoked: the router's ACL lets it do nothing once the router restarts")
    if kind == "user":
        print(f"the browser gateway refuses {name} now (an open connection within 5 s)")
    return EXIT_OK


def _cmd_list(args: argparse.Namespace) -> int:
    revoked = certs.read_revoked(args.dir)
    for client in certs.list_clients(args.dir):
        state = "revoked" if client.common_name in revoked else "allowed"
        print(f"{client.common_name}\t{state}\t{client.directory}")
    return EXIT_OK


def _cmd_config(args: argparse.Namespace) -> int:
    print(json.dumps(router_config(plan_of(args)), indent=2))
    return EXIT_OK


def _cmd_gateway_user(args: argparse.Namespace) -> int:
    from telebot.gateway.admission import GatewayUsers
    from telebot.identity import encode_key, fingerprint, parse_public_key

    users = GatewayUsers.load(args.dir)
    if args.action == "list":
        for name, key in sorted(users.users.items()):
            print(f"{name}\t{encode_key(key)}\t{fingerprint(key)}")
        return EXIT_OK
    if args.action == "add":
        if not (args.dir / "ca.pem").is_file():
            raise ConfigError(f"{args.dir}: not a router directory (run '{PROG} init' first)")
        try:
            key = parse_public_key(args.public_key)
        except ValueError as exc:
            raise ConfigError(f"bad public key for {args.name}: {exc}") from exc
        users.users[args.name] = key
        users.save()
        print(f"{args.name} may use the browser gateway")
        return EXIT_OK
    if users.users.pop(args.name, None) is None:
        raise ConfigError(f"no gateway user named {args.name!r}")
    users.save()
    print(f"{args.name} removed from the gateway users")
    return EXIT_OK


def gateway_address(option: str | None, directory: Path) -> tuple[str, int] | None:
    """Where ``run`` serves the browser gateway: ``--gateway``, else the default once the
    router directory lists a gateway user; None for none. ConfigError on a bad option."""
    from telebot.gateway.admission import GatewayUsers

    if option is None:
        if not GatewayUsers.load(directory).users:
            return None
        option = DEFAULT_GATEWAY
    if option == "off":
        return None
    host, sep, port = option.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--gateway {option}: expected HOST:PORT (e.g. {DEFAULT_GATEWAY}) or off")
    return host, int(port)


async def _run_router(
    plan: RouterPlan,
    events: bool,
    gateway: tuple[str, int] | None = None,
    tls: tuple[Path, Path] | None = None,
) -> int:
    import zenoh  # only 'run' needs zenoh

    from telebot.channels.transports.zenoh import reason_of

    config_text = json.dumps(router_config(plan))
    try:
        config = zenoh.Config.from_json5(config_text)
        session = await asyncio.to_thread(zenoh.open, config)
    except zenoh.ZError as exc:
        raise TransportError(f"cannot start the router: {reason_of(exc)}") from exc
    stop = asyncio.Event()
    try:
        async with _router_gateway(session, plan, gateway, tls) as gateway_url:
            with stop_on_signals(stop):
                ready: dict[str, Any] = {
                    "event": "ready",
                    "zid": str(session.zid()),
                    "listen": [*plan.listen_tls, *plan.listen_quic, *plan.listen_tcp],
                    "members": [m.common_name for m in plan.members],
                    "acl": plan.acl,
                    "peers": list(plan.peers),
                }
                if events:
                    print(json.dumps(ready), flush=True)
                else:
                    print(
                        f"{PROG}: listening on {', '.join(ready['listen'])}; "
                        f"{len(plan.members)} certificate(s) allowed",
                        flush=True,
                    )
                    for peer in plan.peers:
                        print(f"{PROG}: linking to the router at {peer}", flush=True)
                    if gateway_url:
                        print(f"{PROG}: browser gateway at {gateway_url}", flush=True)
                await stop.wait()
    finally:
        await asyncio.to_thread(session.close)
    return EXIT_OK


@contextlib.asynccontextmanager
async def _router_gateway(
    session: Any,
    plan: RouterPlan,
    address: tuple[str, int] | None,
    tls: tuple[Path, Path] | None = None,
) -> AsyncIterator[str | None]:
    """The browser gateway over the router's own session, with the router's certificate
    (or ``tls``: another certificate and key), on a thread of its own (its own loop and
    transport, as on the robot: :class:`~telebot.gateway.thread.GatewayThread`)."""
    if address is None:
        yield None
        return
    from telebot.channels.transports.base import Transport
    from telebot.gateway.admission import UsersAdmitter
    from telebot.gateway.server import Gateway
    from telebot.gateway.thread import GatewayThread
    from telebot.gateway.tls import server_context

    cert, key = tls if tls is not None else (Path(plan.cert), Path(plan.key))
    context = server_context(cert, key)

    def make(transport: Transport) -> Gateway:
        return Gateway(
            transport,
            UsersAdmitter(Path(plan.cert).parent),
            namespace=plan.namespace,
            host=address[0],
            port=address[1],
            ssl_context=context,
        )

    thread = GatewayThread(session, make)
    try:
        gateway = await thread.start()
    except OSError as exc:
        raise ConfigError(f"--gateway {address[0]}:{address[1]}: cannot listen: {exc}") from exc
    try:
        yield gateway.url
    finally:
        await thread.stop()


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``telebot-router``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handlers = {
        "init": _cmd_init,
        "cert": _cmd_cert,
        "revoke": _cmd_revoke,
        "list": _cmd_list,
        "config": _cmd_config,
        "gateway-user": _cmd_gateway_user,
    }
    if args.command == "run":
        try:
            plan, gateway = plan_of(args), gateway_address(args.gateway, args.dir)
            if (args.gateway_cert is None) != (args.gateway_key is None):
                raise ConfigError("--gateway-cert and --gateway-key go together")
            tls = (args.gateway_cert, args.gateway_key) if args.gateway_cert else None
        except ConfigError as exc:
            print(f"{PROG}: error: {exc}", file=sys.stderr)
            return EXIT_USAGE

        async def main_run() -> int:
            return await _run_router(plan, args.events, gateway, tls)

        return run(PROG, main_run, args.log_level)
    try:
        return handlers[args.command](args)
    except (ConfigError, ValueError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
