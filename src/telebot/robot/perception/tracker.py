"""Multi-person tracker with laser and camera fusion (sans-IO).

Tracks live in the map frame. Each has a constant-velocity prediction corrected by an
alpha-beta filter (the steady state of a Kalman filter for that model), so positions are
smoothed and velocities estimated from them:

* **Association**: detections are matched to predicted tracks nearest first, within a gate
  that grows with the time since the track was last seen (a person can only have walked so
  far). A detection outside every gate starts a new *tentative* track; it is never pulled
  onto an existing one, so a detector's jump makes no track lunge.
* **Confirmation**: a track is published (:meth:`PeopleTracker.tracks`) after
  ``confirm_hits`` laser or camera hits; it is dropped after ``lost_after`` seconds unseen
  (tentative ones after ``tentative_lost_after``).
* **Limits**: speeds are capped at ``max_speed``; a correction larger than the gate is
  impossible by construction.
* **Fusion**: a camera detection is a bearing (precise) and a distance (rough). It is
  matched to the track nearest in bearing within ``camera_bearing_gate`` and a loose range
  ratio; it raises that track's confidence and marks it seen by the camera, and only nudges
  its position when the laser has not seen it lately (the laser measures range better).
  An unmatched camera detection starts a tentative track at its estimated position.

Garbage (non-finite numbers, time running backwards) is ignored, never raised: the
tracker runs on sensor data in the robot's control loop.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from telebot.robot.perception.camera import CameraDetection
from telebot.robot.perception.tracks import PersonTrack

__all__ = ["Measurement", "PeopleTracker", "TrackerParams"]


@dataclass(frozen=True, slots=True)
class TrackerParams:
    """Tuning of :class:`PeopleTracker` (metres, seconds)."""

    gate: float = 0.45
    max_speed: float = 2.5
    alpha: float = 0.5
    beta: float = 0.15
    confirm_hits: int = 3
    lost_after: float = 1.2
    max_coast: float = 0.4
    tentative_lost_after: float = 0.5
    merge_distance: float = 0.35
    camera_bearing_gate: float = math.radians(7.0)
    camera_range_ratio: float = 0.5
    camera_alpha: float = 0.2
    camera_recent: float = 2.0


@dataclass(frozen=True, slots=True)
class Measurement:
    """A laser person detection in the map frame."""

    x: float
    y: float
    confidence: float = 0.8


@dataclass(slots=True)
class _Track:
    id: int
    x: float
    y: float
    vx: float = 0.0
    vy: float = 0.0
    first_seen: float = 0.0
    last_seen: float = 0.0
    last_laser: float = -math.inf
    last_camera: float = -math.inf
    hits: int = 1
    quality: float = 0.5
    confirmed: bool = False
    updated_at: float = 0.0
    sources: set[str] = field(default_factory=set)


def _finite(*values: float) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


class PeopleTracker:
    """Tracks people from laser and camera detections (see the module docstring)."""

    def __init__(self, params: TrackerParams | None = None) -> None:
        self.params = params if params is not None else TrackerParams()
        self._tracks: list[_Track] = []
        self._next_id = 1
        self._now = -math.inf
        #: Detections ignored as garbage (non-finite, time going backwards).
        self.rejected = 0

    # ------------------------------------------------------------------ input

    def update_laser(self, now: float, detections: Iterable[Measurement]) -> None:
        """One scan's person detections (map frame) at loop time ``now``."""
        if not self._advance(now):
            return
        good = []
        for d in detections:
            if _finite(d.x, d.y, d.confidence):
                good.append(d)
            else:
                self.rejected += 1
        p = self.params
        pairs = []
        for ti, track in enumerate(self._tracks):
            px, py = self._predict(track, now)
            gate = p.gate + p.max_speed * min(now - track.last_seen, p.lost_after) * 0.5
            for di, d in enumerate(good):
                dist = math.hypot(d.x - px, d.y - py)
                if dist <= gate:
                    pairs.append((dist, ti, di))
        pairs.sort()
        used_t: set[int] = set()
        used_d: set[int] = set()
        for _, ti, di in pairs:
            if ti in used_t or di in used_d:
                continue
            used_t.add(ti)
            used_d.add(di)
            d = good[di]
            self._correct(self._tracks[ti], now, d.x, d.y, p.alpha, d.confidence)
            self._tracks[ti].last_laser = now
            self._tracks[ti].sources.add("laser")
        for di, d in enumerate(good):
            if di not in used_d:
                self._spawn(now, d.x, d.y, d.confidence, "laser")
        self._housekeep(now)

    def update_camera(
        self,
        now: float,
        robot_x: float,
        robot_y: float,
        robot_yaw: float,
        detections: Iterable[CameraDetection],
    ) -> None:
        """One frame's detections; bearings are relative to the robot at ``robot_*`` (map)."""
        if not _finite(robot_x, robot_y, robot_yaw) or not self._advance(now):
            self.rejected += 1
            return
        p = self.params
        for det in detections:
            if not _finite(det.bearing, det.distance, det.confidence) or det.distance <= 0:
                self.rejected += 1
                continue
            world = robot_yaw + det.bearing
            best: _Track | None = None
            best_err = p.camera_bearing_gate
            for track in self._tracks:
                px, py = self._predict(track, now)
                rng = math.hypot(px - robot_x, py - robot_y)
                if rng < 0.2:
                    continue
                err = abs(_wrap(math.atan2(py - robot_y, px - robot_x) - world))
                ratio = abs(rng - det.distance) / max(rng, 0.5)
                # The nearest in bearing, of those at a plausible range.
                if err <= best_err and ratio <= p.camera_range_ratio:
                    best, best_err = track, err
            x = robot_x + det.distance * math.cos(world)
            y = robot_y + det.distance * math.sin(world)
            if best is None:
                self._spawn(now, x, y, det.confidence * 0.6, "camera")
                continue
            best.last_camera = now
            best.sources.add("camera")
            if now - best.last_laser > 0.5:
                # The laser lost the person: keep the track going on the camera alone.
                self._correct(best, now, x, y, p.camera_alpha, det.confidence)
            else:
                best.hits += 1
                best.quality = min(1.0, best.quality + 0.1 * det.confidence)
        self._housekeep(now)

    def tick(self, now: float) -> None:
        """Drop tracks not seen for too long (call it when no sensor data came)."""
        if self._advance(now):
            self._housekeep(now)

    # ------------------------------------------------------------------ output

    def tracks(self) -> list[PersonTrack]:
        """Confirmed tracks, predicted to the latest time given."""
        now = self._now
        out = []
        p = self.params
        for t in self._tracks:
            if not t.confirmed:
                continue
            x, y = self._predict(t, now) if math.isfinite(now) else (t.x, t.y)
            recent = {
                s
                for s, when in (("laser", t.last_laser), ("camera", t.last_camera))
                if now - when <= p.camera_recent
            }
            unseen = max(now - t.last_seen, 0.0)
            confidence = t.quality * max(0.0, 1.0 - unseen / p.lost_after)
            if "camera" in recent and "laser" in recent:
                confidence = min(1.0, confidence + 0.15)
            out.append(
                PersonTrack(
                    id=t.id,
                    x=x,
                    y=y,
                    vx=t.vx,
                    vy=t.vy,
                    confidence=round(min(max(confidence, 0.0), 1.0), 3),
                    first_seen=t.first_seen,
                    last_seen=t.last_seen,
                    sources=frozenset(recent or t.sources),
                )
            )
        return out

    def candidates(self) -> list[tuple[float, float]]:
        """Where every track is, tentative ones too (map frame, as last corrected)."""
        return [(t.x, t.y) for t in self._tracks]

    @property
    def now(self) -> float:
        """The latest loop time given."""
        return self._now

    # ------------------------------------------------------------------ internals

    def _advance(self, now: float) -> bool:
        if not _finite(now) or now < self._now:
            self.rejected += 1
            return False
        self._now = now
        return True

    def _predict(self, track: _Track, now: float) -> tuple[float, float]:
        # Coasting is short: someone unseen may have stopped (at a wall, behind a door).
        dt = min(max(now - track.updated_at, 0.0), self.params.max_coast)
        return track.x + track.vx * dt, track.y + track.vy * dt

    def _correct(
        self, track: _Track, now: float, x: float, y: float, alpha: float, confidence: float
    ) -> None:
        p = self.params
        dt = now - track.updated_at
        px, py = self._predict(track, now)
        rx, ry = x - px, y - py
        track.x, track.y = px + alpha * rx, py + alpha * ry
        if dt > 1e-3:
            track.vx += p.beta * rx / dt
            track.vy += p.beta * ry / dt
            speed = math.hypot(track.vx, track.vy)
            if speed > p.max_speed:
                track.vx *= p.max_speed / speed
                track.vy *= p.max_speed / speed
        track.updated_at = now
        track.last_seen = now
        track.hits += 1
        track.quality = min(1.0, 0.8 * track.quality + 0.2 * min(max(confidence, 0.0), 1.0) + 0.05)
        if track.hits >= p.confirm_hits:
            track.confirmed = True

    def _spawn(self, now: float, x: float, y: float, confidence: float, source: str) -> None:
        track = _Track(
            id=self._next_id,
            x=x,
            y=y,
            first_seen=now,
            last_seen=now,
            updated_at=now,
            quality=min(max(confidence, 0.0), 1.0) * 0.7,
            sources={source},
        )
        if source == "laser":
            track.last_laser = now
        else:
            track.last_camera = now
        self._next_id += 1
        self._tracks.append(track)

    def _housekeep(self, now: float) -> None:
        p = self.params
        self._tracks = [
            t
            for t in self._tracks
            if now - t.last_seen <= (p.lost_after if t.confirmed else p.tentative_lost_after)
        ]
        # Two tracks on one person (a split detection): keep the older, confirmed one.
        keep: list[_Track] = []
        for t in sorted(self._tracks, key=lambda t: (not t.confirmed, t.first_seen, t.id)):
            if (
                any(math.hypot(t.x - k.x, t.y - k.y) < p.merge_distance for k in keep)
                and not t.confirmed
            ):
                continue
            keep.append(t)
        keep.sort(key=lambda t: t.id)
        self._tracks = keep


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
