"""Plain TUM RGB-D folders as a :class:`~sensors.source.Source`, and two close relatives.

1. **TUM RGB-D** (``rgbd_dataset_freiburg*``): ``rgb.txt`` / ``depth.txt`` index files
   (``timestamp filename``), 8-bit colour and 16-bit depth PNGs (5000 counts/m), optional
   ``groundtruth.txt`` (TUM ``t tx ty tz qx qy qz qw``, the camera in the world);
   ``accelerometer.txt`` is ignored.
2. **Keyframe folders** whose index files list frame *indices* instead of stamps (the
   ``tum_fr3_cabinet_keyframes`` sample): stamps come from the ``t`` column of
   ``truth_cam_poses.txt`` (line i = frame i) when it holds real times, else ``index / 30 s``.
3. **Open3D's RGB-D sample** (``rgbd.match``: ``depth_file color_file`` lines, depth in mm):
   stamps ``index / 30 s``.

Intrinsics come from a YAML file in the folder (``fx fy cx cy`` at the top level or under
``camera:``, or ORB-SLAM/OpenCV style ``Camera.fx``), else from the TUM preset the folder name
names (``freiburg1``/``fr1`` ...), else the Kinect v1 default; :meth:`TumFolderSource.describe`
says which. Colour and depth are associated like TUM's ``associate.py`` (20 ms).
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sensors.bounded_read import read_bounded
from sensors.images import (
    MAX_IMAGE_FILE_BYTES,
    ImageError,
    declared_size,
    decode_image,
    decoded_ahead,
    read_image,
)
from sensors.recording import DEFAULT_MAX_DIFFERENCE_NS, associate, counts_to_depth
from sensors.source import PoseStream, SourceBase, SourceOptions
from sensors.tum import load_trajectory, read_stamped_text, yaw_from_quaternion
from sensors.types import (
    NS_PER_S,
    CameraIntrinsics,
    RgbdFrame,
    SensorError,
    format_stamp,
)

log = logging.getLogger(__name__)

TUM_PRESETS: dict[str, tuple[float, float, float, float]] = {  # fx fy cx cy [px], TUM website
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
KINECT_DEFAULT = (525.0, 525.0, 319.5, 239.5)  # fx fy cx cy [px], Kinect v1 factory values
KINECT_SIZE = (640, 480)  # [px] width, height when nothing else says
TUM_DEPTH_SCALE = 5000.0  # [counts/m]
OPEN3D_DEPTH_SCALE = 1000.0  # [counts/m] Open3D's sample depth is in millimetres
INDEX_PERIOD_NS = NS_PER_S // 30  # [ns] assumed frame period when only indices are given
MAX_INDEX_S = 1_000_000  # [s] index "stamps" are small whole numbers; real ones are epoch times
GROUNDTRUTH_FILES = ("groundtruth.txt", "truth_cam_poses.txt")
MAX_WARNINGS = 5  # per frames() pass; the rest are summarised once
_PRESET_RE = re.compile(r"(?:freiburg|(?<![a-z])fr)_?([123])(?!\d)")


@dataclass(frozen=True)
class _Index:
    """One image stream: stamps [ns] and file names relative to the folder."""

    stamps_ns: np.ndarray  # (N,) int64, strictly increasing
    files: list[str]


# --- pure helpers ------------------------------------------------------------------------------


def looks_like_indices(stamps_ns: np.ndarray) -> bool:
    """Whole seconds counting up by one from a small number: frame indices, not times."""
    s = np.asarray(stamps_ns, dtype=np.int64)
    return bool(
        s.size
        and np.all(s % NS_PER_S == 0)
        and np.all(np.diff(s) == NS_PER_S)
        and 0 <= s[0] < MAX_INDEX_S * NS_PER_S
    )


def preset_for_folder(name: str) -> tuple[str, tuple[float, float, float, float]]:
    """(label, fx fy cx cy) of the TUM camera a folder name names, else the Kinect default."""
    match = _PRESET_RE.search(name.lower())
    if match:
        key = f"freiburg{match.group(1)}"
        return f"TUM {key} preset (folder name)", TUM_PRESETS[key]
    return "Kinect v1 default preset", KINECT_DEFAULT


def camera_from_mapping(doc: Mapping[str, Any]) -> dict[str, float] | None:
    """fx, fy, cx, cy (and width, height, depth_scale when given) from a YAML document, or None.

    Accepts the keys at the top level, under ``camera:``, or ORB-SLAM/OpenCV style
    (``Camera.fx``, ``Camera1.fx``, ``DepthMapFactor``).
    """
    candidates: list[Mapping[str, Any]] = [doc]
    for key in ("camera", "Camera"):
        if isinstance(doc.get(key), Mapping):
            candidates.append(doc[key])
    for prefix in ("Camera.", "Camera1."):
        flat = {k[len(prefix) :]: v for k, v in doc.items() if str(k).startswith(prefix)}
        candidates.append(flat)
    for cam in candidates:
        if not all(k in cam for k in ("fx", "fy", "cx", "cy")):
            continue
        try:
            out = {k: float(cam[k]) for k in ("fx", "fy", "cx", "cy")}
            for k in ("width", "height"):
                if k in cam:
                    out[k] = float(cam[k])
            scale = cam.get("depth_scale", doc.get("depth_scale", doc.get("DepthMapFactor")))
            if scale is not None:
                out["depth_scale"] = float(scale)
        except (TypeError, ValueError):
            return None
        return out
    return None


class _LenientLoader(yaml.SafeLoader):
    """SafeLoader that reads OpenCV's ``!!opencv-matrix`` and other unknown tags as plain data."""


def _construct_unknown(loader: yaml.SafeLoader, _suffix: str, node: yaml.Node) -> Any:
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node)
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node)
    return loader.construct_scalar(node)  # type: ignore[arg-type]


_LenientLoader.add_multi_constructor("tag:yaml.org,2002:opencv", _construct_unknown)
_LenientLoader.add_multi_constructor("!", _construct_unknown)


def read_camera_yaml(file: Path) -> dict[str, float] | None:
    """:func:`camera_from_mapping` of a YAML file (OpenCV's ``%YAML:1.0`` line tolerated);
    None when it holds no intrinsics. A file that does not parse is logged as a warning: the
    intrinsics it may have held are not silently replaced by defaults."""
    return _camera_yaml(file)[0]


def _camera_yaml(file: Path) -> tuple[dict[str, float] | None, str | None]:
    """(intrinsics or None, why the file could not be read or None)."""
    try:
        text = file.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        return None, f"{file.name} unreadable ({err.strerror or err})"
    if text.startswith("%YAML:"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        doc = yaml.load(text, Loader=_LenientLoader)  # noqa: S506 (safe loader subclass)
    except (yaml.YAMLError, RecursionError) as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        log.warning("%s: not valid YAML%s; camera intrinsics in it are ignored", file, where)
        return None, f"{file.name} not valid YAML{where}"
    return (camera_from_mapping(doc) if isinstance(doc, Mapping) else None), None


def _read_index(file: Path) -> _Index:
    table = read_stamped_text(file, ("timestamp", "filename"))
    return _Index(table.stamps_ns, [row[0] for row in table.values])


def _read_match(file: Path) -> tuple[_Index, _Index]:
    """Open3D ``rgbd.match``: ``depth_file color_file`` per line -> (rgb, depth) at 30 Hz."""
    try:
        text = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise SensorError(f"{file}: cannot read: {err}") from err
    depth: list[str] = []
    rgb: list[str] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.split()
        if len(tokens) != 2:
            raise SensorError(
                f"{file}:{number}: expected 2 fields (depth_file color_file), got {len(tokens)}"
            )
        depth.append(tokens[0])
        rgb.append(tokens[1])
    stamps = np.arange(len(rgb), dtype=np.int64) * INDEX_PERIOD_NS
    return _Index(stamps, rgb), _Index(stamps.copy(), depth)


# --- source ------------------------------------------------------------------------------------


class TumFolderSource(SourceBase):
    """A TUM RGB-D style folder. Index files are read at open; images lazily by :meth:`frames`.

    ``strict`` makes a missing or bad image an error naming the file; by default the pair is
    skipped, counted by reason in ``skipped`` and logged. ``workers`` threads decode ahead.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        strict: bool = False,
        max_difference_ns: int = DEFAULT_MAX_DIFFERENCE_NS,
        workers: int = 2,
    ) -> None:
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.root = Path(path)
        self.path = str(self.root)
        self.strict = strict
        self.workers = workers
        self.skipped: dict[str, int] = {}
        if not self.root.is_dir():
            raise SensorError(f"{self.root}: not a folder")

        # 1. Index files: TUM rgb.txt/depth.txt, else Open3D's rgbd.match.
        self._groundtruth_file = next(
            (self.root / n for n in GROUNDTRUTH_FILES if (self.root / n).is_file()), None
        )
        self._gt: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        if (self.root / "rgb.txt").is_file() and (self.root / "depth.txt").is_file():
            self.variant = "TUM RGB-D folder"
            rgb, depth = _read_index(self.root / "rgb.txt"), _read_index(self.root / "depth.txt")
            rgb, depth, self.stamps_note = self._resolve_indices(rgb, depth)
            default_scale = TUM_DEPTH_SCALE
        elif (self.root / "rgbd.match").is_file():
            self.variant = "Open3D RGB-D folder (rgbd.match)"
            rgb, depth = _read_match(self.root / "rgbd.match")
            self.stamps_note = "stamps synthesised at 30 Hz from the rgbd.match order"
            default_scale = OPEN3D_DEPTH_SCALE
        else:
            raise SensorError(f"{self.root}: needs rgb.txt and depth.txt (TUM) or rgbd.match")
        self._rgb, self._depth = rgb, depth

        # 2. Associate colour and depth like TUM's associate.py.
        self.rgb_index, self.depth_index = associate(
            rgb.stamps_ns, depth.stamps_ns, max_difference_ns
        )

        # 3. Intrinsics: a YAML in the folder, else a preset by folder name.
        self._intrinsics, self.intrinsics_source = self._resolve_intrinsics(default_scale)

    @classmethod
    def try_open(
        cls, path: Path | str, options: SourceOptions | None = None
    ) -> TumFolderSource | None:
        """A source for a TUM-style folder; None for anything else, including our recordings
        (they hold ``scene.yaml`` and have their own adapter)."""
        path = Path(path)
        if not path.is_dir() or (path / "scene.yaml").is_file():
            return None
        tum = (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()
        strict = options.strict if options else False
        return cls(path, strict=strict) if tum or (path / "rgbd.match").is_file() else None

    def __len__(self) -> int:
        return int(self.rgb_index.size)

    # -- opening helpers --

    def _resolve_indices(self, rgb: _Index, depth: _Index) -> tuple[_Index, _Index, str]:
        """Replace frame indices by stamps (ground-truth times, else 30 Hz); note what was done."""
        if not (looks_like_indices(rgb.stamps_ns) and looks_like_indices(depth.stamps_ns)):
            return rgb, depth, ""
        k_rgb, k_depth = rgb.stamps_ns // NS_PER_S, depth.stamps_ns // NS_PER_S
        last = int(max(k_rgb[-1], k_depth[-1]))
        gt, gt_file = self._groundtruth(), self._groundtruth_file
        if (
            gt is not None
            and gt_file is not None
            and len(gt[0]) > last
            and not looks_like_indices(gt[0])
        ):
            times = gt[0]
            note = f"stamps from the t column of {gt_file.name}"
        else:
            times = np.arange(last + 1, dtype=np.int64) * INDEX_PERIOD_NS
            note = "stamps synthesised at 30 Hz"
            if gt is not None and gt_file is not None and len(gt[0]) <= last:
                # Said, not silent: the user gave stamps that do not cover the frames.
                note += (
                    f" because {gt_file.name} has {len(gt[0])} rows and the frames go "
                    f"to index {last}"
                )
                log.warning("%s: %s", self.root, note)
        note += " (rgb.txt/depth.txt list frame indices)"
        return _Index(times[k_rgb], rgb.files), _Index(times[k_depth], depth.files), note

    def _resolve_intrinsics(self, default_scale: float) -> tuple[CameraIntrinsics, str]:
        camera, source = None, ""
        problems = []
        for file in sorted([*self.root.glob("*.yaml"), *self.root.glob("*.yml")]):
            camera, problem = _camera_yaml(file)
            if problem is not None:
                problems.append(problem)
            if camera is not None:
                source = file.name
                break
        if camera is None:
            source, (fx, fy, cx, cy) = preset_for_folder(self.root.resolve().name)
            camera = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
            if problems:  # said where the user will look: the source's description
                source += f"; {'; '.join(problems)}"
        if not all(math.isfinite(v) for v in camera.values()):
            raise SensorError(f"{self.root}: intrinsics from {source} are not finite: {camera}")
        if "width" in camera and "height" in camera:
            size = (int(camera["width"]), int(camera["height"]))
        else:
            size = self._probe_size()
        try:
            intr = CameraIntrinsics(
                width=size[0],
                height=size[1],
                fx=camera["fx"],
                fy=camera["fy"],
                cx=camera["cx"],
                cy=camera["cy"],
                depth_scale=camera.get("depth_scale", default_scale),
            )
        except SensorError:
            raise SensorError(
                f"{self.root}: intrinsics from {source}: width, height, fx, fy, depth_scale "
                "must be > 0"
            ) from None
        return intr, source

    def _probe_size(self) -> tuple[int, int]:
        """(width, height) of the first decodable colour image; the Kinect's without one."""
        for i in self.rgb_index[:10]:
            try:
                image = read_bounded(
                    self.root / self._rgb.files[int(i)], MAX_IMAGE_FILE_BYTES, SensorError, "image"
                )
                size = declared_size(image) or decode_image(image, "", SensorError).shape[1::-1]
            except SensorError:
                continue
            return int(size[0]), int(size[1])
        return KINECT_SIZE

    def _groundtruth(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if self._gt is None and self._groundtruth_file is not None:
            self._gt = load_trajectory(self._groundtruth_file)
        return self._gt

    # -- Source protocol --

    def describe(self) -> str:
        k = self._intrinsics
        gt = (
            ""
            if self._groundtruth_file is None
            else f", ground truth {self._groundtruth_file.name}"
        )
        note = f", {self.stamps_note}" if self.stamps_note else ""
        return (
            f"{self.variant}, camera {k.width}x{k.height} fx={k.fx:g} fy={k.fy:g} cx={k.cx:g} "
            f"cy={k.cy:g} depth scale {k.depth_scale:g}/m (intrinsics from "
            f"{self.intrinsics_source}), {len(self)} rgb/depth pairs{note}{gt}"
        )

    def stream_stamps(self) -> dict[str, np.ndarray]:
        out = {"rgb": self._rgb.stamps_ns, "depth": self._depth.stamps_ns}
        gt = self._groundtruth()
        if gt is not None:
            out["groundtruth"] = gt[0]
        return out

    def intrinsics(self) -> CameraIntrinsics | None:
        return self._intrinsics

    def frame(self, k: int) -> RgbdFrame:
        """The k-th associated pair (0 <= k < len(self)); raises SensorError on a bad image."""
        i, j = int(self.rgb_index[k]), int(self.depth_index[k])
        size = (self._intrinsics.width, self._intrinsics.height)
        rgb = read_image(self.root / self._rgb.files[i], size, depth=False)
        counts = read_image(self.root / self._depth.files[j], size, depth=True)
        return RgbdFrame(
            stamp_ns=int(self._rgb.stamps_ns[i]),
            rgb=rgb,
            depth_m=counts_to_depth(counts, self._intrinsics.depth_scale),
            intrinsics=self._intrinsics,
        )

    def frames(self) -> Iterator[RgbdFrame]:
        """Associated frames in colour-stamp order, stamped with the colour stamp.

        Decoding runs ``workers`` threads ahead (cv2 releases the GIL). ``skipped`` is reset
        per pass.
        """
        self.skipped = {}
        for k, future in decoded_ahead(self.frame, len(self), self.workers, "tum-decode"):
            try:
                frame = future.result()
            except ImageError as err:
                if self.strict:
                    raise
                self._count_skip(k, err)
                continue
            yield frame
        if sum(self.skipped.values()) > MAX_WARNINGS:
            log.warning("%s: skipped %s frames", self.root, self.skipped)

    def _count_skip(self, k: int, err: ImageError) -> None:
        total = sum(self.skipped.values())
        self.skipped[err.reason] = self.skipped.get(err.reason, 0) + 1
        if total < MAX_WARNINGS:
            stamp = format_stamp(int(self._rgb.stamps_ns[self.rgb_index[k]]))
            log.warning("skipping frame %s: %s", stamp, err)

    def groundtruth(self) -> PoseStream | None:
        """The camera pose in the world, planar: x, y and the yaw of the quaternion."""
        gt = self._groundtruth()
        if gt is None:
            return None
        stamps, xyz, quat = gt
        return PoseStream(
            stamps, xyz[:, 0].copy(), xyz[:, 1].copy(), yaw_from_quaternion(quat), frame="camera"
        )


__all__ = [
    "KINECT_DEFAULT",
    "TUM_PRESETS",
    "TumFolderSource",
    "camera_from_mapping",
    "looks_like_indices",
    "preset_for_folder",
    "read_camera_yaml",
]
