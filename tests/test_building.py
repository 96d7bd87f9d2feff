"""The built-in maps: a realistic building floor and a small test floor, and finding them."""

from __future__ import annotations

import functools
import hashlib
import math
import time
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from telebot.errors import MapError
from telebot.robot.grid import FREE, UNKNOWN, OccupancyGrid
from telebot.robot.mapfile import load_map, load_places, places_path_for, save_map, save_places
from telebot.robot.nav import Pose2D
from telebot.robot.sim import building
from telebot.robot.sim.building import (
    BUILDING_VERSION,
    BUILTIN_MAPS,
    cache_dir,
    generate_building,
    generate_small,
    main,
    resolve_map,
)

MAPS = Path(building.__file__).parent / "maps"
ROBOT_RADIUS = 0.25
MARGIN = 0.05
#: The building's cells. If a change to the generator is intended, bump BUILDING_VERSION
#: (so caches regenerate) and update this hash.
BUILDING_SHA256 = "641574f361ec65fb75f43b9ebd36196728bb9135c8b6b558884e09c520241a08"

Map = tuple[OccupancyGrid, dict[str, Pose2D]]


@functools.cache
def _timed_building() -> tuple[Map, float]:
    """The building, generated once per test session, and how long that took."""
    start = time.perf_counter()
    result = generate_building()
    return result, time.perf_counter() - start


def cached_building() -> Map:
    grid, places = _timed_building()[0]
    return grid, dict(places)


@pytest.fixture(scope="module")
def big() -> Map:
    return cached_building()


@pytest.fixture(scope="module")
def small() -> Map:
    return generate_small()


def known_part(grid: OccupancyGrid) -> OccupancyGrid:
    """The grid cropped to its known cells plus a 1-cell unknown frame (fast to analyse)."""
    bounds = grid.known_bounds()
    assert bounds is not None
    r0, r1, c0, c1 = bounds
    return grid.crop(
        max(r0 - 1, 0), min(r1 + 1, grid.height), max(c0 - 1, 0), min(c1 + 1, grid.width)
    )


def clearance(grid: OccupancyGrid) -> npt.NDArray[np.float32]:
    """Per cell, metres from the cell centre to the nearest cell that is not free."""
    free = (grid.data == FREE).astype(np.uint8)
    dist: npt.NDArray[np.float32] = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return dist * np.float32(grid.resolution)


def reachable_labels(grid: OccupancyGrid, radius: float) -> npt.NDArray[np.int32]:
    """Connected components of where a round robot of ``radius`` fits (0 = it does not).

    A robot centred on a cell keeps ``radius`` from every non-free cell's edge, i.e. its
    centre is more than ``radius + res/2`` from the nearest non-free cell centre.
    """
    fits = (clearance(grid) > radius + grid.resolution / 2).astype(np.uint8)
    _, labels = cv2.connectedComponents(fits, connectivity=8)
    return np.asarray(labels, dtype=np.int32)


def label_of(grid: OccupancyGrid, labels: npt.NDArray[np.int32], pose: Pose2D) -> int:
    row, col = grid.cell_of(pose.x, pose.y)
    return int(labels[row, col])


# --------------------------------------------------------------------------- the building


def test_the_building_is_generated_fast(big: Map) -> None:
    assert _timed_building()[1] <= 2.0


def test_the_building_is_deterministic(big: Map) -> None:
    grid, _ = big
    # Compared with the hash recorded when building-v1 was drawn: the cached map files are
    # named by version, so a generator change without a version bump would reuse stale files.
    assert BUILDING_VERSION == 1
    assert hashlib.sha256(grid.data.tobytes()).hexdigest() == BUILDING_SHA256


def test_the_building_grid_is_4000_square_at_5_cm(big: Map) -> None:
    grid, _ = big
    assert (grid.height, grid.width) == (4000, 4000)
    assert grid.resolution == 0.05
    assert (grid.origin_x, grid.origin_y) == (-100.0, -100.0)
    # World (0, 0) is the map centre and lies in the main corridor.
    assert grid.cell_of(0.0, 0.0) == (2000, 2000)
    assert grid.value_at(0.0, 0.0) == FREE


def test_only_the_building_was_explored(big: Map) -> None:
    grid, _ = big
    explored = float(np.mean(grid.data != UNKNOWN))
    assert 0.05 <= explored <= 0.20
    bounds = grid.known_bounds()
    assert bounds is not None
    r0, r1, c0, c1 = bounds
    height_m, width_m = (r1 - r0) * grid.resolution, (c1 - c0) * grid.resolution
    assert 80 <= width_m <= 100 and 50 <= height_m <= 70
    # Walls enclose the explored floor and every unexplored room inside it (stores, lift
    # shafts, the stairs down): no free cell touches an unknown one.
    part = known_part(grid)
    unknown = (part.data == UNKNOWN).astype(np.uint8)
    near_unknown = cv2.dilate(unknown, np.ones((3, 3), np.uint8)) > 0
    assert not np.any((part.data == FREE) & near_unknown)
    assert np.any(unknown[1:-1, 1:-1])  # there are unexplored rooms inside


def test_the_building_has_walls_rooms_and_furniture(big: Map) -> None:
    grid, _ = big
    part = known_part(grid)
    occupied = float(np.mean(part.data == 100))
    free = float(np.mean(part.data == FREE))
    assert 0.05 < occupied < 0.25  # walls and furniture, not a solid block
    assert free > 0.6
    # Walls are 0.2 m: the wall south of the main corridor, just west of world (0, 0).
    column = part.data[:, part.cell_of(-10.0, 0.0)[1]]
    row_wall = part.cell_of(-10.0, -1.2)[0]
    assert (column[row_wall - 3 : row_wall + 3] == 100).sum() == 4
    # The main corridor is 2.2 m clear.
    clear = clearance(part)
    r, c = part.cell_of(-10.0, 0.0)
    assert 1.0 <= clear[r, c] <= 1.15


def test_the_building_has_the_named_places(big: Map) -> None:
    _, places = big
    assert {"lobby", "kitchen", "lab", "lift", "reception", "office-1", "meeting-room"} <= set(
        places
    )
    assert next(iter(places)) == "lobby"  # the default start
    for pose in places.values():
        assert -math.pi <= pose.yaw < math.pi


@pytest.mark.parametrize("which", ["big", "small"])
def test_every_place_is_on_free_floor_with_room_to_spare(
    which: str, request: pytest.FixtureRequest
) -> None:
    grid, places = request.getfixturevalue(which)
    part = known_part(grid)
    clear = clearance(part)
    for name, pose in places.items():
        row, col = part.cell_of(pose.x, pose.y)
        assert part.data[row, col] == FREE, name
        # Cell centre to the nearest blocked cell's edge.
        assert clear[row, col] - part.resolution / 2 >= 0.6, name


@pytest.mark.parametrize("which", ["big", "small"])
def test_a_round_robot_reaches_every_place_and_every_room(
    which: str, request: pytest.FixtureRequest
) -> None:
    grid, places = request.getfixturevalue(which)
    part = known_part(grid)
    labels = reachable_labels(part, ROBOT_RADIUS + MARGIN)
    home = label_of(part, labels, next(iter(places.values())))
    assert home != 0
    assert {name: label_of(part, labels, pose) for name, pose in places.items()} == dict.fromkeys(
        places, home
    )
    # Nowhere the robot fits is cut off from the rest: every room is reachable.
    assert set(np.unique(labels)) == {0, home}


@pytest.mark.parametrize(
    ("which", "behind_doors", "open_to_corridor"),
    [
        ("big", ["kitchen", "lab", "office-1", "meeting-room", "library", "stairs"], ["lift"]),
        ("small", ["room-a", "room-b"], ["corridor"]),
    ],
)
def test_rooms_are_reached_through_doors(
    which: str,
    behind_doors: list[str],
    open_to_corridor: list[str],
    request: pytest.FixtureRequest,
) -> None:
    grid, places = request.getfixturevalue(which)
    part = known_part(grid)
    # A robot 1.3 m wide fits through the corridors (2.2 m) and the lobby's and lift lobby's
    # wide openings but through no door (0.9–1.2 m): each room it stands in is cut off.
    labels = reachable_labels(part, 0.65)
    home = label_of(part, labels, next(iter(places.values())))
    assert home != 0
    for name in open_to_corridor:
        assert label_of(part, labels, places[name]) == home, name
    for name in behind_doors:
        assert label_of(part, labels, places[name]) not in (0, home), name
    # The normal robot gets in, so it is the doors that connect the rooms.
    labels = reachable_labels(part, ROBOT_RADIUS + MARGIN)
    home = label_of(part, labels, next(iter(places.values())))
    for name in behind_doors:
        assert label_of(part, labels, places[name]) == home, name


# --------------------------------------------------------------------------- the small map


def test_the_small_map(small: Map) -> None:
    grid, places = small
    assert grid.resolution == 0.05
    assert grid.size_m == pytest.approx((14.0, 10.0))
    assert list(places) == ["start", "room-a", "room-b", "corridor"]
    # An unknown border surrounds it.
    data = grid.data
    for edge in (data[0], data[-1], data[:, 0], data[:, -1]):
        assert (edge == UNKNOWN).all()
    assert 0.5 < float(np.mean(data != UNKNOWN)) < 0.9


def test_the_small_map_is_deterministic(small: Map) -> None:
    again, places = generate_small()
    assert np.array_equal(again.data, small[0].data)
    assert places == small[1]


# --------------------------------------------------------------------------- package data


def test_the_packaged_small_map_is_the_generators_output(small: Map, tmp_path: Path) -> None:
    grid, places = small
    save_map(grid, tmp_path / "small.yaml")
    save_places(places, tmp_path / "small.places.toml")
    for name in ("small.yaml", "small.pgm", "small.places.toml"):
        assert (MAPS / name).read_bytes() == (tmp_path / name).read_bytes(), name
    loaded = load_map(resolve_map("small"))
    assert np.array_equal(loaded.data, grid.data)
    assert (loaded.origin_x, loaded.origin_y) == (grid.origin_x, grid.origin_y)
    assert load_places(places_path_for(resolve_map("small"))) == places


def test_the_packaged_building_places_are_the_generators(big: Map, tmp_path: Path) -> None:
    _, places = big
    save_places(places, tmp_path / "building.places.toml")
    packaged = MAPS / "building.places.toml"
    assert packaged.read_bytes() == (tmp_path / "building.places.toml").read_bytes()
    assert load_places(packaged) == places


# --------------------------------------------------------------------------- resolving


@pytest.fixture
def counted_generator(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Replace the building generator by the session's one, counting calls."""
    calls: list[int] = []

    def generate() -> Map:
        calls.append(1)
        return cached_building()

    monkeypatch.setattr(building, "generate_building", generate)
    return calls


def test_the_building_is_generated_into_the_cache_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, counted_generator: list[int], big: Map
) -> None:
    monkeypatch.setenv("TELEBOT_CACHE_DIR", str(tmp_path / "cache"))
    path = resolve_map("building")
    assert path == tmp_path / "cache" / "maps" / "building-v1.yaml"
    assert counted_generator == [1]
    files = sorted(p.name for p in path.parent.iterdir())
    # Nothing half-written is left behind: only the three finished files.
    assert files == ["building-v1.pgm", "building-v1.places.toml", "building-v1.yaml"]
    stamps = {p.name: p.stat().st_mtime_ns for p in path.parent.iterdir()}

    assert resolve_map("building") == path
    assert counted_generator == [1]  # reused, not regenerated
    assert {p.name: p.stat().st_mtime_ns for p in path.parent.iterdir()} == stamps

    grid, places = big
    loaded = load_map(path)
    assert np.array_equal(loaded.data, grid.data)
    assert (loaded.origin_x, loaded.origin_y, loaded.resolution) == (-100.0, -100.0, 0.05)
    assert load_places(places_path_for(path)) == places


def test_an_incomplete_cache_is_regenerated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, counted_generator: list[int]
) -> None:
    monkeypatch.setenv("TELEBOT_CACHE_DIR", str(tmp_path))
    path = resolve_map("building")
    path.with_suffix(".pgm").unlink()
    assert resolve_map("building") == path
    assert counted_generator == [1, 1]
    assert path.with_suffix(".pgm").stat().st_size > 4000 * 4000


def test_cache_dir_follows_the_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TELEBOT_CACHE_DIR", str(tmp_path / "explicit"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "explicit"
    monkeypatch.delenv("TELEBOT_CACHE_DIR")
    assert cache_dir() == tmp_path / "xdg" / "telebot"
    monkeypatch.setenv("XDG_CACHE_HOME", "")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "telebot"


def test_a_map_path_resolves_relative_to_the_base_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "maps").mkdir()
    target = tmp_path / "maps" / "floor.yaml"
    target.write_text("image: floor.pgm\n", encoding="utf-8")
    assert resolve_map("maps/floor.yaml", base_dir=tmp_path) == target
    assert resolve_map(str(target)) == target
    monkeypatch.chdir(tmp_path)
    assert resolve_map("maps/floor.yaml") == Path("maps/floor.yaml")


@pytest.mark.parametrize("spec", ["nowhere.yaml", "buildings", "maps"])
def test_an_unknown_map_names_itself_and_the_built_in_maps(tmp_path: Path, spec: str) -> None:
    (tmp_path / "maps").mkdir()
    with pytest.raises(MapError) as info:
        resolve_map(spec, base_dir=tmp_path)
    message = str(info.value)
    assert repr(spec) in message
    assert str(tmp_path / spec) in message
    assert "built-in maps: building, small" in message
    assert "\n" not in message


def test_builtin_names() -> None:
    assert BUILTIN_MAPS == ("building", "small")
    assert resolve_map("small") == MAPS / "small.yaml"


# --------------------------------------------------------------------------- command line


def test_main_writes_a_loadable_map(
    tmp_path: Path, small: Map, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--name", "small", "--out", str(tmp_path / "out")]) == 0
    yaml_path = tmp_path / "out" / "small.yaml"
    assert np.array_equal(load_map(yaml_path).data, small[0].data)
    assert load_places(places_path_for(yaml_path)) == small[1]
    assert str(yaml_path) in capsys.readouterr().out


def test_main_can_write_only_the_places(
    tmp_path: Path, counted_generator: list[int], big: Map
) -> None:
    assert main(["--name", "building", "--out", str(tmp_path), "--places-only"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["building.places.toml"]
    assert load_places(tmp_path / "building.places.toml") == big[1]
    assert counted_generator == [1]


def test_main_reports_an_unwritable_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("", encoding="utf-8")
    assert main(["--name", "small", "--out", str(blocker / "sub")]) == 1
    assert "error:" in capsys.readouterr().err


def test_main_refuses_unknown_names(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--name", "castle", "--out", "x"])
    assert info.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
