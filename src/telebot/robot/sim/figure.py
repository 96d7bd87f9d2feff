"""Human figures for the simulated cameras: people drawn so that a person detector finds them.

Each person is a flat, camera-facing figure (a billboard) scaled by its distance: head with hair,
neck, a shirt torso with shoulders, arms with hands, trousers legs with shoes. The proportions
are the usual ones of an adult (head about an eighth of the height, shoulders a quarter of it
wide, legs half of it), the shape OpenCV's HOG people detector was trained on; walking legs
spread with the gait (widely when seen from the side). Limbs are darker at their edges, so the
figure reads as round, and everything fades with distance like the rest of the scene. A figure
is hidden where a wall is nearer in its column (the renderer's per-column depth test).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import cv2
import numpy as np
import numpy.typing as npt

from telebot.robot.nav import Pose2D
from telebot.robot.sim.people import STRIDE, PersonTruth

__all__ = ["HAIR_BGR", "SHOE_BGR", "SKIN_BGR", "draw_people"]

#: Skin of faces and hands, hair, shoes.
SKIN_BGR = (120, 160, 205)
HAIR_BGR = (30, 40, 55)
SHOE_BGR = (25, 25, 25)
_NEAREST = 0.35  # metres: nearer than this the camera is inside the person
_SHIFT = 4  # cv2 fixed point: sixteenths of a pixel, for smooth edges at any scale
_SUB = 1 << _SHIFT

Colour = tuple[float, float, float]


def draw_people(
    image: npt.NDArray[np.uint8],
    pose: Pose2D,
    people: Sequence[PersonTruth],
    *,
    focal: float,
    cx: float,
    cy: float,
    mount_height: float,
    wall_depth: npt.NDArray[np.float64],
    fade: Callable[[float], float],
    fog_bgr: tuple[int, int, int],
) -> None:
    """Draw ``people`` into ``image`` as seen by a level camera at ``pose`` (far ones first).

    ``wall_depth`` is each column's wall depth (perpendicular metres); ``fade(depth)`` the
    share of ``fog_bgr`` mixed in at a depth.
    """
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    h, w = image.shape[:2]
    placed = []
    for person in people:
        dx, dy = person.x - pose.x, person.y - pose.y
        depth = dx * c + dy * s
        if depth < _NEAREST:
            continue
        lateral = -dx * s + dy * c  # to the left is positive
        # Seen from the side (walking across the view) the legs scissor widely.
        side = abs(math.sin(person.yaw - math.atan2(dy, dx)))
        placed.append((depth, lateral, side, person))
    placed.sort(key=lambda item: -item[0])
    for depth, lateral, side, person in placed:
        scale = focal / depth
        u = cx - lateral * scale
        height = person.walker.height
        half_w = 0.35 * height * scale
        u0, u1 = max(math.floor(u - half_w), 0), min(math.ceil(u + half_w) + 1, w)
        v0 = max(math.floor(cy - (height + 0.05 - mount_height) * scale), 0)
        v1 = min(math.ceil(cy + mount_height * scale) + 2, h)
        if u0 >= u1 or v0 >= v1:
            continue
        roi = image[v0:v1, u0:u1]
        canvas = roi.copy()
        figure = _Figure(canvas, u - u0, cy - v0, scale, mount_height, fade(depth), fog_bgr)
        figure.draw(person, side)
        visible = wall_depth[u0:u1] > depth
        roi[:, visible] = canvas[:, visible]


class _Figure:
    """Draws one person on a canvas; figure coordinates are metres, x right, z up."""

    def __init__(
        self,
        canvas: npt.NDArray[np.uint8],
        u: float,
        cy: float,
        scale: float,
        mount: float,
        fade: float,
        fog: tuple[int, int, int],
    ) -> None:
        self.canvas = canvas
        self.u, self.cy, self.scale, self.mount = u, cy, scale, mount
        self.fade, self.fog = fade, fog

    def colour(self, bgr: tuple[int, int, int], shade: float = 1.0) -> Colour:
        keep = 1.0 - self.fade
        b, g, r = (
            float(c) * shade * keep + float(f) * self.fade
            for c, f in zip(bgr, self.fog, strict=True)
        )
        return (b, g, r)

    def pt(self, x: float, z: float) -> tuple[int, int]:
        return (
            round((self.u + x * self.scale) * _SUB),
            round((self.cy - (z - self.mount) * self.scale) * _SUB),
        )

    def poly(
        self, points: Sequence[tuple[float, float]], bgr: tuple[int, int, int], shade: float = 1.0
    ) -> None:
        pts = np.array([self.pt(x, z) for x, z in points], dtype=np.int32)
        cv2.fillPoly(self.canvas, [pts], self.colour(bgr, shade), cv2.LINE_AA, _SHIFT)

    def limb(
        self,
        a: tuple[float, float],
        b: tuple[float, float],
        width: float,
        bgr: tuple[int, int, int],
    ) -> None:
        # A dark outer band and a lighter core read as a cylinder.
        for frac, shade in ((1.0, 0.72), (0.5, 1.0)):
            thick = max(round(width * frac * self.scale), 1)
            cv2.line(
                self.canvas,
                self.pt(*a),
                self.pt(*b),
                self.colour(bgr, shade),
                thick,
                cv2.LINE_AA,
                _SHIFT,
            )

    def ellipse(
        self,
        centre: tuple[float, float],
        rx: float,
        rz: float,
        bgr: tuple[int, int, int],
        start: float = 0.0,
        end: float = 360.0,
    ) -> None:
        axes = (max(round(rx * self.scale * _SUB), 1), max(round(rz * self.scale * _SUB), 1))
        cv2.ellipse(
            self.canvas,
            self.pt(*centre),
            axes,
            0.0,
            start,
            end,
            self.colour(bgr),
            -1,
            cv2.LINE_AA,
            _SHIFT,
        )

    def draw(self, person: PersonTruth, side: float) -> None:
        hgt = person.walker.height
        shirt, trousers = person.walker.shirt_bgr, person.walker.trousers_bgr
        swing = math.sin(2.0 * math.pi * person.travelled / STRIDE) if person.walking else 0.0
        spread = 0.02 + 0.16 * abs(swing) * side
        hip_z, shoulder_z = 0.53 * hgt, 0.82 * hgt
        shoulder = 0.12 * hgt
        hip = 0.085 * hgt
        for sign in (-1.0, 1.0):
            foot = sign * (0.07 + spread)
            self.limb((sign * 0.07, hip_z), (foot, 0.08), 0.14, trousers)
            self.poly(
                [(foot - 0.07, 0.0), (foot + 0.07, 0.0), (foot + 0.05, 0.09), (foot - 0.05, 0.09)],
                SHOE_BGR,
            )
        self.poly(
            [
                (-shoulder, shoulder_z - 0.03),
                (-shoulder + 0.05, shoulder_z + 0.02),
                (shoulder - 0.05, shoulder_z + 0.02),
                (shoulder, shoulder_z - 0.03),
                (hip, hip_z + 0.05),
                (hip + 0.01, hip_z - 0.03),
                (-hip - 0.01, hip_z - 0.03),
                (-hip, hip_z + 0.05),
            ],
            shirt,
        )
        hand_z = 0.46 * hgt
        for sign in (-1.0, 1.0):
            hand = sign * (shoulder + 0.02 + 0.04 * abs(swing) * (1.0 - side))
            self.limb(
                (sign * (shoulder - 0.02), shoulder_z - 0.04), (hand, hand_z + 0.05), 0.085, shirt
            )
            self.ellipse((hand, hand_z + 0.02), 0.04, 0.05, SKIN_BGR)
        head_r = 0.062 * hgt
        head_z = hgt - 1.2 * head_r
        self.limb((0.0, shoulder_z), (0.0, head_z - head_r), 0.075, SKIN_BGR)
        self.ellipse((0.0, head_z), 0.85 * head_r, 1.2 * head_r, SKIN_BGR)
        self.ellipse((0.0, head_z), 0.88 * head_r, 1.23 * head_r, HAIR_BGR, 180.0, 360.0)
