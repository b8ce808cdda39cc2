"""Render what a Kinect v1 on a ground robot sees: depth by ray casting (Open3D
RaycastingScene), colour from textured, shaded surfaces, and the Kinect v1 error model.

Depth error model (Khoshelham & Elberink 2012; Smisek et al. 2011): the sensor measures
disparity ``d = f_ir * b / z`` with Gaussian noise of ``disparity_noise`` px and quantises it to
1/``disparity_subpixel`` px, so ``sigma_z ~ z^2 * sigma_d / (f_ir * b)``. Invalid (0) pixels:
outside [depth_min, depth_max], at depth discontinuities, in the IR projector's shadow (the
projector sits ``baseline`` to the camera's right, so near objects shadow what is left of them),
and a small random dropout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.sim.textures import MIP_LEVELS, TEXTURE_SIZE, TextureAtlas, build_atlas
from sensors.sim.world import Box, World
from sensors.types import CameraIntrinsics

# Optical axes (x right, y down, z forward) expressed in camera_link (x forward, y left, z up).
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
AMBIENT = 0.35  # share of light that does not depend on the surface angle
DISTANCE_FALLOFF = 0.04  # [1/m] brightness lost per metre (a dim indoor scene)
NOISE_BANK_FACTOR = 2  # noise banks hold this many frames of samples


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def camera_pose_in_world(
    x: float, y: float, yaw: float, robot: RobotConfig
) -> tuple[np.ndarray, np.ndarray]:
    """base_link pose on the floor -> (R_world_optical 3x3, t_world_optical 3)."""
    r_world_base = _rot_z(yaw)
    t_base_link = np.array([robot.camera_x, robot.camera_y, robot.camera_height])
    r_base_link = _rot_y(robot.camera_pitch) @ _rot_x(robot.camera_roll)
    r_world_opt = r_world_base @ r_base_link @ R_LINK_OPTICAL
    t_world_opt = np.array([x, y, 0.0]) + r_world_base @ t_base_link
    return r_world_opt, t_world_opt


@dataclass(frozen=True, eq=False)
class SceneMesh:
    """Triangles plus, per triangle, the plane mapping a hit point to texture tile coordinates."""

    vertices: np.ndarray  # (V, 3) float32 [m]
    triangles: np.ndarray  # (T, 3) uint32
    normal: np.ndarray  # (T, 3) float32, unit
    u_axis: np.ndarray  # (T, 3) float32: u = p . u_axis + u_offset  [tiles]
    u_offset: np.ndarray  # (T,) float32
    v_axis: np.ndarray  # (T, 3) float32
    v_offset: np.ndarray  # (T,) float32
    texels_per_metre: np.ndarray  # (T,) float32 at the finest mip level
    texture: np.ndarray  # (T,) int64 index into the atlas


# Box corners as (sx, sy, sz) in {0, 1}: sx along length, sy along width, sz up.
_FACES = (  # corner indices, counter-clockwise seen from outside
    (0, 1, 5, 4),  # -y side
    (2, 3, 7, 6),  # +y side
    (3, 0, 4, 7),  # -x side
    (1, 2, 6, 5),  # +x side
    (4, 5, 6, 7),  # top
    (3, 2, 1, 0),  # bottom
)


def _box_corners(b: Box) -> np.ndarray:
    fp = b.footprint()  # counter-clockwise: (-l,-w), (l,-w), (l,w), (-l,w)
    low = np.column_stack([fp, np.full(4, b.z_min)])
    high = np.column_stack([fp, np.full(4, b.z_max)])
    return np.vstack([low, high])


def build_scene_mesh(world: World, atlas_names: tuple[str, ...]) -> SceneMesh:
    verts, tris, normals, uax, uoff, vax, voff, tpm, tex = [], [], [], [], [], [], [], [], []

    def add_quad(c: np.ndarray, quad: tuple, texture: str, scale: float) -> None:
        base = sum(len(v) for v in verts)
        pts = c[list(quad)]
        verts.append(pts)
        tris.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]])
        n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
        n /= np.linalg.norm(n)
        if abs(n[2]) < 0.5:
            # Upright face: u to the right and v downwards as a viewer facing it sees them, so
            # images are neither mirrored nor upside down.
            u = np.cross([0.0, 0.0, 1.0], n)
            u /= np.linalg.norm(u)
            v = np.array([0.0, 0.0, -1.0])
        else:
            u, v = np.array([1.0, 0.0, 0.0]), np.array([0.0, -np.sign(n[2]), 0.0])
        o = pts[0]
        for _ in range(2):
            normals.append(n)
            uax.append(u / scale)
            uoff.append(-(o @ u) / scale)
            vax.append(v / scale)
            voff.append(-(o @ v) / scale)
            tpm.append(TEXTURE_SIZE / scale)
            tex.append(atlas_names.index(texture))

    for b in world.boxes:
        c = _box_corners(b)
        for quad in _FACES:
            add_quad(c, quad, b.texture, b.texture_scale)
    x0, y0, x1, y1 = world.bounds(margin=1.0)
    h = world.ceiling_height
    plane = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0],
                      [x0, y0, h], [x1, y0, h], [x1, y1, h], [x0, y1, h]], dtype=np.float64)  # fmt: skip
    add_quad(plane, (0, 1, 2, 3), world.floor.texture, world.floor.scale)
    add_quad(plane, (4, 7, 6, 5), world.ceiling.texture, world.ceiling.scale)
    f32 = np.float32
    return SceneMesh(
        vertices=np.concatenate(verts).astype(f32),
        triangles=np.array(tris, dtype=np.uint32),
        normal=np.array(normals, f32),
        u_axis=np.array(uax, f32),
        u_offset=np.array(uoff, f32),
        v_axis=np.array(vax, f32),
        v_offset=np.array(voff, f32),
        texels_per_metre=np.array(tpm, f32),
        texture=np.array(tex, np.int64),
    )


def world_textures(world: World) -> tuple[str, ...]:
    names = {b.texture for b in world.boxes} | {world.floor.texture, world.ceiling.texture}
    return tuple(sorted(names))


class KinectRenderer:
    """Renders ``(rgb uint8 HxWx3, depth_m float32 HxW)`` for a base_link pose.

    Randomness comes only from the generator passed to :meth:`render`, so the same seed and
    poses give identical images.
    """

    def __init__(self, world: World, camera: CameraConfig, robot: RobotConfig, sim: SimConfig,
                 noise_seed: int = 0) -> None:  # fmt: skip
        import open3d as o3d  # heavy; imported where used

        self._o3c = o3d.core
        self.camera, self.robot, self.sim = camera, robot, sim
        self.intrinsics = CameraIntrinsics(
            camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
            camera.depth_scale,
        )  # fmt: skip
        self.atlas: TextureAtlas = build_atlas(world_textures(world))
        self.mesh = build_scene_mesh(world, self.atlas.names)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(self.mesh.vertices), o3d.core.Tensor(self.mesh.triangles)
        )
        m = self.mesh
        self._tri_attr = np.ascontiguousarray(np.column_stack(
            [m.u_axis, m.u_offset, m.v_axis, m.v_offset, m.normal, m.texels_per_metre]
        ).astype(np.float32))  # fmt: skip
        self._tri_tex = m.texture.astype(np.int32)
        h, w = camera.height, camera.width
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        # Ray directions in the optical frame with z = 1, so the ray parameter *is* depth z.
        self._dirs_opt = np.stack(
            [(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1
        ).reshape(-1, 3)
        self._dir_norm = np.linalg.norm(self._dirs_opt, axis=1)
        self._rays = np.empty((h * w, 6), np.float32)
        self._cols = u
        # Noise banks: a frame takes a window at a random offset (cheap, seeded, deterministic).
        bank_rng = np.random.default_rng(noise_seed)
        n = h * w
        self._gauss = bank_rng.standard_normal(NOISE_BANK_FACTOR * 3 * n, dtype=np.float32)
        self._uniform = bank_rng.random(NOISE_BANK_FACTOR * n, dtype=np.float32)

    def _window(self, bank: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
        start = int(rng.integers(0, len(bank) - n))
        return bank[start : start + n]

    def cast(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free ray cast: (z [m] (N,) with inf for no hit, triangle id (N,), dirs_world)."""
        r, t = camera_pose_in_world(x, y, yaw, self.robot)
        dirs = self._dirs_opt @ r.T.astype(np.float32)
        self._rays[:, :3] = t.astype(np.float32)
        self._rays[:, 3:] = dirs
        hit = self.scene.cast_rays(self._o3c.Tensor.from_numpy(self._rays))
        z = hit["t_hit"].numpy()
        tri = hit["primitive_ids"].numpy().astype(np.int64)
        return z, tri, dirs

    def true_depth(self, x: float, y: float, yaw: float) -> np.ndarray:
        """Noise-free depth image [m] (inf where nothing is hit), for tests and ground truth."""
        z, _, _ = self.cast(x, y, yaw)
        return z.reshape(self.camera.height, self.camera.width)

    def render(
        self, x: float, y: float, yaw: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        cam, sim = self.camera, self.sim
        h, w, n = cam.height, cam.width, cam.height * cam.width
        z, tri, dirs = self.cast(x, y, yaw)
        hit = np.isfinite(z)
        tri = np.where(hit, tri, 0)
        zf = np.where(hit, z, 0.0).astype(np.float32)
        rgb = self._shade(x, y, yaw, zf, tri, dirs, hit, rng)
        depth = self._kinect_depth(z.reshape(h, w), rng)
        return rgb.reshape(h, w, 3), depth

    def _shade(self, x: float, y: float, yaw: float, z: np.ndarray, tri: np.ndarray,
               dirs: np.ndarray, hit: np.ndarray, rng: np.random.Generator) -> np.ndarray:  # fmt: skip
        _, origin = camera_pose_in_world(x, y, yaw, self.robot)
        attr = self._tri_attr[tri]  # one gather: (N, 12) float32
        p = origin.astype(np.float32) + dirs * z[:, None]
        u = p[:, 0] * attr[:, 0] + p[:, 1] * attr[:, 1] + p[:, 2] * attr[:, 2] + attr[:, 3]
        v = p[:, 0] * attr[:, 4] + p[:, 1] * attr[:, 5] + p[:, 2] * attr[:, 6] + attr[:, 7]
        n_dot_d = dirs[:, 0] * attr[:, 8] + dirs[:, 1] * attr[:, 9] + dirs[:, 2] * attr[:, 10]
        cos_inc = np.maximum(np.abs(n_dot_d) / self._dir_norm, 0.05)
        # Mip level from the texels one pixel's footprint covers on the surface.
        dist = z * self._dir_norm
        texels = dist * attr[:, 11] / (self.camera.fx * cos_inc)
        level = np.clip(np.log2(np.maximum(texels, 1.0)), 0, MIP_LEVELS - 1).astype(np.int32)
        albedo = self.atlas.lookup(self._tri_tex[tri], u, v, level)
        light = (AMBIENT + (1 - AMBIENT) * cos_inc) * np.maximum(1 - DISTANCE_FALLOFF * dist, 0.3)
        light = np.where(hit, light, 0.0).astype(np.float32)
        noise = self._window(self._gauss, 3 * len(z), rng).reshape(-1, 3) * self.sim.rgb_noise
        rgb = albedo * light[:, None] + noise
        return np.clip(rgb, 0, 255).astype(np.uint8)

    def _kinect_depth(self, z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        cam, sim = self.camera, self.sim
        h, w = z.shape
        fb = cam.disparity_focal * cam.baseline  # [px m]
        finite = np.isfinite(z)
        zt = np.where(finite, z, np.inf).astype(np.float32)
        disparity = fb / zt  # 0 where nothing was hit
        noisy = disparity + sim.disparity_noise * self._window(self._gauss, h * w, rng).reshape(
            h, w
        )
        q = float(sim.disparity_subpixel)
        quantised = np.round(noisy * q) / q
        valid = finite & (zt >= cam.depth_min) & (zt <= cam.depth_max) & (quantised > 0)
        with np.errstate(divide="ignore"):
            depth = np.where(valid, fb / np.where(quantised > 0, quantised, 1.0), 0.0)
        valid &= ~self._edges(zt)
        if sim.shadows:
            valid &= ~self._projector_shadow(disparity)
        if sim.depth_dropout > 0:
            valid &= self._window(self._uniform, h * w, rng).reshape(h, w) >= sim.depth_dropout
        return np.where(valid, depth, 0.0).astype(np.float32)

    def _edges(self, z: np.ndarray) -> np.ndarray:
        """Pixels beside a relative depth jump larger than depth_edge_threshold."""
        thr = self.sim.depth_edge_threshold
        if thr <= 0:
            return np.zeros(z.shape, bool)
        zc = np.where(np.isfinite(z), z, 1e3)
        edge = np.zeros(z.shape, bool)
        dx = np.abs(np.diff(zc, axis=1)) > thr * np.minimum(zc[:, 1:], zc[:, :-1])
        dy = np.abs(np.diff(zc, axis=0)) > thr * np.minimum(zc[1:], zc[:-1])
        # The far side of a jump loses its pixel (mixed returns there), as on a real Kinect.
        edge[:, 1:] |= dx & (zc[:, 1:] > zc[:, :-1])
        edge[:, :-1] |= dx & (zc[:, :-1] > zc[:, 1:])
        edge[1:] |= dy & (zc[1:] > zc[:-1])
        edge[:-1] |= dy & (zc[:-1] > zc[1:])
        return edge

    def _projector_shadow(self, disparity: np.ndarray) -> np.ndarray:
        """Pixels the projector (``baseline`` to the right) cannot light.

        A point at column u appears at projector column u_p = u - f*b/z. Along a row the
        projector columns of lit points must increase with u; a pixel whose u_p is not below
        every u_p to its right is hidden behind something nearer.
        """
        scale = self.camera.fx / self.camera.disparity_focal  # disparity in colour pixels
        u_p = self._cols - disparity * scale
        right_min = np.minimum.accumulate(u_p[:, ::-1], axis=1)[:, ::-1]
        min_to_right = np.full_like(u_p, np.inf)
        min_to_right[:, :-1] = right_min[:, 1:]
        return u_p >= min_to_right + 0.5

    def depth_sigma(self, z: np.ndarray | float) -> np.ndarray | float:
        """Model depth standard deviation [m] at depth z: disparity noise plus quantisation."""
        cam, sim = self.camera, self.sim
        sigma_d = math.hypot(sim.disparity_noise, (1.0 / sim.disparity_subpixel) / math.sqrt(12))
        return np.asarray(z) ** 2 * sigma_d / (cam.disparity_focal * cam.baseline)
