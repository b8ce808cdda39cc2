"""Pictures for run directories, drawn with OpenCV (no plotting library on the run path)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from sensors.atomic import atomic_write_bytes

MARGIN_PX = 40  # [px] around the drawing
TARGET_SIZE_PX = 900  # [px] longest side of the drawing area
LINE_PX = 24  # [px] legend line height
COLORS_BGR = [(40, 160, 40), (40, 40, 220), (220, 120, 30), (160, 40, 160), (30, 170, 200)]


def write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - OpenCV only fails here on invalid images
        raise ValueError(f"cannot encode {path}")
    atomic_write_bytes(path, buf.tobytes())


def plot_trajectories(
    path: Path,
    paths: Sequence[tuple[str, np.ndarray, np.ndarray]],
    title: str,
    occupied: np.ndarray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    resolution: float = 0.05,
) -> None:
    """Top view: optional occupancy background (row 0 at the bottom) and labelled x/y paths."""
    # A path without a finite point (every frame of a source unusable) is listed, not drawn.
    finite = [
        np.isfinite(np.asarray(x, float)) & np.isfinite(np.asarray(y, float)) for _, x, y in paths
    ]
    paths = [
        (label, np.asarray(x, float)[ok], np.asarray(y, float)[ok])
        for (label, x, y), ok in zip(paths, finite, strict=True)
    ]
    pts = [np.column_stack([x, y]) for _, x, y in paths if len(x)]
    if pts:
        lo = np.min([p.min(axis=0) for p in pts], axis=0)
        hi = np.max([p.max(axis=0) for p in pts], axis=0)
    else:
        lo = hi = np.asarray(origin, dtype=float)
    if occupied is not None:
        h, w = occupied.shape
        lo = np.minimum(lo, origin)
        hi = np.maximum(hi, [origin[0] + w * resolution, origin[1] + h * resolution])
    span = np.maximum(hi - lo, 1e-3)
    scale = TARGET_SIZE_PX / span.max()  # [px/m]
    header = LINE_PX * (len(paths) + 1) + MARGIN_PX // 2  # title and legend above the plot
    size = (span * scale).astype(int) + 2 * MARGIN_PX
    size[1] += header
    img = np.full((size[1], size[0], 3), 255, np.uint8)

    def to_px(xy: np.ndarray) -> np.ndarray:
        u = (xy[:, 0] - lo[0]) * scale + MARGIN_PX
        v = size[1] - ((xy[:, 1] - lo[1]) * scale + MARGIN_PX)
        return np.column_stack([u, v]).round().astype(np.int32)

    if occupied is not None:
        rows, cols = np.nonzero(occupied)
        centres = np.column_stack(
            [origin[0] + (cols + 0.5) * resolution, origin[1] + (rows + 0.5) * resolution]
        )
        px = to_px(centres)
        half = max(1, int(round(resolution * scale / 2)))
        mask = np.zeros(img.shape[:2], np.uint8)
        ok = (px[:, 0] >= 0) & (px[:, 0] < size[0]) & (px[:, 1] >= 0) & (px[:, 1] < size[1])
        mask[px[ok, 1], px[ok, 0]] = 255
        mask = cv2.dilate(mask, np.ones((2 * half + 1, 2 * half + 1), np.uint8))
        img[mask > 0] = (90, 90, 90)
    for i, (label, x, y) in enumerate(paths):
        color = COLORS_BGR[i % len(COLORS_BGR)]
        if len(x):
            px = to_px(np.column_stack([x, y]))
            cv2.polylines(img, [px.reshape(-1, 1, 2)], False, color, 2, cv2.LINE_AA)
            cv2.circle(img, tuple(int(c) for c in px[0]), 6, color, 2, cv2.LINE_AA)
        else:
            label += " (no poses)"
        cv2.putText(
            img,
            label,
            (MARGIN_PX + 10, 28 + LINE_PX * (i + 1)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            color,
            2,
            cv2.LINE_AA,
        )
    cv2.putText(
        img, title, (MARGIN_PX + 10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.65, (0, 0, 0), 2, cv2.LINE_AA
    )
    # 1 m scale bar, bottom right.
    x1, y1 = size[0] - MARGIN_PX, size[1] - MARGIN_PX // 2
    cv2.line(img, (int(x1 - scale), y1), (x1, y1), (0, 0, 0), 3)
    cv2.putText(img, "1 m", (int(x1 - scale), y1 - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    write_png(path, img)


def gps_chart(
    path: Path,
    estimate: tuple[str, np.ndarray, np.ndarray],
    odom_xy: np.ndarray,
    gps: tuple[np.ndarray, np.ndarray, np.ndarray],
    title: str,
    occupied: np.ndarray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    resolution: float = 0.05,
) -> dict[str, object]:
    """The run chart of `localize --gps` and `live`: the estimate (label, stamps_ns (N,), xy
    (N, 2) [m] in the map), odometry placed in the map (M, 2) and the GPS fixes (stamps_ns,
    xy (K, 2) in the map, sigma_h (K,)) over the map; and the GPS part of the summary (how far
    the estimate lies from the latest fix)."""
    label, est_t, est_xy = estimate
    est_xy = np.asarray(est_xy, float).reshape(-1, 2)
    odom_xy = np.asarray(odom_xy, float).reshape(-1, 2)
    paths = [(label, est_xy[:, 0], est_xy[:, 1]), ("odometry", odom_xy[:, 0], odom_xy[:, 1])]
    paths = [p for p in paths if len(p[1])]
    paths.append(("GPS", gps[1][:, 0], gps[1][:, 1]))
    plot_trajectories(path, paths, title, occupied, origin, resolution)
    gps_err = None
    if len(est_t) and len(gps[0]):
        k = np.clip(np.searchsorted(gps[0], est_t, side="right") - 1, 0, len(gps[0]) - 1)
        d = np.hypot(*(gps[1][k] - est_xy).T)
        gps_err = {"median_m": round(float(np.median(d)), 3), "max_m": round(float(d.max()), 3)}
    return {
        "fixes": int(len(gps[0])),
        "median_sigma_m": round(float(np.median(gps[2])), 3) if len(gps[2]) else None,
        f"gps_vs_{label}": gps_err,
    }


def contact_sheet(
    path: Path,
    frames: Sequence[tuple[np.ndarray, np.ndarray]],
    max_depth_m: float = 5.0,
    width_px: int = 320,
) -> None:
    """Rows of (RGB, colour-mapped depth) thumbnails; invalid depth is black."""
    rows = []
    for rgb, depth in frames:
        h = int(round(rgb.shape[0] * width_px / rgb.shape[1]))
        colour = cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), (width_px, h))
        d8 = (np.clip(np.nan_to_num(depth) / max_depth_m, 0, 1) * 255).astype(np.uint8)
        dc = cv2.applyColorMap(d8, cv2.COLORMAP_TURBO)
        dc[np.nan_to_num(depth) <= 0] = 0
        rows.append(
            np.hstack([colour, cv2.resize(dc, (width_px, h), interpolation=cv2.INTER_NEAREST)])
        )
    write_png(path, np.vstack(rows))
