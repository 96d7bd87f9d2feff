"""Follow-me end to end: the page asks to follow a person, the robot follows, a key stops
it; a follow asked by chat over a call ends when the call drops.

The in-process robot of ``test_web_ui`` (SimNavStack + SafetyDriver + RobotServer on a
memory hub, the UI in Debian's chromium) with a simulated walker and a perfect tracker.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from conftest import ROBOT, USER
from follow_walk import TruthTracks
from rig import FAST_SIM, GENEROUS_TIMEOUT, SLACK, robot_drive, robot_on_hub, user_on_hub
from telebot.channels.transports.memory import MemoryHub
from telebot.reasons import Reason
from telebot.robot.nav import Velocity
from telebot.robot.sim.people import Walker
from telebot.services.client import RobotClient
from test_web_ui import arm, browser_page, page_ready, robot_rig, wait_for


async def test_the_page_follows_a_clicked_person_and_any_key_ends_it(tmp_path: Path) -> None:
    async with robot_rig(tmp_path) as rig, browser_page(rig.ui.url) as page:
        await page_ready(page)
        assert rig.server is not None
        follow = robot_drive(rig.server).follow
        follow.people = TruthTracks(rig.nav)  # a perfect tracker of the simulated people
        # Nobody tracked yet: the button's request is refused with the reason, beside it.
        await arm(rig)
        await page.click("#follow-person")
        await page.wait_for_function(
            "() => document.getElementById('follow-status').textContent.startsWith('refused')",
            timeout=10000,
        )
        assert "nobody is tracked" in await page.inner_text("#follow-status")
        # A person walks east along the corridor in front of the robot (at the start place).
        pose = rig.nav.true_pose
        rig.nav.add_person(
            Walker.along(
                [(pose.x + 1.3, pose.y), (pose.x + 8.5, pose.y)], speed=0.4, start_delay=0.3
            )
        )
        # Clicking the person on the map (the people layer) sends this event.
        await page.evaluate(
            "() => document.dispatchEvent(new CustomEvent('telebot:follow', {detail: {id: 1}}))"
        )
        await page.wait_for_function(
            "() => document.getElementById('follow-status').textContent === 'following person 1'",
            timeout=10000,
        )
        await wait_for(lambda: rig.nav.velocity().linear > 0.2, what="the robot following")
        # Any key stops it: the follow ends at once and the robot stays stopped.
        await page.locator("#map").focus()
        await page.keyboard.press("k")
        await wait_for(lambda: follow.goal is None, timeout=2.0 + SLACK, what="the follow ended")
        await wait_for(lambda: rig.nav.velocity() == Velocity(), what="the robot stopped")
        await page.wait_for_function(
            "() => document.getElementById('follow-status').textContent.startsWith('stopped')",
            timeout=10000,
        )
        await asyncio.sleep(0.3)  # the person walks on: the robot must not
        assert rig.nav.velocity() == Velocity()
        assert rig.stops()[-1] == (USER, "key")


async def test_a_dropped_call_ends_the_follow_and_stops_the_robot(tmp_path: Path) -> None:
    """Over a real call on the memory hub: ``follow`` by chat, then the link is cut."""
    hub = MemoryHub(seed=3)
    async with (
        robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM) as (
            nav,
            safety,
            server,
            _,
        ),
        user_on_hub(tmp_path, hub) as user,
    ):
        follow = robot_drive(server).follow
        follow.people = TruthTracks(nav)
        pose = nav.true_pose  # the start place: the corridor's west end, facing east
        nav.add_person(Walker.along([(pose.x + 1.3, pose.y), (pose.x + 8.5, pose.y)], speed=0.4))
        client = RobotClient(await user.call(ROBOT))
        assert (await client.arm()).ok
        replies = client.chat_replies("follow", timeout=30)
        first = await anext(replies)
        assert (first.text, first.code) == ("following person 1", Reason.ACCEPTED)
        await wait_for(lambda: nav.velocity().linear > 0.2, what="the robot following")
        goal = follow.goal
        assert goal is not None
        hub.cut("robot", "user")  # the driver's link is gone: no hang-up, no stop
        await wait_for(
            lambda: follow.goal is None,
            timeout=GENEROUS_TIMEOUT + 2.0 + SLACK,
            what="the follow ended",
        )
        await wait_for(lambda: nav.velocity() == Velocity(), what="the robot stopped")
        assert not safety.supervisor.armed
        # Presence lost: the call dropped, the supervisor stopped, the follow ended with it.
        assert goal.code == Reason.STOPPED and "dropped" in goal.reason, goal.reason
        await asyncio.sleep(0.3)  # the person walks on: the robot must not
        assert nav.velocity() == Velocity()
        await replies.aclose()
