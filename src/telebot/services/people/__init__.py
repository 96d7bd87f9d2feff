"""The ``people`` service: tracked people and alerts about them, robot → user at 5 Hz.

On the robot, :class:`~telebot.services.people.robot.RobotPeople` (registered as ``people``
by :func:`~telebot.services.registry.robot_services`) runs the robot's
:class:`~telebot.robot.perception.runner.PeoplePerception` (``[people]`` of the config) once
per robot, stepped on every control cycle (before follow-me reads its tracks), and opens a
:class:`~telebot.services.people.robot.PeopleService` on each call: it sends a ``people``
message ``stream_hz`` times a second with the confirmed tracks, and each new alert a few
times (:data:`~telebot.services.people.robot.ALERT_REPEATS`, same ``seq``: the channel is
lossy).

On the user's side, :class:`~telebot.services.people.user.PeopleReceiver` hands updates and
each alert once to the client (:meth:`RobotClient.people
<telebot.services.client.RobotClient.people>`,
:meth:`~telebot.services.client.RobotClient.people_alerts`). Wire format:
:mod:`telebot.services.people.wire` and ``docs/protocol.md`` (the ``people`` channel).

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.people.robot:RobotPeople", user="telebot.services.client:open_people"
)
