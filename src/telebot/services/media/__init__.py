"""Two-way media of a call: the robot's microphone to users, the user's camera and
microphone to the robot, spoken replies (the robot's video is :mod:`telebot.services.video.sender`).

Wire format: :mod:`telebot.services.media.wire` (``docs/protocol.md`` §25). Codecs: PyAV
(:mod:`telebot.services.codecs`); sound in and out: :mod:`telebot.services.media.audio`.

**Robot.** :class:`RobotMedia` is the robot's per-robot ``media`` service (registered
like the others, started and closed with the robot; its settings are the ``[media]``
section of the robot's :class:`~telebot.services.base.ServiceConfig`, a
:class:`~telebot.config.MediaConfig`). With a :class:`RobotMediaService` on each call it:

* streams its microphone (Opus, one packet per 20 ms of the event loop's clock, encoded
  once for all calls) on ``audio`` to every user whose reports ask for it;
* asks every caller for their camera (``video/user``) and microphone (``audio/user``)
  once they came: the user's side sends for up to 2 s unasked, the robot reports on a
  stream from its first frame or packet to the end of the call (a call that sends no
  media gets no reports);
* decodes the user's voice into its speaker sink (``[media] speaker``) and the user's
  pictures for local consumers (:meth:`RobotMedia.on_user_picture`, and the
  shared-memory ring ``[media] user_video_ring``);
* speaks its chat replies (espeak-ng) into the user's audio and/or its own speaker.

**The robot's screen** (the page media-web serves) codes against this API of
:class:`RobotMedia` (the robot's ``server.service("media")``), all on the event loop,
never blocking::

    unsubscribe = media.subscribe(
        on_video=lambda frame: ...,   # CompleteFrame of the user's camera, still encoded
                                      #   (frame.codec: CODEC_H264 / CODEC_VP8 / CODEC_JPEG,
                                      #   frame.keyframe, frame.data, frame.frame_id,
                                      #   frame.capture_time); deltas only after their
                                      #   keyframe (a page decoder can take them in order)
        on_audio=lambda packet: ...,  # AudioPacket of the user's mic (packet.data: Opus,
                                      #   48 kHz mono 20 ms; packet.seq, packet.capture_time)
        on_state=lambda state: ...,   # CallState: state.text ("alice is driving",
                                      #   "connecting…", "no call"), state.user, state.role,
                                      #   state.driving, state.video, state.audio
        codecs=(CODEC_H264, CODEC_VP8), # what the page decodes (asked of the user's side)
    )
    media.state                       # the current CallState
    media.request_keyframe()          # the page's decoder failed: ask the user for one
    unsubscribe()

**User.** :class:`UserMedia` lives on the :class:`~telebot.services.client.RobotClient`
across calls (``robot.media``); its service :class:`UserMediaService` moves the bytes of
the current call: ``robot.audio()`` (an :class:`AudioReceiver`, decoded 20 ms blocks of
the robot's microphone) and ``robot.talk(mic=..., camera=...)`` (send a microphone
source and a picture source to the robot while it asks for them).

The ``media`` service: two-way audio and the user's camera (PyAV, loaded when used).

``[media]``'s video settings (codec, bit rates, keyframe interval, stamping) are the
robot's video's: :func:`~telebot.services.robot.robot_video_settings` reads them.

``wire.py``: the wire format; ``robot.py``: the robot side; ``user.py``: the user side.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.media.robot:RobotMedia",
    user="telebot.services.media.user:open_user_media",
)
