"""Two-way media over real calls on the memory transport: the robot's H.264 video with
stamped frame numbers, its 440 Hz microphone, the user's camera and ~1 kHz microphone, the
robot's sink and screen API, loss and recovery at keyframes, and a stop under a 2 Mbit/s
cap. Plus the PyAV codecs, the audio sources and sinks, and the voice."""

from __future__ import annotations

import asyncio
import contextlib
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import ROBOT, Homes, memory_endpoints, wait_until
from telebot.channels.call import Call
from telebot.channels.transports.memory import MemoryHub
from telebot.config import MediaConfig, ServiceSettings, SimSettings
from telebot.errors import ProtocolError
from telebot.robot.sim.stack import SimNavStack
from telebot.services.base import ServiceConfig
from telebot.services.client import RobotClient
from telebot.services.codecs import (
    OpusDecoder,
    OpusEncoder,
    VideoDecoder,
    VideoEncoder,
    read_number,
    stamp_number,
)
from telebot.services.media import audio as audio_mod
from telebot.services.media.audio import (
    MemorySink,
    ToneSource,
    WavSink,
    WavSource,
    dominant_frequency,
    open_sink,
    open_source,
)
from telebot.services.media.robot import CallState, RobotMedia, Voice
from telebot.services.media.stream import AudioBlock
from telebot.services.media.user import TestPattern
from telebot.services.media.wire import CODEC_H264, CODEC_JPEG, CODEC_VP8, SAMPLE_RATE
from telebot.services.robot import RobotServer
from telebot.services.video.receiver import VideoFrame
from telebot.services.video.wire import CompleteFrame, VideoSettings

FAST = SimSettings(map="small", camera_width=320, camera_height=240, control_hz=50)


def textured(width: int = 320, height: int = 240, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (height // 8, width // 8, 3), dtype=np.uint8)
    return np.kron(small, np.ones((8, 8, 1), dtype=np.uint8))


# --------------------------------------------------------------------------- codecs


@pytest.mark.parametrize("codec", [CODEC_H264, CODEC_VP8, CODEC_JPEG])
def test_encoded_frames_decode_with_their_stamped_numbers(codec: int) -> None:
    encoder, decoder = VideoEncoder(codec), VideoDecoder()
    base = textured()
    for n in range(1, 8):
        frame = encoder.encode(stamp_number(np.roll(base, n, axis=1), n), bitrate=600_000)
        assert frame.keyframe == (n == 1 or codec == CODEC_JPEG)
        image = decoder.decode(frame.data, frame.codec)
        assert image.shape == (240, 320, 3) and read_number(image) == n
    forced = encoder.encode(base, keyframe=True, bitrate=600_000)
    assert forced.keyframe
    if codec == CODEC_H264:  # Annex B, SPS and PPS ahead of the IDR slice
        assert forced.data.startswith(b"\x00\x00\x00\x01") and forced.data[4] & 0x1F == 7


def test_a_corrupt_frame_raises_protocol_error_and_the_next_keyframe_decodes() -> None:
    encoder, decoder = VideoEncoder(CODEC_H264), VideoDecoder()
    frame = encoder.encode(textured(), bitrate=600_000)
    for garbage in (b"\x00\x00\x00\x01\x65" + bytes(range(256)) * 4, b"\xff" * 10, b""):
        with pytest.raises(ProtocolError):
            decoder.decode(garbage, CODEC_H264)
    with pytest.raises(ProtocolError, match="codec 9"):
        decoder.decode(frame.data, 9)
    key = encoder.encode(textured(seed=1), keyframe=True, bitrate=600_000)
    assert decoder.decode(key.data, CODEC_H264).shape == (240, 320, 3)
    assert decoder.errors == 4


def test_keyframes_are_capped_to_about_two_datagrams() -> None:
    encoder = VideoEncoder(CODEC_H264)
    noisy = np.random.default_rng(3).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    sizes = [
        len(encoder.encode(noisy, keyframe=True, bitrate=1_000_000, now=i).data) for i in range(3)
    ]
    assert max(sizes[1:]) <= 2 * 32768, sizes


def test_opus_carries_a_tone_and_conceals_a_lost_packet() -> None:
    encoder, decoder = OpusEncoder(), OpusDecoder()
    tone = ToneSource(440)
    heard = [decoder.decode(encoder.encode(tone.read())) for _ in range(50)]
    assert abs(dominant_frequency(np.concatenate(heard)[4800:]) - 440) < 10
    assert decoder.decode(None).shape == (960,)
    with pytest.raises(ProtocolError):
        decoder.decode(b"\xff\xff\xff\xff\xff")
    assert decoder.decode(encoder.encode(tone.read())).shape == (960,)  # still works


def test_audio_sources_and_sinks(tmp_path: Path) -> None:
    path = tmp_path / "tone.wav"
    sink = open_sink(f"wav:{path}")
    tone = open_source("tone:1000")
    for _ in range(25):
        sink.write(tone.read())
    sink.close()
    source = WavSource(path)
    assert abs(dominant_frequency(np.concatenate([source.read() for _ in range(25)])) - 1000) < 10
    memory = open_sink("memory")
    assert isinstance(memory, MemorySink)
    memory.write(np.ones(960, dtype=np.int16))
    assert memory.total == 960
    for bad in ("tone:0", "mp3:x", "wav:"):
        with pytest.raises(ValueError, match="audio source"):
            open_source(bad)
    with pytest.raises(ValueError, match="cannot read WAV"):
        WavSource(tmp_path / "missing.wav")
    WavSink(tmp_path / "x.wav").close()


def test_a_missing_sounddevice_is_a_clear_one_line_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "sounddevice", None)  # import fails
    with pytest.raises(RuntimeError, match=r"telebot\[audio\]") as info:
        audio_mod.open_source("default")
    assert "\n" not in str(info.value)


def test_a_missing_synthesiser_is_a_one_line_error() -> None:
    voice = Voice(("no-such-espeak-binary",))
    assert voice.error is not None and "not installed" in voice.error and "\n" not in voice.error
    with pytest.raises(RuntimeError, match="not installed"):
        voice.synthesise("hello")


# A stand-in for espeak-ng: writes a 22,050 Hz WAV of a 700 Hz tone to stdout.
FAKE_ESPEAK = (
    sys.executable,
    "-c",
    "import io,sys,wave,math,struct;b=io.BytesIO();w=wave.open(b,'wb');w.setnchannels(1);"
    "w.setsampwidth(2);w.setframerate(22050);"
    "w.writeframes(b''.join(struct.pack('<h',int(9000*math.sin(2*math.pi*700*i/22050)))"
    " for i in range(22050)));w.close();sys.stdout.buffer.write(b.getvalue())",
)


# --------------------------------------------------------------------------- calls


@dataclass
class Rig:
    nav: SimNavStack
    server: RobotServer
    media: RobotMedia
    speaker: MemorySink
    client: RobotClient
    hub: MemoryHub


@contextlib.asynccontextmanager
async def media_call(homes: Homes, *, voice: str = "off") -> AsyncIterator[Rig]:
    """A simulated robot with H.264 video (stamped), a 440 Hz mic and a memory speaker, in a
    call with a user who sends a test pattern and a 1 kHz tone."""
    loop = asyncio.get_running_loop()
    nav = SimNavStack.from_settings(FAST, now=loop.time())
    video = VideoSettings(
        width=320, height=240, codecs=(CODEC_H264, CODEC_JPEG), stamp=True, max_fps=20
    )
    # The robot's media is its registered service, set up by its [media] section.
    settings = MediaConfig(
        mic="tone:440", speaker="memory", voice=voice, voice_command=list(FAKE_ESPEAK)
    )
    server = RobotServer(
        nav,
        ServiceSettings(),
        control_hz=50,
        map_name="small",
        config=ServiceConfig(video=video, media=settings),
    )
    media, speaker = robot_media(server)
    await server.prepare()
    hub = MemoryHub(seed=7)
    async with memory_endpoints(homes, hub) as (robot_endpoint, user_endpoint):
        server.attach(robot_endpoint)
        runner = asyncio.create_task(server.run(), name="robot-loop")
        client = RobotClient(await user_endpoint.call(ROBOT))
        client.talk(mic="tone:1000", camera=TestPattern(320, 240))
        try:
            yield Rig(nav, server, media, speaker, client, hub)
        finally:
            client.talk()
            with contextlib.suppress(Exception):
                await client.call.hangup()
            await client.aclose()
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)  # closes the media
    await asyncio.sleep(0.05)


def robot_media(server: RobotServer) -> tuple[RobotMedia, MemorySink]:
    """The robot's media service and its speaker (``[media] speaker = "memory"``)."""
    media = server.service("media")
    assert isinstance(media, RobotMedia) and isinstance(media.speaker, MemorySink)
    return media, media.speaker


async def collect_audio(client: RobotClient, seconds: float) -> list[AudioBlock]:
    blocks: list[AudioBlock] = []
    async with client.audio() as audio:
        async for block in audio:
            blocks.append(block)
            if len(blocks) >= seconds * 50:
                break
    return blocks


async def test_a_two_way_call_carries_video_and_voice_both_ways(homes: Homes) -> None:
    states: list[CallState] = []
    async with media_call(homes) as rig:
        encoded: list[CompleteFrame] = []
        unsubscribe = rig.media.subscribe(on_video=encoded.append, on_state=states.append)
        async with rig.client.video() as video:
            got: list[VideoFrame] = [await video.next_frame(10) for _ in range(15)]
        blocks = await collect_audio(rig.client, 1.0)
        await wait_until(lambda: rig.speaker.total >= SAMPLE_RATE and len(encoded) >= 5)
        unsubscribe()
        heard_by_robot = rig.speaker.samples(0.5)
        decoded_by_robot = rig.media.user_frames_decoded
        final_state = rig.media.state
    # The user decodes H.264, the robot's stamped numbers are the frame ids, in order.
    assert {f.codec for f in got} == {CODEC_H264}
    assert [read_number(f.image) for f in got] == [f.frame_id for f in got]
    assert [f.frame_id for f in got] == sorted({f.frame_id for f in got})
    # The user hears 440 Hz; the robot's speaker hears the user's 1 kHz tone.
    samples = np.concatenate([b.samples for b in blocks])[-SAMPLE_RATE // 2 :]
    assert abs(dominant_frequency(samples) - 440) < 15
    assert abs(dominant_frequency(heard_by_robot) - 1000) < 15
    # The robot decodes the user's camera; the screen gets its frames still encoded.
    assert decoded_by_robot >= 5 and rig.media.user_picture is not None
    assert encoded[0].keyframe and {f.codec for f in encoded} <= {CODEC_VP8, CODEC_H264}
    assert states[0].text.startswith("connecting") and final_state.user == "alice"
    assert final_state.video and final_state.audio and "alice is" in final_state.text


async def test_with_10_percent_loss_video_recovers_at_keyframes(homes: Homes) -> None:
    async with media_call(homes) as rig:
        for a, b in (("robot", "user"), ("user", "robot")):
            rig.hub.link(a, b).loss = 0.1
        sender = rig.server.video_of(rig.client.call.id)
        assert sender is not None
        async with rig.client.video() as video:
            got = [await video.next_frame(10) for _ in range(40)]
        await wait_until(lambda: rig.media.user_frames_decoded >= 10)
    # Frames were lost: the user skipped deltas, asked for keyframes, and the robot forced
    # them (paced); every picture decoded is the frame it claims to be (none was decoded
    # off a broken reference) and the stream went on after each loss.
    assert video.gate.waits >= 1 and video.gate.skipped >= 1
    assert video.requests.sent >= 1 and sender.pacer.forced >= 1
    assert all(read_number(f.image) == f.frame_id for f in got)
    ids = [f.frame_id for f in got]
    assert ids == sorted(set(ids))
    assert rig.media.user_frames_corrupt == 0


async def test_a_stop_is_not_held_up_by_media_on_a_2_mbit_link(homes: Homes) -> None:
    async with media_call(homes) as rig:
        for a, b in (("robot", "user"), ("user", "robot")):
            rig.hub.link(a, b).bandwidth = 250_000  # 2 Mbit/s
        async with rig.client.video() as video:
            await video.next_frame(10)
            blocks_task = asyncio.create_task(collect_audio(rig.client, 1.0))
            await wait_until(lambda: rig.media.user_frames_decoded >= 5)
            times = []
            for _ in range(5):
                started = time.perf_counter()
                ack = await rig.client.stop(timeout=5.0)
                times.append(time.perf_counter() - started)
                assert ack.ok
            await video.next_frame(10)  # video still flows
            await blocks_task
    assert max(times) < 1.0, times


async def test_the_robot_speaks_its_chat_replies_into_the_users_audio(homes: Homes) -> None:
    async with media_call(homes, voice="user") as rig, rig.client.audio() as audio:
        reply = await rig.client.chat("where are you")
        assert reply.final_text
        await wait_until(lambda: rig.media.spoken >= 1)
        heard = []
        async for block in audio:
            heard.append(block.samples)
            if len(heard) >= 40:
                break
    # The fake synthesiser's 700 Hz is mixed over the 440 Hz microphone.
    spectrum = np.abs(np.fft.rfft(np.concatenate(heard).astype(float)))
    freqs = np.fft.rfftfreq(len(np.concatenate(heard)), 1 / SAMPLE_RATE)
    near_700 = spectrum[(freqs > 680) & (freqs < 720)].max()
    assert near_700 > 0.1 * spectrum.max()


async def test_talk_with_a_missing_wav_file_is_a_usage_error(tmp_path: Path) -> None:
    import io

    from telebot.apps.talk_cli import talk
    from telebot.config import AppConfig

    err = io.StringIO()
    code = await talk(
        "guiabot", home=tmp_path, config=AppConfig(), mic=str(tmp_path / "nope.wav"), stream=err
    )
    assert code == 2 and "cannot read WAV file" in err.getvalue()
    assert err.getvalue().count("\n") == 1


async def test_garbage_on_the_media_channels_is_dropped_and_counted(homes: Homes) -> None:
    from telebot.channels.transports.base import Lane
    from telebot.services.media.wire import USER_AUDIO, USER_VIDEO
    from telebot.services.video.wire import fragment

    async with media_call(homes) as rig:
        await wait_until(lambda: rig.media.user_frames_decoded >= 2 and rig.speaker.total > 0)
        call = rig.client.call
        junk_video = [
            b"\x01",
            "text",
            b"\x01\x83" + bytes(40),
            *fragment(10**6, "user", 1.0, b"\x00\x00\x00\x01\x65" + bytes(500), codec=CODEC_H264),
            *fragment(2, "user", 1.0, b"not a vp8 frame", codec=CODEC_VP8, keyframe=True),
            *fragment(3, "user", 1.0, b"x", codec=0x55),
        ]
        for payload in junk_video:
            call.channel(USER_VIDEO, lane=Lane.BULK).send(payload)
        for payload in (b"\x03\x10", b"\x03\x10" + bytes(12) + b"\xff\xff\xff", "x", b"\x02" * 5):
            call.channel(USER_AUDIO, lane=Lane.BULK).send(payload)
        decoded = rig.media.user_frames_decoded
        heard = rig.speaker.total
        # The call goes on: more user frames decoded and more voice heard after the junk.
        await wait_until(
            lambda: rig.media.user_frames_decoded >= decoded + 5 and rig.speaker.total > heard
        )
        service = rig.media.user_video._service
        assert service is not None
        stats = service.reassembler.stats
        assert stats.malformed >= 3  # short, text, unknown codec
        assert stats.absurd + stats.late + stats.malformed >= 4
        [robot_side] = rig.media._calls.values()
        audio_stats = robot_side.audio_in.sequencer.stats
        assert audio_stats.malformed + audio_stats.late >= 3
        assert rig.client.call.active


async def test_the_robot_asks_for_the_users_media_only_once_it_came(homes: Homes) -> None:
    """A call that sends no media gets no reports on video/user and audio/user (§25); once
    the call sends voice or pictures, the robot reports on that stream (and only on it)."""
    from telebot.channels.channel import ReceivedDatagram
    from telebot.channels.transports.base import Lane
    from telebot.services.media.wire import USER_AUDIO, USER_VIDEO, encode_audio
    from telebot.services.video.wire import encode_jpeg, fragment

    loop = asyncio.get_running_loop()
    nav = SimNavStack.from_settings(FAST, now=loop.time())
    settings = MediaConfig(voice="off", speaker="memory")
    server = RobotServer(
        nav,
        ServiceSettings(),
        control_hz=50,
        map_name="small",
        config=ServiceConfig(media=settings),
    )
    media, _ = robot_media(server)
    await server.prepare()
    reports: dict[str, list[bytes]] = {USER_VIDEO: [], USER_AUDIO: []}
    async with memory_endpoints(homes, MemoryHub(seed=3)) as (robot_endpoint, user_endpoint):
        server.attach(robot_endpoint)
        runner = asyncio.create_task(server.run(), name="robot-loop")
        try:
            call = await user_endpoint.call(ROBOT)  # a bare call: no media service, no media
            channels = {name: call.channel(name, lane=Lane.BULK) for name in reports}
            for name, channel in channels.items():

                def on_datagram(datagram: ReceivedDatagram, into: list[bytes] = reports[name]):
                    into.append(datagram.payload)

                channel.set_callback(on_datagram)
            await wait_until(lambda: len(media._calls) == 1)
            await asyncio.sleep(1.0)  # five report intervals: a window to count in
            assert reports == {USER_VIDEO: [], USER_AUDIO: []}
            # Voice comes: the robot asks for more of it, still not for pictures.
            opus = OpusEncoder().encode(np.zeros(960, dtype=np.int16))
            for seq in range(3):
                channels[USER_AUDIO].send(encode_audio(seq, time.time(), opus))
            await wait_until(lambda: len(reports[USER_AUDIO]) >= 3)
            assert reports[USER_VIDEO] == []
            picture = encode_jpeg(np.zeros((48, 64, 3), dtype=np.uint8), 80)
            for datagram in fragment(0, "user", time.time(), picture, codec=CODEC_JPEG):
                channels[USER_VIDEO].send(datagram)
            await wait_until(lambda: len(reports[USER_VIDEO]) >= 3)
            await wait_until(lambda: media.user_frames_decoded >= 1)
            assert call.active
            await call.hangup()
        finally:
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)


async def test_the_users_media_stops_unasked_after_the_probe(homes: Homes) -> None:
    """Against a robot that never asks (no §25 media service), the user's camera and
    microphone go out for the probe time only, then stop; the call goes on."""
    from telebot.channels.channel import ReceivedDatagram
    from telebot.channels.transports.base import Lane
    from telebot.services.media.wire import USER_AUDIO, USER_MEDIA_PROBE, USER_VIDEO

    got: dict[str, list[float]] = {USER_VIDEO: [], USER_AUDIO: []}
    async with memory_endpoints(homes, MemoryHub(seed=4)) as (robot_endpoint, user_endpoint):

        def on_call(robot_call: Call) -> None:
            for name, into in got.items():

                def on_datagram(datagram: ReceivedDatagram, into: list[float] = into) -> None:
                    into.append(loop.time())

                robot_call.channel(name, lane=Lane.BULK).set_callback(on_datagram)

        loop = asyncio.get_running_loop()
        robot_endpoint.on_call = on_call
        client = RobotClient(await user_endpoint.call(ROBOT))
        try:
            client.talk(mic="tone:1000", camera=TestPattern(160, 120))
            await wait_until(lambda: len(got[USER_VIDEO]) > 2 and len(got[USER_AUDIO]) > 2)
            await asyncio.sleep(USER_MEDIA_PROBE)

            async def quiet() -> bool:
                """Whether nothing more comes for a second, within 20 s."""
                for _ in range(20):
                    counts = {name: len(times) for name, times in got.items()}
                    await asyncio.sleep(1.0)  # a window to count in
                    if {name: len(times) for name, times in got.items()} == counts:
                        return True
                return False

            assert await quiet(), {name: len(times) for name, times in got.items()}
            assert client.call.active
        finally:
            client.talk()
            with contextlib.suppress(Exception):
                await client.call.hangup()
            await client.aclose()
