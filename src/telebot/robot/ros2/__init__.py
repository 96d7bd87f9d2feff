"""The ROS 2 robot: a Nav2 robot driven over rmw_zenoh's wire format, with no ROS installed.

Message types and CDR are :mod:`telebot.rosmsg`'s (shared with the simulator).

- :mod:`.keys`: rmw_zenoh's key expressions, liveliness tokens and attachments (sans-IO).
- :mod:`.node`: a ROS 2 node on a zenoh session: publishers, subscriptions, services,
  actions, graph discovery.
- :mod:`.convert`: ROS messages to telebot's robot types (map, poses, tf, path, battery).
- :mod:`.stack`: :class:`~telebot.robot.ros2.stack.Ros2NavStack`, the ``"ros2"`` adapter.
- :mod:`.simrobot`: the simulator served as a ROS 2 / Nav2 robot (``telebot-sim``).

This is the one package inside ``telebot.robot`` that may import zenoh.
"""
