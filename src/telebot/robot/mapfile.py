"""Map files: ROS ``map_server`` maps (a YAML file and an image) and named-place files.

:func:`load_map` reads a map exactly as nav2_map_server's ``map_io`` does, so any map a ROS 2
robot uses loads here unchanged, and :func:`save_map` writes what ``map_saver`` writes (a
binary PGM: free 254, occupied 0, unknown 205, plus its YAML), so any ROS tool loads our maps.

This module is the one home of the map_server image and YAML conventions; the map transfer
(:mod:`telebot.services.mapxfer.wire`) uses them through :func:`grid_to_image`,
:func:`image_to_grid` and :func:`map_yaml`. Writing, each cell becomes a pixel of
map_saver's trinary image:

======================================  =====  ========
cell value                              pixel  meaning
======================================  =====  ========
0 … :data:`CELL_FREE_MAX`               254    free
:data:`CELL_OCCUPIED_MIN` … 100         0      occupied
-1, anything else                       205    unknown
======================================  =====  ========

The two limits are the save thresholds as percentages, and the YAML beside the image names
those thresholds, so every loader reads 254, 205 and 0 back as free, unknown and occupied.

Loading, per pixel (``M`` is 255 for 8-bit images, 65535 for 16-bit ones):

* ``shade`` is the mean of the colour channels divided by ``M``; in *trinary* mode an alpha
  channel, when the image has one, is averaged in too (nav2 and ROS 1 do this "to preserve
  existing behavior"), so a transparent pixel reads lighter;
* ``p = 1 - shade`` (or ``shade`` when ``negate``) is how occupied the pixel is;
* *trinary*: ``p > occupied_thresh`` → 100, ``p < free_thresh`` → 0, otherwise -1;
* *scale*: a pixel that is not fully opaque → -1, then as trinary except that values in
  between become ``rint((p - free) / (occupied - free) · 100)``;
* *raw*: ``round(shade · 255)`` as it is, values above 100 → -1 (``negate`` is ignored).

The image's top row is the row farthest from the origin, so rows are flipped to make row 0
the one nearest the origin, as :class:`~telebot.robot.grid.OccupancyGrid` wants.

Every problem raises one :class:`~telebot.errors.MapError` line naming the file.

Places files are TOML, one table per place (metres, degrees counter-clockwise)::

    [places.kitchen]
    x = -13.0
    y = -27.0
    yaw_deg = -90.0
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import numpy.typing as npt
import yaml
from pydantic import AfterValidator, Field

from telebot.config import StrictModel, load_toml
from telebot.errors import MapError
from telebot.robot.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid
from telebot.robot.nav import Pose2D, normalize_angle

__all__ = [
    "CELL_FREE_MAX",
    "CELL_OCCUPIED_MIN",
    "MAP_MODES",
    "PIXEL_FREE",
    "PIXEL_OCCUPIED",
    "PIXEL_UNKNOWN",
    "PLACE_NAME_PATTERN",
    "SAVE_FREE_THRESH",
    "SAVE_OCCUPIED_THRESH",
    "PlaceEntry",
    "PlacesFile",
    "grid_to_image",
    "image_to_grid",
    "load_map",
    "load_places",
    "map_yaml",
    "places_path_for",
    "save_map",
    "save_places",
]

#: The ``mode`` values nav2_map_server understands.
MAP_MODES = ("trinary", "scale", "raw")

#: Thresholds written by :func:`save_map`. ``map_saver`` in ROS 2 defaults to a free
#: threshold of 0.25, but then its own unknown grey (205, p = 50/255 ≈ 0.196) reloads as
#: *free* (a known nav2 pitfall, slam_toolbox issue #587); ROS 1's 0.196 keeps it unknown in
#: every loader while 254 stays free and 0 occupied.
SAVE_OCCUPIED_THRESH = 0.65
SAVE_FREE_THRESH = 0.196

#: Cells up to this value (20) are written free, from :data:`CELL_OCCUPIED_MIN` (65) up
#: occupied, the rest unknown: the save thresholds as percentages, the one rule for every
#: map image we write.
CELL_FREE_MAX = round(SAVE_FREE_THRESH * 100.0)
CELL_OCCUPIED_MIN = round(SAVE_OCCUPIED_THRESH * 100.0)

#: Pixel values of map_saver's trinary images.
PIXEL_FREE = 254
PIXEL_OCCUPIED = 0
PIXEL_UNKNOWN = 205

#: What a place name may look like.
PLACE_NAME_PATTERN = re.compile(r"[a-z][a-z0-9_-]*")

# An origin yaw this close to zero is float noise from a quaternion round trip, not a rotation.
_YAW_TOLERANCE = 1e-6


# --------------------------------------------------------------------------- map YAML


@dataclass(frozen=True, slots=True)
class _Reading:
    """How a map YAML says its image's pixels become cells."""

    mode: str
    negate: bool
    occupied_thresh: float
    free_thresh: float


#: How :func:`map_yaml` (and so :func:`save_map`) says to read the image.
_SAVED = _Reading(
    mode="trinary",
    negate=False,
    occupied_thresh=SAVE_OCCUPIED_THRESH,
    free_thresh=SAVE_FREE_THRESH,
)


@dataclass(frozen=True, slots=True)
class _MapMeta:
    """The validated contents of a map YAML file."""

    image: Path
    resolution: float
    origin_x: float
    origin_y: float
    reading: _Reading


def _number(path: Path, doc: Mapping[str, Any], key: str) -> float:
    """``doc[key]`` as a finite float, or a MapError naming ``path`` and ``key``."""
    if key not in doc:
        raise MapError(f"{path}: missing key '{key}'")
    return _as_number(path, key, doc[key])


def _as_number(path: Path, key: str, value: Any) -> float:
    # yaml-cpp (nav2) parses any scalar that reads as a number, so a PyYAML string such as
    # "5e-2" (YAML 1.1 wants a dot) is accepted too; booleans are not numbers here.
    if isinstance(value, bool):
        raise MapError(f"{path}: '{key}' must be a number, not {value!r}")
    if isinstance(value, int | float):
        number = float(value)
    elif isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            raise MapError(f"{path}: '{key}' must be a number, not {value!r}") from None
    else:
        raise MapError(f"{path}: '{key}' must be a number, not {value!r}")
    if not math.isfinite(number):
        raise MapError(f"{path}: '{key}' must be finite, not {value!r}")
    return number


def _read_file(path: Path, where: str, *, missing: str, directory: str) -> bytes:
    """The bytes of ``path``; a MapError ``"<where>: …"`` if missing, a folder or unreadable."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise MapError(f"{where}: {missing}") from None
    except IsADirectoryError:
        raise MapError(f"{where}: {directory}") from None
    except OSError as exc:
        raise MapError(f"{where}: cannot read: {exc.strerror}") from exc


def _read_map_yaml(path: Path) -> _MapMeta:
    """Read and check a map YAML file; every problem is one MapError line."""
    raw = _read_file(
        path, str(path), missing="no such map file", directory="is a directory, not a map YAML file"
    )
    try:
        doc = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        # PyYAML's own message spans several lines and quotes the text; keep what and where.
        reason = " ".join(str(exc).split())
        if isinstance(exc, yaml.MarkedYAMLError) and exc.problem and exc.problem_mark:
            mark = exc.problem_mark
            reason = f"{exc.problem} (line {mark.line + 1}, column {mark.column + 1})"
        raise MapError(f"{path}: invalid YAML: {reason}") from exc
    if not isinstance(doc, dict):
        raise MapError(f"{path}: expected a YAML mapping of map settings, not {doc!r:.60}")

    if "image" not in doc:
        raise MapError(f"{path}: missing key 'image'")
    image = doc["image"]
    if not isinstance(image, str) or not image.strip():
        raise MapError(f"{path}: 'image' must be a file name, not {image!r}")
    image_path = Path(image)
    if not image_path.is_absolute():
        image_path = path.parent / image_path

    resolution = _number(path, doc, "resolution")
    if resolution <= 0:
        raise MapError(f"{path}: resolution {resolution} must be positive")

    if "origin" not in doc:
        raise MapError(f"{path}: missing key 'origin'")
    origin = doc["origin"]
    if not isinstance(origin, list) or len(origin) != 3:
        raise MapError(f"{path}: 'origin' must be a list [x, y, yaw], not {origin!r}")
    ox, oy, oyaw = (_as_number(path, "origin", value) for value in origin)
    if abs(oyaw) > _YAW_TOLERANCE:
        raise MapError(f"{path}: origin yaw {oyaw:g} is not supported: rotate the map")

    if "negate" not in doc:
        raise MapError(f"{path}: missing key 'negate'")
    negate = doc["negate"]
    if isinstance(negate, bool):
        pass
    elif isinstance(negate, int) and negate in (0, 1):
        negate = bool(negate)
    else:
        raise MapError(f"{path}: 'negate' must be 0, 1, true or false, not {negate!r}")

    occupied = _number(path, doc, "occupied_thresh")
    free = _number(path, doc, "free_thresh")
    for key, value in (("occupied_thresh", occupied), ("free_thresh", free)):
        if not 0.0 <= value <= 1.0:
            raise MapError(f"{path}: {key} {value:g} must be between 0 and 1")
    if free >= occupied:
        raise MapError(f"{path}: free_thresh {free:g} must be below occupied_thresh {occupied:g}")

    mode = doc.get("mode", "trinary")
    # nav2 lower-cases the mode before matching it.
    if not isinstance(mode, str) or mode.lower() not in MAP_MODES:
        raise MapError(f"{path}: unknown mode {mode!r} (expected trinary, scale or raw)")

    return _MapMeta(
        image=image_path,
        resolution=resolution,
        origin_x=ox,
        origin_y=oy,
        reading=_Reading(
            mode=mode.lower(), negate=negate, occupied_thresh=occupied, free_thresh=free
        ),
    )


# --------------------------------------------------------------------------- image → grid


def _decode_image(yaml_path: Path, image_path: Path) -> npt.NDArray[Any]:
    """The image as OpenCV decodes it with ``IMREAD_UNCHANGED`` (channels and depth kept)."""
    where = f"{yaml_path}: image {image_path}"
    raw = _read_file(image_path, where, missing="no such file", directory="is a directory")
    # imdecode is imread's decoder without imread's stderr chatter and path-encoding pitfalls.
    image: npt.NDArray[Any] | None = None
    import cv2  # here, not at the top: a user's client imports this module, never this decoder

    if raw:
        try:
            image = cv2.imdecode(np.frombuffer(raw, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:
            image = None
    if image is None or image.size == 0:
        raise MapError(f"{where}: not an image OpenCV can decode")
    if image.dtype not in (np.uint8, np.uint16):
        raise MapError(f"{where}: unsupported pixel type {image.dtype} (8- or 16-bit only)")
    if image.ndim == 3 and image.shape[2] not in (1, 2, 3, 4):
        raise MapError(f"{where}: unsupported number of channels {image.shape[2]}")
    return image


def _channel_sums(
    image: npt.NDArray[Any], with_alpha: bool
) -> tuple[npt.NDArray[Any], int, npt.NDArray[np.bool_] | None]:
    """Per pixel: the sum of the channels to average, how many there are, and transparency.

    A grey pixel stands for equal red, green and blue, as ImageMagick reads it: alone it is
    its own mean; with alpha averaged in it weighs three channels against alpha's one.
    """
    maxval = 65535 if image.dtype == np.uint16 else 255
    if image.ndim == 2 or image.shape[2] == 1:
        # Indexing the lookup table with the pixels themselves needs no wide copy.
        return image.reshape(image.shape[0], image.shape[1]), 1, None
    if image.shape[2] == 2:  # grey + alpha
        colour = image[:, :, 0].astype(np.uint32) * 3
    else:
        colour = image[:, :, :3].sum(axis=2, dtype=np.uint32)
    if image.shape[2] == 3:
        return colour, 3, None
    alpha = image[:, :, -1]
    transparent = alpha != maxval
    if with_alpha:
        return colour + alpha, 4, transparent
    return colour, 3, transparent


def _image_to_cells(image: npt.NDArray[Any], reading: _Reading) -> npt.NDArray[np.int8]:
    """Occupancy values for each pixel, in image row order (top row first)."""
    maxval = 65535 if image.dtype == np.uint16 else 255
    sums, count, transparent = _channel_sums(image, with_alpha=reading.mode == "trinary")
    # Each pixel's value depends only on its channel sum, so classify every possible sum
    # once (in float64, as nav2 does) and index: exact, and fast on 4000 × 4000 maps.
    possible = np.arange(count * maxval + 1, dtype=np.float64)
    shade = (possible / count) / maxval
    lut = np.empty(possible.shape, dtype=np.int8)
    if reading.mode == "raw":
        percent = np.floor(shade * 255.0 + 0.5)  # std::round: halves away from zero
        inside = (percent >= FREE) & (percent <= OCCUPIED)
        lut[:] = UNKNOWN
        lut[inside] = percent[inside].astype(np.int8)
    else:
        occ = shade if reading.negate else 1.0 - shade
        occupied = reading.occupied_thresh < occ
        free = occ < reading.free_thresh
        if reading.mode == "scale":
            scaled = np.rint(
                (occ - reading.free_thresh)
                / (reading.occupied_thresh - reading.free_thresh)
                * 100.0
            )
            lut[:] = np.clip(scaled, 0, 100).astype(np.int8)
        else:
            lut[:] = UNKNOWN
        lut[occupied] = OCCUPIED
        lut[free] = FREE
    cells: npt.NDArray[np.int8] = lut[sums]
    if reading.mode == "scale" and transparent is not None:
        cells[transparent] = UNKNOWN
    return cells


def _grid_of_image(
    image: npt.NDArray[Any],
    reading: _Reading,
    resolution: float,
    origin_x: float,
    origin_y: float,
) -> OccupancyGrid:
    # The image's top row is the grid row farthest from the origin.
    cells = _image_to_cells(image, reading)
    return OccupancyGrid(
        data=np.ascontiguousarray(cells[::-1]),
        resolution=resolution,
        origin_x=origin_x,
        origin_y=origin_y,
    )


def image_to_grid(
    image: npt.NDArray[Any], resolution: float, origin_x: float, origin_y: float
) -> OccupancyGrid:
    """The grid of a map image as map_server reads it with the YAML of :func:`map_yaml`.

    Trinary mode with :data:`SAVE_OCCUPIED_THRESH` and :data:`SAVE_FREE_THRESH`: 254 → 0,
    0 → 100, 205 → -1, other shades by their occupancy ``1 - v/M``; the exact inverse of
    :func:`grid_to_image` for grids of -1/0/100. ``image`` is 8- or 16-bit, grey or colour,
    as OpenCV decodes it with ``IMREAD_UNCHANGED``; its top row is the grid's last.
    ValueError for a bad georeference.
    """
    return _grid_of_image(image, _SAVED, resolution, origin_x, origin_y)


def load_map(path: Path) -> OccupancyGrid:
    """Load a ROS map_server map (YAML + image) as nav2_map_server does.

    Raises :class:`~telebot.errors.MapError` (one line naming the file) when the YAML or
    the image is missing, unreadable or invalid, or when the origin is rotated.
    """
    path = Path(path)
    meta = _read_map_yaml(path)
    image = _decode_image(path, meta.image)
    return _grid_of_image(image, meta.reading, meta.resolution, meta.origin_x, meta.origin_y)


# --------------------------------------------------------------------------- saving


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so readers see the old file or the whole new one, never half.

    The bytes go to a temporary file in the same folder, which then replaces ``path``.
    """
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as tmp:
            tmp.write(data)
            tmp.flush()
            # Without this a crash soon after os.replace could leave an empty file in place.
            os.fsync(tmp.fileno())
        os.chmod(tmp_name, 0o644)  # mkstemp makes 0600; map files are not secret
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise


def _cell_to_pixel() -> npt.NDArray[np.uint8]:
    # Indexed by the cell's int8 value read as uint8, so -1 (255) and every value outside
    # 0..100 land on "unknown".
    lut = np.full(256, PIXEL_UNKNOWN, dtype=np.uint8)
    lut[0 : CELL_FREE_MAX + 1] = PIXEL_FREE
    lut[CELL_OCCUPIED_MIN:101] = PIXEL_OCCUPIED
    return lut


_CELL_TO_PIXEL = _cell_to_pixel()


def grid_to_image(grid: OccupancyGrid) -> npt.NDArray[np.uint8]:
    """The grid as map_saver's trinary 8-bit grey image (top row = farthest grid row).

    Cells 0 … :data:`CELL_FREE_MAX` become 254 (free), :data:`CELL_OCCUPIED_MIN` … 100
    become 0 (occupied), everything else 205 (unknown).
    """
    return np.ascontiguousarray(_CELL_TO_PIXEL[grid.data[::-1].view(np.uint8)])


def map_yaml(image_name: str, resolution: float, origin_x: float, origin_y: float) -> str:
    """The ROS map_server YAML that loads ``image_name`` (an image of :func:`grid_to_image`).

    Trinary mode, ``negate: 0``, thresholds :data:`SAVE_OCCUPIED_THRESH` and
    :data:`SAVE_FREE_THRESH`, under which 254, 205 and 0 load as free, unknown and occupied
    in every loader. ValueError for an empty name or a bad georeference.
    """
    if not image_name or not isinstance(image_name, str):
        raise ValueError("image_name must be a file name")
    for what, value in (("resolution", resolution), ("origin_x", origin_x), ("origin_y", origin_y)):
        if not math.isfinite(value):
            raise ValueError(f"{what} must be finite, not {value}")
    if resolution <= 0:
        raise ValueError(f"resolution must be positive, not {resolution}")
    meta = {
        "image": image_name,
        "mode": _SAVED.mode,
        "resolution": float(resolution),
        "origin": [float(origin_x), float(origin_y), 0.0],
        "negate": int(_SAVED.negate),
        "occupied_thresh": _SAVED.occupied_thresh,
        "free_thresh": _SAVED.free_thresh,
    }
    # PyYAML writes floats with full precision and a dot, so the origin reads back exactly.
    return yaml.safe_dump(meta, sort_keys=False, default_flow_style=None)


def _pgm_bytes(grid: OccupancyGrid) -> bytes:
    """The grid as map_saver's trinary P5 PGM."""
    header = (
        f"P5\n# CREATOR: telebot.robot.mapfile {grid.resolution:.3f} m/pix\n"
        f"{grid.width} {grid.height}\n255\n"
    ).encode("ascii")
    return header + grid_to_image(grid).tobytes()


def save_map(grid: OccupancyGrid, yaml_path: Path) -> None:
    """Write ``grid`` as ``<stem>.pgm`` plus ``yaml_path``, as ROS ``map_saver`` does.

    The image of :func:`grid_to_image` and the YAML of :func:`map_yaml`; a grid of -1/0/100
    loads back identical. Each file is replaced atomically, the YAML last, so a YAML that
    exists always has its image beside it.
    """
    yaml_path = Path(yaml_path)
    image_path = yaml_path.with_name(f"{yaml_path.stem}.pgm")
    text = map_yaml(image_path.name, grid.resolution, grid.origin_x, grid.origin_y)
    try:
        yaml_path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_write(image_path, _pgm_bytes(grid))
        _atomic_write(yaml_path, text.encode("utf-8"))
    except OSError as exc:
        raise MapError(f"{yaml_path}: cannot write the map: {exc.strerror or exc}") from exc


# --------------------------------------------------------------------------- places


def _check_place_name(name: str) -> str:
    if not PLACE_NAME_PATTERN.fullmatch(name):
        raise ValueError(
            f"place name {name!r} must be lowercase letters, digits, '-' and '_', "
            "starting with a letter"
        )
    return name


PlaceName = Annotated[str, Field(max_length=64), AfterValidator(_check_place_name)]


class PlaceEntry(StrictModel):
    """One ``[places.NAME]`` table: position in metres, heading in degrees (CCW)."""

    x: float = Field(strict=True, allow_inf_nan=False)
    y: float = Field(strict=True, allow_inf_nan=False)
    yaw_deg: float = Field(default=0.0, strict=True, allow_inf_nan=False)


class PlacesFile(StrictModel):
    """A places TOML file: ``[places.NAME]`` tables, in the order they are written."""

    places: dict[PlaceName, PlaceEntry] = Field(default_factory=dict)


def load_places(path: Path) -> dict[str, Pose2D]:
    """Read a places TOML file; yaw comes back in radians, wrapped into ``[-π, π)``.

    Raises :class:`~telebot.errors.ConfigError` (one line naming the file and the key).
    """
    parsed = load_toml(Path(path), PlacesFile)
    return {
        name: Pose2D(entry.x, entry.y, normalize_angle(math.radians(entry.yaw_deg)))
        for name, entry in parsed.places.items()
    }


def _toml_float(value: float) -> str:
    text = repr(float(value))
    return "0.0" if text == "-0.0" else text


def save_places(places: Mapping[str, Pose2D], path: Path) -> None:
    """Write ``places`` as a places TOML file (atomically), in their order.

    Positions are rounded to the micrometre and headings to 0.001° in (-180, 180], which
    hides float noise and changes no pose that matters.
    """
    lines = [
        "# Named places of a map: position in metres (map frame), heading in degrees",
        "# counter-clockwise from +x.",
    ]
    for name, pose in places.items():
        _check_place_name(name)
        values = (pose.x, pose.y, pose.yaw)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise ValueError(f"place {name!r} has a coordinate that is not finite: {pose}")
        yaw_deg = round(math.degrees(normalize_angle(pose.yaw)), 3)
        if yaw_deg <= -180.0:
            yaw_deg = 180.0
        lines += [
            "",
            f"[places.{name}]",
            f"x = {_toml_float(round(pose.x, 6))}",
            f"y = {_toml_float(round(pose.y, 6))}",
            f"yaw_deg = {_toml_float(yaw_deg)}",
        ]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, ("\n".join(lines) + "\n").encode("utf-8"))


def places_path_for(yaml_path: Path) -> Path:
    """The places file that belongs to a map: ``<stem>.places.toml`` beside its YAML."""
    yaml_path = Path(yaml_path)
    return yaml_path.with_name(f"{yaml_path.stem}.places.toml")
