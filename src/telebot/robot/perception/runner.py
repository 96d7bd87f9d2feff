"""``PeoplePerception``: leg detection, the HOG camera detector and the tracker run on a robot.

This is the robot-side driver of the sans-IO pieces: :meth:`PeoplePerception.step` (called
from the robot's control loop with loop time) reads the NavStack's latest laser scan (an
adapter with a laser: :class:`~telebot.robot.nav.LaserSource`) at ``scan_hz`` and a camera
frame at ``camera_hz``. Leg candidates are put in the map frame with the robot's pose, those
on the map's walls dropped (a door jamb is as narrow as a leg), and the rest handed to the
:class:`~telebot.robot.perception.tracker.PeopleTracker`.

HOG takes tens of milliseconds a frame, longer than a control cycle may, so with
``threaded=True`` (the daemon) it runs on one worker thread, off the event loop (OpenCV
releases the GIL): a frame is handed over when the previous one is done and its people are
collected at a later step. It looks only when the laser has a candidate in front of the
camera (the camera confirms; in an empty corridor it costs nothing). Tests and benchmarks pass ``threaded=False`` and get the same
results synchronously.

It is a :class:`~telebot.robot.perception.tracks.PeopleSource` (follow-me reads it) and keeps
the alerts it raises (:attr:`alerts`, numbered) for the ``people`` service to send.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from telebot.config import PeopleSettings
from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import LaserScanLike, LaserSource, NavStack, Pose2D, normalize_angle
from telebot.robot.perception.alerts import AlertWatcher, PeopleAlert
from telebot.robot.perception.camera import CameraDetection, HogPeopleDetector
from telebot.robot.perception.legs import LegDetector
from telebot.robot.perception.tracker import Measurement, PeopleTracker
from telebot.robot.perception.tracks import PersonTrack

__all__ = ["STATIC_CLEARANCE", "NumberedAlert", "PeoplePerception", "StaticMap"]

log = logging.getLogger(__name__)

#: Leg candidates this close (m) to a wall or unknown space of the map are the map's own.
STATIC_CLEARANCE = 0.1
#: The camera looks when a laser candidate is within this range (m) …
CAMERA_RANGE = 8.0
#: … and within its field of view widened by this much (radians) either side.
CAMERA_MARGIN = math.radians(5.0)
#: Alerts kept for the services to pick up.
KEPT_ALERTS = 32


@dataclass(frozen=True, slots=True)
class NumberedAlert:
    """An alert and its number (1, 2, …: services send the ones they have not sent)."""

    seq: int
    stamp: float
    alert: PeopleAlert


class StaticMap:
    """Whether a map-frame point is on the map's walls (or unknown space), with clearance."""

    def __init__(self, grid: OccupancyGrid, clearance: float = STATIC_CLEARANCE) -> None:
        solid = ((grid.data >= 50) | (grid.data < 0)).astype(np.uint8)
        reach = max(math.ceil(clearance / grid.resolution), 0)
        if reach:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
            solid = np.asarray(cv2.dilate(solid, kernel), dtype=np.uint8)
        self._solid: npt.NDArray[np.uint8] = solid
        self._grid = grid

    def __call__(self, x: float, y: float) -> bool:
        """True where ``(x, y)`` is within the clearance of a wall, or off the map."""
        row, col = self._grid.cell_of(x, y)
        if not (0 <= row < self._grid.height and 0 <= col < self._grid.width):
            return True
        return bool(self._solid[row, col])


class PeoplePerception:
    """Runs person detection and tracking on ``nav`` (see the module docstring)."""

    def __init__(
        self,
        nav: NavStack,
        settings: PeopleSettings | None = None,
        *,
        threaded: bool = True,
    ) -> None:
        self.nav = nav
        self.settings = settings = settings if settings is not None else PeopleSettings()
        self.legs = LegDetector()
        self.tracker = PeopleTracker()
        self.watcher = AlertWatcher(
            settings.alert_distance, settings.screen_distance, settings.screen_seconds
        )
        self._hog: HogPeopleDetector | None = None
        self._threaded = threaded
        self._pool: ThreadPoolExecutor | None = None
        self._pending: tuple[Future[list[CameraDetection]], Pose2D, float] | None = None
        self._next_scan = -math.inf
        self._next_frame = -math.inf
        self._last_scan: LaserScanLike | None = None
        self._static: StaticMap | None = None
        self._map_version: int | None = None
        self._alert_seq = 0
        #: The latest alerts, oldest first.
        self.alerts: deque[NumberedAlert] = deque(maxlen=KEPT_ALERTS)
        #: Camera detections of the last frame looked at (for the video overlay).
        self.last_camera: list[CameraDetection] = []
        self._camera_fov: float | None = None
        self._failed = False
        self._closed = False

    # ------------------------------------------------------------------ PeopleSource

    def tracks(self) -> list[PersonTrack]:
        """The confirmed tracks now."""
        return self.tracker.tracks()

    # ------------------------------------------------------------------ driving

    def step(self, now: float) -> None:
        """Look at new sensor data due at loop time ``now``; raise alerts."""
        if not self.settings.enabled or self._closed:
            return
        try:
            self._collect_frame(now)
            if now >= self._next_scan:
                self._next_scan = now + 1.0 / self.settings.scan_hz
                self._scan(now)
            camera_due = self.settings.camera_hz > 0 and now >= self._next_frame
            near = self._in_view() if camera_due and self._pending is None else []
            if near:
                self._next_frame = now + 1.0 / self.settings.camera_hz
                self._start_frame(now, near)
            self.tracker.tick(now)
            pose = self.nav.pose().pose
            for alert in self.watcher.update(now, pose, self.tracker.tracks()):
                self._alert_seq += 1
                self.alerts.append(NumberedAlert(self._alert_seq, now, alert))
                log.info("people alert: %s", alert.text)
        except Exception:
            # Perception informs; it must never take the control loop down. Say it once.
            if not self._failed:
                log.exception("people perception failed: no people are tracked")
            self._failed = True

    def close(self) -> None:
        """Stop the detector thread."""
        self._closed = True
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    # ------------------------------------------------------------------ laser

    def static_map(self) -> StaticMap:
        """The map's walls with clearance (rebuilt when the map changes)."""
        version = self.nav.map_version()
        if self._static is None or version != self._map_version:
            self._static = StaticMap(self.nav.map())
            self._map_version = version
        return self._static

    def _scan(self, now: float) -> None:
        if not isinstance(self.nav, LaserSource):
            return
        scan = self.nav.laser_scan()
        if scan is None or scan is self._last_scan:
            return
        self._last_scan = scan
        pose = self.nav.pose().pose
        self.tracker.update_laser(now, self.detect_scan(scan, pose))

    def detect_scan(self, scan: LaserScanLike, pose: Pose2D) -> list[Measurement]:
        """People in ``scan`` taken at ``pose``, in the map frame, off the map's walls."""
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        static = self.static_map()

        def on_map(x: float, y: float) -> bool:
            return static(pose.x + x * c - y * s, pose.y + x * s + y * c)

        found = self.legs.people(scan.angles, scan.ranges, scan.range_max, static=on_map)
        return [
            Measurement(pose.x + p.x * c - p.y * s, pose.y + p.x * s + p.y * c, p.confidence)
            for p in found
        ]

    # ------------------------------------------------------------------ camera

    def _detector(self) -> HogPeopleDetector:
        if self._hog is None:
            self._hog = HogPeopleDetector()
        return self._hog

    def _in_view(self) -> list[tuple[float, float]]:
        # HOG costs tens of milliseconds a frame: it looks only when the laser has a
        # candidate (tentative tracks too) in front of the camera, and only where it is.
        pose = self.nav.pose().pose
        fov = self._fov()
        if fov is None:
            return []
        half = math.radians(fov) / 2.0 + CAMERA_MARGIN
        near = []
        for x, y in self.tracker.candidates():
            dx, dy = x - pose.x, y - pose.y
            bearing = normalize_angle(math.atan2(dy, dx) - pose.yaw)
            distance = math.hypot(dx, dy)
            if abs(bearing) <= half and distance <= CAMERA_RANGE:
                near.append((bearing, distance))
        return near

    def _fov(self) -> float | None:
        if self._camera_fov is None:
            infos = {info.name: info.fov_deg for info in self.nav.cameras()}
            self._camera_fov = infos.get(self.settings.camera, math.nan)
        return None if math.isnan(self._camera_fov) else self._camera_fov

    def _start_frame(self, now: float, near: list[tuple[float, float]]) -> None:
        fov = self._fov()
        if fov is None:
            return
        frame = self.nav.get_frame(self.settings.camera)
        pose = self.nav.pose().pose
        detector = self._detector()
        if not self._threaded:
            self._camera_done(now, pose, detector.detect(frame.image, fov, near))
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="people-hog")
        future = self._pool.submit(detector.detect, frame.image, fov, near)
        self._pending = (future, pose, now)

    def _collect_frame(self, now: float) -> None:
        if self._pending is None:
            return
        future, pose, _taken = self._pending
        if not future.done():
            return
        self._pending = None
        try:
            detections = future.result()
        except Exception:
            log.exception("camera person detection failed")
            return
        self._camera_done(now, pose, detections)

    def _camera_done(self, now: float, pose: Pose2D, detections: list[CameraDetection]) -> None:
        self.last_camera = detections
        self.tracker.update_camera(now, pose.x, pose.y, pose.yaw, detections)
