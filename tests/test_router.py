"""telebot-router: robots and users as zenoh clients of a TLS router with access control.

One router per module (``telebot-router run`` in its own process, mutual TLS on a free
loopback port, the ACL made from the certificates issued), three robot daemons; the user
and a second user in this process; an admin certificate gives a raw zenoh session that sees everything
the router forwards. The router-restart test runs last: it kills the shared router.
"""

from __future__ import annotations

import asyncio
import datetime
import json
import subprocess
import sys
import tomllib
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import NameOID

from conftest import wait_until
from rig import REAL_TIMEOUT, SLACK, Process
from router_rig import RouterRig
from telebot.apps import router_cli
from telebot.channels.transports.zenoh import ZenohTransport, build_zenoh_config
from telebot.config import AppConfig, RobotConfig, ZenohSettings, load_toml
from telebot.errors import CallEnded, CallTimeout, ConfigError, TransportError
from telebot.identity import ContactBook, Identity, KnownRobots, Role
from telebot.router import acl, certs
from telebot.services.client import ConnectionEvent, connect
from telebot.testing.net import free_port

pytestmark = pytest.mark.zenoh

ROBOTS = ("guiabot", "rover", "scout")
USER = "alice"
OTHER_USER = "bob"


@dataclass
class Fleet:
    """The shared router, its robots (daemons) and the user's and admin's certificates."""

    base: Path
    router: RouterRig
    user_home: Path
    user: certs.ClientCert
    admin: certs.ClientCert
    other_user: certs.ClientCert
    robot_certs: dict[str, certs.ClientCert]
    daemons: dict[str, Process]
    #: The router's QUIC endpoint (beside its TLS one, as ``telebot-router run`` offers).
    quic: str


def _start_robot(
    fleet_base: Path,
    router: RouterRig,
    name: str,
    cert: certs.ClientCert,
    endpoint: str | None = None,
) -> Process:
    config = router.write_robot_config(
        fleet_base / f"{name}.toml", cert, timeout=REAL_TIMEOUT, endpoint=endpoint
    )
    process = Process(
        [
            "telebot.apps.robot_cli",
            "run",
            "--home",
            str(fleet_base / name),
            "--config",
            str(config),
            "--events",
        ]
    )
    line = process.next_line(timeout=60)
    assert '"ready"' in line, line
    return process


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    base = tmp_path_factory.mktemp("fleet")
    router = RouterRig(base)
    user_id = Identity.generate(USER)
    user_home = base / USER
    user_id.save(user_home)
    known = KnownRobots.load(user_home)
    robot_certs = {}
    for name in ROBOTS:
        robot = Identity.generate(name)
        robot.save(base / name)
        book = ContactBook.load(base / name)
        book.add(USER, user_id.public_key, Role.DRIVER)
        book.save()
        known.add(name, robot.public_key)
        robot_certs[name] = router.issue("robot", name)
    known.save()
    user = router.issue("user", USER)
    admin = router.issue("admin", "ops")
    other_user = router.issue("user", OTHER_USER)
    quic = f"quic/127.0.0.1:{free_port('udp')}"
    router.start(extra=("--quic", quic))
    daemons: dict[str, Process] = {}
    try:
        for name in ROBOTS:
            # scout dials the router's QUIC endpoint (its calls' data on a second session).
            endpoint = quic if name == "scout" else None
            daemons[name] = _start_robot(base, router, name, robot_certs[name], endpoint)
        yield Fleet(base, router, user_home, user, admin, other_user, robot_certs, daemons, quic)
    finally:
        for process in daemons.values():
            process.stop()
        router.stop()


def _raw_session(fleet: Fleet, client: certs.ClientCert) -> zenoh.Session:
    """A bare zenoh session through the router with ``client``'s certificate."""
    return zenoh.open(build_zenoh_config(fleet.router.zenoh(client)))


async def test_presence_of_every_robot_comes_through_the_router(fleet: Fleet) -> None:
    transport = ZenohTransport(fleet.router.zenoh(fleet.user))
    seen: set[str] = set()
    await transport.open()
    try:
        transport.watch_presence(
            "telebot/presence/robot/*/*", lambda key, alive: alive and seen.add(key.split("/")[3])
        )
        await wait_until(lambda: seen == set(ROBOTS))
    finally:
        await transport.close()


async def test_a_call_goes_through_the_router_and_it_sees_only_sealed_frames(
    fleet: Fleet,
) -> None:
    marker = f"secret-{uuid.uuid4().hex}"
    frames: list[tuple[str, bytes]] = []
    admin = await asyncio.to_thread(_raw_session, fleet, fleet.admin)
    try:
        admin.declare_subscriber(
            "telebot/**", lambda s: frames.append((str(s.key_expr), s.payload.to_bytes()))
        )
        config = fleet.router.app_config(fleet.user)
        async with connect("guiabot", home=fleet.user_home, config=config, timeout=20) as client:
            replies = [r.text async for r in client.chat_replies(marker)]
            assert replies, "the robot answered through the router"
            await wait_until(lambda: any("/call/" in key for key, _ in frames))
        assert any(key.startswith("telebot/robot/guiabot/call/") for key, _ in frames)
        assert any(key.startswith(f"telebot/user/{USER}/") for key, _ in frames)
        assert not any(marker.encode() in payload for _, payload in frames)
    finally:
        await asyncio.to_thread(admin.close)


async def test_a_user_calls_a_robot_over_the_routers_quic_endpoint(fleet: Fleet) -> None:
    # The user on QUIC (its certificate and the ACL as on TLS), the robot on TLS.
    config = fleet.router.app_config(fleet.user)
    config.transport.zenoh.connect = [fleet.quic]
    async with connect("guiabot", home=fleet.user_home, config=config, timeout=20) as client:
        assert (await client.pose()).state
        assert [r.text async for r in client.chat_replies("help")]
    # A certificate from another CA is refused on QUIC as on TLS.
    stranger = RouterRig(fleet.base / "other-quic").issue("user", USER)
    wrong = fleet.router.zenoh(stranger).model_copy(update={"connect": [fleet.quic]})
    with pytest.raises(TransportError, match="certificate"):
        await ZenohTransport(wrong).open()


async def test_a_robot_and_a_user_both_on_quic_each_with_a_data_session(fleet: Fleet) -> None:
    # scout and the user each open two sessions to the router (the calls' data on the
    # second): the ACL lets both of each through, and pose, chat and a stop all arrive.
    config = fleet.router.app_config(fleet.user)
    config.transport.zenoh.connect = [fleet.quic]
    async with (
        ZenohTransport(config.transport.zenoh) as transport,
        connect(
            "scout", home=fleet.user_home, config=config, transport=transport, timeout=20
        ) as client,
    ):
        assert transport.data_session is not None
        assert (await client.pose()).state
        assert [r.text async for r in client.chat_replies("help")]
        assert (await client.stop()).ok
        assert client.reconnects == 0


async def test_the_acl_keeps_a_robot_off_another_robots_keys(fleet: Fleet) -> None:
    got: list[str] = []
    tokens: list[str] = []
    rover_got: list[bytes] = []
    admin = await asyncio.to_thread(_raw_session, fleet, fleet.admin)
    rover = await asyncio.to_thread(_raw_session, fleet, fleet.robot_certs["rover"])
    user = await asyncio.to_thread(_raw_session, fleet, fleet.user)
    bob = await asyncio.to_thread(_raw_session, fleet, fleet.other_user)
    bob_got: list[str] = []
    try:
        admin.declare_subscriber("telebot/**", lambda s: got.append(s.payload.to_string()))
        # bob may not read alice's keys: his subscription is dropped by the router.
        bob.declare_subscriber(f"telebot/user/{USER}/**", lambda s: bob_got.append(""))
        bob_token = bob.liveliness().declare_token(f"telebot/presence/user/{OTHER_USER}/0")
        admin.liveliness().declare_subscriber(
            "telebot/presence/*/*/*", lambda s: tokens.append(str(s.key_expr)), history=True
        )
        # The real guiabot, and bob's token, declared after his subscription (same link).
        await wait_until(lambda: any("/guiabot/" in t for t in tokens))
        await wait_until(lambda: any(f"/{OTHER_USER}/" in t for t in tokens))
        # rover sends on guiabot's inbox, claims guiabot's presence and subscribes to its
        # inbox, then does what it may (a put to a user, a token of its own): once those
        # came through, the router had handled the others, on the same link, before.
        rover.put("telebot/robot/guiabot/in", "from-rover")
        fake = rover.liveliness().declare_token("telebot/presence/robot/guiabot/FAKE")
        rover.declare_subscriber("telebot/robot/guiabot/in", lambda s: rover_got.append(b""))
        rover.put(f"telebot/user/{USER}/0000000000000000/in/rover", "rover-allowed")
        probe = rover.liveliness().declare_token("telebot/presence/robot/rover/PROBE")
        await wait_until(lambda: "rover-allowed" in got and any("PROBE" in t for t in tokens))
        user.put(f"telebot/robot/guiabot/in/{USER}", "from-user")  # the user may
        await wait_until(lambda: "from-user" in got)
        assert "from-rover" not in got
        assert not any(t.endswith("/FAKE") for t in tokens)
        assert not rover_got  # nor may rover read guiabot's inbox
        assert not bob_got  # "rover-allowed" went to alice's inbox, not to bob
        fake.undeclare()
        probe.undeclare()
        bob_token.undeclare()
    finally:
        for session in (admin, rover, user, bob):
            await asyncio.to_thread(session.close)


async def test_a_user_cannot_put_on_another_users_call_keys_and_calls_still_work(
    fleet: Fleet,
) -> None:
    """bob, certified, sniffs the key alice's call frames go to and puts on it: the router
    drops his frames (the key names alice), while alice's call goes on through it. The
    same for rover, a certified robot, on alice's side of her call with guiabot."""
    seen: list[tuple[str, bytes]] = []
    admin = await asyncio.to_thread(_raw_session, fleet, fleet.admin)
    bob = await asyncio.to_thread(_raw_session, fleet, fleet.other_user)
    rover = await asyncio.to_thread(_raw_session, fleet, fleet.robot_certs["rover"])
    try:
        admin.declare_subscriber(
            "telebot/**",
            lambda s: seen.append((str(s.key_expr), s.payload.to_bytes())),
        )
        config = fleet.router.app_config(fleet.user)
        async with connect("guiabot", home=fleet.user_home, config=config, timeout=20) as client:
            # Both sides' control frames (heartbeats) seen, whichever came first.
            for side in ("telebot/robot/", "telebot/user/"):
                await wait_until(
                    lambda side=side: any(
                        k.startswith(side) and k.endswith("/ctl") for k, _ in seen
                    )
                )
            alices_ctl = next(
                key for key, _ in seen if key.startswith("telebot/robot/") and key.endswith("/ctl")
            )
            users_ctl = next(
                key for key, _ in seen if key.startswith("telebot/user/") and key.endswith("/ctl")
            )
            rover.put(users_ctl, b"rover-forged-ctl")
            rover.put(f"telebot/user/{USER}/0000000000000000/in/rover", b"rover-allowed")
            alices_data = alices_ctl.removesuffix("/ctl") + "/data"
            bob.put(alices_ctl, b"bob-forged-ctl")
            bob.put(alices_data, b"bob-forged-data")
            # What bob may do, after: once it came through, the router had handled the
            # two puts before it on the same link.
            bob.put(f"telebot/robot/guiabot/in/{OTHER_USER}", b"bob-allowed")
            await wait_until(lambda: any(p == b"bob-allowed" for _, p in seen))
            await wait_until(lambda: any(p == b"rover-allowed" for _, p in seen))
            assert not any(p.startswith(b"bob-forged") for _, p in seen), alices_ctl
            assert not any(p.startswith(b"rover-forged") for _, p in seen), users_ctl
            replies = [r.text async for r in client.chat_replies("where")]
            assert replies, "alice's call works through the router"
            assert client.reconnects == 0 and client.call.active
        assert f"/call/{USER}/" in alices_ctl  # the keys name their sender
        assert "/call/guiabot/" in users_ctl
    finally:
        for session in (admin, bob, rover):
            await asyncio.to_thread(session.close)


async def test_a_client_without_a_certificate_is_refused_with_one_line(fleet: Fleet) -> None:
    no_cert = ZenohSettings(
        mode="client", connect=[fleet.router.endpoint], multicast_scouting=False
    )
    transport = ZenohTransport(no_cert)
    with pytest.raises(TransportError, match="certificate") as refused:
        await transport.open()
    assert "\n" not in str(refused.value)
    # A wrong CA: a certificate from another router's CA is refused just the same.
    other = RouterRig(fleet.base / "other")
    stranger = other.issue("user", USER)
    wrong = fleet.router.zenoh(stranger)
    with pytest.raises(TransportError, match="certificate"):
        await ZenohTransport(wrong).open()


def test_missing_tls_files_are_named_by_key_before_any_connection(
    fleet: Fleet, tmp_path: Path
) -> None:
    config = tmp_path / "user.toml"
    config.write_text(
        "[transport.zenoh]\n"
        'mode = "client"\n'
        f'connect = ["{fleet.router.endpoint}"]\n'
        "[transport.zenoh.tls]\n"
        f'ca = "{fleet.user.ca}"\n'
        f'cert = "{tmp_path / "nope.pem"}"\n'
        f'key = "{fleet.user.key}"\n'
    )
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "telebot.apps.user_cli",
            "robots",
            "--home",
            str(fleet.user_home),
            "--config",
            str(config),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "transport.zenoh.tls.cert" in lines[0] and "nope.pem" in lines[0]


def test_the_printed_config_is_the_one_the_router_runs(fleet: Fleet) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "telebot.apps.router_cli", "config", str(fleet.router.dir)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    printed: dict[str, Any] = json.loads(done.stdout)
    subjects = printed["access_control"]["subjects"]
    assert {"id": "robot-rover", "cert_common_names": ["robot:rover"]} in subjects
    assert printed["transport"]["link"]["tls"]["enable_mtls"] is True
    assert printed["scouting"]["multicast"]["enabled"] is False
    # By default the router offers TLS and QUIC (the link across the internet) on 7447,
    # QUIC with datagrams for best-effort frames (zenoh's mixed reliability).
    assert printed["listen"]["endpoints"] == [
        "tls/0.0.0.0:7447",
        "quic/0.0.0.0:7447?mixed_rel=auto",
    ]
    zenoh.Config.from_json5(done.stdout)  # zenoh (and so zenohd -c) takes it as it is


def test_a_revoked_name_leaves_the_acl(tmp_path: Path) -> None:
    root = tmp_path / "r"
    certs.init_ca(root)
    certs.issue_client(root, "robot", "a")
    certs.issue_client(root, "user", "b")
    certs.revoke(root, "robot", "a")
    revoked = certs.read_revoked(root)
    members = [
        acl.Member(c.kind, c.name) for c in certs.list_clients(root) if c.common_name not in revoked
    ]
    names = [s.get("cert_common_names") for s in acl.acl_config(members)["subjects"]]
    assert ["user:b"] in names and ["robot:a"] not in names
    certs.issue_client(root, "robot", "a", force=True)  # a new certificate lets it back in
    assert certs.read_revoked(root) == set()


def test_the_example_configs_are_valid() -> None:
    root = Path(__file__).resolve().parents[1] / "configs" / "router"
    robot = load_toml(root / "robot.toml", RobotConfig)
    user = load_toml(root / "user.toml", AppConfig)
    for config in (robot, user):
        zenoh_settings = config.transport.zenoh
        assert zenoh_settings.mode == "client" and zenoh_settings.tls.enabled
        assert all(e.startswith("tls/") for e in zenoh_settings.connect)


def test_certificates_name_their_holder_and_the_router_its_addresses(tmp_path: Path) -> None:
    root = tmp_path / "r"
    certs.init_ca(root, ["10.1.2.3", "router.example.org"])
    router = x509.load_pem_x509_certificate((root / "router.pem").read_bytes())
    sans = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {str(ip) for ip in sans.get_values_for_type(x509.IPAddress)} >= {"127.0.0.1", "10.1.2.3"}
    assert set(sans.get_values_for_type(x509.DNSName)) == {"localhost", "router.example.org"}
    robot = certs.issue_client(root, "robot", "guiabot")
    cert = x509.load_pem_x509_certificate(robot.cert.read_bytes())
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "robot:guiabot"
    certs.check_signed_by(robot.cert, root / "ca.pem")
    with pytest.raises(ConfigError, match="already has a CA"):
        certs.init_ca(root)
    # An existing certificate is taken only from this CA and with the right common name.
    other = tmp_path / "o"
    certs.init_ca(other)
    stranger = certs.issue_client(other, "robot", "rover")
    with pytest.raises(ConfigError, match="not issued by the CA"):
        certs.import_client(root, "robot", "rover", stranger.cert)
    with pytest.raises(ConfigError, match="expected 'user:guiabot'"):
        certs.import_client(root, "user", "guiabot", robot.cert)


def test_an_existing_rsa_ca_issues_the_certificates(tmp_path: Path) -> None:
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "our CA")])
    now = datetime.datetime.now(datetime.UTC)
    ca = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(1)
        .not_valid_before(now)
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    (tmp_path / "ca.pem").write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    (tmp_path / "ca.key").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    root = tmp_path / "r"
    certs.init_ca(root, ca=tmp_path / "ca.pem", ca_key=tmp_path / "ca.key")
    user = certs.issue_client(root, "user", "alice")
    certs.check_signed_by(user.cert, tmp_path / "ca.pem")
    certs.check_signed_by(root / "router.pem", tmp_path / "ca.pem")


def test_half_a_tls_setting_is_named_before_any_connection(tmp_path: Path) -> None:
    settings = ZenohSettings.model_validate(
        {"mode": "client", "connect": ["tls/127.0.0.1:1"], "tls": {"ca": str(tmp_path)}}
    )
    with pytest.raises(TransportError, match=r"transport\.zenoh\.tls\.cert is not set"):
        build_zenoh_config(settings)


def test_router_commands_fail_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert router_cli.main(["config", str(tmp_path / "none")]) == 2
    assert router_cli.main(["cert", str(tmp_path / "none"), "--user", "bob"]) == 2
    root = tmp_path / "r"
    assert router_cli.main(["init", str(root)]) == 0
    assert router_cli.main(["config", str(root), "--listen", "tcp/127.0.0.1:1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("telebot-router: error: ") for line in err)
    assert "init" in err[0] and "ca.pem" in err[1] and "not a tls/ endpoint" in err[2]


def test_cert_prints_client_settings_for_quic_with_tls_where_udp_is_blocked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "r"
    assert router_cli.main(["init", str(root)]) == 0
    capsys.readouterr()
    assert router_cli.main(["cert", str(root), "--user", "bob"]) == 0
    printed = capsys.readouterr().out.splitlines()
    settings = tomllib.loads("\n".join(printed[2:]))["transport"]["zenoh"]
    assert settings["connect"] == ["quic/127.0.0.1:7447"]
    assert '# where UDP is blocked: connect = ["tls/127.0.0.1:7447"]' in printed
    assert ZenohSettings.model_validate(settings).tls.cert == root / "clients/user-bob/cert.pem"


async def test_a_certificate_outside_the_acl_gets_a_reason_not_a_hang(fleet: Fleet) -> None:
    # Issued after the router started, so not in its ACL: the same as a revoked one.
    late = fleet.router.issue("user", "mallory")
    home = fleet.base / "mallory"
    Identity.generate("mallory").save(home)
    known = KnownRobots.load(home)
    known.add("guiabot", Identity.load(fleet.base / "guiabot").public_key)
    known.save()
    config = fleet.router.app_config(late)
    with pytest.raises(CallTimeout) as refused:
        async with connect("guiabot", home=home, config=config, timeout=2):
            pass
    message = str(refused.value)
    assert "\n" not in message and "access control" in message and "user:mallory" in message


async def test_router_restart_mid_call_the_call_comes_back_and_the_robot_stayed_latched(
    fleet: Fleet,
) -> None:
    # Last in the module: it kills the shared router.
    config = fleet.router.app_config(fleet.user, timeout=REAL_TIMEOUT)
    loop = asyncio.get_running_loop()
    events: list[ConnectionEvent] = []
    async with connect("guiabot", home=fleet.user_home, config=config, timeout=20) as client:
        client.on_connection.append(events.append)
        assert (await client.arm()).ok
        replies = client.chat_replies("fwd 3")
        assert (await anext(replies)).text == "Forward command received"
        first = client.call
        fleet.router.stop()
        with pytest.raises(CallEnded):
            async for _ in replies:
                pass
        await wait_until(lambda: any(e.state == "reconnecting" for e in events))
        await asyncio.to_thread(fleet.router.start, port=fleet.router.port)
        healed = loop.time()
        await wait_until(lambda: client.reconnects == 1, timeout=20 + SLACK)
        assert client.call is not first
        await wait_until(
            lambda: client.latest_safety.value is not None and not client.latest_safety.value.armed
        )
        pose = await client.pose()
        assert pose.goal is None and pose.v == 0.0  # stopped at the drop, nothing resumed
        stopped = await client.telemetry()
        assert not stopped.armed and stopped.stop_reason
        assert loop.time() - healed < 20 + SLACK
