"""Camera person detection (sans-IO): OpenCV's built-in HOG people detector on a frame.

The detector (Dalal–Triggs HOG with the linear SVM that ships inside OpenCV,
``cv2.HOGDescriptor_getDefaultPeopleDetector``) needs no model download. Frames are scaled to
``width`` pixels wide first: the detector's cost grows with the pixel count, and at 480 pixels
an adult 2 … 6 m from the robot's cameras is still taller than its 128-pixel window's person.

A detection gives a *bearing* (from the box's centre column and the camera's field of view,
REP-103: positive to the left) and a rough *distance* (from the box's height, taking people
as :data:`PERSON_HEIGHT` tall, the person filling the middle three quarters of the box as in
the detector's training windows). The laser is far better at distance; the tracker uses the
camera to confirm tracks and to keep one through a moment the laser misses.
"""

from __future__ import annotations

import math
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

    def detect(self, image: npt.NDArray[np.uint8], fov_deg: float) -> list[CameraDetection]:
        """People in ``image`` (BGR or grey ``uint8``) from a camera of ``fov_deg`` across.

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
        small = (
            image if factor == 1.0 else cv2.resize(image, (round(w * factor), round(h * factor)))
        )
        boxes, weights = self._hog.detectMultiScale(
            small, winStride=(8, 8), padding=(8, 8), scale=self.scale
        )
        focal = (w / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
        cx = (w - 1) / 2.0
        out = []
        for box, weight in zip(boxes, np.ravel(weights), strict=False):
            if float(weight) < self.threshold:
                continue
            x, y, bw, bh = (float(v) / factor for v in box)
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
