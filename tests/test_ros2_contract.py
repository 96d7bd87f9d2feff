"""The NavStack contract suite on the ROS 2 adapter, against telebot-sim across processes.

One telebot-sim (its own zenoh router, the small map, a fast base) and one
:class:`~telebot.robot.ros2.stack.Ros2NavStack` joined to it serve the whole module; each
check starts by stopping the robot wherever the last one left it.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from conftest import SLACK, Process
from rig import FAST_SIM, write_config
from telebot.config import RobotConfig
from telebot.robot.ros2.stack import Ros2NavStack
from telebot.testing.navstack import NavStackContract, Subject, check_optional
from telebot.testing.net import free_port

# The module's first test also starts telebot-sim and joins it (slow on a loaded machine).
pytestmark = [pytest.mark.zenoh, pytest.mark.timeout(180)]


@pytest.fixture(scope="module")
def ros2_robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ros2NavStack]:
    tmp = tmp_path_factory.mktemp("ros2_contract")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = write_config(tmp / "robot.toml", sim=FAST_SIM)
    sim = Process(
        ["telebot.apps.sim_cli", "--config", str(config), "--listen", endpoint, "--map", "small"]
    )
    try:
        line = sim.next_line(timeout=30)
        assert "serving map 'small' as ROS 2 robot on" in line, line
        # A long lease: a loaded machine can starve the link's keep-alives past the default
        # 0.5 s, and the dropped link fails the running goal (test_ros2_e2e keeps 0.5 s).
        settings = {"router": [endpoint], "connect_timeout": 10.0 + SLACK, "lease": 5.0}
        robot = Ros2NavStack.from_config(
            RobotConfig.model_validate({"robot": {"kind": "ros2"}, "ros2": settings})
        )
        try:
            yield robot
        finally:
            robot.stop()
            robot.close()
    finally:
        sim.stop(graceful=True)


class TestRos2Adapter(NavStackContract):
    @pytest.fixture
    def subject(self, ros2_robot: Ros2NavStack) -> Subject:
        return Subject(ros2_robot)

    async def test_optional(self, subject: Subject) -> None:
        """A Nav2 robot has every optional ability but being stepped, and each works."""
        report = await check_optional(subject)
        assert report.failed == {}, str(report)
        assert list(report.lacks) == ["stepped by the caller's clock"]
