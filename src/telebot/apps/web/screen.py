"""The robot's own screen: a local page with the remote user's face, name, call state, voice.

As the Guiabot's top screen showed Skype, ``telebot-robot run`` serves
``http://127.0.0.1:8090/`` (``[screen]`` in the config, ``--screen HOST:PORT|off``) for a
browser in kiosk mode on the robot's display. The page (``static/screen.html``) shows the
video of the user who is sending theirs full screen, their name, the call state ("alice is
driving", "connecting…") and plays their voice. While the user's camera is off (no picture
of it for ``USER_VIDEO_STALE`` s: turned off, or stalled) the page clears the picture and
says "alice's camera is off" instead. This process never decodes: it passes the
encoded frames and Opus packets on to the page, whose ``media.js`` decodes them with
WebCodecs (the code the user's page uses).

Websocket ``/ws`` (server → page; docs/protocol.md §19)::

    {"type": "state", "user": "alice", "text": "alice is driving", "call": true,
     "video": true}
    binary: media messages (:func:`~telebot.apps.web.media_relay.pack_media`)

and page → server ``{"type": "keyframe"}`` when the page lost a frame (or just opened)
and needs a keyframe; :attr:`RobotScreen.on_keyframe` passes it on to the user's sender.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any, assert_never

from aiohttp import web

from telebot.apps.web.media_relay import pack_media
from telebot.apps.web.messages import SCREEN_PAGE, Keyframe, PageMessageError, parse_page_message
from telebot.apps.web.pageserver import PageServer
from telebot.config import ScreenSettings
from telebot.services.media.wire import CODEC_H264, CODEC_JPEG, CODEC_NAMES, CODEC_VP8

if TYPE_CHECKING:
    from telebot.services.media.robot import CallState, RobotMedia
    from telebot.services.media.wire import AudioPacket
    from telebot.services.video.wire import CompleteFrame

__all__ = ["RobotScreen", "bind_screen", "parse_screen_option", "robot_screen"]

log = logging.getLogger(__name__)

#: Media messages a page may have in flight before audio is dropped (video: one at a time).
MAX_AUDIO_IN_FLIGHT = 8
#: What the screen page decodes (WebCodecs; JPEG as the browser's image decoder does).
SCREEN_CODECS = (CODEC_H264, CODEC_VP8, CODEC_JPEG)


class _Page:
    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.frame: asyncio.Task[None] | None = None
        self.audio: set[asyncio.Task[None]] = set()
        self.frames_skipped = 0


class RobotScreen(PageServer):
    """Serves the robot's screen page: ``async with RobotScreen(port=8090) as screen: ...``.

    Feed it with :meth:`show_state`, :meth:`video` and :meth:`audio` (encoded, as they came
    from the user); ``on_keyframe`` is called when a page needs a keyframe. ``port`` 0 picks
    a free port (see :attr:`url`).
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 8090) -> None:
        super().__init__(
            host=host, port=port, owner="screen page", expected=(ConnectionError, RuntimeError)
        )
        self.pages: set[_Page] = set()
        #: Called when a page asks for a keyframe of the user's video.
        self.on_keyframe: Callable[[], None] = lambda: None
        self.state: dict[str, Any] = {
            "type": "state",
            "user": "",
            "text": "",
            "call": False,
            "video": False,
        }
        self.frames_sent = 0

    def routes(self, router: web.UrlDispatcher) -> None:
        """The screen page and its websocket."""
        router.add_get("/", self._index)
        router.add_get("/ws", self._websocket)

    async def start(self) -> None:
        """Serve the page (OSError if the address is taken)."""
        await self.serve()
        log.info("robot screen at %s", self.url)

    async def close(self) -> None:
        """Close the pages and the server; idempotent."""
        for page in list(self.pages):
            with contextlib.suppress(Exception):
                await page.ws.close()
        await self.stop_serving()

    # -- what the page shows ----------------------------------------------------------

    def show_state(self, user: str, text: str, *, call: bool, video: bool = False) -> None:
        """The call state line: ``user`` on the line (or ""), ``text`` for people; ``video``:
        whether the user's camera is coming (else the page says it is off)."""
        state = {"type": "state", "user": user, "text": text, "call": call, "video": video}
        if state == self.state:
            return
        self.state = state
        self.send_all([page.ws for page in self.pages], state)

    def video(self, codec: str, key: bool, frame_id: int, capture_time: float, data: bytes) -> None:
        """One encoded picture of the user's camera (H.264 Annex B, VP8 or JPEG)."""
        header = {
            "kind": "video",
            "codec": codec,
            "key": key,
            "frame_id": frame_id,
            "capture_time": capture_time,
        }
        message = pack_media(header, data)
        for page in list(self.pages):
            if page.ws.closed:
                continue
            if page.frame is not None and not page.frame.done():
                # A slow page skips a frame, never queues: it sees the gap and asks for a
                # keyframe (a delta after a skipped frame would not decode right).
                page.frames_skipped += 1
                continue
            page.frame = self._tasks.spawn(page.ws.send_bytes(message))
            self.frames_sent += 1

    def audio(self, seq: int, capture_time: float, data: bytes) -> None:
        """One Opus packet of the user's microphone."""
        message = pack_media({"kind": "audio", "seq": seq, "capture_time": capture_time}, data)
        for page in list(self.pages):
            if page.ws.closed or len(page.audio) >= MAX_AUDIO_IN_FLIGHT:
                continue
            task = self._tasks.spawn(page.ws.send_bytes(message))
            page.audio.add(task)
            task.add_done_callback(page.audio.discard)

    # -- HTTP -------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return self.html("screen.html")

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        ws = await self.accept(request, heartbeat=2.0, max_msg_size=1 << 12)
        page = _Page(ws)
        self.pages.add(page)
        try:
            await ws.send_str(json.dumps(self.state))
            async for data in self.received(ws):
                if isinstance(data, str):
                    self._on_message(data)
        finally:
            self.pages.discard(page)
        return ws

    def _on_message(self, text: str) -> None:
        try:
            msg = parse_page_message(text, SCREEN_PAGE)
        except PageMessageError as exc:
            # The page is the robot's own: a bad message is a bug to log, never an answer.
            log.debug("screen page message ignored: %s", exc)
            return
        match msg:
            case Keyframe():
                try:
                    self.on_keyframe()
                except Exception:
                    log.exception("keyframe request failed")
            case _:
                assert_never(msg)


def parse_screen_option(text: str, settings: ScreenSettings) -> ScreenSettings:
    """``--screen``: ``off``, ``HOST:PORT``, ``:PORT`` or ``PORT`` (ValueError if neither)."""
    if text.strip().lower() == "off":
        return settings.model_copy(update={"enabled": False})
    host, sep, port_text = text.strip().rpartition(":")
    if not sep:
        host = settings.host
    host = host.strip("[]") or settings.host
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"expected HOST:PORT or off, got {text!r}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"port must be 0..65535, got {port}")
    return ScreenSettings(enabled=True, host=host, port=port)


@contextlib.asynccontextmanager
async def robot_screen(
    settings: ScreenSettings, media: RobotMedia | None
) -> AsyncIterator[RobotScreen | None]:
    """The robot's screen as ``[screen]`` says, fed from ``media``; None when off.

    A taken port is logged as a warning and the robot runs on without a screen: a display
    is a comfort, never a reason for the robot not to answer calls.
    """
    if not settings.enabled:
        yield None
        return
    screen = RobotScreen(host=settings.host, port=settings.port)
    try:
        await screen.start()
    except OSError as exc:
        log.warning("robot screen not served at %s: %s", screen.url, exc.strerror or exc)
        yield None
        return
    try:
        unbind = bind_screen(screen, media) if media is not None else (lambda: None)
        try:
            yield screen
        finally:
            unbind()
    finally:
        await screen.close()


def bind_screen(screen: RobotScreen, media: RobotMedia) -> Callable[[], None]:
    """Feed ``screen`` from the robot's media: the user's encoded video and voice and the
    call state; the screen's keyframe requests go to the user. Returns the unbinding."""

    def on_video(frame: CompleteFrame) -> None:
        codec = CODEC_NAMES.get(frame.codec, "")
        screen.video(codec, frame.keyframe, frame.frame_id, frame.capture_time, frame.data)

    def on_audio(packet: AudioPacket) -> None:
        screen.audio(packet.seq, packet.capture_time, packet.data)

    def on_state(state: CallState) -> None:
        screen.show_state(
            state.user or "", state.text, call=state.user is not None, video=state.video
        )

    screen.on_keyframe = media.request_keyframe
    return media.subscribe(
        on_video=on_video, on_audio=on_audio, on_state=on_state, codecs=SCREEN_CODECS
    )
