"""The simulated cameras: first-person views of the map, people in them, and the two cameras."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from telebot.robot.grid import OCCUPIED, UNKNOWN, OccupancyGrid
from telebot.robot.nav import Pose2D
from telebot.robot.sim.camera import CameraModel, Renderer, default_cameras
from telebot.robot.sim.world import Obstacle

RES = 0.05
NAVCAM, USERCAM = default_cameras()
Image = npt.NDArray[np.uint8]


def hall() -> OccupancyGrid:
    """A walled 12 m × 6 m hall (free x ∈ [1, 13), y ∈ [1, 7)) with a short partition.

    The partition is a wall 0.2 m thick at x ∈ [8, 8.2), y ∈ [2, 4]; unknown surrounds it all.
    """
    data = np.full((160, 280), UNKNOWN, dtype=np.int8)
    data[16:144, 16:264] = OCCUPIED
    data[20:140, 20:260] = 0
    data[40:80, 160:164] = OCCUPIED
    return OccupancyGrid(data, RES, 0.0, 0.0)


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return Renderer(hall())


def channels(image: Image) -> tuple[Image, Image, Image]:
    """B, G, R as signed ints, so differences do not wrap."""
    signed = image.astype(np.int32)
    return signed[..., 0], signed[..., 1], signed[..., 2]  # type: ignore[return-value]


def obstacle_pixels(image: Image) -> npt.NDArray[np.bool_]:
    """Pixels in the obstacle colour: strongly red-orange (red ≫ green > blue)."""
    b, g, r = channels(image)
    return (r >= 90) & (r > 2 * g) & (r > 3 * b)


def wall_pixels(image: Image) -> npt.NDArray[np.bool_]:
    """Pixels of real walls: warm (red well above blue); floor and ceiling are cool greys."""
    b, _, r = channels(image)
    return (r - b >= 12) & ~obstacle_pixels(image)


def unknown_pixels(image: Image) -> npt.NDArray[np.bool_]:
    """Pixels of unknown space: dark slate blue (blue well above red)."""
    b, _, r = channels(image)
    return b - r >= 25


def centre(image: Image, half_width: int = 8) -> Image:
    w = image.shape[1]
    return image[:, w // 2 - half_width : w // 2 + half_width]


@pytest.mark.parametrize("camera", [NAVCAM, USERCAM], ids=lambda c: c.name)
def test_frame_shape_and_dtype(renderer: Renderer, camera: CameraModel) -> None:
    image = renderer.render(Pose2D(3.0, 4.0, 0.0), camera)
    assert image.shape == (480, 640, 3)
    assert image.dtype == np.uint8
    assert image.flags.c_contiguous


def test_other_resolutions_follow_the_camera_model(renderer: Renderer) -> None:
    small = default_cameras(160, 120)
    assert [c.name for c in small] == ["navcam", "usercam"]
    for camera in small:
        assert renderer.render(Pose2D(3.0, 4.0, 0.5), camera).shape == (120, 160, 3)
    # An odd height puts a row exactly on the horizon (at infinite depth): fully faded.
    odd = CameraModel("odd", fov_deg=60.0, mount_height=0.5, width=161, height=121)
    image = renderer.render(Pose2D(3.0, 4.0, 0.5), odd)
    assert image.shape == (121, 161, 3)


def test_the_two_default_cameras() -> None:
    assert NAVCAM.name == "navcam" and USERCAM.name == "usercam"
    assert USERCAM.fov_deg > NAVCAM.fov_deg
    assert USERCAM.mount_height > NAVCAM.mount_height
    info = USERCAM.info()
    assert (info.name, info.width, info.height, info.fov_deg) == ("usercam", 640, 480, 90.0)


def test_moving_forward_and_turning_change_the_picture(renderer: Renderer) -> None:
    # In the middle of the hall, facing the long way: mostly floor, ceiling and far walls.
    pose = Pose2D(3.0, 4.0, 0.0)
    base = renderer.render(pose, NAVCAM).astype(np.int16)
    forward = renderer.render(Pose2D(3.3, 4.0, 0.0), NAVCAM).astype(np.int16)
    turned = renderer.render(Pose2D(3.0, 4.0, math.radians(5.0)), NAVCAM).astype(np.int16)
    h = base.shape[0]
    # The floor alone (bottom quarter, all floor from here) shows the motion: tiles slide.
    floor = slice(3 * h // 4, h)
    assert np.mean(np.abs(base[floor] - forward[floor])) > 5.0
    assert np.mean(np.abs(base[floor] - turned[floor])) > 5.0
    assert np.mean(np.abs(base - forward)) > 5.0
    assert np.mean(np.abs(base - turned)) > 5.0


def test_an_obstacle_in_front_shows_in_the_centre_and_goes_when_removed(
    renderer: Renderer,
) -> None:
    pose = Pose2D(3.0, 4.0, 0.0)
    person = Obstacle(5.0, 4.0, radius=0.25, height=1.7)
    for camera in (NAVCAM, USERCAM):
        with_person = renderer.render(pose, camera, [person])
        without = renderer.render(pose, camera)
        middle = obstacle_pixels(centre(with_person))
        # A 1.7 m person 2 m away covers a tall run of the centre columns.
        assert middle.mean() > 0.25, camera.name
        assert not obstacle_pixels(without).any(), camera.name
        # …and only around the centre: the edges of the image are untouched.
        assert np.array_equal(with_person[:, :200], without[:, :200])
        assert np.array_equal(with_person[:, -200:], without[:, -200:])


def test_left_in_the_world_is_left_in_the_image(renderer: Renderer) -> None:
    # REP-103: +y is the robot's left when it faces +x.
    pose = Pose2D(3.0, 4.0, 0.0)
    image = renderer.render(pose, NAVCAM, [Obstacle(5.0, 4.8, radius=0.2)])
    columns = np.flatnonzero(obstacle_pixels(image).any(axis=0))
    assert columns.size > 0 and columns.max() < image.shape[1] // 2


def test_a_near_wall_fills_the_column_and_a_far_one_less(renderer: Renderer) -> None:
    near = renderer.render(Pose2D(12.4, 4.0, 0.0), NAVCAM)  # east wall (x = 13) 0.6 m ahead
    far = renderer.render(Pose2D(8.0, 5.5, 0.0), NAVCAM)  # the same wall 5 m ahead
    h = near.shape[0]
    near_rows = wall_pixels(centre(near)).mean(axis=1) > 0.5
    far_rows = wall_pixels(centre(far)).mean(axis=1) > 0.5
    assert near_rows.sum() > 0.9 * h
    # 2.5 m at 5 m with a 457 px focal length: ~230 rows, under half the image.
    assert 0.3 * h < far_rows.sum() < 0.6 * h
    # The low navcam sees more wall above the horizon than below it.
    rows = np.flatnonzero(far_rows)
    assert (h / 2 - rows.min()) > (rows.max() - h / 2)


def test_the_taller_camera_sees_more_wall_below_the_horizon(renderer: Renderer) -> None:
    pose = Pose2D(8.0, 5.5, 0.0)
    for camera in (NAVCAM, USERCAM):
        image = renderer.render(pose, camera)
        rows = np.flatnonzero(wall_pixels(centre(image)).mean(axis=1) > 0.5)
        above, below = camera.height / 2 - rows.min(), rows.max() - camera.height / 2
        # The wall's top is (2.5 - h) above the lens and its foot h below: the ratio shows.
        ratio = (2.5 - camera.mount_height) / camera.mount_height
        assert above / below == pytest.approx(ratio, rel=0.1), camera.name


def test_an_obstacle_behind_a_wall_is_hidden(renderer: Renderer) -> None:
    pose = Pose2D(5.0, 3.0, 0.0)  # facing the partition (x = 8, y ∈ [2, 4]) 3 m away
    hidden = Obstacle(10.0, 3.0, radius=0.3)
    image = renderer.render(pose, USERCAM, [hidden])
    assert not obstacle_pixels(image).any()
    assert np.array_equal(image, renderer.render(pose, USERCAM))
    # The same person in front of the partition is seen.
    seen = renderer.render(pose, USERCAM, [Obstacle(7.0, 3.0, radius=0.3)])
    assert obstacle_pixels(centre(seen)).mean() > 0.25


def test_a_short_obstacle_shows_the_wall_above_it(renderer: Renderer) -> None:
    pose = Pose2D(9.0, 4.0, 0.0)  # east wall 4 m ahead
    child = Obstacle(10.5, 4.0, radius=0.2, height=0.6)
    image = centre(renderer.render(pose, USERCAM, [child]))
    rows_obstacle = np.flatnonzero(obstacle_pixels(image).mean(axis=1) > 0.5)
    rows_wall = np.flatnonzero(wall_pixels(image).mean(axis=1) > 0.5)
    assert rows_obstacle.size > 0 and rows_wall.size > 0
    assert rows_wall.min() < rows_obstacle.min()  # wall visible above the child's head


def test_unknown_space_is_drawn_distinctly(renderer: Renderer) -> None:
    # A hall whose east wall is missing: the robot looks into unexplored space.
    data = hall().data.copy()
    data[20:140, 260:264] = UNKNOWN
    open_hall = Renderer(OccupancyGrid(data, RES, 0.0, 0.0))
    pose = Pose2D(9.0, 4.0, 0.0)
    unknown = centre(open_hall.render(pose, NAVCAM))
    walled = centre(renderer.render(pose, NAVCAM))
    assert unknown_pixels(unknown).mean() > 0.2
    assert not unknown_pixels(walled).any()
    assert wall_pixels(walled).mean() > 0.2
    assert not wall_pixels(unknown).any()


def test_navcam_and_usercam_differ(renderer: Renderer) -> None:
    pose = Pose2D(3.0, 4.0, 0.3)
    nav = renderer.render(pose, NAVCAM)
    user = renderer.render(pose, USERCAM)
    assert np.mean(np.abs(nav.astype(np.int16) - user.astype(np.int16))) > 10.0


def test_rendering_is_deterministic() -> None:
    pose = Pose2D(4.2, 3.3, -0.4)
    people = [Obstacle(6.0, 2.5), Obstacle(7.5, 3.0, radius=0.3, height=1.2)]
    first = Renderer(hall()).render(pose, USERCAM, people)
    second = Renderer(hall())
    assert second.render(pose, USERCAM, people).tobytes() == first.tobytes()
    assert second.render(pose, USERCAM, people).tobytes() == first.tobytes()


@pytest.mark.parametrize(
    "pose",
    [Pose2D(-4.0, 3.0, 0.0), Pose2D(0.9, 4.0, 1.0), Pose2D(500.0, -500.0, 2.0)],
    ids=["outside", "in-a-wall", "far-away"],
)
def test_poses_outside_the_map_or_in_a_wall_do_not_crash(renderer: Renderer, pose: Pose2D) -> None:
    image = renderer.render(pose, NAVCAM, [Obstacle(1.0, 1.0)])
    assert image.shape == (480, 640, 3)


def test_a_person_standing_on_the_camera_fills_the_view(renderer: Renderer) -> None:
    image = renderer.render(Pose2D(3.0, 4.0, 0.0), NAVCAM, [Obstacle(3.1, 4.0, radius=0.3)])
    assert obstacle_pixels(centre(image)).mean() > 0.9


def test_camera_models_are_validated() -> None:
    with pytest.raises(ValueError, match="field of view"):
        CameraModel("bad", fov_deg=180.0, mount_height=1.0)
    with pytest.raises(ValueError, match="mount height"):
        CameraModel("bad", fov_deg=60.0, mount_height=0.0)
    with pytest.raises(ValueError, match="above the walls"):
        Renderer(hall(), wall_height=1.0).render(Pose2D(3.0, 4.0), USERCAM)
