"""The ``plan`` service: the robot's planned path and named places, for the user's map view.

On the robot, :class:`~telebot.services.plan.robot.PlanService` (registered as ``plan`` by
:func:`~telebot.services.registry.robot_services`) sends each call a ``plan`` message as
soon as the plan changes (a new goal, a replan, the goal's end: then an empty one) and again
every :data:`~telebot.services.plan.robot.PLAN_EVERY` seconds, so a lost one heals and a
user who joins sees the plan at once; and the ``places`` at the call's start, on change and
every :data:`~telebot.services.plan.robot.PLACES_EVERY` seconds. The plan is read from the
NavStack and simplified once per change for every call
(:class:`~telebot.services.plan.robot.PlanSource`, shared per NavStack).

On the user's side, :class:`~telebot.services.plan.user.PlanReceiver` hands new plans and
places to the client (:attr:`RobotClient.latest_plan
<telebot.services.client.RobotClient.latest_plan>`); repeats and plans older than the newest
seen (reordered on the lossy link) are dropped. Wire format:
:mod:`telebot.services.plan.wire` and ``docs/protocol.md`` §16.4.

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.plan.robot:PlanService", user="telebot.services.client:open_plan"
)
