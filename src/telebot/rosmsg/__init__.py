"""ROS 2 message encoding, shared by the robot adapters: no zenoh, no ROS install.

- :mod:`.types`: ROS message, service and action types (CDR through rosbags) and their
  RIHS01 type hashes (REP 2011).
- :mod:`.messages`: a robot's state (map, poses, plan, scan, battery, pictures) as the
  messages a Nav2 robot publishes.
- :mod:`.topics`: the simulator's streams as ROS 2 topics in CDR (its
  :class:`~telebot.robot.nav.TopicSource`, for the ``relay`` service).

It sits between the robot's types (:mod:`telebot.robot.nav`, :mod:`telebot.robot.grid`)
and the adapters that use it: the simulator (:mod:`telebot.robot.sim`) and the ROS 2 robot
(:mod:`telebot.robot.ros2`, which adds rmw_zenoh's wire names and the zenoh node).
"""
