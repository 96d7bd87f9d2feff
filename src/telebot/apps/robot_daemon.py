"""``telebot-robot run``: the robot daemon.

Starts the robot adapter that ``[robot] kind`` names (``"sim"``: the simulated robot on
its map; see :mod:`telebot.robot`), opens the transport (zenoh peer by default), answers
calls from the contacts and serves chat, map, pose, goals and telemetry on each.
On SIGINT / SIGTERM it stops the robot first, then hangs up its calls, then exits.
"""

from __future__ import annotations

import asyncio
import logging
import math
from pathlib import Path

from telebot.apps.common import stop_on_signals
from telebot.apps.web.screen import robot_screen
from telebot.channels.call import RobotEndpoint
from telebot.channels.transports import create_transport
from telebot.config import RobotConfig
from telebot.errors import RobotError
from telebot.gateway.robot import robot_gateway
from telebot.identity import ContactBook, Identity
from telebot.robot import create_robot
from telebot.services.base import ServiceConfig
from telebot.services.media.robot import RobotMedia
from telebot.services.recording import Recorder
from telebot.services.registry import robot_services
from telebot.services.robot import EventSink, RobotServer, robot_video_settings
from telebot.services.safety.robot import SafetyDriver

__all__ = ["SHUTDOWN_REASON", "deadman_time", "serve_robot"]

log = logging.getLogger(__name__)

SHUTDOWN_REASON = "robot shutting down"


def deadman_time(config: RobotConfig) -> float:
    """How long the driver may be silent before the robot stops.

    The driver's last heartbeat may have left up to one heartbeat interval before its
    link died, so the deadman fires that much before ``call.timeout``: the robot is then
    stopped within ``call.timeout`` of the moment the driver went silent, not of its last
    heartbeat. Never less than half the timeout, so a few lost heartbeats do not stop it.
    """
    timeout = config.call.timeout
    return max(timeout - 1.0 / config.call.heartbeat_hz, timeout / 2)


def _recorder(config: RobotConfig, audit: Path, home: Path | None) -> Recorder | None:
    """The call recorder ``[recording]`` asks for (files beside the audit log by default)."""
    settings = config.recording
    if not settings.enabled:
        return None
    directory = settings.dir if settings.dir is not None else audit.parent
    if not directory.is_absolute() and home is not None:
        directory = home / directory
    log.info("recording every call into %s", directory)
    return Recorder(
        directory,
        max_bytes=settings.max_bytes,
        max_seconds=settings.max_seconds,
        keep=settings.keep,
        keep_bytes=settings.keep_bytes,
        streams=settings.streams,
    )


async def serve_robot(
    config: RobotConfig,
    identity: Identity,
    contacts: ContactBook,
    *,
    base_dir: Path | None = None,
    home: Path | None = None,
    emit: EventSink | None = None,
    stop: asyncio.Event | None = None,
) -> None:
    """Run the robot until ``stop`` is set or SIGINT / SIGTERM arrives.

    The robot is the adapter ``config.robot.kind`` names; its top speed (the safety
    supervisor's hard cap) is the speed cap it reports when created. Relative paths in the
    config (``sim.map``, ``sim.places``) are taken from ``base_dir`` (the config file's
    folder); relative audit log and recording paths from ``home`` (the robot's home). With
    ``[recording] enabled``, every call is recorded as MCAP (:mod:`telebot.services.recording`).
    The robot starts
    stopped and disarmed: a driver must re-arm it (``arm``).
    """
    emit = emit if emit is not None else (lambda event: None)
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    nav = await asyncio.to_thread(create_robot, config, base_dir=base_dir, now=loop.time())
    recorder: Recorder | None = None
    try:
        # Read before the supervisor's start-up stop sets the cap to zero.
        max_speed = nav.speed_limit
        if not (isinstance(max_speed, int | float) and math.isfinite(max_speed) and max_speed > 0):
            raise RobotError(
                f"robot {config.robot.kind!r} reports a top speed of {max_speed!r} m/s"
            )
        # The adapter says how fast its control loop runs, what its map is called and
        # whether it is simulated (video frames are then stamped unless [media] says).
        control_hz = nav.control_hz
        if not (
            isinstance(control_hz, int | float) and math.isfinite(control_hz) and control_hz > 0
        ):
            raise RobotError(
                f"robot {config.robot.kind!r} reports a control rate of {control_hz!r} Hz"
            )
        simulated = nav.simulated
        map_label = nav.map_name
        audit = config.safety.audit_log
        if not audit.is_absolute() and home is not None:
            audit = home / audit
        safety = SafetyDriver(
            nav,
            timeout=deadman_time(config),
            max_speed=max_speed,
            usercam_while_moving=config.safety.usercam_while_moving,
            stale_video=config.safety.stale_video,
            audit_path=audit,
        )
        recorder = _recorder(config, audit, home)
        services = robot_services()
        if recorder is not None:
            services.register("recording", recorder.service)
            safety.on_audit = recorder.audit
            recorder.start()
        with safety:  # from here on the watchdog runs, and the audit log is closed at the end
            server = RobotServer(
                nav,
                config.services,
                control_hz=control_hz,
                map_name=map_label,
                emit=emit,
                safety=safety,
                services=services,
                config=ServiceConfig(
                    video=robot_video_settings(config.video, config.media, simulated=simulated),
                    media=config.media,
                    relay=config.relay,
                    people=config.people,
                    follow=config.follow,
                    drive=config.drive,
                ),
            )
            # The robot's screen shows the user the media service hears and sees.
            media = server.service("media")
            await server.prepare()
            with stop_on_signals(stop):
                async with (
                    robot_screen(config.screen, media if isinstance(media, RobotMedia) else None),
                    create_transport(config.transport) as transport,
                    RobotEndpoint(
                        transport,
                        identity,
                        contacts,
                        settings=config.call,
                        namespace=config.namespace,
                    ) as endpoint,
                    # After the endpoint: a browser's first HELLO finds the robot listening.
                    robot_gateway(
                        config.gateway,
                        transport,
                        contacts,
                        home if home is not None else Path.cwd(),
                        config.namespace,
                    ),
                ):
                    server.attach(endpoint)
                    runner = asyncio.create_task(server.run(), name="robot-loop")
                    pose = nav.pose().pose
                    log.info(
                        "robot %s ready on map %s at (%.2f, %.2f)",
                        identity.name,
                        map_label,
                        pose.x,
                        pose.y,
                    )
                    emit(
                        {
                            "event": "ready",
                            "robot": identity.name,
                            "map": map_label,
                            "kind": config.robot.kind,
                            "places": sorted(nav.places()),
                        }
                    )
                    try:
                        stopped = asyncio.create_task(stop.wait())
                        done, _ = await asyncio.wait(
                            {runner, stopped}, return_when=asyncio.FIRST_COMPLETED
                        )
                        if runner in done:
                            runner.result()  # a crashed loop is an error, not a quiet exit
                    finally:
                        # Fail safe order: the robot stops before anything else happens, its loop
                        # ends, and the calls are hung up before the event loop runs again (close
                        # hangs up before its first await and takes no new call), so no driver
                        # can re-arm it in between.
                        safety.stop(None, SHUTDOWN_REASON)
                        runner.cancel()
                        stopped.cancel()
                        emit({"event": "stopping", "calls": len(endpoint.calls)})
                        await endpoint.close(SHUTDOWN_REASON)
                        # The loop's end closed the robot's services (the media's devices).
                        await asyncio.gather(runner, stopped, return_exceptions=True)
    finally:
        if recorder is not None:  # after the calls ended: their ends are in the file
            await asyncio.to_thread(recorder.close)
        # An adapter holding a connection (the ROS 2 robot's node) lets go of it last,
        # after the stop above has reached the base.
        await asyncio.to_thread(nav.close)
