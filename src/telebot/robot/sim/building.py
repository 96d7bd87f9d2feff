"""Built-in maps for the simulated robot, drawn by deterministic generators.

``building`` (the default) is one floor of an office building as a SLAM run would map it:
4000 × 4000 cells at 0.05 m (200 m × 200 m), the origin at (-100, -100), so world (0, 0) is
the centre of the map. The building, 90 m × 60 m (x ∈ [-45, 45], y ∈ [-30, 30], plus half
the outer walls' thickness), is centred on it: world (0, 0) is the middle of the main
east-west corridor, where the corridor from the lobby meets it, in front of the lift lobby.
Everything outside the building is unknown (-1), as are the closed rooms the robot never
entered (stores, server room, lift shafts, the flight of stairs going down). About 13 % of
the grid is known.

Floor plan (plan coordinates: the building's south-west corner is (0, 0), so world = plan −
(45, 30); y grows northwards)::

    y 46..60  open office B | library | meeting room E | board room | workshop | open office C
    y 43.6-46 ─────────────────────── north corridor ───────────────────────────────────────
    y 31-43.6 offices 13-16 ‖ WC · store │ lift lobby, 3 lifts │ WC · server ‖ offices 17-20
    y 29-31   ─────────────────────── main corridor (world y = 0) ──────────────────────────
    y 16-29   meeting A, B / offices 1-4 ‖ print / 5, 6 ┃ quiet / 7, 8 ‖ meeting C, D / 9-12
    y 14-16.4 ─────────────────────── south corridor ───────────────────────────────────────
    y 0..14   lab | meeting room | kitchen | lobby (entrance) | training | open office | stairs

``‖`` are the two north-south cross corridors (x = 30 and 60), ``┃`` the corridor from the
lobby to the main corridor (x = 45). Corridors are 2.2 m clear, walls 0.2 m, doors 0.9–1.2 m.

``small`` is a 12 m × 8 m floor (two rooms and a corridor) for fast tests; world (0, 0) is
its south-west outer corner and a 1 m unknown border surrounds it.

``small`` ships as package data (``maps/small.*``); the 16 MB building image is generated on
first use into :func:`cache_dir` by :func:`resolve_map`. After changing a generator,
regenerate the package data with ``python -m telebot.robot.sim.building --name small --out
src/telebot/robot/sim/maps`` (and ``--name building --places-only``), and bump
:data:`BUILDING_VERSION` when the building's cells change so stale caches are not reused.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt

from telebot.errors import MapError
from telebot.robot.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid
from telebot.robot.mapfile import places_path_for, save_map, save_places
from telebot.robot.nav import Pose2D, normalize_angle

__all__ = [
    "BUILDING_VERSION",
    "BUILTIN_MAPS",
    "cache_dir",
    "generate_building",
    "generate_small",
    "main",
    "resolve_map",
]

#: Names :func:`resolve_map` understands besides file paths.
BUILTIN_MAPS = ("building", "small")

#: Part of the cached building's file name: bump it whenever the building's cells change.
BUILDING_VERSION = 1

_RESOLUTION = 0.05
#: Interior and outer walls alike (m).
_WALL = 0.2
_MAPS_DIR = Path(__file__).resolve().parent / "maps"


class _Floor:
    """Draws a floor plan into an occupancy grid, in plan coordinates (metres).

    Plan point (0, 0) is cell corner ``(row0, col0)``; all coordinates in the plans are
    multiples of the resolution, so rounding only removes float noise.
    """

    def __init__(self, rows: int, cols: int, row0: int, col0: int) -> None:
        self.data: npt.NDArray[np.int8] = np.full((rows, cols), UNKNOWN, dtype=np.int8)
        self.row0 = row0
        self.col0 = col0

    def fill(self, x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        """Set the cells of the rectangle ``[x0, x1] × [y0, y1]`` to ``value``."""
        c0 = self.col0 + round(x0 / _RESOLUTION)
        c1 = self.col0 + round(x1 / _RESOLUTION)
        r0 = self.row0 + round(y0 / _RESOLUTION)
        r1 = self.row0 + round(y1 / _RESOLUTION)
        self.data[r0:r1, c0:c1] = value

    def hwall(self, y: float, x0: float, x1: float) -> None:
        """A wall centred on the line ``y`` from ``x0`` to ``x1`` (its ends meet crossings)."""
        h = _WALL / 2
        self.fill(x0 - h, y - h, x1 + h, y + h, OCCUPIED)

    def vwall(self, x: float, y0: float, y1: float) -> None:
        """A wall centred on the line ``x`` from ``y0`` to ``y1``."""
        h = _WALL / 2
        self.fill(x - h, y0 - h, x + h, y1 + h, OCCUPIED)

    def hdoor(self, y: float, x0: float, width: float) -> None:
        """An opening in the wall along ``y`` from ``x0`` to ``x0 + width``."""
        h = _WALL / 2
        self.fill(x0, y - h, x0 + width, y + h, FREE)

    def vdoor(self, x: float, y0: float, width: float) -> None:
        """An opening in the wall along ``x`` from ``y0`` to ``y0 + width``."""
        h = _WALL / 2
        self.fill(x - h, y0, x + h, y0 + width, FREE)

    def block(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """Furniture (or anything solid) covering ``[x0, x1] × [y0, y1]``."""
        self.fill(x0, y0, x1, y1, OCCUPIED)

    def unseen(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """The inside of the walled box ``[x0, x1] × [y0, y1]`` was never mapped (closed room)."""
        h = _WALL / 2
        self.fill(x0 + h, y0 + h, x1 - h, y1 - h, UNKNOWN)

    def grid(self, plan_x: float, plan_y: float) -> OccupancyGrid:
        """The finished grid, georeferenced so plan (0, 0) is world ``(plan_x, plan_y)``."""
        return OccupancyGrid(
            data=self.data,
            resolution=_RESOLUTION,
            origin_x=plan_x - self.col0 * _RESOLUTION,
            origin_y=plan_y - self.row0 * _RESOLUTION,
        )


# --------------------------------------------------------------------------- the building

# Building extent and where plan (0, 0) lands in the 4000 × 4000 grid: world (-45, -30).
_BUILDING_W = 90.0
_BUILDING_H = 60.0
_GRID_CELLS = 4000
_GRID_ORIGIN = -100.0
_PLAN_OFFSET = (-45.0, -30.0)


def _office(floor: _Floor, x0: float, x1: float, door_y: float, back_y: float) -> None:
    """A cellular office between partitions ``x0`` and ``x1``: door near ``x0``, desk at the back.

    ``door_y`` is the corridor wall the door is in and ``back_y`` the wall behind the desk.
    """
    floor.hdoor(door_y, x0 + 0.6, 1.0)
    if back_y > door_y:
        floor.block(x0 + 2.5, back_y - 0.85, x0 + 5.0, back_y - 0.1)  # desk
        floor.block(x1 - 0.6, door_y + 1.2, x1 - 0.1, door_y + 2.6)  # filing cabinet
    else:
        floor.block(x0 + 2.5, back_y + 0.1, x0 + 5.0, back_y + 0.85)
        floor.block(x1 - 0.6, door_y - 2.6, x1 - 0.1, door_y - 1.2)


def _meeting(floor: _Floor, x0: float, x1: float, door_y: float, back_y: float) -> None:
    """A meeting room: door near ``x0`` and a table in the middle."""
    floor.hdoor(door_y, x0 + 1.0, 1.2)
    lo, hi = sorted((door_y, back_y))
    mid = (lo + hi) / 2
    floor.block(x0 + 3.0, mid - 1.0, x1 - 3.0, mid + 1.0)


def _pose(x: float, y: float, yaw_deg: float) -> Pose2D:
    """A place as :func:`~telebot.robot.mapfile.load_places` would read it back, exactly."""
    return Pose2D(round(x, 6), round(y, 6), normalize_angle(math.radians(yaw_deg)))


def _desk_cluster(floor: _Floor, x: float, y: float) -> None:
    """Four desks pushed together (3.2 m × 1.6 m) with their lower-left corner at (x, y)."""
    floor.block(x, y, x + 3.2, y + 1.6)


def _draw_building(floor: _Floor) -> None:
    """The office floor described in the module docstring, in plan coordinates."""
    w, h = _BUILDING_W, _BUILDING_H
    half = _WALL / 2
    floor.fill(-half, -half, w + half, h + half, FREE)

    # Outer walls. The entrance's glass doors (south, into the lobby) are closed: a wall.
    floor.hwall(0.0, 0.0, w)
    floor.hwall(h, 0.0, w)
    floor.vwall(0.0, 0.0, h)
    floor.vwall(w, 0.0, h)

    # East-west corridors: south (y 14–16.4), main (28.8–31.2), north (43.6–46).
    for y in (14.0, 16.4, 28.8, 31.2, 43.6, 46.0):
        floor.hwall(y, 0.0, w)
    # North-south cross corridors (x = 30 and 60) link all three, and the corridor from the
    # lobby (x = 45) links the south corridor to the main one.
    for x in (28.8, 31.2, 58.8, 61.2):
        floor.vwall(x, 16.4, 28.8)
        floor.vwall(x, 31.2, 43.6)
    for x in (43.8, 46.2):
        floor.vwall(x, 16.4, 28.8)
    # Back-to-back offices between the corridors share a spine wall.
    for x0, x1 in ((0.0, 28.8), (31.2, 43.8), (46.2, 58.8), (61.2, w)):
        floor.hwall(22.6, x0, x1)
    for x0, x1 in ((0.0, 28.8), (31.2, 40.0), (50.0, 58.8), (61.2, w)):
        floor.hwall(37.4, x0, x1)
    # Openings where corridors cross corridor walls (the clear 2.2 m between the walls).
    for x0 in (28.9, 58.9):
        for y in (16.4, 28.8, 31.2, 43.6):
            floor.hdoor(y, x0, 2.2)
    for y in (16.4, 28.8):
        floor.hdoor(y, 43.9, 2.2)

    _draw_south_rooms(floor)
    _draw_middle_rooms(floor)
    _draw_core(floor)
    _draw_north_rooms(floor)

    # A few things along the main corridor, as in any real one: a water cooler, a plant and
    # a bench, each leaving well over a metre of corridor free.
    floor.block(20.0, 28.9, 20.5, 29.4)
    floor.block(52.0, 30.5, 52.6, 31.1)
    floor.block(70.0, 30.6, 72.0, 31.1)


def _draw_south_rooms(floor: _Floor) -> None:
    """Rooms between the south façade and the south corridor (doors in the wall y = 14)."""
    for x in (14.0, 26.0, 38.0, 52.0, 64.0, 78.0):
        floor.vwall(x, 0.0, 14.0)

    # Lab: two rows of benches and an equipment rack.
    floor.hdoor(14.0, 3.0, 1.2)
    floor.hdoor(14.0, 10.0, 1.2)
    floor.block(2.0, 3.0, 12.0, 4.0)
    floor.block(2.0, 7.0, 12.0, 8.0)
    floor.block(13.2, 1.0, 13.9, 6.0)

    # Meeting room with a large conference table.
    floor.hdoor(14.0, 15.0, 1.0)
    floor.block(16.5, 5.0, 23.5, 8.0)

    # Kitchen: L-shaped counter along the south and west walls, an island, two tables.
    floor.hdoor(14.0, 27.0, 1.2)
    floor.hdoor(14.0, 35.5, 1.2)
    floor.block(26.1, 0.1, 37.9, 0.75)
    floor.block(26.1, 0.75, 26.75, 6.0)
    floor.block(29.5, 4.0, 33.5, 5.0)
    floor.block(28.0, 8.5, 30.0, 10.5)
    floor.block(32.5, 8.5, 34.5, 10.5)

    # Lobby: a 5 m opening onto the south corridor, reception counter, sofas, coffee table.
    floor.hdoor(14.0, 42.5, 5.0)
    floor.block(48.0, 6.0, 51.2, 6.8)
    floor.block(38.6, 3.0, 39.4, 6.0)
    floor.block(38.6, 8.0, 39.4, 11.0)
    floor.block(40.5, 4.0, 41.5, 5.0)

    # Training room: two rows of tables.
    floor.hdoor(14.0, 62.5, 1.0)
    floor.block(54.0, 4.0, 62.0, 4.8)
    floor.block(54.0, 7.0, 62.0, 7.8)

    # Open office with four desk clusters around a structural column.
    floor.hdoor(14.0, 65.0, 1.2)
    floor.hdoor(14.0, 76.4, 1.2)
    for x in (66.0, 72.0):
        for y in (2.5, 7.0):
            _desk_cluster(floor, x, y)
    floor.block(70.8, 5.6, 71.2, 6.0)

    # East end: a closed store (never entered) and the stairwell. The flight going up is
    # solid to the laser; the flight going down is never seen, so it stays unknown.
    floor.hwall(7.0, 78.0, 90.0)
    floor.unseen(78.0, 0.0, 90.0, 7.0)
    floor.hdoor(14.0, 79.0, 1.2)
    floor.block(81.5, 10.7, 89.9, 13.9)  # flight up
    floor.block(81.5, 10.5, 89.9, 10.7)  # wall between the flights
    floor.fill(81.5, 7.1, 89.9, 10.5, UNKNOWN)  # flight down
    floor.block(81.45, 7.1, 81.55, 10.7)  # railing along the landing


def _draw_middle_rooms(floor: _Floor) -> None:
    """Offices and meeting rooms in the two bands between the three corridors."""
    # Band between the south and main corridors: offices open south, rooms behind open north.
    for x0, x1, parts in ((0.0, 28.8, 4), (31.2, 43.8, 2), (46.2, 58.8, 2), (61.2, 90.0, 4)):
        step = (x1 - x0) / parts
        for i in range(1, parts):
            floor.vwall(x0 + i * step, 16.4, 22.6)
        for i in range(parts):
            _office(floor, x0 + i * step, x0 + (i + 1) * step, 16.4, 22.6)
    for x in (14.4, 75.6):
        floor.vwall(x, 22.6, 28.8)
    for x0, x1 in ((0.0, 14.4), (14.4, 28.8), (61.2, 75.6), (75.6, 90.0)):
        _meeting(floor, x0, x1, 28.8, 22.6)
    # Print room: two printers and a paper cupboard against the spine wall.
    floor.hdoor(28.8, 42.0, 1.0)
    floor.block(33.0, 22.7, 35.0, 23.5)
    floor.block(37.0, 22.7, 39.0, 23.5)
    floor.block(31.3, 24.0, 31.9, 27.0)
    # Quiet room: two sofas facing each other.
    floor.hdoor(28.8, 47.2, 1.0)
    floor.block(49.0, 22.7, 56.0, 23.5)
    floor.block(57.9, 24.0, 58.7, 27.5)

    # Band between the main and north corridors (the middle, 31.2–58.8, is the core).
    for x0, x1 in ((0.0, 28.8), (61.2, 90.0)):
        step = (x1 - x0) / 4
        for i in range(1, 4):
            floor.vwall(x0 + i * step, 31.2, 43.6)
        for i in range(4):
            _office(floor, x0 + i * step, x0 + (i + 1) * step, 31.2, 37.4)
            _office(floor, x0 + i * step, x0 + (i + 1) * step, 43.6, 37.4)


def _draw_core(floor: _Floor) -> None:
    """Lift lobby with three lift shafts, toilets, a cleaners' store and the server room."""
    floor.vwall(40.0, 31.2, 43.6)
    floor.vwall(50.0, 31.2, 43.6)
    # Lift lobby: 6 m open to the main corridor, a bench along its west wall.
    floor.hdoor(31.2, 42.0, 6.0)
    floor.block(40.1, 33.0, 40.6, 36.0)
    # Lift core: closed lift doors face the lobby; shafts and machine room are never seen.
    floor.block(40.0, 37.9, 50.0, 38.1)
    floor.block(40.0, 40.5, 50.0, 40.7)
    floor.block(40.0, 38.0, 41.2, 40.6)
    floor.block(48.8, 38.0, 50.0, 40.6)
    for x in (43.7, 46.3):
        floor.vwall(x, 38.0, 40.6)
    for x0, x1 in ((41.1, 43.7), (43.7, 46.3), (46.3, 48.9)):
        floor.unseen(x0, 38.0, x1, 40.6)
    floor.unseen(40.0, 40.6, 50.0, 43.6)
    # Toilets open onto the main corridor; the store and server room behind are locked.
    floor.hdoor(31.2, 32.0, 1.0)
    floor.hdoor(31.2, 56.8, 1.0)
    floor.block(36.0, 36.5, 39.9, 37.3)  # washbasins
    floor.block(50.1, 36.5, 54.0, 37.3)
    floor.unseen(31.2, 37.4, 40.0, 43.6)
    floor.unseen(50.0, 37.4, 58.8, 43.6)


def _draw_north_rooms(floor: _Floor) -> None:
    """Rooms between the north corridor and the north façade (doors in the wall y = 46)."""
    for x in (18.0, 30.0, 42.0, 54.0, 72.0):
        floor.vwall(x, 46.0, 60.0)
    # Open office B and C: six desk clusters each, a column in the middle.
    for x0, doors in ((0.0, (1.0, 15.5)), (72.0, (73.0, 87.5))):
        for door in doors:
            floor.hdoor(46.0, door, 1.2)
        for dx in (2.0, 7.5, 13.0):
            for y in (50.0, 54.5):
                _desk_cluster(floor, x0 + dx, y)
        floor.block(x0 + 8.8, 48.0, x0 + 9.2, 48.4)
    # Library: three long shelves.
    floor.hdoor(46.0, 19.0, 1.2)
    for y in (50.0, 53.0, 56.0):
        floor.block(20.0, y, 28.0, y + 0.5)
    # Meeting room E and the board room.
    floor.hdoor(46.0, 31.0, 1.2)
    floor.block(33.0, 51.5, 39.0, 54.5)
    floor.hdoor(46.0, 52.4, 1.2)
    floor.block(44.5, 51.5, 51.5, 54.5)
    # Workshop: benches along the north wall and two machines.
    floor.hdoor(46.0, 55.0, 1.2)
    floor.hdoor(46.0, 69.5, 1.2)
    floor.block(56.0, 59.0, 70.0, 59.9)
    floor.block(58.0, 52.0, 60.0, 54.0)
    floor.block(64.0, 52.0, 66.0, 54.0)


# Places of the building in plan coordinates: x, y, heading in degrees (CCW from east).
# Each stands on open floor, at least 0.6 m from anything, facing what it is named after.
_BUILDING_PLACES: tuple[tuple[str, float, float, float], ...] = (
    ("lobby", 45.0, 5.0, 90.0),  # by the entrance, facing the way in
    ("reception", 49.6, 5.0, 90.0),  # in front of the reception counter
    ("kitchen", 31.5, 2.5, -90.0),  # at the counter
    ("lab", 7.0, 5.5, -90.0),  # between the bench rows
    ("lift", 45.0, 36.0, 90.0),  # facing the lift doors
    ("meeting-room", 20.0, 10.5, -90.0),  # at the conference table
    ("office-1", 3.8, 19.5, 90.0),  # facing the desk
    ("corridor-east", 80.0, 30.0, 0.0),
    ("corridor-west", 10.0, 30.0, 180.0),
    ("library", 24.0, 48.5, 90.0),
    ("board-room", 48.0, 49.0, 90.0),
    ("workshop", 62.0, 49.0, 90.0),
    ("stairs", 79.8, 10.0, 0.0),  # on the landing, facing the flights
    ("open-office", 71.0, 11.5, -90.0),
)


def generate_building() -> tuple[OccupancyGrid, dict[str, Pose2D]]:
    """The default map: an office floor in a 4000 × 4000 grid (0.05 m), and its places.

    World (0, 0) is the map centre, in the main corridor in front of the lift lobby (see the
    module docstring for the plan). Places are in world coordinates, lobby first.
    """
    row0 = round((_PLAN_OFFSET[1] - _GRID_ORIGIN) / _RESOLUTION)
    col0 = round((_PLAN_OFFSET[0] - _GRID_ORIGIN) / _RESOLUTION)
    floor = _Floor(_GRID_CELLS, _GRID_CELLS, row0, col0)
    _draw_building(floor)
    dx, dy = _PLAN_OFFSET
    grid = floor.grid(dx, dy)
    places = {name: _pose(x + dx, y + dy, yaw) for name, x, y, yaw in _BUILDING_PLACES}
    return grid, places


# --------------------------------------------------------------------------- the small map


def generate_small() -> tuple[OccupancyGrid, dict[str, Pose2D]]:
    """A 12 m × 8 m floor for fast tests, with its places (``start`` first).

    A corridor along the south side, rooms A (west) and B (east) north of it, each behind a
    1 m door, a table in room B. World (0, 0) is the south-west outer corner; the grid
    (280 × 200 cells) adds 1 m of unknown all round.
    """
    floor = _Floor(200, 280, 20, 20)
    half = _WALL / 2
    floor.fill(-half, -half, 12.0 + half, 8.0 + half, FREE)
    floor.hwall(0.0, 0.0, 12.0)
    floor.hwall(8.0, 0.0, 12.0)
    floor.vwall(0.0, 0.0, 8.0)
    floor.vwall(12.0, 0.0, 8.0)
    floor.hwall(2.4, 0.0, 12.0)  # corridor wall
    floor.vwall(6.0, 2.4, 8.0)  # between the rooms
    floor.hdoor(2.4, 2.0, 1.0)  # room A
    floor.hdoor(2.4, 9.0, 1.0)  # room B
    floor.block(8.5, 5.0, 10.5, 6.2)  # table in room B
    places = {
        "start": _pose(1.0, 1.2, 0.0),  # west end of the corridor
        "room-a": _pose(3.0, 5.2, 0.0),
        "room-b": _pose(9.5, 4.0, 90.0),  # facing the table
        "corridor": _pose(10.5, 1.2, 180.0),  # east end, looking back west
    }
    return floor.grid(0.0, 0.0), places


# --------------------------------------------------------------------------- resolving


def cache_dir() -> Path:
    """Where generated maps are cached.

    ``$TELEBOT_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/telebot``, else
    ``~/.cache/telebot``.
    """
    env = os.environ.get("TELEBOT_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "telebot"


def _write_builtin(name: str, yaml_path: Path) -> None:
    """Generate the built-in map ``name`` and write it (places, image, YAML last)."""
    grid, places = generate_building() if name == "building" else generate_small()
    places_path = places_path_for(yaml_path)
    try:
        yaml_path.parent.mkdir(parents=True, exist_ok=True)
        save_places(places, places_path)
    except OSError as exc:
        raise MapError(f"{places_path}: cannot write: {exc.strerror or exc}") from exc
    save_map(grid, yaml_path)


def resolve_map(spec: str, base_dir: Path | None = None) -> Path:
    """The map YAML file that ``spec`` names.

    ``"small"`` is the packaged map; ``"building"`` is generated into
    ``<cache_dir>/maps/building-v<N>.yaml`` (with its ``.pgm`` and ``.places.toml``) the first
    time and reused after. Every file is written to a temporary name and renamed, the YAML
    last, so another process generating at the same time never reads half a file. Anything
    else is a path to a map YAML file (relative to ``base_dir`` when given) that must exist.

    Raises :class:`~telebot.errors.MapError` naming the map when it cannot be found or
    written.
    """
    if spec == "small":
        return _MAPS_DIR / "small.yaml"
    if spec == "building":
        yaml_path = cache_dir() / "maps" / f"building-v{BUILDING_VERSION}.yaml"
        needed = (yaml_path, yaml_path.with_suffix(".pgm"), places_path_for(yaml_path))
        if not all(p.is_file() for p in needed):
            _write_builtin("building", yaml_path)
        return yaml_path
    path = Path(spec).expanduser()
    if base_dir is not None and not path.is_absolute():
        path = Path(base_dir) / path
    if not path.is_file():
        what = "is not a file" if path.exists() else "no such file"
        raise MapError(f"map {spec!r}: {path}: {what} (built-in maps: {', '.join(BUILTIN_MAPS)})")
    return path


# --------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> int:
    """``python -m telebot.robot.sim.building --name NAME --out DIR``: write a built-in map."""
    parser = argparse.ArgumentParser(
        prog="python -m telebot.robot.sim.building",
        description="Write a built-in map (ROS map_server YAML + PGM) and its places file.",
    )
    parser.add_argument("--name", choices=BUILTIN_MAPS, default="building")
    parser.add_argument("--out", type=Path, required=True, help="folder to write into")
    parser.add_argument("--places-only", action="store_true", help="write only <name>.places.toml")
    args = parser.parse_args(argv)
    yaml_path: Path = args.out / f"{args.name}.yaml"
    places_path = places_path_for(yaml_path)
    try:
        if args.places_only:
            _, places = generate_building() if args.name == "building" else generate_small()
            save_places(places, places_path)
            print(places_path)
        else:
            _write_builtin(args.name, yaml_path)
            print(yaml_path)
            print(yaml_path.with_suffix(".pgm"))
            print(places_path)
    except (MapError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
