"""Two linked routers (docs/protocol.md §22.5): a robot on its site's router, a user on a
cloud router, ``telebot-router run --peer-router`` linking them, the ACL on both.

Real processes on loopback: two ``telebot-router run`` (sharing one CA), a robot daemon
connected to the site router, the user's zenoh session connected to the cloud router.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from conftest import wait_until
from rig import REAL_TIMEOUT, Process
from router_rig import RouterRig
from telebot.apps import router_cli
from telebot.errors import CallTimeout
from telebot.identity import ContactBook, Identity, KnownRobots, Role
from telebot.services.client import RobotClient, connect

pytestmark = pytest.mark.zenoh

ROBOT = "guiabot"


@dataclass
class Mesh:
    """The site router (the robot's), the cloud router (the users'), linked."""

    base: Path
    site: RouterRig
    cloud: RouterRig
    robot: Process


def _user(base: Path, name: str, robot_key: bytes, book: ContactBook) -> Path:
    """A user's home that knows the robot, listed as a driver in the robot's book."""
    identity = Identity.generate(name)
    home = base / name
    identity.save(home)
    known = KnownRobots.load(home)
    known.add(ROBOT, robot_key)
    known.save()
    book.add(name, identity.public_key, Role.DRIVER)
    return home


def _speed(client: RobotClient) -> float:
    pose = client.latest_pose.value
    return -1.0 if pose is None else abs(pose.v)


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mesh]:
    base = tmp_path_factory.mktemp("mesh")
    cloud = RouterRig(base / "cloud")
    site = RouterRig(base / "site", ca=cloud)  # one CA for both routers
    robot_id = Identity.generate(ROBOT)
    robot_id.save(base / ROBOT)
    book = ContactBook.load(base / ROBOT)
    for name in ("alice", "carol"):
        _user(base, name, robot_id.public_key, book)
    book.save()
    robot_cert = site.issue("robot", ROBOT)
    cloud.issue("user", "alice")  # alice uses the cloud router
    site.issue("user", "carol")  # carol is listed at the site router only
    cloud.start()
    ready = site.start(extra=("--peer-router", cloud.endpoint))
    assert ready["peers"] == [cloud.endpoint]
    config = site.write_robot_config(base / "robot.toml", robot_cert, timeout=REAL_TIMEOUT)
    robot = Process(
        [
            *("telebot.apps.robot_cli", "run", "--home", str(base / ROBOT)),
            *("--config", str(config), "--events"),
        ]
    )
    try:
        line = robot.next_line(timeout=60)
        assert '"ready"' in line, line
        yield Mesh(base, site, cloud, robot)
    finally:
        robot.stop()
        site.stop()
        cloud.stop()


async def test_a_user_on_the_cloud_router_calls_and_stops_a_robot_on_the_site_router(
    mesh: Mesh,
) -> None:
    config = mesh.cloud.app_config(mesh.cloud.client("user", "alice"))
    async with connect(ROBOT, home=mesh.base / "alice", config=config, timeout=20) as client:
        assert (await client.arm()).ok
        replies = client.chat_replies("fwd 3")
        assert (await anext(replies)).text == "Forward command received"
        await wait_until(lambda: _speed(client) > 0)
        ack = await client.stop()
        assert ack.ok, ack
        stopped = await client.telemetry()
        assert not stopped.armed and stopped.stop_reason
        await wait_until(lambda: _speed(client) == 0.0)


@pytest.mark.parametrize(
    ("router", "user", "listed_at"), [("cloud", "carol", "site"), ("site", "alice", "cloud")]
)
async def test_each_router_enforces_its_own_acl(
    mesh: Mesh, router: str, user: str, listed_at: str
) -> None:
    """A user whose certificate (from the shared CA) only the *other* router lists gets
    nothing through this one: the call times out naming the certificate."""
    rig: RouterRig = getattr(mesh, router)
    cert = getattr(mesh, listed_at).client("user", user)
    config = rig.app_config(cert)
    with pytest.raises(CallTimeout) as refused:
        async with connect(ROBOT, home=mesh.base / user, config=config, timeout=2):
            pass
    assert f"user:{user}" in str(refused.value)


def test_the_peer_router_flag_makes_the_link_and_the_acl_lets_a_router_in(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "site"
    router_cli.main(["init", str(root)])
    capsys.readouterr()
    peer = "tls/cloud.example.com:7447"
    assert router_cli.main(["config", str(root), "--peer-router", peer]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["connect"] == {"endpoints": [peer], "exit_on_failure": False}
    acl = printed["access_control"]
    assert {"id": "router", "cert_common_names": ["telebot-router"]} in acl["subjects"]
    (rule,) = [r for r in acl["rules"] if r["id"] == "router"]
    assert rule["key_exprs"] == ["telebot/**"] and rule["flows"] == ["ingress"]
    # A link is TLS or nothing: a plain endpoint is one line naming it.
    assert router_cli.main(["config", str(root), "--peer-router", "tcp/1.2.3.4:7447"]) == 2
    err = capsys.readouterr().err
    assert "tcp/1.2.3.4:7447" in err and "tls/" in err and err.count("\n") == 1
