"""Renderer: geometry against analytic answers, and the Kinect v1 error model against its spec."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.sim.render import KinectRenderer, camera_pose_in_world
from sensors.sim.world import world_from_dict
from tests.sim_worlds import NOISELESS, room, wall_ahead

CAMERA = CameraConfig()
ROBOT = RobotConfig()


def renderer(
    world: dict,
    sim: SimConfig = NOISELESS,
    robot: RobotConfig = ROBOT,
    noise_seed: int = 0,
    camera: CameraConfig = CAMERA,
    backend: str = "raster",
) -> KinectRenderer:
    return KinectRenderer(
        world_from_dict(world), camera, robot, sim, noise_seed=noise_seed, backend=backend
    )


BACKENDS = pytest.mark.parametrize("backend", ["raster", "raycast"])


def centre(image: np.ndarray) -> float:
    return float(image[CAMERA.height // 2, CAMERA.width // 2])


@BACKENDS
def test_centre_pixel_depth_equals_distance_to_a_wall_ahead(backend: str) -> None:
    r = renderer(room([wall_ahead(2.05)]), backend=backend)  # the wall's near face is at 2.0 m
    assert centre(r.true_depth(0.0, 0.0, 0.0)) == pytest.approx(2.0, abs=1e-4)


@BACKENDS
def test_depth_is_z_along_the_optical_axis_not_ray_length(backend: str) -> None:
    r = renderer(room([wall_ahead(2.05)]), backend=backend)
    depth = r.true_depth(0.0, 0.0, 0.0)
    # A fronto-parallel wall has the same z in every pixel that sees it.
    row = depth[CAMERA.height // 2]
    assert np.allclose(row, 2.0, atol=1e-4)


def test_noisy_depth_on_a_known_wall_is_within_the_noise_model() -> None:
    sim = SimConfig()
    r = renderer(room([wall_ahead(2.05)]), sim=replace(sim, depth_dropout=0.0))
    _, depth = r.render(0.0, 0.0, 0.0, np.random.default_rng(1))
    patch = depth[200:280, 280:360]
    sigma = float(r.depth_sigma(2.0))
    step = 2.0**2 / (CAMERA.disparity_focal * CAMERA.baseline) / sim.disparity_subpixel
    assert np.all(np.abs(patch - 2.0) <= 5 * sigma + step)
    assert abs(float(patch.mean()) - 2.0) < 0.01


@pytest.mark.parametrize("z", [1.0, 3.0])
def test_depth_noise_sigma_matches_the_model_within_20_percent(z: float) -> None:
    # A slanted wall spreads true disparities over many quantisation steps, as real scenes do.
    r = renderer(
        room([wall_ahead(z + 0.05, yaw_deg=40.0)]),
        sim=replace(SimConfig(), depth_dropout=0.0, shadows=False, depth_edge_threshold=0.0),
    )
    truth = r.true_depth(0.0, 0.0, 0.0)
    residuals = []
    rng = np.random.default_rng(7)
    for _ in range(4):
        _, depth = r.render(0.0, 0.0, 0.0, rng)
        near = (np.abs(truth - z) < 0.1 * z) & (depth > 0)
        residuals.append((depth[near] - truth[near]) / r.depth_sigma(truth[near]))
    normalised = np.concatenate(residuals)
    assert normalised.size > 5000
    assert 0.8 <= float(normalised.std()) <= 1.2


def test_depth_sigma_grows_with_distance_squared() -> None:
    r = renderer(room([wall_ahead(3.0)]), sim=SimConfig())
    assert float(r.depth_sigma(3.0)) / float(r.depth_sigma(1.0)) == pytest.approx(9.0)
    # Kinect v1 literature: ~1.5-3 mm at 1 m, a few cm at 4 m.
    assert 0.001 < float(r.depth_sigma(1.0)) < 0.004


def test_depth_outside_the_sensor_range_is_invalid() -> None:
    sim = replace(NOISELESS, shadows=False)
    near = renderer(room([wall_ahead(0.35)]), sim=sim)
    far = renderer(room([wall_ahead(6.0)]), sim=sim)
    rng = np.random.default_rng(0)
    assert centre(near.render(0, 0, 0, rng)[1]) == 0.0
    assert centre(far.render(0, 0, 0, rng)[1]) == 0.0


@BACKENDS
def test_tilted_camera_sees_the_floor_where_geometry_says(backend: str) -> None:
    pitch = 0.5  # [rad] nose down
    robot = replace(ROBOT, camera_pitch=pitch, camera_height=0.5)
    # Principal point on the centre pixel, so that pixel's ray is the optical axis.
    camera = replace(CAMERA, cx=CAMERA.width // 2, cy=CAMERA.height // 2)
    r = renderer(room([wall_ahead(8.0)]), robot=robot, camera=camera, backend=backend)
    # The optical axis meets the floor after h / sin(pitch) along the ray: that is its depth z.
    assert centre(r.true_depth(0.0, 0.0, 0.0)) == pytest.approx(0.5 / math.sin(pitch), abs=1e-3)


def test_camera_pose_follows_robot_yaw_and_extrinsics() -> None:
    robot = replace(ROBOT, camera_x=0.1, camera_height=0.4)
    rot, t = camera_pose_in_world(1.0, 2.0, math.pi / 2, robot)
    assert np.allclose(t, [1.0, 2.1, 0.4])
    assert np.allclose(rot[:, 2], [0.0, 1.0, 0.0], atol=1e-12)  # optical z looks along +y
    assert np.allclose(rot[:, 1], [0.0, 0.0, -1.0], atol=1e-12)  # image down is world down


def test_projector_shadow_falls_left_of_a_near_object() -> None:
    box = {"name": "box", "center": [1.5, 0.0], "size": [0.2, 0.4, 2.0]}
    sim = replace(NOISELESS, shadows=True)
    r = renderer(room([wall_ahead(3.05)], [box]), sim=sim)
    _, depth = r.render(0.0, 0.0, 0.0, np.random.default_rng(0))
    row = depth[CAMERA.height // 2]
    truth = r.true_depth(0.0, 0.0, 0.0)[CAMERA.height // 2]
    on_box = np.flatnonzero(truth < 2.0)
    left, right = on_box[0], on_box[-1]
    # Shadow width on the wall: f * b * (1/z_near - 1/z_far) in colour pixels.
    expected = CAMERA.fx * CAMERA.baseline * (1 / 1.4 - 1 / 3.0)
    shadow = np.flatnonzero(row[:left] == 0)
    assert len(shadow) == pytest.approx(expected, abs=2)
    assert np.all(row[right + 1 :] > 0)


def test_same_seed_same_images_and_different_seed_different_noise() -> None:
    r = renderer(room([wall_ahead(2.0)]), sim=SimConfig(), noise_seed=3)
    a = r.render(0.0, 0.0, 0.0, np.random.default_rng(5))
    b = r.render(0.0, 0.0, 0.0, np.random.default_rng(5))
    c = r.render(0.0, 0.0, 0.0, np.random.default_rng(6))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[1], c[1])


def test_colour_image_is_textured_enough_for_features() -> None:
    import cv2

    world = room([{**wall_ahead(2.0), "texture": "astronaut", "texture_scale": 1.5}])
    r = renderer(world, sim=SimConfig())
    rgb, _ = r.render(0.0, 0.0, 0.0, np.random.default_rng(0))
    keypoints = cv2.ORB_create(nfeatures=1000).detect(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert len(keypoints) > 300


@pytest.mark.parametrize("world_name", ["house", "office"])
def test_rasteriser_agrees_with_open3d_ray_casting(world_name: str) -> None:
    from pathlib import Path

    from sensors.sim.motion import drive_route
    from sensors.sim.world import load_world

    world = load_world(Path(__file__).resolve().parents[3] / "scenes" / f"{world_name}.yaml")
    traj = drive_route(world, SimConfig())
    fast = KinectRenderer(world, CAMERA, ROBOT, NOISELESS, backend="raster")
    reference = KinectRenderer(world, CAMERA, ROBOT, NOISELESS, backend="raycast")
    for i in np.linspace(0, len(traj.x) - 1, 8).round().astype(int):
        pose = (float(traj.x[i]), float(traj.y[i]), float(traj.yaw[i]))
        za, zb = fast.true_depth(*pose), reference.true_depth(*pose)
        same = np.isclose(za, zb, rtol=1e-3) | (np.isinf(za) & np.isinf(zb))
        # Only pixels on silhouette edges may fall on the other side of an edge.
        assert same.mean() > 0.99, pose
        _, face_a, _ = fast.geometry(*pose)
        _, face_b, _ = reference.geometry(*pose)
        assert (face_a == face_b).mean() > 0.99, pose
