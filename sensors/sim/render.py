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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.extrinsics import camera_pose_in_world
from sensors.sim.textures import (
    MIP_LEVELS,
    TEXTURE_BITS,
    TEXTURE_SIZE,
    TextureAtlas,
    build_atlas,
)
from sensors.sim.world import Box, World
from sensors.types import CameraIntrinsics

AMBIENT = 0.35  # share of light that does not depend on the surface angle
DISTANCE_FALLOFF = 0.04  # [1/m] brightness lost per metre (a dim indoor scene)
NOISE_BANK_FACTOR = 2  # noise banks hold this many frames of samples
Z_NEAR = 0.02  # [m] near clipping plane of the rasteriser
RASTER_SHIFT = 4  # fractional bits of polygon vertices handed to OpenCV
MIN_COS_INCIDENCE = 0.05  # grazing surfaces are shaded as if at ~87 degrees
EDGE_KERNEL = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))  # 4-neighbourhood
LUT_SIZE = 256  # cv2.LUT maps uint8 indices: the fast shading path needs faces + 1 <= 256
LEVEL_KEY_BITS = 3  # a pixel's (texture, mip level) key is texture << 3 | level, in a uint8
FLOAT32_EXPONENT_SHIFT = 23  # bits of the float32 mantissa
FLOAT32_EXPONENT_BIAS = 127
SHADOW_WINDOW_MAX = 60  # [px] beyond this reach a running minimum beats cv2.erode's window
BAND_ROWS = 120  # rows processed at a time, so a band's temporaries stay in cache


@dataclass(frozen=True, eq=False)
class SceneFaces:
    """Every quad face of the world, with the plane that maps a point to texture tiles."""

    corners: np.ndarray  # (F, 4, 3) float64 [m] world, counter-clockwise seen from outside
    normal: np.ndarray  # (F, 3) unit, pointing out of the solid
    u_axis: np.ndarray  # (F, 3): u = p . u_axis + u_offset  [tiles]
    u_offset: np.ndarray  # (F,)
    v_axis: np.ndarray  # (F, 3)
    v_offset: np.ndarray  # (F,)
    texels_per_metre: np.ndarray  # (F,) at the finest mip level
    texture: np.ndarray  # (F,) int32 index into the atlas

    def __len__(self) -> int:
        return len(self.corners)


# Box corners: 0-3 the footprint at z_min (counter-clockwise), 4-7 the same at z_max.
_FACES = (  # corner indices, counter-clockwise seen from outside
    (0, 1, 5, 4),  # -y side
    (2, 3, 7, 6),  # +y side
    (3, 0, 4, 7),  # -x side
    (1, 2, 6, 5),  # +x side
    (4, 5, 6, 7),  # top
    (3, 2, 1, 0),  # bottom
)


def _box_corners(b: Box) -> np.ndarray:
    fp = b.footprint()
    low = np.column_stack([fp, np.full(4, b.z_min)])
    high = np.column_stack([fp, np.full(4, b.z_max)])
    return np.vstack([low, high])


def build_scene_faces(world: World, atlas_names: tuple[str, ...]) -> SceneFaces:
    quads, normals, uax, uoff, vax, voff, tpm, tex = [], [], [], [], [], [], [], []

    def add_quad(c: np.ndarray, quad: tuple[int, ...], texture: str, scale: float) -> None:
        pts = c[list(quad)]
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
        quads.append(pts)
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
    corners_2d = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    plane = np.vstack(
        [np.column_stack([corners_2d, np.zeros(4)]), np.column_stack([corners_2d, np.full(4, h)])]
    )
    add_quad(plane, (0, 1, 2, 3), world.floor.texture, world.floor.scale)
    add_quad(plane, (4, 7, 6, 5), world.ceiling.texture, world.ceiling.scale)
    return SceneFaces(
        corners=np.array(quads),
        normal=np.array(normals),
        u_axis=np.array(uax),
        u_offset=np.array(uoff),
        v_axis=np.array(vax),
        v_offset=np.array(voff),
        texels_per_metre=np.array(tpm),
        texture=np.array(tex, np.int32),
    )


# Rows of the per-frame face table (see face_table); one extra column is the "no surface" face.
# The shading rows come first so shading gathers one contiguous block of them.
(TU_A, TU_B, TU_C, TU_D, TV_A, TV_B, TV_C, TV_D, ABS_D, MIP_K, INVZ_A, INVZ_B, INVZ_C) = range(13)
SHADING_ROWS = 10


def face_table(
    faces: SceneFaces, r_wo: np.ndarray, t_wo: np.ndarray, cam: CameraConfig
) -> np.ndarray:
    """Per-face coefficients for one camera pose, (13, F + 1) float32, so that for a pixel (u, v)
    on face f (d = ((u - cx)/fx, (v - cy)/fy, 1) its ray in the optical frame):

    * inverse depth   1/z   = A u + B v + C           (a plane is affine in 1/z)
    * texture tile    u_tex = z (a u + b v + c) + d   (and v_tex alike)
    * cos incidence   |n.d|/|d| = ABS_D * (1/z) / |d|  (ABS_D = distance from camera to plane)
    * texels a pixel covers     = z^2 |d|^2 * MIP_K

    The last column is all zeros: pixels that see nothing.
    """
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    n_c = faces.normal @ r_wo  # rows: R^T n
    d_c = np.einsum("fi,fi->f", n_c, (faces.corners[:, 0] - t_wo) @ r_wo)  # n_c . o_c
    d_c = np.where(np.abs(d_c) < 1e-9, 1e-9, d_c)
    table = np.zeros((13, len(faces) + 1), np.float64)

    def affine(vec: np.ndarray, rows: tuple[int, int, int], scale: np.ndarray) -> None:
        a, b, c = rows
        table[a, :-1] = vec[:, 0] / fx * scale
        table[b, :-1] = vec[:, 1] / fy * scale
        table[c, :-1] = (vec[:, 2] - vec[:, 0] * cx / fx - vec[:, 1] * cy / fy) * scale

    affine(n_c, (INVZ_A, INVZ_B, INVZ_C), 1.0 / d_c)
    affine(faces.u_axis @ r_wo, (TU_A, TU_B, TU_C), np.ones(len(faces)))
    affine(faces.v_axis @ r_wo, (TV_A, TV_B, TV_C), np.ones(len(faces)))
    table[TU_D, :-1] = faces.u_axis @ t_wo + faces.u_offset
    table[TV_D, :-1] = faces.v_axis @ t_wo + faces.v_offset
    table[ABS_D, :-1] = np.abs(d_c)
    table[MIP_K, :-1] = faces.texels_per_metre / (fx * np.abs(d_c))
    return table.astype(np.float32)


def _clip_near(poly: np.ndarray, z_near: float) -> np.ndarray:
    """Sutherland-Hodgman against the plane z = z_near (optical frame); poly (k, 3)."""
    out = []
    k = len(poly)
    for i in range(k):
        a, b = poly[i], poly[(i + 1) % k]
        a_in, b_in = a[2] >= z_near, b[2] >= z_near
        if a_in:
            out.append(a)
        if a_in != b_in:
            s = (z_near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out)


def rasterize(
    faces: SceneFaces, table: np.ndarray, r_wo: np.ndarray, t_wo: np.ndarray, cam: CameraConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffered scan conversion of the visible faces.

    Returns (inverse depth 1/z (H, W) float32, 0 = nothing; face index (H, W) int32, F = none).
    Each face is filled with OpenCV over its bounding box and its exact plane depth is compared
    with the buffer there, so cost grows with the screen area faces cover, not with pixels x faces.
    """
    return _scan_convert(faces, table, r_wo, t_wo, cam, np.dtype(np.int32))


def _scan_convert(
    faces: SceneFaces,
    table: np.ndarray,
    r_wo: np.ndarray,
    t_wo: np.ndarray,
    cam: CameraConfig,
    face_dtype: np.dtype,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rasterize` with the face index in ``face_dtype`` (uint8 when F + 1 <= 256: the
    renderer's shading reads it with cv2.LUT, and a byte per pixel is cheaper to write)."""
    h, w = cam.height, cam.width
    n_faces = len(faces)
    invz = np.zeros((h, w), np.float32)
    face = np.full((h, w), n_faces, face_dtype)
    cam_pos = t_wo
    # Back faces and faces wholly outside one frustum plane never reach the loop.
    front = np.einsum("fi,fi->f", faces.normal, cam_pos - faces.corners[:, 0]) > 1e-6
    pc = (faces.corners - t_wo) @ r_wo  # (F, 4, 3) optical frame
    x, y, z = pc[..., 0], pc[..., 1], pc[..., 2]
    outside = (
        np.all(z < Z_NEAR, axis=1)
        | np.all(x * cam.fx < (-0.5 - cam.cx) * z, axis=1)
        | np.all(x * cam.fx > (w - 0.5 - cam.cx) * z, axis=1)
        | np.all(y * cam.fy < (-0.5 - cam.cy) * z, axis=1)
        | np.all(y * cam.fy > (h - 0.5 - cam.cy) * z, axis=1)
    )
    drawn = np.flatnonzero(front & ~outside)
    # Screen polygons of all faces in front of the near plane at once; the few that cross it are
    # clipped and projected one by one.
    whole = np.all(z[drawn] >= Z_NEAR, axis=1)
    polygons = [_screen_polygon(pc[f], cam) for f in drawn[~whole]]
    with np.errstate(divide="ignore", invalid="ignore"):
        u_all = x[drawn[whole]] / z[drawn[whole]] * cam.fx + cam.cx
        v_all = y[drawn[whole]] / z[drawn[whole]] * cam.fy + cam.cy
    polygons += list(zip(u_all, v_all, strict=True))
    order = np.concatenate([drawn[~whole], drawn[whole]])
    cols = np.arange(w, dtype=np.float32)
    rows = np.arange(h, dtype=np.float32)[:, None]
    # In face order, as ties in the z-buffer go to the face drawn first.
    for f, (u, v) in sorted(zip(order.tolist(), polygons, strict=True), key=lambda fp: fp[0]):
        if len(u) < 3:
            continue
        x0, x1 = max(math.floor(u.min()), 0), min(math.ceil(u.max()) + 1, w)
        y0, y1 = max(math.floor(v.min()), 0), min(math.ceil(v.max()) + 1, h)
        if x0 >= x1 or y0 >= y1:
            continue
        a, b, c = table[INVZ_A, f], table[INVZ_B, f], table[INVZ_C, f]
        plane = cols[x0:x1] * a + (rows[y0:y1] * b + c)
        view = invz[y0:y1, x0:x1]
        # closer = inside the polygon and nearer than the buffer (OpenCV: 0/255 & 0/1 = 0/1).
        closer = cv2.compare(plane, view, cv2.CMP_GT)
        inside = np.zeros_like(closer)
        pts = np.round(np.column_stack([u - x0, v - y0]) * (1 << RASTER_SHIFT)).astype(np.int32)
        cv2.fillConvexPoly(inside, pts, 1, lineType=cv2.LINE_8, shift=RASTER_SHIFT)
        cv2.bitwise_and(closer, inside, dst=closer)
        cv2.copyTo(plane, closer, view)  # in place: view is a window of invz
        cv2.copyTo(np.full(closer.shape, f, face_dtype), closer, face[y0:y1, x0:x1])
    return invz, face


def _screen_polygon(poly: np.ndarray, cam: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) of a polygon (k, 3) in the optical frame, clipped at Z_NEAR."""
    poly = _clip_near(poly, Z_NEAR)
    if len(poly) < 3:
        return np.empty(0), np.empty(0)
    return (poly[:, 0] / poly[:, 2] * cam.fx + cam.cx, poly[:, 1] / poly[:, 2] * cam.fy + cam.cy)


def _open3d_scene(faces: SceneFaces) -> object:
    """Open3D RaycastingScene of the faces, two triangles per quad (triangle 2f, 2f+1 = face f)."""
    import open3d as o3d  # heavy; only the reference backend needs it

    verts = faces.corners.reshape(-1, 3).astype(np.float32)
    base = 4 * np.arange(len(faces), dtype=np.uint32)[:, None]
    tris = np.stack([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3).astype(np.uint32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor.from_numpy(verts), o3d.core.Tensor.from_numpy(tris))
    return scene


def world_textures(world: World) -> tuple[str, ...]:
    names = {b.texture for b in world.boxes} | {world.floor.texture, world.ceiling.texture}
    return tuple(sorted(names))


def camera_intrinsics(camera: CameraConfig) -> CameraIntrinsics:
    return CameraIntrinsics(
        camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, camera.depth_scale
    )


class KinectRenderer:
    """Renders ``(rgb uint8 HxWx3, depth_m float32 HxW)`` for a base_link pose.

    ``sim.renderer`` picks the geometry backend: "raster" (fast z-buffered scan conversion) or
    "raycast" (Open3D RaycastingScene, the reference the rasteriser is tested against). Both feed
    the same shading and Kinect error model. Randomness comes only from the generator passed to
    :meth:`render`, so the same seed and poses give identical images.
    """

    def __init__(
        self,
        world: World,
        camera: CameraConfig,
        robot: RobotConfig,
        sim: SimConfig,
        noise_seed: int = 0,
        backend: str | None = None,
    ) -> None:
        self.camera, self.robot, self.sim = camera, robot, sim
        self.backend = backend or sim.renderer
        self.intrinsics = camera_intrinsics(camera)
        self.atlas: TextureAtlas = build_atlas(world_textures(world))
        self.faces = build_scene_faces(world, self.atlas.names)
        self._scene = None
        if self.backend == "raycast":
            self._scene = _open3d_scene(self.faces)
        h, w = camera.height, camera.width
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        self._u, self._v = u.ravel(), v.ravel()
        # Ray directions in the optical frame with z = 1, so the ray parameter *is* depth z.
        self._dirs_opt = np.stack(
            [(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1
        ).reshape(-1, 3)
        self._dir_norm2 = np.einsum("ij,ij->i", self._dirs_opt, self._dirs_opt)
        self._dir_norm = np.sqrt(self._dir_norm2)
        self._cols = u
        self._tex = np.append(self.faces.texture, 0).astype(np.int32)
        self._fast_shading = len(self.faces) + 1 <= LUT_SIZE and (
            len(self.atlas.names) << LEVEL_KEY_BITS <= LUT_SIZE
        )
        self._face_dtype = np.dtype(np.uint8 if self._fast_shading else np.int32)
        if self._fast_shading:
            self._init_shading_luts()
        # Noise banks: a frame takes a window at a random offset (cheap, seeded, deterministic).
        bank_rng = np.random.default_rng(noise_seed)
        n = h * w
        gauss = bank_rng.standard_normal(NOISE_BANK_FACTOR * n, dtype=np.float32)
        uniform = bank_rng.random(NOISE_BANK_FACTOR * n, dtype=np.float32)
        # Scaled and thresholded once here rather than per frame (the same products and
        # comparisons, element by element).
        self._disparity_noise = np.float32(sim.disparity_noise) * gauss  # [px]
        self._kept = uniform >= sim.depth_dropout  # survives the random dropout
        rgb = np.round(bank_rng.standard_normal(NOISE_BANK_FACTOR * 4 * n) * sim.rgb_noise)
        self._rgb_plus = np.clip(rgb, 0, 255).astype(np.uint8)
        self._rgb_minus = np.clip(-rgb, 0, 255).astype(np.uint8)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="kinect-depth")

    def _init_shading_luts(self) -> None:
        """256-entry tables of the fast shading path (see :meth:`_shade`)."""
        # Biased float32 exponent -> mip level: floor(log2 x) clipped to the chain, and level 0
        # for 0, subnormals, inf and NaN, exactly as clip(frexp(x)[1] - 1, 0, MIP_LEVELS - 1).
        level = np.clip(np.arange(LUT_SIZE) - FLOAT32_EXPONENT_BIAS, 0, MIP_LEVELS - 1)
        level[-1] = 0
        self._level_lut = level.astype(np.uint8).reshape(1, -1)
        texture_key = np.zeros(LUT_SIZE, np.uint8)
        texture_key[: len(self._tex)] = self._tex << LEVEL_KEY_BITS
        self._texture_key_lut = texture_key.reshape(1, -1)
        # (texture, level) key -> the level's texel (0, 0) in the atlas, and the mask that turns
        # ty << TEXTURE_BITS into the level's row term ((ty & 511) >> L) << (TEXTURE_BITS + L).
        block = np.zeros(LUT_SIZE, np.int32)
        row_mask = np.zeros(LUT_SIZE, np.uint32)
        for t in range(len(self.atlas.names)):
            for lev in range(MIP_LEVELS):
                key = t << LEVEL_KEY_BITS | lev
                block[key] = self.atlas.level_origin[t, lev]
                row_mask[key] = (TEXTURE_SIZE - (1 << lev)) << TEXTURE_BITS
        self._block_lut = block.reshape(1, -1)
        self._row_mask_lut = row_mask.view(np.int32).reshape(1, -1)

    def noise_offsets(self, rng: np.random.Generator) -> tuple[int, int, int]:
        """Where one frame's colour, disparity and dropout noise start in their banks: the
        draws :meth:`render` makes, in its order (a caller may draw them to skip a frame)."""
        n = self.camera.height * self.camera.width
        return (
            int(rng.integers(0, len(self._rgb_plus) - 4 * n)),
            int(rng.integers(0, len(self._disparity_noise) - n)),
            int(rng.integers(0, len(self._kept) - n)),
        )

    def geometry(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free (inverse depth (H, W), face index (H, W) int32, face table) for a base
        pose."""
        invz, face, table = self._geometry(x, y, yaw)
        return invz, face.astype(np.int32, copy=False), table

    def _geometry(
        self, x: float, y: float, yaw: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`geometry` with the face index in ``self._face_dtype``."""
        r, t = camera_pose_in_world(x, y, yaw, self.robot)
        table = face_table(self.faces, r, t, self.camera)
        if self._scene is None:
            invz, face = _scan_convert(self.faces, table, r, t, self.camera, self._face_dtype)
        else:
            invz, face = self._raycast(r, t)
            face = face.astype(self._face_dtype, copy=False)
        return invz, face, table

    def _raycast(self, r: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import open3d as o3d

        h, w = self.camera.height, self.camera.width
        rays = np.empty((h * w, 6), np.float32)
        rays[:, :3] = t
        rays[:, 3:] = self._dirs_opt @ r.T.astype(np.float32)
        hit = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))  # type: ignore[attr-defined]
        z = hit["t_hit"].numpy().reshape(h, w)
        tri = hit["primitive_ids"].numpy().astype(np.int64).reshape(h, w)
        ok = np.isfinite(z)
        with np.errstate(divide="ignore"):
            invz = np.where(ok, 1.0 / z, 0.0).astype(np.float32)
        face = np.where(ok, tri // 2, len(self.faces)).astype(np.int32)
        return invz, face

    def true_depth(self, x: float, y: float, yaw: float) -> np.ndarray:
        """Noise-free depth image [m] (inf where nothing is hit), for tests and ground truth."""
        invz, _, _ = self.geometry(x, y, yaw)
        return self.true_depth_from_invz(invz)

    def render(
        self, x: float, y: float, yaw: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.camera.height, self.camera.width
        invz, face, table = self._geometry(x, y, yaw)
        # Draw the noise windows here, in a fixed order, so threading cannot change the output.
        rgb_noise, d0, k0 = self.noise_offsets(rng)
        depth_noise = self._disparity_noise[d0 : d0 + h * w]
        kept = self._kept[k0 : k0 + h * w]
        # numpy releases the GIL on whole-image work: colour and depth run on both cores.
        pending = self._pool.submit(self._kinect_depth, invz, depth_noise, kept)
        if self._fast_shading:
            rgb = self._shade(invz, face, table, rgb_noise)
        else:
            rgb = self._shade_reference(
                invz.ravel(), face.ravel().astype(np.intp), table, rgb_noise
            )
        return rgb.reshape(h, w, 3), pending.result()

    def _shade(
        self, invz: np.ndarray, face: np.ndarray, table: np.ndarray, noise_start: int
    ) -> np.ndarray:
        """:meth:`_shade_reference`, bit for bit, at under half the cost: invz (H, W) float32,
        face (H, W) uint8. Per-face coefficients are read with cv2.LUT on the uint8 face index
        (about 2x faster than np.take), the texture coordinates come out already in finest-level
        texels (the tile rows are scaled by TEXTURE_SIZE, a power of two, so every product and
        sum is the reference's scaled exactly), the mip level is read off the float32 exponent
        bits, and one (texture, level) key gives both the atlas block and the row mask. The image
        is shaded in bands of rows so each band's temporaries stay in the L2 cache.
        """
        h, w = self.camera.height, self.camera.width
        lut = np.zeros((SHADING_ROWS, 1, LUT_SIZE), np.float32)
        lut[:, 0, : table.shape[1]] = table[:SHADING_ROWS]
        lut[TU_A : TU_D + 1] *= TEXTURE_SIZE
        lut[TV_A : TV_D + 1] *= TEXTURE_SIZE
        rgb = np.empty((h, w, 3), np.uint8)
        for r0 in range(0, h, BAND_ROWS):
            rows = slice(r0, min(r0 + BAND_ROWS, h))
            pixels = slice(r0 * w, rows.stop * w)
            albedo, light8 = self._shade_band(invz[rows], face[rows], lut, pixels)
            self._finish(albedo, light8, noise_start + 4 * pixels.start, out=rgb[rows])
        return rgb

    def _shade_band(
        self, invz: np.ndarray, face: np.ndarray, lut: np.ndarray, pixels: slice
    ) -> tuple[np.ndarray, np.ndarray]:
        """Albedo (rows, W, 4) and light (rows, W) uint8 of one band of rows; ``pixels`` is the
        band's range in the flattened image."""
        shape = invz.shape

        def coef(row: int) -> np.ndarray:
            return cv2.LUT(face, lut[row]).reshape(-1)

        invz = invz.reshape(-1)
        u, v = self._u[pixels], self._v[pixels]
        dir_norm, dir_norm2 = self._dir_norm[pixels], self._dir_norm2[pixels]
        # 1. Depth along the optical axis, 0 where nothing is seen. invz is never negative or NaN,
        #    so "not invz > 0" and "invz <= 0" are the same pixels.
        nothing = invz <= 0
        with np.errstate(divide="ignore"):
            z = np.divide(1.0, invz)
        np.copyto(z, np.float32(0), where=nothing)
        # 2. Texel coordinates on the finest level: z (a u + b v + c) + d, in the reference's
        #    order of operations.
        tex_x = coef(TU_A)
        tex_x *= u
        tmp = coef(TU_B)
        tmp *= v
        tex_x += tmp
        tex_x += coef(TU_C)
        tex_x *= z
        tex_x += coef(TU_D)
        tex_y = coef(TV_A)
        tex_y *= u
        np.multiply(coef(TV_B), v, out=tmp)
        tex_y += tmp
        tex_y += coef(TV_C)
        tex_y *= z
        tex_y += coef(TV_D)
        # 3. Mip level = floor(log2(texels per pixel)) from the exponent bits, and the key.
        texels = np.multiply(z, z, out=tmp)
        texels *= dir_norm2
        texels *= coef(MIP_K)
        exponent = (texels.view(np.uint32) >> FLOAT32_EXPONENT_SHIFT).astype(np.uint8)
        key = cv2.add(
            cv2.LUT(face, self._texture_key_lut).reshape(-1),
            cv2.LUT(exponent, self._level_lut).reshape(-1),
        )
        # 4. Atlas address: origin + ((ty & 511) >> L << (9 + L)) + (tx & 511), one gather.
        row = tex_y.astype(np.int32)
        row <<= TEXTURE_BITS
        np.bitwise_and(row, cv2.LUT(key, self._row_mask_lut).reshape(-1), out=row)
        flat = tex_x.astype(np.int32)
        flat &= TEXTURE_SIZE - 1
        flat += row
        np.add(flat, cv2.LUT(key, self._block_lut).reshape(-1), out=flat)
        albedo = np.take(self.atlas.texels, flat).view(np.uint8).reshape(*shape, 4)
        # 5. Lambert with ambient and a distance falloff, 8-bit.
        cos_inc = coef(ABS_D)
        cos_inc *= invz
        cos_inc /= dir_norm
        np.maximum(cos_inc, MIN_COS_INCIDENCE, out=cos_inc)
        falloff = np.multiply(z, dir_norm, out=tmp)
        falloff *= DISTANCE_FALLOFF
        np.subtract(1, falloff, out=falloff)
        np.maximum(falloff, 0.3, out=falloff)
        light = cos_inc
        light *= 1 - AMBIENT
        light += AMBIENT
        light *= falloff
        light *= 255
        light8 = light.astype(np.uint8).reshape(shape)
        np.copyto(light8, np.uint8(0), where=nothing.reshape(shape))
        return albedo, light8

    def _finish(
        self,
        albedo: np.ndarray,
        light8: np.ndarray,
        noise_start: int,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Albedo (H, W, 4) uint8 x light (H, W) uint8 / 255, plus sensor noise -> RGB (of the
        whole image or of a band of its rows)."""
        h, w = light8.shape
        shaded = cv2.multiply(albedo, cv2.merge([light8] * 4), scale=1 / 255)
        # Sensor noise in whole 8-bit levels, added and subtracted with saturation.
        start = noise_start
        plus = self._rgb_plus[start : start + 4 * h * w].reshape(h, w, 4)
        minus = self._rgb_minus[start : start + 4 * h * w].reshape(h, w, 4)
        shaded = cv2.subtract(cv2.add(shaded, plus), minus)
        return cv2.cvtColor(shaded, cv2.COLOR_RGBA2RGB, dst=out)

    def _shade_reference(
        self, invz: np.ndarray, face: np.ndarray, table: np.ndarray, noise_start: int
    ) -> np.ndarray:
        """The readable shading kernel :meth:`_shade` reproduces bit for bit: invz (N,) float32,
        face (N,) intp. Also the path for worlds too big for 8-bit face indices."""
        g = np.take(table[:SHADING_ROWS], face, axis=1)  # (10, N): one gather for all of them
        z = np.zeros_like(invz)
        np.divide(1.0, invz, out=z, where=invz > 0)  # 0 where nothing is seen
        u, v = self._u, self._v
        tu = z * (g[TU_A] * u + g[TU_B] * v + g[TU_C]) + g[TU_D]
        tv = z * (g[TV_A] * u + g[TV_B] * v + g[TV_C]) + g[TV_D]
        cos_inc = np.maximum(g[ABS_D] * invz / self._dir_norm, MIN_COS_INCIDENCE)
        # Mip level = floor(log2(texels per pixel)), read off the float exponent.
        texels = z * z * self._dir_norm2 * g[MIP_K]
        level = np.clip(np.frexp(texels)[1] - 1, 0, MIP_LEVELS - 1).astype(np.int32)
        albedo = self.atlas.lookup(self._tex[face], tu, tv, level)
        dist = z * self._dir_norm
        light = (AMBIENT + (1 - AMBIENT) * cos_inc) * np.maximum(1 - DISTANCE_FALLOFF * dist, 0.3)
        light[invz <= 0] = 0.0
        h, w = self.camera.height, self.camera.width
        light8 = (light * 255).astype(np.uint8).reshape(h, w)
        return self._finish(albedo.reshape(h, w, 4), light8, noise_start)

    def true_depth_from_invz(self, invz: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return np.where(invz > 0, 1.0 / invz, np.inf).astype(np.float32)

    def _kinect_depth(self, invz: np.ndarray, noise: np.ndarray, kept: np.ndarray) -> np.ndarray:
        """Inverse true depth (0 = no hit) -> Kinect v1 depth [m] (0 = invalid); ``noise`` holds
        the disparity noise [px] and ``kept`` whether the pixel survives the random dropout, one
        per pixel.

        Disparity is proportional to inverse depth, so the whole model works on 1/z. Everything
        but the edge test is per row, so it runs in bands of rows that stay in cache.
        """
        h, w = invz.shape
        edges = self._edges(invz)  # needs the neighbouring rows: whole image at once
        noise, kept = noise.reshape(h, w), kept.reshape(h, w)
        depth = np.empty((h, w), np.float32)
        for r0 in range(0, h, BAND_ROWS):
            rows = slice(r0, min(r0 + BAND_ROWS, h))
            self._kinect_depth_band(invz[rows], noise[rows], kept[rows], edges[rows], depth[rows])
        return depth

    def _kinect_depth_band(
        self,
        invz: np.ndarray,
        noise: np.ndarray,
        kept: np.ndarray,
        edges: np.ndarray,
        depth: np.ndarray,
    ) -> None:
        """:meth:`_kinect_depth` of one band of rows, given its depth-edge mask, into ``depth``."""
        cam, sim = self.camera, self.sim
        fb = np.float32(cam.disparity_focal * cam.baseline)  # [px m]
        disparity = fb * invz  # 0 where nothing was hit
        quantised = disparity + noise
        q = np.float32(sim.disparity_subpixel)
        quantised *= q
        np.round(quantised, out=quantised)
        quantised /= q
        valid = invz >= 1 / cam.depth_max
        valid &= invz <= 1 / cam.depth_min
        valid &= quantised > 0
        valid &= ~edges
        if sim.shadows:
            valid &= ~self._projector_shadow(disparity)
        if sim.depth_dropout > 0:
            valid &= kept
        # fb / quantised everywhere, then 0 where invalid: cheaper than a masked divide.
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            np.divide(fb, quantised, out=depth)
        np.copyto(depth, np.float32(0), where=~valid)

    def _edges(self, invz: np.ndarray) -> np.ndarray:
        """The far side of every relative depth jump above ``depth_edge_threshold`` (mixed
        returns there make a real Kinect drop the pixel): pixels farther than their nearest
        4-neighbour by more than the threshold, z > (1 + thr) z_near, i.e. in inverse depth
        1/z < max_neighbour(1/z) / (1 + thr)."""
        thr = self.sim.depth_edge_threshold
        if thr <= 0:
            return np.zeros(invz.shape, bool)
        nearest = cv2.dilate(invz, EDGE_KERNEL, borderType=cv2.BORDER_REPLICATE)
        return invz * np.float32(1 + thr) < nearest

    def _projector_shadow(self, disparity: np.ndarray) -> np.ndarray:
        """Pixels the projector (``baseline`` to the right) cannot light.

        A point at column u appears at projector column u_p = u - f*b/z. Along a row the
        projector columns of lit points must increase with u; a pixel whose u_p is not below
        every u_p to its right is hidden behind something nearer.

        Only the next ``reach`` = ceil(max f*b/z) + 2 columns can hide a pixel: farther right,
        u_p[k] >= k - max f*b/z > j + 1 >= u_p[j]. So when that reach is short, the minimum to the
        right is a running minimum over a window (cv2.erode, cost ~ reach) and the result is the
        same bit for bit; near objects fall back to the full running minimum.
        """
        scale = self.camera.fx / self.camera.disparity_focal  # disparity in colour pixels
        u_p = disparity * scale
        np.subtract(self._cols[: len(u_p)], u_p, out=u_p)
        # min_to_right[:, j] = min(u_p[:, j + 1:]), inf in the last column (nothing to its right).
        min_to_right = np.empty_like(u_p)
        min_to_right[:, -1] = np.inf
        shift = float(disparity.max()) * scale  # [px] the largest u - u_p
        if math.isfinite(shift) and shift < SHADOW_WINDOW_MAX:
            reach = math.ceil(shift) + 2
            # min(u_p[:, j + 1 : j + 1 + reach]), written in place
            kernel = np.ones((1, reach), np.uint8)
            cv2.erode(
                u_p[:, 1:],
                kernel,
                dst=min_to_right[:, :-1],
                anchor=(0, 0),
                borderType=cv2.BORDER_CONSTANT,
                borderValue=np.inf,
            )
        else:
            np.minimum.accumulate(u_p[:, :0:-1], axis=1, out=min_to_right[:, -2::-1])
        min_to_right += 0.5
        return u_p >= min_to_right

    def depth_sigma(self, z: np.ndarray | float) -> np.ndarray | float:
        """Model depth standard deviation [m] at depth z: disparity noise plus quantisation."""
        cam, sim = self.camera, self.sim
        sigma_d = math.hypot(sim.disparity_noise, (1.0 / sim.disparity_subpixel) / math.sqrt(12))
        return np.asarray(z) ** 2 * sigma_d / (cam.disparity_focal * cam.baseline)
