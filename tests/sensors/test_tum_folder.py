from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from sensors.source import Source, open_source
from sensors.tum_folder import (
    INDEX_PERIOD_NS,
    TumFolderSource,
    looks_like_indices,
    preset_for_folder,
)
from sensors.types import NS_PER_S, SensorError

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
KINECT = DATA / "kinect"
CABINET = KINECT / "tum_fr3_cabinet_keyframes"
needs_data = pytest.mark.skipif(not KINECT.is_dir(), reason="../shared/data/kinect is absent")

MS = 1_000_000  # [ns]
W, H = 8, 6  # [px] tiny synthetic images
T0 = 1_305_031_102_175_304_000  # [ns] a TUM-like epoch stamp
CAMERA_YAML = "camera:\n  fx: 10.0\n  fy: 11.0\n  cx: 3.5\n  cy: 2.5\n"


def write_tum_folder(
    root: Path,
    n: int = 3,
    depth_offset_ns: int = 4 * MS,
    yaml_text: str | None = CAMERA_YAML,
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """A TUM RGB-D folder with n frames at 30 Hz; returns (rgb, depth counts, rgb stamps)."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(3)
    stamps = T0 + np.arange(n, dtype=np.int64) * INDEX_PERIOD_NS
    rgbs, depths = [], []
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    for t in stamps:
        rgb = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        counts = rng.integers(2500, 20000, size=(H, W), dtype=np.uint16)
        counts[0, 0] = 0
        t_rgb = f"{t // NS_PER_S}.{t % NS_PER_S:09d}"
        td = t + depth_offset_ns
        t_depth = f"{td // NS_PER_S}.{td % NS_PER_S:09d}"
        cv2.imwrite(str(root / "rgb" / f"{t_rgb}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "depth" / f"{t_depth}.png"), counts)
        rgb_lines.append(f"{t_rgb} rgb/{t_rgb}.png")
        depth_lines.append(f"{t_depth} depth/{t_depth}.png")
        rgbs.append(rgb)
        depths.append(counts)
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "accelerometer.txt").write_text("# accelerometer data\n1.0 0 0 9.81\n")
    if yaml_text is not None:
        (root / "camera.yaml").write_text(yaml_text)
    return rgbs, depths, stamps


def test_frames_round_trip_with_rgb_order_depth_scale_and_rgb_stamps(tmp_path):
    rgbs, depths, stamps = write_tum_folder(tmp_path / "seq")
    src = TumFolderSource(tmp_path / "seq")

    frames = list(src.frames())
    assert isinstance(src, Source)
    assert len(src) == len(frames) == 3 and src.skipped == {}
    k = src.intrinsics()
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (W, H, 10.0, 11.0, 3.5, 2.5)
    assert k.depth_scale == 5000.0
    for frame, rgb, counts, t in zip(frames, rgbs, depths, stamps, strict=True):
        assert frame.stamp_ns == t
        np.testing.assert_array_equal(frame.rgb, rgb)
        assert frame.depth_m.dtype == np.float32
        np.testing.assert_allclose(frame.depth_m, counts / 5000.0, rtol=1e-6)
    assert frames[0].depth_m[0, 0] == 0.0
    assert "camera.yaml" in src.describe() and "3 rgb/depth pairs" in src.describe()
    assert set(src.stream_stamps()) == {"rgb", "depth"}
    assert src.groundtruth() is None and src.odometry() is None and list(src.scans()) == []


def test_depth_more_than_20ms_from_any_rgb_is_not_associated(tmp_path):
    write_tum_folder(tmp_path / "seq", depth_offset_ns=25 * MS)
    # 25 ms late: each depth is 8.3 ms early for the next rgb, so two pairs remain.
    src = TumFolderSource(tmp_path / "seq")
    assert len(src) == 2
    assert [f.stamp_ns for f in src.frames()] == list(T0 + np.array([1, 2]) * INDEX_PERIOD_NS)


def test_opencv_style_yaml_with_camera_dot_keys_sets_intrinsics_and_depth_factor(tmp_path):
    yaml_text = (
        "%YAML:1.0\n# ORB-SLAM settings\nCamera.fx: 535.4\nCamera.fy: 539.2\n"
        "Camera.cx: 320.1\nCamera.cy: 247.6\nDepthMapFactor: 1000.0\n"
        "M: !!opencv-matrix\n  rows: 1\n  cols: 1\n  dt: d\n  data: [1.0]\n"
    )
    write_tum_folder(tmp_path / "seq", yaml_text=yaml_text)
    k = TumFolderSource(tmp_path / "seq").intrinsics()
    assert (k.fx, k.fy, k.cx, k.cy, k.depth_scale) == (535.4, 539.2, 320.1, 247.6, 1000.0)


def test_without_yaml_the_folder_name_picks_the_tum_preset(tmp_path):
    write_tum_folder(tmp_path / "rgbd_dataset_freiburg2_desk", yaml_text=None)
    src = TumFolderSource(tmp_path / "rgbd_dataset_freiburg2_desk")
    k = src.intrinsics()
    assert (k.fx, k.fy, k.cx, k.cy) == (520.9, 521.0, 325.1, 249.7)
    assert (k.width, k.height) == (W, H)  # from the first image
    assert "TUM freiburg2 preset" in src.describe()


@pytest.mark.parametrize(
    ("name", "fx"),
    [("rgbd_dataset_freiburg1_xyz", 517.3), ("tum_fr3_cabinet", 535.4), ("kitchen", 525.0)],
)
def test_preset_for_folder_names(name, fx):
    assert preset_for_folder(name)[1][0] == fx


def test_missing_image_is_skipped_counted_and_warned(tmp_path, caplog):
    write_tum_folder(tmp_path / "seq")
    missing = sorted((tmp_path / "seq" / "depth").iterdir())[1]
    missing.unlink()
    src = TumFolderSource(tmp_path / "seq")
    with caplog.at_level(logging.WARNING, logger="sensors.tum_folder"):
        frames = list(src.frames())
    assert len(frames) == 2
    assert src.skipped == {"missing": 1}
    assert missing.name in caplog.text


def test_missing_image_in_strict_mode_is_an_error_naming_the_file(tmp_path):
    write_tum_folder(tmp_path / "seq")
    missing = sorted((tmp_path / "seq" / "rgb").iterdir())[2]
    missing.unlink()
    src = TumFolderSource(tmp_path / "seq", strict=True)
    with pytest.raises(SensorError, match=rf"{missing.name}: image is missing"):
        list(src.frames())


def test_truncated_png_is_skipped_as_truncated(tmp_path):
    write_tum_folder(tmp_path / "seq")
    png = sorted((tmp_path / "seq" / "rgb").iterdir())[0]
    png.write_bytes(png.read_bytes()[:-20])
    src = TumFolderSource(tmp_path / "seq")
    assert len(list(src.frames())) == 2
    assert src.skipped == {"truncated": 1}


def test_image_of_the_wrong_size_is_skipped_as_wrong_size(tmp_path):
    write_tum_folder(tmp_path / "seq")
    png = sorted((tmp_path / "seq" / "depth").iterdir())[2]
    cv2.imwrite(str(png), np.zeros((H + 1, W), np.uint16))
    src = TumFolderSource(tmp_path / "seq")
    assert len(list(src.frames())) == 2
    assert src.skipped == {"wrong_size": 1}


def test_non_monotonic_index_stamps_are_an_error_naming_file_and_line(tmp_path):
    write_tum_folder(tmp_path / "seq")
    rgb_txt = tmp_path / "seq" / "rgb.txt"
    lines = rgb_txt.read_text().splitlines()
    lines[3], lines[4] = lines[4], lines[3]  # data lines 2 and 3 swapped
    rgb_txt.write_text("\n".join(lines) + "\n")
    with pytest.raises(SensorError, match=r"rgb\.txt:5: non-monotonic timestamp"):
        TumFolderSource(tmp_path / "seq")


def test_index_stamps_without_groundtruth_are_synthesised_at_30hz(tmp_path):
    root = tmp_path / "keyframes"
    write_tum_folder(root)
    for name in ("rgb.txt", "depth.txt"):
        rows = [ln.split() for ln in (root / name).read_text().splitlines() if ln[0] != "#"]
        (root / name).write_text("".join(f"{k} {f}\n" for k, (_, f) in enumerate(rows)))
    src = TumFolderSource(root)
    assert [f.stamp_ns for f in src.frames()] == [0, INDEX_PERIOD_NS, 2 * INDEX_PERIOD_NS]
    assert "synthesised at 30 Hz" in src.describe()


def test_groundtruth_is_the_planar_camera_pose(tmp_path):
    write_tum_folder(tmp_path / "seq")
    s = np.sqrt(0.5)  # 90 degrees about z
    (tmp_path / "seq" / "groundtruth.txt").write_text(
        f"# ground truth\n1305031102.1 1.0 2.0 3.0 0 0 {s} {s}\n1305031102.2 1.5 2.5 3.0 0 0 0 1\n"
    )
    gt = TumFolderSource(tmp_path / "seq").groundtruth()
    assert gt is not None and gt.frame == "camera"
    np.testing.assert_array_equal(
        gt.stamps_ns, [1_305_031_102_100_000_000, 1_305_031_102_200_000_000]
    )
    np.testing.assert_allclose(gt.x, [1.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(gt.yaw, [np.pi / 2, 0.0], atol=1e-12)


def test_looks_like_indices_only_for_small_consecutive_whole_seconds():
    assert looks_like_indices(np.arange(5) * NS_PER_S)
    assert not looks_like_indices(np.arange(5) * INDEX_PERIOD_NS)
    assert not looks_like_indices(T0 + np.arange(5) * NS_PER_S)


def test_try_open_leaves_our_recordings_and_other_paths_alone(tmp_path):
    write_tum_folder(tmp_path / "seq")
    assert isinstance(TumFolderSource.try_open(tmp_path / "seq"), TumFolderSource)
    assert isinstance(open_source(tmp_path / "seq"), TumFolderSource)
    (tmp_path / "seq" / "scene.yaml").write_text("camera: {}\n")
    assert TumFolderSource.try_open(tmp_path / "seq") is None
    assert TumFolderSource.try_open(tmp_path / "seq" / "rgb.txt") is None
    assert TumFolderSource.try_open(tmp_path) is None


@needs_data
def test_cabinet_keyframes_read_with_groundtruth_stamps_and_fr3_intrinsics():
    src = open_source(CABINET)
    assert isinstance(src, TumFolderSource)
    frames = list(src.frames())
    assert len(frames) == 29 and src.skipped == {}
    k = src.intrinsics()
    assert (k.width, k.height, k.fx, k.fy, k.depth_scale) == (640, 480, 535.4, 539.2, 5000.0)
    gt = src.groundtruth()
    assert gt is not None and len(gt.stamps_ns) == 29
    np.testing.assert_array_equal([f.stamp_ns for f in frames], gt.stamps_ns)
    assert frames[0].stamp_ns == 1_341_841_278_842_700_000
    valid = frames[0].depth_m[frames[0].depth_m > 0]
    assert valid.size > 0.5 * 640 * 480 and 0.5 < float(np.median(valid)) < 4.0
    assert "truth_cam_poses.txt" in src.describe()


@needs_data
def test_open3d_sample_reads_five_frames_in_millimetres():
    src = open_source(KINECT)
    assert isinstance(src, TumFolderSource)
    frames = list(src.frames())
    assert len(frames) == 5 and src.intrinsics().depth_scale == 1000.0
    assert frames[1].stamp_ns == INDEX_PERIOD_NS
    valid = frames[0].depth_m[frames[0].depth_m > 0]
    assert 0.5 < float(np.median(valid)) < 3.0


def test_yaml_with_non_positive_focal_length_is_an_error_naming_the_yaml(tmp_path):
    write_tum_folder(tmp_path / "seq", yaml_text="fx: 0\nfy: 10\ncx: 3.5\ncy: 2.5\n")
    with pytest.raises(SensorError, match=r"intrinsics from camera\.yaml: .* must be > 0"):
        TumFolderSource(tmp_path / "seq")


def test_an_unparseable_camera_yaml_is_said_not_silently_replaced_by_the_preset(tmp_path, caplog):
    root = tmp_path / "rgbd_dataset_freiburg2_desk"
    write_tum_folder(root, yaml_text="fx: 520.9\nfy: [521.0\ncx: 325.1\n")
    with caplog.at_level(logging.WARNING):
        src = TumFolderSource(root)
    assert "camera.yaml: not valid YAML at line" in caplog.text
    assert "freiburg2 preset (folder name); camera.yaml not valid YAML at line 3" in src.describe()


def test_non_finite_intrinsics_are_an_error_naming_the_yaml(tmp_path):
    write_tum_folder(tmp_path / "seq", yaml_text="fx: .nan\nfy: 10\ncx: 3.5\ncy: 2.5\n")
    with pytest.raises(SensorError, match=r"intrinsics from camera\.yaml are not finite"):
        TumFolderSource(tmp_path / "seq")
    write_tum_folder(
        tmp_path / "seq2", yaml_text="fx: 1\nfy: 1\ncx: 1\ncy: 1\nwidth: .inf\nheight: 4\n"
    )
    with pytest.raises(SensorError, match=r"intrinsics from camera\.yaml are not finite"):
        TumFolderSource(tmp_path / "seq2")


def test_ground_truth_too_short_for_index_stamps_is_said_when_stamps_are_synthesised(
    tmp_path, caplog
):
    root = tmp_path / "keyframes"
    write_tum_folder(root)
    for name in ("rgb.txt", "depth.txt"):
        rows = [ln.split() for ln in (root / name).read_text().splitlines() if ln[0] != "#"]
        (root / name).write_text("".join(f"{k} {f}\n" for k, (_, f) in enumerate(rows)))
    (root / "groundtruth.txt").write_text("1305031102.1 1 2 3 0 0 0 1\n")
    with caplog.at_level(logging.WARNING):
        src = TumFolderSource(root)
    assert "synthesised at 30 Hz because groundtruth.txt has 1 rows" in src.describe()
    assert "frames go to index 2" in caplog.text
