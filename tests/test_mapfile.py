"""ROS map_server map files and places files: loading as nav2 does, saving as map_saver does."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from telebot.errors import ConfigError, MapError
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import (
    SAVE_FREE_THRESH,
    SAVE_OCCUPIED_THRESH,
    grid_to_image,
    image_to_grid,
    load_map,
    load_places,
    map_yaml,
    places_path_for,
    save_map,
    save_places,
)
from telebot.robot.nav import Pose2D

U, F, X = -1, 0, 100  # unknown, free, occupied (X marks a wall)


def write_pgm(path: Path, pixels: npt.NDArray[np.uint8]) -> None:
    """A binary (P5) PGM, written by hand so the test does not trust OpenCV's writer."""
    height, width = pixels.shape
    path.write_bytes(f"P5\n{width} {height}\n255\n".encode() + pixels.tobytes())


def write_map(
    folder: Path,
    pixels: npt.NDArray[Any] | None = None,
    *,
    image: Any = "map.pgm",
    name: str = "map.yaml",
    **overrides: Any,
) -> Path:
    """A map YAML (nav2 defaults, keys overridable; ``None`` drops a key) and its image."""
    if pixels is not None:
        if str(image).endswith(".pgm"):
            write_pgm(folder / image, pixels)
        else:
            assert cv2.imwrite(str(folder / image), pixels)
    meta: dict[str, Any] = {
        "image": image,  # may be None (dropped) or mistyped on purpose
        "mode": "trinary",
        "resolution": 0.05,
        "origin": [0.0, 0.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    meta.update(overrides)
    meta = {key: value for key, value in meta.items() if value is not None}
    path = folder / name
    path.write_text(yaml.safe_dump(meta), encoding="utf-8")
    return path


def row(*values: int) -> npt.NDArray[np.uint8]:
    return np.array([values], dtype=np.uint8)


# --------------------------------------------------------------------------- loading


def test_trinary_thresholds_follow_nav2(tmp_path: Path) -> None:
    # p = (255 - v) / 255: 0 → 1.0, 89 → 0.651, 90 → 0.647, 205 → 0.196.., 206 → 0.192, 254.
    path = write_map(tmp_path, row(0, 89, 90, 205, 206, 254, 255))
    grid = load_map(path)
    assert grid.data.tolist() == [[X, X, U, U, F, F, F]]


def test_the_unknown_grey_is_free_with_ros2s_default_free_thresh(tmp_path: Path) -> None:
    # The reason save_map writes 0.196: at 0.25, map_saver's own unknown grey reads as free.
    path = write_map(tmp_path, row(205), free_thresh=0.25)
    assert load_map(path).data.tolist() == [[F]]


def test_rows_are_flipped_and_georeferenced(tmp_path: Path) -> None:
    pixels = np.array([[0, 254, 254], [254, 254, 205]], dtype=np.uint8)  # top row first
    path = write_map(tmp_path, pixels, resolution=0.1, origin=[-2.5, 3.0, 0.0])
    grid = load_map(path)
    assert grid.data.tolist() == [[F, F, U], [X, F, F]]  # row 0 = bottom image row
    assert (grid.resolution, grid.origin_x, grid.origin_y) == (0.1, -2.5, 3.0)
    assert grid.value_at(-2.45, 3.15) == X  # top-left pixel is at the far (high y) row


def test_negate_swaps_black_and_white(tmp_path: Path) -> None:
    path = write_map(tmp_path, row(0, 100, 254), negate=1)
    assert load_map(path).data.tolist() == [[F, U, X]]
    path = write_map(tmp_path, row(0, 100, 254), negate=True, name="b.yaml")
    assert load_map(path).data.tolist() == [[F, U, X]]


def test_scale_mode_scales_values_between_the_thresholds(tmp_path: Path) -> None:
    # free 0.2, occupied 0.8: p = 0.502 → rint(0.302 / 0.6 · 100) = 50; p = 0.8 exactly is
    # not above occupied_thresh → 100 by scaling; p = 0.2 (v = 204) → rint(≈0) = 0.
    path = write_map(
        tmp_path, row(0, 51, 127, 204, 255), mode="scale", free_thresh=0.2, occupied_thresh=0.8
    )
    assert load_map(path).data.tolist() == [[X, 100, 50, 0, F]]


def test_scale_mode_honours_negate(tmp_path: Path) -> None:
    path = write_map(
        tmp_path, row(0, 128, 255), mode="scale", negate=1, free_thresh=0.2, occupied_thresh=0.8
    )
    # p = 0.502 → 50 as above; black is free, white occupied.
    assert load_map(path).data.tolist() == [[F, 50, X]]


def test_raw_mode_keeps_values_and_ignores_negate(tmp_path: Path) -> None:
    pixels = row(0, 1, 50, 100, 101, 205, 255)
    for negate in (0, 1):
        path = write_map(tmp_path, pixels, mode="raw", negate=negate, name=f"{negate}.yaml")
        assert load_map(path).data.tolist() == [[0, 1, 50, 100, U, U, U]]


def test_mode_is_case_insensitive_like_nav2(tmp_path: Path) -> None:
    path = write_map(tmp_path, row(0, 254), mode="Trinary")
    assert load_map(path).data.tolist() == [[X, F]]


def test_a_colour_png_map_averages_its_channels(tmp_path: Path) -> None:
    # BGR pixels: mean 85 → p 0.667 (occupied), mean 170 → 0.333 (unknown), white, black.
    bgr = np.array([[[255, 0, 0], [0, 255, 255], [255, 255, 255], [0, 0, 0]]], dtype=np.uint8)
    path = write_map(tmp_path, bgr, image="map.png")
    assert load_map(path).data.tolist() == [[X, U, F, X]]


def test_a_16_bit_png_map(tmp_path: Path) -> None:
    grey = np.array([[0, 52428, 65535]], dtype=np.uint16)  # p = 1, 0.2, 0
    path = write_map(tmp_path, grey, image="map.png")
    assert load_map(path).data.tolist() == [[X, U, F]]


def test_alpha_is_averaged_in_trinary_and_means_unknown_in_scale(tmp_path: Path) -> None:
    # Opaque white, transparent white, opaque black (BGRA).
    bgra = np.array([[[255, 255, 255, 255], [255, 255, 255, 0], [0, 0, 0, 255]]], np.uint8)
    # Trinary: transparent white averages to 191.25 → p = 0.25 → unknown; opaque black
    # averages to 63.75 → p = 0.75 → occupied.
    path = write_map(tmp_path, bgra, image="map.png")
    assert load_map(path).data.tolist() == [[F, U, X]]
    path = write_map(tmp_path, bgra, image="map.png", mode="scale", name="scale.yaml")
    assert load_map(path).data.tolist() == [[F, U, X]]
    # Scale ignores alpha for the value: a barely transparent white pixel is still unknown.
    bgra[0, 0, 3] = 254
    cv2.imwrite(str(tmp_path / "map.png"), bgra)
    assert load_map(path).data.tolist()[0][0] == U


def test_an_absolute_image_path(tmp_path: Path) -> None:
    images = tmp_path / "images"
    images.mkdir()
    write_pgm(images / "abs.pgm", row(0, 254))
    folder = tmp_path / "maps"
    folder.mkdir()
    path = write_map(folder, image=str(images / "abs.pgm"))
    assert load_map(path).data.tolist() == [[X, F]]


def test_numbers_that_yaml_1_1_reads_as_strings_are_accepted(tmp_path: Path) -> None:
    # "5e-2" is a string to PyYAML but a number to yaml-cpp (nav2); take it as nav2 does.
    write_pgm(tmp_path / "map.pgm", row(0))
    path = tmp_path / "map.yaml"
    path.write_text(
        "image: map.pgm\nresolution: 5e-2\norigin: [0, 0, 0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n",
        encoding="utf-8",
    )
    assert load_map(path).resolution == 0.05


# --------------------------------------------------------------------------- errors


def _case(tmp_path: Path, **overrides: Any) -> Path:
    write_pgm(tmp_path / "map.pgm", row(0, 254))
    return write_map(tmp_path, **overrides)


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        ({"image": None}, "missing key 'image'"),
        ({"resolution": None}, "missing key 'resolution'"),
        ({"origin": None}, "missing key 'origin'"),
        ({"negate": None}, "missing key 'negate'"),
        ({"occupied_thresh": None}, "missing key 'occupied_thresh'"),
        ({"free_thresh": None}, "missing key 'free_thresh'"),
        ({"image": 3}, "'image' must be a file name"),
        ({"image": ""}, "'image' must be a file name"),
        ({"resolution": "fine"}, "'resolution' must be a number"),
        ({"resolution": True}, "'resolution' must be a number"),
        ({"resolution": 0}, "resolution 0.0 must be positive"),
        ({"resolution": -0.05}, "must be positive"),
        ({"resolution": float("nan")}, "'resolution' must be finite"),
        ({"resolution": float("inf")}, "'resolution' must be finite"),
        ({"origin": [1.0, 2.0]}, "'origin' must be a list [x, y, yaw]"),
        ({"origin": "0 0 0"}, "'origin' must be a list [x, y, yaw]"),
        ({"origin": [0.0, "left", 0.0]}, "'origin' must be a number"),
        ({"origin": [0.0, float("inf"), 0.0]}, "'origin' must be finite"),
        ({"origin": [0.0, 0.0, 0.3]}, "origin yaw 0.3 is not supported: rotate the map"),
        ({"negate": 2}, "'negate' must be 0, 1, true or false"),
        ({"negate": "no way"}, "'negate' must be 0, 1, true or false"),
        ({"occupied_thresh": 1.5}, "occupied_thresh 1.5 must be between 0 and 1"),
        ({"free_thresh": -0.1}, "free_thresh -0.1 must be between 0 and 1"),
        ({"free_thresh": 0.7}, "free_thresh 0.7 must be below occupied_thresh 0.65"),
        ({"free_thresh": 0.65}, "must be below occupied_thresh"),
        ({"occupied_thresh": "high"}, "'occupied_thresh' must be a number"),
        ({"mode": "binary"}, "unknown mode 'binary'"),
        ({"mode": 1}, "unknown mode 1"),
        ({"image": "elsewhere.pgm"}, "elsewhere.pgm: no such file"),
    ],
)
def test_every_bad_map_yaml_is_one_map_error_line_naming_the_file(
    tmp_path: Path, overrides: dict[str, Any], fragment: str
) -> None:
    path = _case(tmp_path, **overrides)
    with pytest.raises(MapError) as info:
        load_map(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    assert fragment in message
    assert "\n" not in message


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("image: [unclosed\n", "invalid YAML"),
        ("- image: map.pgm\n", "expected a YAML mapping"),
        ("", "expected a YAML mapping"),
        ("\tkey: value\n", "invalid YAML"),
    ],
)
def test_yaml_that_does_not_parse_is_a_map_error(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(MapError) as info:
        load_map(path)
    assert str(info.value).startswith(f"{path}: ")
    assert fragment in str(info.value)
    assert "\n" not in str(info.value)


def test_a_missing_yaml_is_a_map_error(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.yaml"
    with pytest.raises(MapError, match="no such map file") as info:
        load_map(path)
    assert str(path) in str(info.value)
    with pytest.raises(MapError, match="is a directory"):
        load_map(tmp_path)


@pytest.mark.parametrize(
    "content", [b"", b"P5\n2 2\n255\n", b"not an image at all", b"\x89PNG\r\n\x1a\n\x00"]
)
def test_an_image_that_does_not_decode_is_a_map_error(tmp_path: Path, content: bytes) -> None:
    path = write_map(tmp_path)
    (tmp_path / "map.pgm").write_bytes(content)
    with pytest.raises(MapError) as info:
        load_map(path)
    assert str(info.value).startswith(f"{path}: image {tmp_path / 'map.pgm'}: ")
    assert "not an image OpenCV can decode" in str(info.value)


def test_an_image_that_is_a_directory_is_a_map_error(tmp_path: Path) -> None:
    (tmp_path / "map.pgm").mkdir()
    path = write_map(tmp_path)
    with pytest.raises(MapError, match=r"map\.pgm: is a directory"):
        load_map(path)


def test_a_tiny_origin_yaw_is_float_noise_and_accepted(tmp_path: Path) -> None:
    path = _case(tmp_path, origin=[1.0, 2.0, 1e-12])
    assert load_map(path).origin_x == 1.0


# --------------------------------------------------------------------------- saving


def test_save_map_writes_what_map_saver_writes(tmp_path: Path) -> None:
    data = np.array([[F, X, U], [X, F, F]], dtype=np.int8)
    grid = OccupancyGrid(data=data, resolution=0.05, origin_x=-1.5, origin_y=2.25)
    yaml_path = tmp_path / "out" / "floor.yaml"
    save_map(grid, yaml_path)
    pgm = (tmp_path / "out" / "floor.pgm").read_bytes()
    assert pgm.startswith(b"P5\n")
    # The top image row is the grid's last row; free 254, occupied 0, unknown 205.
    assert pgm.endswith(bytes([0, 254, 254, 254, 0, 205]))
    meta = yaml.safe_load(yaml_path.read_text(encoding="utf-8"))
    assert meta == {
        "image": "floor.pgm",
        "mode": "trinary",
        "resolution": 0.05,
        "origin": [-1.5, 2.25, 0.0],
        "negate": 0,
        "occupied_thresh": SAVE_OCCUPIED_THRESH,
        "free_thresh": SAVE_FREE_THRESH,
    }
    # OpenCV (any image library) reads the same pixels.
    image = cv2.imread(str(tmp_path / "out" / "floor.pgm"), cv2.IMREAD_UNCHANGED)
    assert image.tolist() == [[0, 254, 254], [254, 0, 205]]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["floor.pgm", "floor.yaml"]


def test_save_map_writes_non_trinary_values_as_map_saver_does(tmp_path: Path) -> None:
    # ≤ 20 (rint of free_thresh · 100) free, ≥ 65 occupied, between and out of range unknown.
    data = np.array([[0, 20, 21, 64, 65, 100, 101, -5]], dtype=np.int8)
    save_map(OccupancyGrid(data, 0.1, 0.0, 0.0), tmp_path / "m.yaml")
    assert load_map(tmp_path / "m.yaml").data.tolist() == [[F, F, U, U, X, X, U, U]]


def test_grid_to_image_and_image_to_grid_are_what_save_map_and_load_map_do(
    tmp_path: Path,
) -> None:
    data = np.array([[0, 20, 21, 64, 65, 100, 101, -5], [X, F, U, F, X, U, F, X]], dtype=np.int8)
    grid = OccupancyGrid(data, 0.1, -2.0, 3.0)
    save_map(grid, tmp_path / "m.yaml")
    image = grid_to_image(grid)
    assert image.dtype == np.uint8
    assert image.tolist() == cv2.imread(str(tmp_path / "m.pgm"), cv2.IMREAD_UNCHANGED).tolist()
    loaded = load_map(tmp_path / "m.yaml")
    again = image_to_grid(image, 0.1, -2.0, 3.0)
    assert np.array_equal(again.data, loaded.data)
    assert (again.resolution, again.origin_x, again.origin_y) == (0.1, -2.0, 3.0)


def test_map_yaml_refuses_bad_numbers() -> None:
    with pytest.raises(ValueError, match="resolution"):
        map_yaml("m.png", 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="origin_x"):
        map_yaml("m.png", 0.05, math.nan, 0.0)
    with pytest.raises(ValueError, match="image_name"):
        map_yaml("", 0.05, 0.0, 0.0)


trinary = arrays(
    np.int8,
    st.tuples(st.integers(1, 12), st.integers(1, 12)),
    elements=st.sampled_from([U, F, X]),
)
coordinate = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(
    data=trinary,
    resolution=st.floats(1e-3, 10.0, allow_nan=False),
    origin_x=coordinate,
    origin_y=coordinate,
)
def test_trinary_grids_round_trip_exactly(
    data: npt.NDArray[np.int8], resolution: float, origin_x: float, origin_y: float
) -> None:
    grid = OccupancyGrid(data=data, resolution=resolution, origin_x=origin_x, origin_y=origin_y)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "map.yaml"
        save_map(grid, path)
        loaded = load_map(path)
    assert np.array_equal(loaded.data, grid.data)
    assert (loaded.resolution, loaded.origin_x, loaded.origin_y) == (
        resolution,
        origin_x,
        origin_y,
    )


def test_save_map_replaces_an_existing_map(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    save_map(OccupancyGrid(np.full((2, 2), X, np.int8), 0.05, 0.0, 0.0), path)
    save_map(OccupancyGrid(np.full((1, 3), F, np.int8), 0.05, 0.0, 0.0), path)
    assert load_map(path).data.tolist() == [[F, F, F]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pgm", "m.yaml"]


def test_save_map_into_an_unwritable_place_is_a_map_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder", encoding="utf-8")
    with pytest.raises(MapError, match="cannot write the map"):
        save_map(OccupancyGrid(np.zeros((1, 1), np.int8), 0.05, 0, 0), blocker / "m.yaml")


# --------------------------------------------------------------------------- places


def test_places_load_with_yaw_in_radians(tmp_path: Path) -> None:
    path = tmp_path / "p.places.toml"
    path.write_text(
        "[places.lab]\nx = 1.5\ny = -2\nyaw_deg = 90\n\n"
        "[places.kitchen_2]\nx = 0.0\ny = 3.25\n\n"
        "[places.back-door]\nx = 4\ny = 5\nyaw_deg = 270.0\n",
        encoding="utf-8",
    )
    places = load_places(path)
    assert list(places) == ["lab", "kitchen_2", "back-door"]  # file order is kept
    assert (places["lab"].x, places["lab"].y) == (1.5, -2.0)
    assert places["lab"].yaw == pytest.approx(math.pi / 2)
    assert places["kitchen_2"] == Pose2D(0.0, 3.25, 0.0)
    assert places["back-door"].yaw == pytest.approx(-math.pi / 2)


def test_places_round_trip(tmp_path: Path) -> None:
    places = {
        "lobby": Pose2D(0.0, -25.0, math.pi / 2),
        "far-corner": Pose2D(-44.123456, 29.5, -3.0),
        "back": Pose2D(1.0, 2.0, -math.pi),
        "x1": Pose2D(1e-7, -0.0, 0.1),
    }
    path = tmp_path / "sub" / "p.places.toml"
    save_places(places, path)
    loaded = load_places(path)
    assert list(loaded) == list(places)
    for name, pose in places.items():
        assert loaded[name].x == pytest.approx(pose.x, abs=1e-6)
        assert loaded[name].y == pytest.approx(pose.y, abs=1e-6)
        assert math.cos(loaded[name].yaw - pose.yaw) == pytest.approx(1.0, abs=1e-9)
    assert "yaw_deg = 180.0" in path.read_text(encoding="utf-8")  # not -180
    assert "yaw_deg = -171.887" in path.read_text(encoding="utf-8")  # -3 rad, 0.001°


def test_save_places_refuses_bad_names_and_numbers(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="place name 'Lobby'"):
        save_places({"Lobby": Pose2D(0, 0)}, tmp_path / "p.toml")
    with pytest.raises(ValueError, match="not finite"):
        save_places({"lobby": Pose2D(math.nan, 0)}, tmp_path / "p.toml")
    assert not (tmp_path / "p.toml").exists()


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("[places.Lobby]\nx = 1\ny = 2\n", "places.Lobby.[key]: Value error, place name 'Lobby'"),
        ("[places.2nd]\nx = 1\ny = 2\n", "place name '2nd'"),
        ('[places."a b"]\nx = 1\ny = 2\n', "place name 'a b'"),
        ("[places.lab]\ny = 2\n", "places.lab.x: Field required"),
        ('[places.lab]\nx = "1"\ny = 2\n', "places.lab.x: Input should be a valid number"),
        ("[places.lab]\nx = true\ny = 2\n", "places.lab.x"),
        ("[places.lab]\nx = nan\ny = 2\n", "places.lab.x: Input should be a finite number"),
        ("[places.lab]\nx = 1\ny = inf\n", "places.lab.y: Input should be a finite number"),
        ("[places.lab]\nx = 1\ny = 2\nyaw_deg = -inf\n", "places.lab.yaw_deg"),
        ("[places.lab]\nx = 1\ny = 2\nyaw = 90\n", "places.lab.yaw: unknown key"),
        ("[place.lab]\nx = 1\ny = 2\n", "place: unknown key"),
        ("[places.lab\n", "invalid TOML"),
    ],
)
def test_bad_places_files_are_one_config_error_line(
    tmp_path: Path, text: str, fragment: str
) -> None:
    path = tmp_path / "bad.places.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_places(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    assert fragment in message
    assert "\n" not in message


def test_a_missing_places_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_places(tmp_path / "none.places.toml")


def test_an_empty_places_file_has_no_places(tmp_path: Path) -> None:
    path = tmp_path / "empty.places.toml"
    path.write_text("# nothing yet\n", encoding="utf-8")
    assert load_places(path) == {}


def test_places_path_for_sits_beside_the_yaml() -> None:
    assert places_path_for(Path("/maps/floor-2.yaml")) == Path("/maps/floor-2.places.toml")
    assert places_path_for(Path("rel/a.b.yaml")) == Path("rel/a.b.places.toml")
