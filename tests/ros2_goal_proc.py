"""A ROS 2 action client in its own process: sends one navigate_to_pose goal, then waits.

Run by tests/test_ros2_sim.py, which kills it (SIGKILL) while the goal runs: the simulated
robot must stop when this client's liveliness token leaves the graph.

    python -m ros2_goal_proc ENDPOINT X Y     (with tests/ on PYTHONPATH)

Prints ``accepted`` (or ``rejected``) once the server answers, then ``status N`` when the
goal ends, if it ends before the process is killed.
"""

from __future__ import annotations

import sys
import threading

from telebot.robot.ros2.node import Ros2Node


def main() -> int:
    endpoint, x, y = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
    node = Ros2Node(name="goal_sender", connect=[endpoint])
    atype = node.library.action("nav2_msgs/action/NavigateToPose")
    client = node.action_client("navigate_to_pose", atype)
    done = threading.Event()
    pose = node.library.message("geometry_msgs/msg/PoseStamped")
    goal = atype.goal.make(
        pose=pose.make(
            header=node.library.message("std_msgs/msg/Header").make(frame_id="map"),
            pose=node.library.message("geometry_msgs/msg/Pose").make(
                position=node.library.message("geometry_msgs/msg/Point").make(x=x, y=y),
                orientation=node.library.message("geometry_msgs/msg/Quaternion").make(w=1.0),
            ),
        )
    )

    def on_accepted(_goal_id: bytes, accepted: bool) -> None:
        print("accepted" if accepted else "rejected", flush=True)

    def on_result(status: int, _result: object, _text: str) -> None:
        print(f"status {status}", flush=True)
        done.set()

    client.send_goal(
        goal, on_accepted=on_accepted, on_feedback=lambda fb: None, on_result=on_result
    )
    done.wait()
    node.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
