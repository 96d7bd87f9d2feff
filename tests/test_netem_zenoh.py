"""A robot and a user over real zenoh sessions through the network emulator.

The robot answers on a zenoh session of its own that listens on TCP; the user's session
(client mode) reaches it only through a :class:`~telebot.netem.NetemProxy` playing the
``wifi`` profile on zenoh's TCP link, and the test forces the profile's roaming gap
(300 ms) while the robot drives. Over zenoh's ``udp/`` link, an outage long enough to drop
the call: the first call back hears the robot.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, Literal

import pytest

from conftest import ROBOT, wait_until
from rig import GENEROUS_TIMEOUT, robot_on_hub
from telebot.channels.transports.memory import MemoryHub
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import AppConfig, ServiceSettings, ZenohSettings
from telebot.netem import NetemProxy, profile
from telebot.robot.nav import Velocity
from telebot.robot.sim.stack import SimNavStack
from telebot.services.client import connect
from telebot.services.safety.robot import SafetyDriver
from telebot.testing.net import free_port

ROAM = profile("wifi").outages.duration  # type: ignore[union-attr]


def through(proxy: NetemProxy, timeout: float, **sections: Any) -> AppConfig:
    """A user's config that reaches the robot only through ``proxy`` (client mode: a client
    connects only where it is told, never around the proxy), with call ``timeout``."""
    zenoh = {"mode": "client", "connect": [proxy.endpoint], "multicast_scouting": False}
    return AppConfig.model_validate(
        {"transport": {"zenoh": zenoh}, "call": {"timeout": timeout}, **sections}
    )


@contextlib.asynccontextmanager
async def robot_behind(
    tmp_path: Path, profile_name: str, link: Literal["tcp", "udp"], timeout: float
) -> AsyncIterator[tuple[SimNavStack, SafetyDriver, NetemProxy]]:
    """A robot (20 poses a second, call ``timeout``) on a zenoh session of its own that
    listens on ``link``, and a :class:`NetemProxy` in front of it playing ``profile_name``:
    (its navigation stack, its safety service, the proxy)."""
    listen = f"{link}/127.0.0.1:{free_port(link)}"
    robot_transport = ZenohTransport(ZenohSettings(listen=[listen], multicast_scouting=False))
    async with (
        robot_on_hub(
            tmp_path,
            MemoryHub(),
            transport=robot_transport,
            timeout=timeout,
            services=ServiceSettings(pose_hz=20.0),
        ) as (nav, safety, _server, _endpoint),
        NetemProxy(profile_name, f"{link}/127.0.0.1:0", listen, seed=1) as proxy,
    ):
        yield nav, safety, proxy


@pytest.mark.zenoh
async def test_a_call_over_wifi_survives_a_roaming_gap_and_a_stop_sent_into_it_arrives(
    tmp_path: Path,
) -> None:
    # The rig's generous call timeout: this test is about the link, not about how long a
    # silence the deadman forgives (TCP turns the 300 ms gap into a longer stall).
    async with robot_behind(tmp_path, "wifi", "tcp", GENEROUS_TIMEOUT) as (nav, safety, proxy):
        config = through(proxy, GENEROUS_TIMEOUT)
        async with connect(ROBOT, home=tmp_path / "user", config=config, timeout=20) as client:
            assert (await client.arm()).ok
            first = client.call
            replies = client.chat_replies("fwd 3")
            assert (await anext(replies)).text == "Forward command received"
            await wait_until(lambda: nav.velocity() != Velocity())
            loop = asyncio.get_running_loop()
            proxy.outage(ROAM)  # the Wi-Fi roams: nothing gets through either way
            sent = loop.time()
            ack = await client.stop(timeout=10)
            took = loop.time() - sent
            # The stop went into the gap: TCP held it and delivered it after the gap...
            assert ack.ok
            assert took >= ROAM - 0.05, f"acknowledged {took:.3f} s after, inside the gap"
            assert proxy.stats.up.retransmitted >= 1 and proxy.stats.cut == 0
            # ...and the robot is at rest, latched, on the same call: no drop, no redial.
            assert nav.velocity() == Velocity() and not safety.supervisor.armed
            async for _ in replies:  # the move's final reply: it was stopped
                pass
            assert client.call is first and client.reconnects == 0
            assert (await client.telemetry()).stop_reason


@pytest.mark.zenoh
@pytest.mark.parametrize("data_session", [True, False])
async def test_a_calls_data_goes_on_a_connection_of_its_own(
    tmp_path: Path, data_session: bool
) -> None:
    # With ``data_session`` the user's zenoh dials twice: pose and pictures (the call's
    # ``/data`` keys) on one connection, stops, heartbeats and presence on the other, so
    # pictures never fill the congestion window a stop needs. The call works either way.
    async with robot_behind(tmp_path, "lan", "tcp", GENEROUS_TIMEOUT) as (nav, safety, proxy):
        config = through(proxy, GENEROUS_TIMEOUT)
        config.transport.zenoh.data_session = data_session
        async with (
            ZenohTransport(config.transport.zenoh) as transport,
            connect(
                ROBOT, home=tmp_path / "user", config=config, transport=transport, timeout=20
            ) as client,
        ):
            assert (await client.arm()).ok and safety.supervisor.armed
            await client.pose(timeout=10)  # the data key's
            assert client.reconnects == 0
            assert proxy.stats.connections == (2 if data_session else 1)
            if data_session:
                # The pose rides the second session: with it gone no pose comes, and the
                # call, its heartbeats and a stop go on over the first.
                assert transport.data_session is not None
                transport.data_session.close()
                # What was on its way may still come; then nothing, where 20 poses a
                # second would keep coming over the first session.
                quiet, last = 0.0, client.latest_pose.value
                async with asyncio.timeout(10):
                    while quiet < 1.0:
                        await asyncio.sleep(0.1)
                        now = client.latest_pose.value
                        quiet = 0.0 if now is not last else quiet + 0.1
                        last = now
            assert (await client.stop()).ok  # the control key's
            assert not safety.supervisor.armed and nav.velocity() == Velocity()
            assert client.reconnects == 0


@pytest.mark.zenoh
async def test_the_first_call_back_after_an_outage_hears_the_robot(tmp_path: Path) -> None:
    # zenoh's udp/ link never repeats a lost declaration: a call set up during the outage
    # would subscribe into the void, and nothing of it would ever come back. The client
    # redials on keys it subscribed to while the link was good (``_listen_ahead``), so the
    # first new call hears the robot.
    timeout = 1.0  # both sides: the outage drops the call, a loaded machine does not
    async with robot_behind(tmp_path, "lan", "udp", timeout) as (_nav, _safety, proxy):
        config = through(proxy, timeout, reconnect={"base": 0.05, "cap": 0.5})
        async with connect(ROBOT, home=tmp_path / "user", config=config, timeout=20) as client:
            await client.pose(timeout=10)
            poses: list[int] = []  # the client's reconnection count at each pose

            async def follow() -> None:
                async for _ in client.poses():
                    poses.append(client.reconnects)

            follower = asyncio.create_task(follow())
            try:
                proxy.outage(3 * timeout)
                await wait_until(lambda: client.reconnects >= 1, timeout=20)
                await wait_until(lambda: any(n >= 1 for n in poses), timeout=20)
            finally:
                follower.cancel()
                await asyncio.gather(follower, return_exceptions=True)
            first_back = next(n for n in poses if n >= 1)
            assert first_back == 1, f"the robot was heard again only on call {first_back}"
