"""Renderer output is pinned bit for bit: recordings are cached by configuration and every
accuracy figure was measured on them, so a speed-up must not change a single byte.

The hashes below were computed with the renderer as of commit 66a4a08, before its shading,
depth model and texture atlas were optimised. If a change is *meant* to alter the images,
regenerate them and say so in the commit: every cached recording becomes stale.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import sensors.sim.render as render_module
from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.sim.motion import drive_route
from sensors.sim.render import KinectRenderer
from sensors.sim.textures import MIP_LEVELS, TEXTURE_SIZE, build_atlas, texture_image
from sensors.sim.world import World, load_world, world_from_dict

REPO = Path(__file__).resolve().parents[3]
Pose = tuple[float, float, float]  # x [m], y [m], yaw [rad] of base_link
ROUTE_FRACTIONS = (0.0, 0.13, 0.29, 0.41, 0.57, 0.72, 0.88, 1.0)  # poses along the route
NO_RGB_NOISE = replace(SimConfig(), shadows=False, depth_dropout=0.0, rgb_noise=0.0)
# A pillar 0.4 m in front of the camera and one it straddles: the projector shadow is wider
# than the renderer's windowed minimum, and faces cross the near clipping plane.
NEAR_PILLARS = {
    "name": "near",
    "walls": [{"from": [3.0, -10.0], "to": [3.0, 10.0], "thickness": 0.1, "texture": "brick"}],
    "furniture": [
        {"name": "a", "center": [0.5, 0.05], "size": [0.2, 0.1, 2.0], "texture": "coffee"},
        {"name": "b", "center": [0.15, -0.3], "size": [0.6, 0.1, 1.0], "texture": "wood"},
    ],
    "start": [0.0, 0.0, 0.0],
    "route": [[1.0, 0.0]],
}
NEAR_POSES: tuple[Pose, ...] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.3), (-0.1, 0.05, -0.4))

GOLDEN = {
    "house-default": "f5129d07d847cf15586e3467e5275c392f6119ca7a259a858a43f01efcb4a9f3",
    "house-other-seeds": "ee5ef54460752842cd2939065a0c86e07da19e16715f876113ca4bd800a6178e",
    "house-no-rgb-noise": "9d7224ba074e3e64d7790d7dd40de1e6fab855928db516f7f7756d78fa99a877",
    "office-default": "7c93468d1c64bd10bfcb30e532bb34a444febbd8a4ffd1ffb08a8a5fcb89d36e",
    "near-pillars": "158906d95d1637df7ff4467474e320e53d79c3d89f94880cba7153b37d6641af",
}


def route_poses(world: World) -> list[Pose]:
    traj = drive_route(world, SimConfig())
    idx = [round(f * (len(traj.t_ns) - 1)) for f in ROUTE_FRACTIONS]
    return [(float(traj.x[i]), float(traj.y[i]), float(traj.yaw[i])) for i in idx]


def render_digest(
    world: World, poses: Sequence[Pose], sim: SimConfig, noise_seed: int, rng_seed: int
) -> str:
    """One sha256 over rgb and depth bytes of every pose, then the generator's next draws (so
    the renderer must consume the generator exactly as before)."""
    r = KinectRenderer(
        world, CameraConfig(), RobotConfig(), sim, noise_seed=noise_seed, backend="raster"
    )
    rng = np.random.default_rng(rng_seed)
    digest = hashlib.sha256()
    for pose in poses:
        rgb, depth = r.render(*pose, rng)
        assert rgb.dtype == np.uint8 and rgb.shape == (480, 640, 3)
        assert depth.dtype == np.float32 and depth.shape == (480, 640)
        digest.update(np.ascontiguousarray(rgb).tobytes())
        digest.update(np.ascontiguousarray(depth).tobytes())
    digest.update(rng.integers(0, 2**62, size=4).tobytes())
    return digest.hexdigest()


@pytest.mark.parametrize(
    ("case", "scene", "sim", "noise_seed", "rng_seed"),
    [
        ("house-default", "house.yaml", SimConfig(), 0, 0),
        ("house-other-seeds", "house.yaml", SimConfig(), 3, 17),
        ("house-no-rgb-noise", "house.yaml", NO_RGB_NOISE, 0, 5),
        ("office-default", "office.yaml", SimConfig(), 1, 2),
    ],
)
def test_route_frames_are_bit_identical_to_the_pinned_ones(
    case: str, scene: str, sim: SimConfig, noise_seed: int, rng_seed: int
) -> None:
    world = load_world(REPO / "scenes" / scene)
    assert render_digest(world, route_poses(world), sim, noise_seed, rng_seed) == GOLDEN[case]


def test_frames_with_near_objects_are_bit_identical_to_the_pinned_ones() -> None:
    world = world_from_dict(NEAR_PILLARS)
    assert render_digest(world, NEAR_POSES, SimConfig(), 2, 9) == GOLDEN["near-pillars"]


@pytest.mark.parametrize("backend", ["raster", "raycast"])
def test_fast_shading_equals_the_reference_kernel(backend: str) -> None:
    world = load_world(REPO / "scenes" / "house.yaml")
    r = KinectRenderer(world, CameraConfig(), RobotConfig(), SimConfig(), backend=backend)
    assert r._fast_shading
    for pose in route_poses(world)[::3]:
        invz, face, table = r._geometry(*pose)
        fast = r._shade(invz, face, table, noise_start=123)
        reference = r._shade_reference(invz.ravel(), face.ravel().astype(np.intp), table, 123)
        assert np.array_equal(fast, reference), pose


def test_renderer_without_the_fast_path_gives_the_same_frames() -> None:
    world = world_from_dict(NEAR_PILLARS)
    fast = KinectRenderer(world, CameraConfig(), RobotConfig(), SimConfig(), noise_seed=1)
    slow = KinectRenderer(world, CameraConfig(), RobotConfig(), SimConfig(), noise_seed=1)
    slow._fast_shading = False  # what a world of more than 255 faces gets
    rng_a, rng_b = np.random.default_rng(4), np.random.default_rng(4)
    for pose in NEAR_POSES:
        a, b = fast.render(*pose, rng_a), slow.render(*pose, rng_b)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_windowed_projector_shadow_equals_the_full_running_minimum(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    r = KinectRenderer(world_from_dict(NEAR_PILLARS), CameraConfig(), RobotConfig(), SimConfig())
    rng = np.random.default_rng(3)
    # Piecewise-constant disparities (surfaces) with noise; 39 px is a surface at 1 m.
    steps = rng.uniform(0.0, 39.0, size=(120, 16)).astype(np.float32)
    disparity = np.repeat(steps, 40, axis=1) + rng.normal(0, 0.5, (120, 640)).astype(np.float32)
    disparity = np.maximum(disparity, 0, dtype=np.float32)
    windowed = r._projector_shadow(disparity)
    monkeypatch.setattr(render_module, "SHADOW_WINDOW_MAX", 0.0)  # always the running minimum
    full = r._projector_shadow(disparity)
    assert windowed.any() and not windowed.all()
    assert np.array_equal(windowed, full)


def test_atlas_lookup_reads_the_nearest_texel_of_the_mip_level() -> None:
    import cv2

    names = ("brick", "wood")
    atlas = build_atlas(names)
    rng = np.random.default_rng(0)
    n = 20_000
    tex = rng.integers(0, len(names), n).astype(np.int32)
    u = rng.uniform(-3, 3, n).astype(np.float32)
    v = rng.uniform(-3, 3, n).astype(np.float32)
    level = rng.integers(0, MIP_LEVELS, n).astype(np.int32)
    got = atlas.lookup(tex, u, v, level)[:, :3]
    for t, name in enumerate(names):
        img = texture_image(name)
        for lev in range(MIP_LEVELS):
            pick = (tex == t) & (level == lev)
            side = TEXTURE_SIZE >> lev
            # Finest-level texel, wrapped, then down to the level.
            tx = ((u[pick] * TEXTURE_SIZE).astype(np.int64) % TEXTURE_SIZE) >> lev
            ty = ((v[pick] * TEXTURE_SIZE).astype(np.int64) % TEXTURE_SIZE) >> lev
            assert img.shape[0] == side
            assert np.array_equal(got[pick], img[ty, tx]), (name, lev)
            img = cv2.pyrDown(img)
