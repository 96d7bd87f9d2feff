"""The ``relay`` service: any robot topic to the user, as CDR, over the call.

On the robot, :class:`~telebot.services.relay.robot.RelayService` (registered as ``relay``
by :func:`~telebot.services.registry.robot_services`) answers a call's ``relay`` requests
(:mod:`telebot.services.relay.wire`): the topic list, and relays started and stopped per
request. Topics come from the NavStack when it is a :class:`~telebot.robot.nav.TopicSource`
(the ROS 2 robot: any topic on its zenoh network; the simulator: its own streams).

Flooding cannot starve control:

- the source's callback (any thread) only puts the message in the relay's bounded queue (one
  deep when *latest only*, :data:`~telebot.services.relay.robot.QUEUE` otherwise; the oldest
  is dropped and counted) and wakes the event loop once, however many messages come;
- each relay sends at most ``rate`` messages/s (the robot's ``[relay] max_rate`` if the user
  gave none): a message that comes before the relay is due again is dropped and counted,
  except with *latest only*, where the newest waits for its turn (so the user gets the
  newest message at the rate);
- all relays of a call share a byte budget (``[relay] max_bytes_per_second``): small
  messages (one datagram) go first, a large one's fragments are paced to the budget on the
  BULK lane, and a message that would wait more than
  :data:`~telebot.services.relay.robot.MAX_BACKLOG` seconds is dropped and counted.

The stop, safety and chat channels are on other lanes and never queue behind relay data.
Relays end with the call (:meth:`~telebot.services.relay.robot.RelayService.close`), and
each one whose topic is gone from the robot ends by itself (an ``ended`` message: the user's
stream ends). Refused relays (a topic the caller's role may not have, by ``[relay]``) are
written to the safety audit log.

On the user's side, :class:`~telebot.services.relay.user.RelayReceiver` rebuilds messages
and hands them to the :class:`~telebot.services.relay.user.TopicStream` of their stream
(:meth:`RobotClient.relay <telebot.services.client.RobotClient.relay>`).

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.relay.robot:RelayService", user="telebot.services.client:open_relay"
)
