"""Simulated cameras: first-person views rendered from the occupancy grid, Wolfenstein-style.

One ray per image column is cast through the map (the laser's :class:`RayCaster`, so walls
are where the laser sees them); its *perpendicular* distance to the image plane (not the
Euclidean one, which would bend straight walls into a fisheye) sets the wall slice's top and
bottom from the wall height and the camera's mount height. Floor and ceiling are planes,
so each is one perspective warp (a homography) of a small periodic tile texture anchored
in world coordinates: the 1 m tiles slide and turn with the robot even in an empty room.

Conventions and colours (BGR):

* walls (:data:`WALL_BGR`): warm cream (red > blue), 1 m seams along the wall and a darker
  skirting board; faces whose normal is along ±y are drawn darker (:data:`SIDE_Y_SHADE`) than
  those along ±x, so corners read;
* floor: 1 m tiles in two cool greys (blue ≥ red) with dark grout lines; ceiling: light cool
  grey 1 m panels with a light in every other one. Warm walls and cool floors keep the two
  apart by colour alone;
* unknown space (:data:`UNKNOWN_BGR`) — unexplored, which the laser treats as solid — is a
  dark slate blue wall, without seams or skirting, so it is never mistaken for a real wall;
* people and other round obstacles (:data:`OBSTACLE_BGR`): orange-red cylinders, shaded by
  the angle of their surface, hidden behind nearer walls (per-column depth test); where
  several overlap in a column, the nearest is drawn;
* everything fades with distance towards :data:`FOG_BGR` (near black, like a corridor whose
  lights are far away), reaching it at ``view_distance``; a column that hits nothing within
  it shows that colour;
* the camera's name is written in the top-left corner.

A pose outside the map or inside a wall sees solid unknown / wall everywhere (the laser reads
0 there too).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import CameraInfo, Pose2D
from telebot.robot.sim.figure import draw_people
from telebot.robot.sim.laser import (
    CELL_OCCUPIED,
    CELL_UNKNOWN,
    SIDE_X,
    SIDE_Y,
    RayCaster,
    intersect_circles,
)
from telebot.robot.sim.people import PersonTruth
from telebot.robot.sim.world import Obstacle

__all__ = [
    "FOG_BGR",
    "OBSTACLE_BGR",
    "SIDE_Y_SHADE",
    "SKIRTING_BGR",
    "UNKNOWN_BGR",
    "WALL_BGR",
    "CameraModel",
    "Renderer",
    "default_cameras",
]

#: Wall colour (BGR), before face and distance shading.
WALL_BGR = (178, 206, 222)
#: Skirting board at the foot of the walls.
SKIRTING_BGR = (92, 110, 128)
#: Unknown (unexplored) space, which is solid for the robot.
UNKNOWN_BGR = (92, 52, 36)
#: People and other round obstacles.
OBSTACLE_BGR = (20, 90, 255)
#: What everything fades to at ``view_distance``.
FOG_BGR = (22, 22, 22)
#: Brightness of wall faces whose normal is along ±y (those along ±x are 1.0).
SIDE_Y_SHADE = 0.72

_SKIRTING_HEIGHT = 0.12  # metres
_SEAM_WIDTH = 0.05  # metres, the dark line every metre along a wall
_SEAM_SHADE = 0.8
# Floor and ceiling textures repeat every 2 m (two 1 m tiles each way), _TEX_PPM texels a metre.
_TEX_PERIOD = 2.0
_TEX_PPM = 32
_MAX_CACHED_CAMERAS = 8


@dataclass(frozen=True, slots=True)
class CameraModel:
    """A pinhole camera on the robot, looking along its heading, level with the floor."""

    name: str
    #: Horizontal field of view, degrees; the vertical one follows from the aspect ratio
    #: (square pixels).
    fov_deg: float
    #: Metres above the floor.
    mount_height: float
    width: int = 640
    height: int = 480
    description: str = ""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fov_deg) and 0.0 < self.fov_deg < 180.0):
            raise ValueError(f"field of view must be in (0, 180) degrees, not {self.fov_deg}")
        if not (math.isfinite(self.mount_height) and self.mount_height > 0.0):
            raise ValueError(f"mount height must be positive, not {self.mount_height}")
        if self.width < 8 or self.height < 8:
            raise ValueError(f"image size {self.width}×{self.height} is too small")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (the same horizontally and vertically)."""
        return (self.width / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)

    def info(self) -> CameraInfo:
        """This camera as the navigation interface describes it."""
        return CameraInfo(
            name=self.name,
            width=self.width,
            height=self.height,
            fov_deg=self.fov_deg,
            description=self.description,
        )


def default_cameras(width: int = 640, height: int = 480) -> tuple[CameraModel, ...]:
    """The robot's two cameras: ``navcam`` (low, for driving) then ``usercam`` (for people)."""
    return (
        CameraModel(
            name="navcam",
            fov_deg=70.0,
            mount_height=0.5,
            width=width,
            height=height,
            description="forward-looking navigation camera, 70° at 0.5 m",
        ),
        CameraModel(
            name="usercam",
            fov_deg=90.0,
            mount_height=1.4,
            width=width,
            height=height,
            description="wide camera at head height, for talking to people",
        ),
    )


def _tile_textures() -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]:
    """Floor and ceiling textures, one 2 m × 2 m period each, texel (row, col) = (y, x)."""
    n = int(_TEX_PERIOD * _TEX_PPM)
    half = n // 2
    iy, ix = np.indices((n, n))
    checker = ((iy // half) + (ix // half)) % 2 == 1
    grout = ((iy % half) < 1) | ((ix % half) < 1)
    floor = np.empty((n, n, 3), dtype=np.uint8)
    floor[...] = (150, 142, 134)
    floor[checker] = (120, 113, 106)
    floor[grout] = (72, 68, 64)
    ceiling = np.empty((n, n, 3), dtype=np.uint8)
    ceiling[...] = (206, 202, 198)
    # A light panel in the middle of every other tile.
    lo, hi = half // 4, half - half // 4
    panel = checker & ((iy % half) >= lo) & ((iy % half) < hi)
    panel &= ((ix % half) >= lo) & ((ix % half) < hi)
    ceiling[panel] = (250, 248, 244)
    ceiling[grout] = (160, 156, 152)
    return floor, ceiling


def _fade(depth: npt.NDArray[np.float64], view_distance: float) -> npt.NDArray[np.float64]:
    """How much of the fog colour to mix in at ``depth`` (0 near, 1 at ``view_distance``)."""
    # Slightly faster than linear near the camera so that depth reads at room scale.
    return np.asarray(np.clip(depth / view_distance, 0.0, 1.0) ** 0.75, dtype=np.float64)


@dataclass(frozen=True, slots=True, eq=False)
class _Optics:
    """Everything about a camera that does not depend on the pose, computed once per camera."""

    focal: float
    cx: float
    cy: float
    horizon_row: int  # first floor row
    offsets: npt.NDArray[np.float64]  # ray angle of each column relative to the heading
    cos_offsets: npt.NDArray[np.float64]
    rows: npt.NDArray[np.int16]  # (H, 1) row indices
    # Fog over floor and ceiling depends only on the image row: out = tex·keep/255 + add.
    keep: npt.NDArray[np.uint8]  # (H, W, 3)
    add: npt.NDArray[np.uint8]  # (H, W, 3)


class Renderer:
    """Renders camera frames from an occupancy grid (see the module docstring).

    ``wall_height`` is the height of every wall and of the ceiling; ``view_distance`` is how
    far the cameras see before everything has faded to :data:`FOG_BGR`.
    """

    __slots__ = (
        "_caster",
        "_ceiling_tex",
        "_floor_tex",
        "_optics",
        "view_distance",
        "wall_height",
    )

    def __init__(
        self, grid: OccupancyGrid, *, wall_height: float = 2.5, view_distance: float = 30.0
    ) -> None:
        if not (math.isfinite(wall_height) and wall_height > 0.0):
            raise ValueError(f"wall height must be positive, not {wall_height}")
        if not (math.isfinite(view_distance) and view_distance > 0.0):
            raise ValueError(f"view distance must be positive, not {view_distance}")
        self.wall_height = float(wall_height)
        self.view_distance = float(view_distance)
        self._caster = RayCaster(grid)
        self._floor_tex, self._ceiling_tex = _tile_textures()
        self._optics: dict[CameraModel, _Optics] = {}

    def render(
        self,
        pose: Pose2D,
        camera: CameraModel,
        obstacles: Sequence[Obstacle] = (),
        people: Sequence[PersonTruth] = (),
    ) -> npt.NDArray[np.uint8]:
        """The BGR ``uint8`` image (camera.height, camera.width, 3) seen from ``pose``.

        ``people`` are drawn as human figures (see :mod:`telebot.robot.sim.figure`).
        """
        if not all(math.isfinite(v) for v in (pose.x, pose.y, pose.yaw)):
            raise ValueError(f"camera pose must be finite, not {pose}")
        if camera.mount_height >= self.wall_height:
            raise ValueError(
                f"camera {camera.name!r} at {camera.mount_height} m is above the walls "
                f"({self.wall_height} m)"
            )
        optics = self._optics_for(camera)
        image = self._floor_and_ceiling(pose, camera, optics)
        wall_depth = self._draw_walls(image, pose, camera, optics)
        if obstacles:
            self._draw_obstacles(image, pose, camera, optics, obstacles, wall_depth)
        if people:
            view = self.view_distance
            draw_people(
                image,
                pose,
                people,
                focal=optics.focal,
                cx=optics.cx,
                cy=optics.cy,
                mount_height=camera.mount_height,
                wall_depth=wall_depth,
                fade=lambda depth: float(_fade(np.array([depth]), view)[0]),
                fog_bgr=FOG_BGR,
            )
        # White on a black outline: readable on the light ceiling and on dark fog alike.
        for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
            cv2.putText(
                image,
                camera.name,
                (6, 16),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.45,
                colour,
                thickness,
                cv2.LINE_AA,
            )
        return image

    # ------------------------------------------------------------------ per camera

    def _optics_for(self, camera: CameraModel) -> _Optics:
        cached = self._optics.get(camera)
        if cached is not None:
            return cached
        w, h = camera.width, camera.height
        focal = camera.focal_px
        # Pixel (row, col) is centred on its integer coordinates, as cv2's warps assume.
        cx = (w - 1) / 2.0
        cy = (h - 1) / 2.0
        horizon_row = math.floor(cy) + 1
        cols = np.arange(w, dtype=np.float64)
        # Columns right of the centre look right of the heading: clockwise, negative angle.
        offsets = -np.arctan((cols - cx) / focal)
        rows = (np.arange(h, dtype=np.float64) - cy).reshape(h, 1)
        # Depth of the floor (below the horizon) and ceiling (above) seen by each row.
        # (The row on the horizon itself, which exists when the height is odd, is at infinity.)
        with np.errstate(divide="ignore"):
            floor_depth = camera.mount_height * focal / rows
            ceiling_depth = (self.wall_height - camera.mount_height) * focal / -rows
        depth = np.where(rows > 0, floor_depth, np.where(rows < 0, ceiling_depth, np.inf))
        fade = _fade(depth, self.view_distance)
        keep = np.broadcast_to(np.round(255.0 * (1.0 - fade))[:, :, None], (h, w, 3))
        add = np.broadcast_to(fade[:, :, None] * np.array(FOG_BGR, dtype=np.float64), (h, w, 3))
        optics = _Optics(
            focal=focal,
            cx=cx,
            cy=cy,
            horizon_row=horizon_row,
            offsets=offsets,
            cos_offsets=np.cos(offsets),
            rows=np.arange(h, dtype=np.int16).reshape(h, 1),
            keep=np.ascontiguousarray(keep, dtype=np.uint8),
            add=np.ascontiguousarray(np.round(add), dtype=np.uint8),
        )
        if len(self._optics) >= _MAX_CACHED_CAMERAS:
            self._optics.clear()
        self._optics[camera] = optics
        return optics

    # ------------------------------------------------------------------ floor and ceiling

    def _plane_warp(
        self, pose: Pose2D, optics: _Optics, height_above: float, row0: int, below: bool
    ) -> npt.NDArray[np.float64]:
        """Homography from image pixels (of rows from ``row0``) to texels of a horizontal plane.

        The plane is ``height_above`` metres below the camera (``below``) or above it. A pixel
        ``(u, v)`` sees the plane at depth ``z = height·f / |v - cy|``, at world offset
        ``z·forward + z·(u - cx)/f·right`` from the camera, which is projective in ``(u, v)``.
        """
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        f, cx = optics.focal, optics.cx
        hgt = height_above
        # Homogeneous w = |v - cy| for this strip of rows.
        sign = 1.0 if below else -1.0
        w_row = np.array([0.0, sign, sign * (row0 - optics.cy)])
        # The texture repeats, so only the pose modulo the period matters: keeps numbers small.
        px = pose.x % _TEX_PERIOD
        py = pose.y % _TEX_PERIOD
        x_row = np.array([hgt * s, 0.0, hgt * (f * c - cx * s)]) + px * w_row
        y_row = np.array([-hgt * c, 0.0, hgt * (f * s + cx * c)]) + py * w_row
        return np.stack((x_row * _TEX_PPM, y_row * _TEX_PPM, w_row))

    def _floor_and_ceiling(
        self, pose: Pose2D, camera: CameraModel, optics: _Optics
    ) -> npt.NDArray[np.uint8]:
        w, h = camera.width, camera.height
        split = optics.horizon_row
        image = np.empty((h, w, 3), dtype=np.uint8)
        floor_m = self._plane_warp(pose, optics, camera.mount_height, split, below=True)
        image[split:] = cv2.warpPerspective(
            self._floor_tex,
            floor_m,
            (w, h - split),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_WRAP,
        )
        ceil_m = self._plane_warp(
            pose, optics, self.wall_height - camera.mount_height, 0, below=False
        )
        image[:split] = cv2.warpPerspective(
            self._ceiling_tex,
            ceil_m,
            (w, split),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_WRAP,
        )
        cv2.multiply(image, optics.keep, dst=image, scale=1.0 / 255.0)
        cv2.add(image, optics.add, dst=image)
        return image

    # ------------------------------------------------------------------ walls

    def _draw_walls(
        self,
        image: npt.NDArray[np.uint8],
        pose: Pose2D,
        camera: CameraModel,
        optics: _Optics,
    ) -> npt.NDArray[np.float64]:
        """Draw the wall slices; return each column's wall depth (perpendicular metres)."""
        directions = pose.yaw + optics.offsets
        # Cast far enough that the edge columns also reach view_distance of *depth*.
        reach = self.view_distance / float(optics.cos_offsets.min())
        hits = self._caster.cast(pose.x, pose.y, directions, reach)
        depth = np.minimum(hits.distance * optics.cos_offsets, self.view_distance)
        hit = (hits.kind == CELL_OCCUPIED) | (hits.kind == CELL_UNKNOWN)
        depth = np.where(hit, depth, self.view_distance)
        safe = np.maximum(depth, 1e-3)

        # Base colour per column, then seams, face shading and fog.
        base = np.where(
            (hits.kind == CELL_UNKNOWN)[:, None],
            np.array(UNKNOWN_BGR, dtype=np.float64),
            np.array(WALL_BGR, dtype=np.float64),
        )
        bright = np.where(hits.side == SIDE_Y, SIDE_Y_SHADE, 1.0)
        # Where along the face the ray hit (y on a face normal to x, x otherwise): seams.
        hx = pose.x + hits.distance * np.cos(directions)
        hy = pose.y + hits.distance * np.sin(directions)
        along = np.where(hits.side == SIDE_X, hy, hx)
        seam = (np.mod(along, 1.0) < _SEAM_WIDTH) & (hits.kind == CELL_OCCUPIED)
        bright = np.where(seam, bright * _SEAM_SHADE, bright)
        fade = _fade(depth, self.view_distance)[:, None]
        fog = np.array(FOG_BGR, dtype=np.float64)
        wall_col = base * bright[:, None] * (1.0 - fade) + fog * fade
        skirt_col = np.array(SKIRTING_BGR, dtype=np.float64) * bright[:, None] * (1.0 - fade)
        skirt_col += fog * fade
        # No skirting on unknown space, nor on the fog column.
        skirt_col = np.where((hits.kind == CELL_OCCUPIED)[:, None], skirt_col, wall_col)

        scale = optics.focal / safe
        top = optics.cy - (self.wall_height - camera.mount_height) * scale
        skirt = optics.cy + (camera.mount_height - _SKIRTING_HEIGHT) * scale
        bottom = optics.cy + camera.mount_height * scale
        self._fill_columns(image, optics, top, skirt, wall_col)
        self._fill_columns(image, optics, skirt, bottom, skirt_col)
        return depth

    @staticmethod
    def _fill_columns(
        image: npt.NDArray[np.uint8],
        optics: _Optics,
        top: npt.NDArray[np.float64],
        bottom: npt.NDArray[np.float64],
        colours: npt.NDArray[np.float64],
    ) -> None:
        """Paint the rows ``top ≤ v < bottom`` of each column ``c`` in ``colours[c]``."""
        h = image.shape[0]
        # Integer rows: row v is inside [top, bottom) iff ceil(top) ≤ v < ceil(bottom). The
        # int16 comparison and cv2's masked copy are ~10× faster than a 3-channel np.where.
        t = np.clip(np.ceil(top), 0, h).astype(np.int16)
        b = np.clip(np.ceil(bottom), 0, h).astype(np.int16)
        mask = ((optics.rows >= t) & (optics.rows < b)).view(np.uint8)
        src = np.repeat(np.round(colours).astype(np.uint8)[None, :, :], h, axis=0)
        cv2.copyTo(src, mask, image)

    # ------------------------------------------------------------------ obstacles

    def _draw_obstacles(
        self,
        image: npt.NDArray[np.uint8],
        pose: Pose2D,
        camera: CameraModel,
        optics: _Optics,
        obstacles: Sequence[Obstacle],
        wall_depth: npt.NDArray[np.float64],
    ) -> None:
        """Draw the nearest obstacle of each column where it is nearer than the wall."""
        directions = pose.yaw + optics.offsets
        dist, which = intersect_circles(pose.x, pose.y, directions, obstacles)
        depth = dist * optics.cos_offsets
        visible = (which >= 0) & (depth < wall_depth)
        if not visible.any():
            return
        # Columns that show no obstacle get harmless stand-in values and an empty slice.
        depth = np.where(visible, depth, self.view_distance)
        dist = np.where(visible, dist, 0.0)
        idx = np.where(visible, which, 0)
        heights = np.array([o.height for o in obstacles], dtype=np.float64)[idx]
        centres = np.array([(o.x, o.y) for o in obstacles], dtype=np.float64)[idx]
        # Lambert-like shading: bright where the surface faces the camera, darker at the rims,
        # so a cylinder looks round rather than like a flat board.
        ray_x, ray_y = np.cos(directions), np.sin(directions)
        nx = pose.x + dist * ray_x - centres[:, 0]
        ny = pose.y + dist * ray_y - centres[:, 1]
        norm = np.maximum(np.hypot(nx, ny), 1e-9)
        facing = np.clip(-(nx * ray_x + ny * ray_y) / norm, 0.0, 1.0)
        bright = 0.55 + 0.45 * facing
        fade = _fade(depth, self.view_distance)[:, None]
        colours = np.array(OBSTACLE_BGR, dtype=np.float64) * bright[:, None] * (1.0 - fade)
        colours += np.array(FOG_BGR, dtype=np.float64) * fade
        scale = optics.focal / np.maximum(depth, 1e-3)
        top = np.where(visible, optics.cy - (heights - camera.mount_height) * scale, np.inf)
        bottom = np.where(visible, optics.cy + camera.mount_height * scale, -np.inf)
        self._fill_columns(image, optics, top, bottom, colours)
