"""Video over a call's "video" channel: the robot's :class:`VideoSender`, the user's
:class:`VideoReceiver` (and :func:`frames`).

The protocol (fragments, reassembly, receiver reports, rate adaptation) is sans-IO in
:mod:`telebot.services.video.wire`; sender.py and receiver.py grab pictures, encode them, move the
datagrams and keep time with the event loop.

Robot, one sender per call (several calls may share one NavStack; a picture taken for one
call within half a frame interval is reused by the others, and so is its JPEG)::

    sender = VideoSender.for_call(call, nav, VideoSettings(max_fps=30))
    sender.start()
    ...  # sender.fps, sender.width, sender.height, sender.quality for telemetry
    await sender.close()          # or sender.stop() from a callback

User::

    async with VideoReceiver(video_channel(call)) as video:
        async for frame in video:                  # VideoFrame: BGR numpy image and metadata
            show(frame.image)

A user client (:class:`~telebot.services.client.RobotClient`) keeps its video across calls
(a reconnect opens a new one): a :class:`VideoFeed` holds the subscribers, and its call
service :class:`VideoFeedService` (registered as ``video``) reassembles the frames and
reports back on whichever call is current. ``robot.video()`` is a :class:`VideoReceiver`
on the feed; the web UI subscribes to the feed's whole JPEG frames::

    unsubscribe = robot.video_feed.subscribe(lambda complete: forward(complete.data))

The sender streams only while its receiver's reports come (the receiver sends one at
once and then every ``report_interval``, and a *bye* when it closes), so a user who does
not watch costs nothing. Both ends stop by themselves when the call ends.

Codecs (``docs/protocol.md`` §25): each receiver report lists the codecs the receiver
decodes (none: an old client, JPEG); the sender uses its first preference among them
(``VideoSettings.codecs``). H.264 and VP8 frames are encoded on a worker thread
(:class:`~telebot.services.codecs.ThreadedEncoder`) at the controller's rate, with a
keyframe every ``keyframe_interval`` s and on request (paced by
:class:`~telebot.services.media.wire.KeyframePacer`); receivers decode delta frames only
in an unbroken chain (:class:`~telebot.services.media.wire.KeyframeGate`) and ask for a
keyframe after a loss.

Timing (measured, 640 × 480 from the simulated camera): rendering takes ~2.5 ms, JPEG
encoding ~0.4 ms and decoding ~0.4 ms, so both run on the event loop: a thread hand-off
would cost about as much as it saves. H.264 encoding takes ~3 ms (off the loop), decoding
~2 ms (on the user's loop, as frames arrive).

The ``video`` service: the robot's camera to the user (JPEG, H.264, VP8).

``wire.py``: the wire format; ``sender.py`` (the camera's encoder and pacing) and
``receiver.py`` (reassembly, decoding, the feed) are the stream machinery both hosts' video
sides use, and the media service reuses for the user's camera; ``stream.py`` what both share.
"""

from telebot.services.base import ServiceSpec

#: Its sides, loaded when a host starts (see :mod:`telebot.services.registry`).
SERVICE = ServiceSpec(
    robot="telebot.services.robot:RobotVideo", user="telebot.services.client:open_video"
)
