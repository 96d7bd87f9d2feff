"""Camera person detection (sans-IO): OpenCV's built-in HOG people detector on a frame.

The detector (Dalal–Triggs HOG with the linear SVM that ships inside OpenCV,
``cv2.HOGDescriptor_getDefaultPeopleDetector``) needs no model download. Frames are scaled to
``width`` pixels wide first: the detector's cost grows with the pixel count, and at 480 pixels
an adult 2 … 6 m from the robot's cameras is still taller than its 128-pixel window's person.

A detection gives a *bearing* (from the box's centre column and the camera's field of view,
REP-103: positive to the left) and a rough *distance* (from the box's height, taking people
as :data:`PERSON_HEIGHT` tall, the person filling the middle three quarters of the box as in
the detector's training windows). The laser is far better at distance; the tracker uses the
camera to confirm tracks and to keep one through a moment the laser misses. Given where the
laser sees people (``near``), only the image columns where they would be are searched.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["PERSON_HEIGHT", "CameraDetection", "HogPeopleDetector"]

#: Assumed height of a person (metres), for the distance from a box's height.
PERSON_HEIGHT = 1.7
# Share of a HOG box's height that the person fills (96 of 128 pixels in training).
_FILL = 0.75


@dataclass(frozen=True, slots=True)
class CameraDetection:
    """A person in one frame: bearing (radians, robot frame, left positive) and distance."""

    bearing: float
    distance: float
    confidence: float
    #: The box in the frame's pixels: x, y, width, height.
    box: tuple[int, int, int, int]


class HogPeopleDetector:
    """Finds upright people in BGR frames (see the module docstring)."""

    def __init__(self, *, width: int = 480, threshold: float = 0.5, scale: float = 1.05) -> None:
        if width < 64:
            raise ValueError(f"detection width must be at least 64 pixels, not {width}")
        self.width = width
        self.threshold = threshold
        self.scale = scale
        self._hog = cv2.HOGDescriptor()
        self._hog.setSVMDetector(np.asarray(cv2.HOGDescriptor.getDefaultPeopleDetector()))

    def detect(
        self,
        image: npt.NDArray[np.uint8],
        fov_deg: float,
        near: Sequence[tuple[float, float]] | None = None,
    ) -> list[CameraDetection]:
        """People in ``image`` (BGR or grey ``uint8``) from a camera of ``fov_deg`` across.

        ``near``: (bearing, distance) of people the laser sees; then only the columns where
        they would appear are searched (a fraction of the frame's cost), else all of it.
        A frame that is not an image (wrong shape or type, too small) gives no detections.
        """
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
            return []
        if image.ndim not in (2, 3) or image.shape[0] < 64 or image.shape[1] < 32:
            return []
        if not (math.isfinite(fov_deg) and 0.0 < fov_deg < 180.0):
            return []
        h, w = image.shape[:2]
        factor = min(self.width / w, 1.0)
        focal = (w / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
        cx = (w - 1) / 2.0
        windows = [(0, w)] if near is None else _windows(near, focal, cx, w, factor)
        out = []
        for c0, c1 in windows:
            crop = image[:, c0:c1]
            size = (max(round((c1 - c0) * factor), 1), round(h * factor))
            small = crop if factor == 1.0 else cv2.resize(crop, size)
            if small.shape[1] < 64 or small.shape[0] < 128:
                continue
            boxes, weights = self._hog.detectMultiScale(
                small, winStride=(8, 8), padding=(8, 8), scale=self.scale
            )
            for box, weight in zip(boxes, np.ravel(weights), strict=False):
                if float(weight) < self.threshold:
                    continue
                x, y, bw, bh = (float(v) / factor for v in box)
                x += c0
                bearing = math.atan((cx - (x + bw / 2.0)) / focal)
                depth = PERSON_HEIGHT * focal / max(_FILL * bh, 1.0)
                confidence = 1.0 - math.exp(-float(weight))
                out.append(
                    CameraDetection(
                        bearing,
                        depth / math.cos(bearing),
                        confidence,
                        (round(x), round(y), round(bw), round(bh)),
                    )
                )
        return out


def _windows(
    near: Sequence[tuple[float, float]], focal: float, cx: float, width: int, factor: float
) -> list[tuple[int, int]]:
    """Column ranges (merged where they overlap) that hold the people ``near``."""
    spans = []
    for bearing, distance in near:
        if not (math.isfinite(bearing) and math.isfinite(distance)) or abs(bearing) >= 1.5:
            continue
        depth = max(distance * math.cos(bearing), 0.5)
        u = cx - math.tan(bearing) * focal
        # Half a detector box (half as wide as tall, the person three quarters of its
        # height), the laser's error, and the detector's padding; at least a window.
        half = 0.5 * (PERSON_HEIGHT / _FILL) * focal / depth / 2.0
        half += 0.3 * focal / depth + 16.0
        half = max(half, 48.0 / factor)
        c0, c1 = max(math.floor(u - half), 0), min(math.ceil(u + half), width)
        if c1 > c0:
            spans.append((c0, c1))
    spans.sort()
    merged: list[tuple[int, int]] = []
    for c0, c1 in spans:
        if merged and c0 <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], c1))
        else:
            merged.append((c0, c1))
    return merged
