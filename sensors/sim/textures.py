"""Texture catalogue for the simulator: scikit-image's bundled photographs plus procedural ones,
stored as one flat mip-mapped atlas so a frame's colours are a single vectorised gather."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sensors.types import WorldError

TEXTURE_BITS = 9
TEXTURE_SIZE = 1 << TEXTURE_BITS  # [px] side of the finest mip level
MIP_LEVELS = 7  # 512 .. 8 px

# Photographs shipped inside the scikit-image wheel (no download): name -> file.
PHOTO_FILES = {
    "brick": "brick.png",
    "grass": "grass.png",
    "gravel": "gravel.png",
    "coffee": "coffee.png",
    "astronaut": "astronaut.png",
    "chelsea": "chelsea.png",
    "rocket": "rocket.jpg",
    "hubble": "hubble_deep_field.jpg",
    "motorcycle": "motorcycle_left.png",
    "retina": "retina.jpg",
    "camera": "camera.png",
    "coins": "coins.png",
    "page": "page.png",
    "text": "text.png",
    "moon": "moon.png",
    "ihc": "ihc.png",
    "horse": "horse.png",
    "cell": "cell.png",
}
PROCEDURAL = ("plaster", "wood", "tiles", "carpet", "matte")  # append: the index seeds the noise
TEXTURE_NAMES = tuple(PHOTO_FILES) + PROCEDURAL


def _square(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    s = min(h, w)
    img = img[(h - s) // 2 : (h - s) // 2 + s, (w - s) // 2 : (w - s) // 2 + s]
    return cv2.resize(img, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_AREA)


def _photo(name: str) -> np.ndarray:
    import skimage.data  # heavy; only the simulator needs it
    from PIL import Image  # Pillow comes with scikit-image; it reads these files quietly

    path = Path(skimage.data.__file__).parent / PHOTO_FILES[name]
    try:
        with Image.open(path) as im:
            img = np.asarray(im.convert("RGB"))
    except OSError as err:
        raise WorldError(
            f"texture '{name}': cannot read {path} (is scikit-image installed?)"
        ) from err
    return _square(img)


def _fractal_noise(rng: np.random.Generator, octaves: int = 6) -> np.ndarray:
    """Tileable-ish value noise in [0, 1]: sum of upsampled random grids."""
    out = np.zeros((TEXTURE_SIZE, TEXTURE_SIZE), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = 4 << o
        grid = rng.random((n, n)).astype(np.float32)
        out += amp * cv2.resize(grid, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.6
    out /= total
    return (out - out.min()) / max(float(np.ptp(out)), 1e-6)


def _procedural(name: str) -> np.ndarray:
    rng = np.random.default_rng(PROCEDURAL.index(name) + 7)  # fixed: a world looks the same
    noise = _fractal_noise(rng)
    yy, xx = np.mgrid[0:TEXTURE_SIZE, 0:TEXTURE_SIZE].astype(np.float32) / TEXTURE_SIZE
    if name == "plaster":
        base = np.array([225, 218, 205], np.float32)
        shade = 0.8 + 0.35 * noise
    elif name == "wood":
        base = np.array([160, 110, 65], np.float32)
        rings = 0.5 + 0.5 * np.sin(2 * np.pi * (8 * yy + 1.5 * noise))
        planks = (np.floor(xx * 4) % 2) * 0.12
        shade = 0.65 + 0.3 * rings + planks + 0.1 * noise
    elif name == "tiles":
        base = np.array([200, 205, 210], np.float32)
        grout = ((xx * 4) % 1 < 0.03) | ((yy * 4) % 1 < 0.03)
        shade = np.where(grout, 0.45, 0.85 + 0.25 * noise)
    elif name == "matte":  # dim flat paint without any pattern: nothing for ORB but edges
        base = np.array([80, 78, 74], np.float32)
        shade = np.ones_like(noise)
    else:  # carpet
        base = np.array([120, 70, 80], np.float32)
        fine = rng.random((TEXTURE_SIZE, TEXTURE_SIZE)).astype(np.float32)
        shade = 0.6 + 0.3 * noise + 0.3 * fine
    return np.clip(base * shade[..., None], 0, 255).astype(np.uint8)


def texture_image(name: str) -> np.ndarray:
    """(TEXTURE_SIZE, TEXTURE_SIZE, 3) uint8 RGB."""
    if name in PHOTO_FILES:
        return _photo(name)
    if name in PROCEDURAL:
        return _procedural(name)
    raise WorldError(f"unknown texture '{name}' (known: {', '.join(TEXTURE_NAMES)})")


@dataclass(frozen=True, eq=False)
class TextureAtlas:
    """All textures at all mip levels in one flat array of packed RGBA texels.

    Each texture owns two TEXTURE_SIZE x TEXTURE_SIZE grids: the finest level, and every coarser
    level L >= 1 interleaved in a second grid on the rows whose lowest set bit is L - 1, each
    texel repeated 2^L times along its row. The texel a pixel with finest-level texel (tx, ty)
    reads on level L is then at ``level_origin[texture, L] + ((ty >> L) << (TEXTURE_BITS + L)) +
    tx``: the row term is ``(ty << TEXTURE_BITS)`` under a per-level bit mask, so a frame's lookup
    needs no per-pixel shift by the level (twice the finest level's memory, 1.5x a mip chain).
    """

    names: tuple[str, ...]
    texels: np.ndarray  # (N,) uint32: RGBA packed, so a lookup is one 1-D gather
    level_origin: np.ndarray  # (textures, MIP_LEVELS) int32: address of each level's texel (0, 0)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def lookup(
        self, tex_id: np.ndarray, u: np.ndarray, v: np.ndarray, level: np.ndarray
    ) -> np.ndarray:
        """Nearest texel of texture ``tex_id`` at tile coordinates (u, v) (1.0 = one tile) on mip
        ``level``; returns (N, 4) uint8 RGBA (alpha unused). The readable reference of the
        renderer's fused lookup (``KinectRenderer._shade``).

        Level L has side TEXTURE_SIZE >> L, so its texel is the finest level's texel shifted
        right by L and wrapping is a bit mask: integer shifts only, no per-pixel size lookup.
        """
        mask = np.int32(TEXTURE_SIZE - 1)
        tx = (u * TEXTURE_SIZE).astype(np.int32) & mask
        ty = (v * TEXTURE_SIZE).astype(np.int32) & mask
        flat = ((ty >> level) << (TEXTURE_BITS + level)) + tx + self.level_origin[tex_id, level]
        return np.take(self.texels, flat).view(np.uint8).reshape(-1, 4)


def _with_alpha(img: np.ndarray) -> np.ndarray:
    return np.concatenate([img, np.zeros(img.shape[:-1] + (1,), np.uint8)], axis=-1)


@functools.lru_cache(maxsize=4)
def build_atlas(names: tuple[str, ...]) -> TextureAtlas:
    grid = TEXTURE_SIZE * TEXTURE_SIZE
    if 2 * grid * len(names) >= 2**31:  # pragma: no cover - thousands of textures
        raise WorldError("texture atlas too large for 32-bit indices")
    texels = np.zeros((len(names), 2, TEXTURE_SIZE, TEXTURE_SIZE, 4), np.uint8)
    origin = np.zeros((len(names), MIP_LEVELS), np.int64)
    for t, name in enumerate(names):
        img = texture_image(name)
        texels[t, 0] = _with_alpha(img)
        origin[t, 0] = 2 * t * grid
        for level in range(1, MIP_LEVELS):
            img = cv2.pyrDown(img)
            first_row = 1 << (level - 1)
            texels[t, 1, first_row :: 1 << level] = np.repeat(_with_alpha(img), 1 << level, axis=1)
            origin[t, level] = (2 * t + 1) * grid + first_row * TEXTURE_SIZE
    return TextureAtlas(
        names, texels.reshape(-1, 4).view(np.uint32).ravel(), origin.astype(np.int32)
    )
