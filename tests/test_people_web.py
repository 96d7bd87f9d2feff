"""The web page's people layer (static/people.js) in a real browser: tracks drawn on the
map, marked in the video, alerts in the chat. Reuses the web UI tests' rig."""

from __future__ import annotations

from pathlib import Path

from telebot.robot.sim.people import Walker
from test_web_ui import ARTIFACTS, browser_page, page_ready, robot_rig


async def test_the_page_draws_people_marks_them_in_the_video_and_shows_alerts(
    tmp_path: Path,
) -> None:
    async with robot_rig(tmp_path) as rig:
        start = rig.nav.true_pose
        # Someone walks up the corridor towards the robot and stops 1.4 m in front of it.
        rig.nav.add_person(
            # Slowly (0.6 m/s), so a loaded machine still sees it closing in within 2.5 m.
            Walker.along([(start.x + 5.0, start.y), (start.x + 1.4, start.y)], speed=0.6)
        )
        async with browser_page(rig.ui.url) as page:
            await page_ready(page)
            await page.wait_for_function("() => window.telebotUI.drawn.people === 1", timeout=15000)
            # The first alert says it approaches (a "screen" alert may follow once it stands).
            await page.wait_for_function(
                "() => window.telebotUI.state.peopleAlerts.length >= 1", timeout=15000
            )
            alert = await page.evaluate("() => window.telebotUI.state.peopleAlerts[0]")
            assert alert["kind"] == "approaching", alert
            assert alert["text"].startswith("person approaching ahead, ")
            log = await page.locator("#chat-log").inner_text()
            assert "person approaching ahead" in log
            # The video overlay has the person's box (yellow pixels somewhere on it).
            await page.wait_for_function("() => window.telebotUI.state.frames > 0")
            yellow = await page.evaluate(
                """() => {
                  const c = document.getElementById('people-overlay');
                  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                  let n = 0;
                  for (let i = 0; i < d.length; i += 4)
                    if (d[i] > 200 && d[i + 1] > 200 && d[i + 2] < 80 && d[i + 3] > 0) n++;
                  return n;
                }"""
            )
            assert yellow > 20
            # Listed under the video with a follow button (follow-me picks it by id).
            row = await page.locator("#people-list .person").first.inner_text()
            assert row.startswith("#") and "ahead" in row and "follow" in row
            ARTIFACTS.mkdir(exist_ok=True)
            await page.screenshot(path=str(ARTIFACTS / "web_ui_people.png"))
