"""Charts of a navigate run: commanded vs smoothed velocity and acceleration with the smoother's
limits, drawn with OpenCV like the other run pictures (:mod:`rgbdnav.report`: no plotting library
on the run path; matplotlib's import alone costs seconds)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from nav.config import SmootherConfig
from sensors.atomic import atomic_write_bytes

PANEL_PX = (620, 300)  # [px] width, height of one panel's plot area
PAD_PX = (70, 50, 30, 45)  # [px] left, top, right, bottom around a plot area
FONT = cv2.FONT_HERSHEY_SIMPLEX
BLACK, GRAY, BLUE, RED, LIGHT = (
    (0, 0, 0),
    (150, 150, 150),
    (200, 110, 30),
    (40, 40, 220),
    (230, 230, 230),
)
ACCEL_VIEW = 3.0  # the acceleration panels show +- this many times the largest limit
DASH_PX = 8  # [px] dash length of limit lines
TICKS = 5  # y tick labels per panel


def accelerations(t_s: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Finite-difference acceleration over each interval with positive duration: (mid times
    [s], a [unit/s^2])."""
    dt = np.diff(t_s)
    ok = dt > 0
    return (0.5 * (t_s[1:] + t_s[:-1]))[ok], (np.diff(v)[ok] / dt[ok])


class _Panel:
    """One plot area inside the canvas, with data -> pixel mapping."""

    def __init__(
        self,
        img: np.ndarray,
        x0: int,
        y0: int,
        t_range: tuple[float, float],
        y_range: tuple[float, float],
    ) -> None:
        self.img, self.x0, self.y0 = img, x0, y0
        self.t0, self.t1 = t_range
        self.lo, self.hi = y_range

    def px(self, t: np.ndarray, y: np.ndarray) -> np.ndarray:
        w, h = PANEL_PX
        u = self.x0 + (t - self.t0) / max(self.t1 - self.t0, 1e-9) * w
        yc = np.clip(y, self.lo, self.hi)
        v = self.y0 + h - (yc - self.lo) / max(self.hi - self.lo, 1e-9) * h
        return np.column_stack([u, v]).round().astype(np.int32)

    def frame(self, title: str, unit: str) -> None:
        w, h = PANEL_PX
        cv2.rectangle(self.img, (self.x0, self.y0), (self.x0 + w, self.y0 + h), BLACK, 1)
        for y in np.linspace(self.lo, self.hi, TICKS):
            ((_, v),) = self.px(np.array([self.t0]), np.array([y]))
            cv2.line(self.img, (self.x0, int(v)), (self.x0 + w, int(v)), LIGHT, 1)
            cv2.putText(
                self.img, f"{y:+.2f}", (self.x0 - 62, int(v) + 4), FONT, 0.4, BLACK, 1, cv2.LINE_AA
            )
        if self.lo < 0.0 < self.hi:
            ((_, v),) = self.px(np.array([self.t0]), np.array([0.0]))
            cv2.line(self.img, (self.x0, int(v)), (self.x0 + w, int(v)), GRAY, 1)
        for t in np.linspace(self.t0, self.t1, 6):
            ((u, _),) = self.px(np.array([t]), np.array([self.lo]))
            cv2.putText(
                self.img,
                f"{t:.0f}",
                (int(u) - 8, self.y0 + h + 16),
                FONT,
                0.4,
                BLACK,
                1,
                cv2.LINE_AA,
            )
        cv2.putText(
            self.img,
            f"{title} [{unit}]",
            (self.x0, self.y0 - 10),
            FONT,
            0.55,
            BLACK,
            1,
            cv2.LINE_AA,
        )
        cv2.putText(
            self.img,
            "simulated time [s]",
            (self.x0 + w - 140, self.y0 + h + 34),
            FONT,
            0.4,
            BLACK,
            1,
            cv2.LINE_AA,
        )

    def line(self, t: np.ndarray, y: np.ndarray, color: tuple[int, int, int], width: int) -> None:
        if len(t) > 1:
            cv2.polylines(
                self.img, [self.px(t, y).reshape(-1, 1, 2)], False, color, width, cv2.LINE_AA
            )

    def limit(self, value: float, label: str) -> None:
        w, _ = PANEL_PX
        ((_, v),) = self.px(np.array([self.t0]), np.array([value]))
        for u in range(self.x0, self.x0 + w, 2 * DASH_PX):
            cv2.line(self.img, (u, int(v)), (min(u + DASH_PX, self.x0 + w), int(v)), RED, 1)
        cv2.putText(
            self.img,
            f"{label} {value:+.2f}",
            (self.x0 + 6, int(v) - 4),
            FONT,
            0.4,
            RED,
            1,
            cv2.LINE_AA,
        )


def velocity_chart(
    path: Path,
    rows: Sequence[tuple[float, int, str, float, float, float, float, int, int]],
    limits: SmootherConfig,
) -> None:
    """Four panels: linear and angular velocity (controller command in gray, smoother output in
    blue) with max/min_velocity, and their accelerations with max_accel/max_decel (the command
    steps leave the acceleration view; the smoothed line must stay inside the dashed limits).
    ``rows`` are the commands.csv rows."""
    data = np.array([(r[0], r[3], r[4], r[5], r[6]) for r in rows], dtype=np.float64)
    t = data[:, 0]
    t_range = (float(t[0]), float(max(t[-1], t[0] + 1e-3)))
    w, h = PANEL_PX
    cell_w, cell_h = PAD_PX[0] + w + PAD_PX[2], PAD_PX[1] + h + PAD_PX[3]
    header = 60
    img = np.full((header + 2 * cell_h, 2 * cell_w, 3), 255, np.uint8)
    cv2.putText(
        img,
        f"velocity smoother at {limits.smoothing_frequency:g} Hz (feedback {limits.feedback})",
        (PAD_PX[0], 26),
        FONT,
        0.65,
        BLACK,
        2,
        cv2.LINE_AA,
    )
    cv2.putText(
        img,
        "gray: controller command   blue: smoothed (to the wheels)   red: limits",
        (PAD_PX[0], 48),
        FONT,
        0.5,
        BLACK,
        1,
        cv2.LINE_AA,
    )
    for col, (name, unit, axis) in enumerate((("linear", "m/s", 0), ("angular", "rad/s", 2))):
        cmd, smoothed = data[:, 1 + col], data[:, 3 + col]
        lo, hi = limits.min_velocity[axis], limits.max_velocity[axis]
        span = max(hi - lo, 1e-3)
        x0 = col * cell_w + PAD_PX[0]
        p = _Panel(img, x0, header + PAD_PX[1], t_range, (lo - 0.1 * span, hi + 0.1 * span))
        p.frame(f"{name} velocity", unit)
        p.line(t, cmd, GRAY, 1)
        p.line(t, smoothed, BLUE, 2)
        p.limit(hi, "max_velocity")
        p.limit(lo, "min_velocity")
        amax = max(abs(limits.max_accel[axis]), abs(limits.max_decel[axis]), 1e-3)
        p = _Panel(
            img, x0, header + cell_h + PAD_PX[1], t_range, (-ACCEL_VIEW * amax, ACCEL_VIEW * amax)
        )
        p.frame(f"{name} acceleration", f"{unit}/s")
        for series, color, width in ((cmd, GRAY, 1), (smoothed, BLUE, 2)):
            tm, acc = accelerations(t, series)
            p.line(tm, acc, color, width)
        p.limit(limits.max_accel[axis], "max_accel")
        p.limit(limits.max_decel[axis], "max_decel")
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV only fails here on invalid images
        raise ValueError(f"cannot encode {path}")
    atomic_write_bytes(path, buf.tobytes())


__all__ = ["accelerations", "velocity_chart"]
