from __future__ import annotations

import logging

import numpy as np
import pytest

from sensors.images import ImageError
from sensors.recording import (
    Recording,
    RecordingWriter,
    associate,
    counts_to_depth,
    depth_to_counts,
)
from sensors.types import NO_RGB, CameraIntrinsics, RgbdFrame, SensorError

MS = 1_000_000  # [ns]
INTR = CameraIntrinsics(width=8, height=6, fx=10.0, fy=10.0, cx=3.5, cy=2.5)
SCENE = {"robot": {"track_m": 0.3}, "seed": 7, "groundtruth_frame": "base_link"}


def make_frame(stamp_ns: int, seed: int) -> RgbdFrame:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, size=(6, 8, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.5, size=(6, 8)).astype(np.float32)
    depth[0, 0] = np.nan
    depth[0, 1] = 0.0
    depth[0, 2] = -1.0
    depth[0, 3] = 100.0  # beyond 65535 / 5000 m
    return RgbdFrame(stamp_ns, rgb, depth, INTR)


def write_recording(path, stamps_ns=(1_000 * MS, 1_033 * MS, 1_066 * MS)) -> list[RgbdFrame]:
    frames = [make_frame(t, seed) for seed, t in enumerate(stamps_ns)]
    with RecordingWriter(path, INTR, SCENE, workers=2) as writer:
        for frame in frames:
            writer.add_frame(frame)
    return frames


def test_frames_round_trip_with_exact_rgb_and_quantised_depth(tmp_path):
    written = write_recording(tmp_path / "rec")
    rec = Recording.open(tmp_path / "rec")

    frames = list(rec.frames())
    assert len(rec) == len(frames) == 3
    assert rec.intrinsics == INTR
    assert rec.scene["seed"] == 7 and rec.scene["robot"] == {"track_m": 0.3}
    for want, got in zip(written, frames, strict=True):
        assert got.stamp_ns == want.stamp_ns
        np.testing.assert_array_equal(got.rgb, want.rgb)
        assert got.depth_m.dtype == np.float32
        np.testing.assert_array_equal(got.depth_m[0, :4], 0.0)  # NaN, 0, <0, too far -> 0
        np.testing.assert_allclose(got.depth_m[1:], want.depth_m[1:], atol=1.0 / INTR.depth_scale)


def test_index_files_are_tum_style_with_exact_stamps(tmp_path):
    write_recording(tmp_path / "rec", stamps_ns=(12_033_333_333,))
    lines = (tmp_path / "rec" / "rgb.txt").read_text().splitlines()
    assert lines[0].startswith("# ")
    assert lines[-1] == "12.033333333 rgb/12.033333333.png"
    assert (tmp_path / "rec" / "depth" / "12.033333333.png").is_file()


def test_wheels_imu_and_groundtruth_round_trip_with_exact_stamps(tmp_path):
    path = tmp_path / "rec"
    stamps = np.array([1_000_000_001, 1_010_000_002, 1_020_000_003, 1_030_000_004])
    with RecordingWriter(path, INTR, SCENE) as writer:
        writer.add_frame(make_frame(1_000 * MS, 0))
        writer.add_wheels(stamps[:2], np.array([0, 3]), np.array([0, -2]))
        writer.add_wheels(stamps[2:], np.array([7, 12]), np.array([-5, -9]))
        writer.add_imu(stamps, np.array([0.0, 0.125, -1.0 / 3.0, 2.5]))
        writer.set_groundtruth(
            stamps, np.array([0, 0.1, 0.2, 0.3]), np.zeros(4), np.array([0.0, 0.5, -3.0, 3.1])
        )
    rec = Recording.open(path)

    t, left, right = rec.wheels()
    assert t.dtype == left.dtype == right.dtype == np.int64
    np.testing.assert_array_equal(t, stamps)
    np.testing.assert_array_equal(left, [0, 3, 7, 12])
    np.testing.assert_array_equal(right, [0, -2, -5, -9])

    imu = rec.imu()
    assert imu is not None
    np.testing.assert_array_equal(imu[0], stamps)
    np.testing.assert_array_equal(imu[1], [0.0, 0.125, -1.0 / 3.0, 2.5])

    gt = rec.groundtruth_planar()
    assert gt is not None
    np.testing.assert_array_equal(gt[0], stamps)
    np.testing.assert_allclose(gt[1], [0, 0.1, 0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(gt[3], [0.0, 0.5, -3.0, 3.1], atol=1e-12)
    full = rec.groundtruth()
    assert full is not None
    np.testing.assert_array_equal(full[1][:, 2], 0.0)


def test_optional_streams_are_absent_when_not_written(tmp_path):
    write_recording(tmp_path / "rec")
    rec = Recording.open(tmp_path / "rec")
    assert rec.imu() is None and rec.groundtruth() is None and rec.groundtruth_planar() is None
    assert all(a.size == 0 and a.dtype == np.int64 for a in rec.wheels())


def test_exception_in_with_body_leaves_previous_recording_and_no_staging(tmp_path):
    path = tmp_path / "rec"
    first = write_recording(path)
    with pytest.raises(RuntimeError, match="boom"):
        with RecordingWriter(path, INTR, SCENE) as writer:
            writer.add_frame(make_frame(5_000 * MS, 9))
            raise RuntimeError("boom")

    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
    rec = Recording.open(path)
    assert [f.stamp_ns for f in rec.frames()] == [f.stamp_ns for f in first]


def test_closing_replaces_an_existing_recording(tmp_path):
    path = tmp_path / "rec"
    write_recording(path)
    write_recording(path, stamps_ns=(7_000 * MS,))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
    assert len(Recording.open(path)) == 1
    assert len(list((path / "rgb").iterdir())) == 1


def test_writer_rejects_frame_stamps_that_do_not_increase(tmp_path):
    with pytest.raises(SensorError, match="strictly increase"):
        with RecordingWriter(tmp_path / "rec", INTR, SCENE) as writer:
            writer.add_frame(make_frame(2_000 * MS, 0))
            writer.add_frame(make_frame(2_000 * MS, 1))
    assert not (tmp_path / "rec").exists()


@pytest.mark.parametrize("missing", ["rgb.txt", "depth.txt", "scene.yaml"])
def test_missing_index_or_scene_file_is_named(tmp_path, missing):
    write_recording(tmp_path / "rec")
    (tmp_path / "rec" / missing).unlink()
    with pytest.raises(SensorError, match=rf"missing {missing}; a recording folder holds"):
        Recording.open(tmp_path / "rec")


def test_malformed_index_line_names_file_and_line(tmp_path):
    write_recording(tmp_path / "rec")
    index = tmp_path / "rec" / "depth.txt"
    index.write_text(index.read_text() + "1.5\n")
    with pytest.raises(SensorError, match=r"depth\.txt:6: expected 2 fields"):
        Recording.open(tmp_path / "rec")


def test_bad_timestamp_names_file_and_line(tmp_path):
    write_recording(tmp_path / "rec")
    (tmp_path / "rec" / "rgb.txt").write_text("# c\nabc rgb/x.png\n")
    with pytest.raises(SensorError, match=r"rgb\.txt:2: bad timestamp"):
        Recording.open(tmp_path / "rec")


@pytest.mark.parametrize(
    ("second", "kind"), [("0.5", "non-monotonic"), ("1.000000000", "duplicate")]
)
def test_non_increasing_index_stamp_names_file_and_line(tmp_path, second, kind):
    write_recording(tmp_path / "rec")
    (tmp_path / "rec" / "rgb.txt").write_text(
        f"# c\n1.0 rgb/1.000000000.png\n{second} rgb/1.033000000.png\n"
    )
    with pytest.raises(SensorError, match=rf"rgb\.txt:3: {kind} timestamp"):
        Recording.open(tmp_path / "rec")


def test_non_integer_wheel_counts_name_file_and_line(tmp_path):
    write_recording(tmp_path / "rec")
    (tmp_path / "rec" / "wheels.txt").write_text("1.0 0 0\n1.1 2.5 3\n")
    with pytest.raises(SensorError, match=r"wheels\.txt:2: .*integer encoder counts"):
        Recording.open(tmp_path / "rec").wheels()


def test_truncated_png_raises_naming_the_file(tmp_path):
    write_recording(tmp_path / "rec")
    png = tmp_path / "rec" / "depth" / "1.033000000.png"
    png.write_bytes(png.read_bytes()[:-20])
    frames = Recording.open(tmp_path / "rec").frames()
    next(frames)
    with pytest.raises(SensorError, match=r"depth/1\.033000000\.png: truncated PNG"):
        next(frames)


def test_missing_and_wrong_size_images_raise_naming_the_file(tmp_path):
    write_recording(tmp_path / "rec")
    (tmp_path / "rec" / "rgb" / "1.000000000.png").unlink()
    with pytest.raises(SensorError, match=r"rgb/1\.000000000\.png: image is missing"):
        list(Recording.open(tmp_path / "rec").frames())

    other = CameraIntrinsics(width=4, height=3, fx=10.0, fy=10.0, cx=2.0, cy=1.5)
    with RecordingWriter(tmp_path / "small", other, {}) as writer:
        writer.add_frame(
            RgbdFrame(1_000 * MS, np.zeros((3, 4, 3), np.uint8), np.ones((3, 4), np.float32), other)
        )
    (tmp_path / "small" / "scene.yaml").write_bytes((tmp_path / "rec" / "scene.yaml").read_bytes())
    with pytest.raises(SensorError, match=r"rgb/1\.000000000\.png: image is 4x3, camera is 8x6"):
        list(Recording.open(tmp_path / "small").frames())


def test_skip_bad_counts_skipped_frames_and_logs_a_warning(tmp_path, caplog):
    write_recording(tmp_path / "rec")
    (tmp_path / "rec" / "rgb" / "1.000000000.png").unlink()
    png = tmp_path / "rec" / "depth" / "1.066000000.png"
    png.write_bytes(png.read_bytes()[:100])
    rec = Recording.open(tmp_path / "rec")
    with caplog.at_level(logging.WARNING, logger="sensors.recording"):
        frames = list(rec.frames(skip_bad=True))
    assert [f.stamp_ns for f in frames] == [1_033 * MS]
    assert rec.skipped == {"missing": 1, "truncated": 1}
    assert sum("skipping frame" in r.message for r in caplog.records) == 2


def test_frames_whose_colour_is_not_wanted_skip_its_decode_but_not_its_checks(tmp_path):
    stamps = tuple(1_000 * MS + 33 * MS * k for k in range(6))
    write_recording(tmp_path / "rec", stamps_ns=stamps)
    full = list(Recording.open(tmp_path / "rec").frames())
    rec = Recording.open(tmp_path / "rec")
    asked: list[int] = []

    def even(i: int) -> bool:
        asked.append(i)
        return i % 2 == 0

    got = list(rec.frames(rgb_wanted=even))
    assert [f.stamp_ns for f in got] == list(stamps)
    for i, (want, f) in enumerate(zip(full, got, strict=True)):
        np.testing.assert_array_equal(f.depth_m, want.depth_m)
        if i % 2 == 0:
            np.testing.assert_array_equal(f.rgb, want.rgb)
        else:
            assert f.rgb is NO_RGB and f.rgb.size == 0 and not f.rgb.flags.writeable
    assert set(asked) >= set(range(6))
    # A bad frame moves the count of the frames after it: the wanted ones still get colour
    # (the others may), and a truncated colour PNG is found although its colour is not wanted.
    (tmp_path / "rec" / "depth" / "1.033000000.png").unlink()
    png = tmp_path / "rec" / "rgb" / "1.132000000.png"
    png.write_bytes(png.read_bytes()[:-12])
    rec = Recording.open(tmp_path / "rec")
    got = list(rec.frames(skip_bad=True, rgb_wanted=lambda i: i % 2 == 0))
    assert [f.stamp_ns for f in got] == [stamps[0], stamps[2], stamps[3], stamps[5]]
    assert rec.skipped == {"missing": 1, "truncated": 1}
    np.testing.assert_array_equal(got[0].rgb, full[0].rgb)
    np.testing.assert_array_equal(got[2].rgb, full[3].rgb)
    with pytest.raises(ImageError, match="truncated PNG"):
        rec.frame(4, rgb=False)


def test_slightly_offset_depth_is_associated_to_the_nearest_rgb(tmp_path):
    path = tmp_path / "rec"
    write_recording(path, stamps_ns=(1_000 * MS, 1_033 * MS, 1_066 * MS, 1_100 * MS))
    # depth 5 ms late, one depth frame dropped, one extra depth 30 ms away from any rgb
    (path / "depth.txt").write_text(
        "# depth maps\n"
        "1.005000000 depth/1.000000000.png\n"
        "1.038000000 depth/1.033000000.png\n"
        "1.105000000 depth/1.100000000.png\n"
        "1.200000000 depth/1.066000000.png\n"
    )
    rec = Recording.open(path)
    assert len(rec) == 3
    np.testing.assert_array_equal(rec.rgb_index, [0, 1, 3])
    np.testing.assert_array_equal(rec.depth_index, [0, 1, 2])
    assert [f.stamp_ns for f in rec.frames()] == [1_000 * MS, 1_033 * MS, 1_100 * MS]


def test_association_is_one_to_one_like_tum_associate():
    # Greedy by smallest difference: (10, 9) first, then 0 falls back to -15.
    ia, ib = associate(np.array([0, 10]), np.array([-15, 9]), max_difference_ns=20)
    np.testing.assert_array_equal(ia, [0, 1])
    np.testing.assert_array_equal(ib, [0, 1])
    # Both rgb stamps want depth 5; only the nearer one (4) gets it.
    ia, ib = associate(np.array([0, 4]), np.array([5]), max_difference_ns=20)
    np.testing.assert_array_equal(ia, [1])
    np.testing.assert_array_equal(ib, [0])
    # The window is strict, as in associate.py.
    ia, _ = associate(np.array([0]), np.array([20]), max_difference_ns=20)
    assert ia.size == 0


def associate_reference(a, b, max_difference):
    """TUM associate.py, verbatim in spirit: all pairs in the window, greedy by difference."""
    pairs = sorted(
        (abs(x - y), i, j)
        for i, x in enumerate(a)
        for j, y in enumerate(b)
        if abs(x - y) < max_difference
    )
    used_a, used_b, out = set(), set(), []
    for _, i, j in pairs:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out)


def test_association_matches_the_greedy_reference_on_jittered_streams():
    rng = np.random.default_rng(3)
    for _ in range(50):
        a = np.unique(rng.integers(0, 1000, size=rng.integers(0, 40)))
        b = np.unique(rng.integers(0, 1000, size=rng.integers(0, 40)))
        ia, ib = associate(a, b, max_difference_ns=25)
        assert list(zip(ia.tolist(), ib.tolist(), strict=True)) == associate_reference(a, b, 25)


@pytest.mark.parametrize(
    ("key", "value"), [("fx", ".nan"), ("fy", ".inf"), ("cx", ".nan"), ("depth_scale", "-.inf")]
)
def test_intrinsics_that_are_not_finite_are_an_error_naming_the_scene_file(tmp_path, key, value):
    # fx: .nan passed the "> 0" check and every frame then failed downstream (issue #16).
    write_recording(tmp_path / "rec")
    scene = tmp_path / "rec" / "scene.yaml"
    text = scene.read_text()
    assert f"\n  {key}: " in text
    lines = [
        f"  {key}: {value}" if line.startswith(f"  {key}: ") else line for line in text.splitlines()
    ]
    scene.write_text("\n".join(lines) + "\n")
    with pytest.raises(SensorError, match=r"scene\.yaml: camera intrinsics .* must be finite"):
        Recording.open(tmp_path / "rec")


@pytest.mark.parametrize("field", ["width", "fx", "fy", "cx", "depth_scale"])
def test_camera_intrinsics_refuse_nan_and_non_positive_values_wherever_they_are_built(field):
    good = {"width": 4, "height": 3, "fx": 5.0, "fy": 5.0, "cx": 2.0, "cy": 1.5}
    for bad in (float("nan"), float("inf")) if field in ("cx",) else (float("nan"), 0, -1.0):
        with pytest.raises(SensorError, match="must be finite"):
            CameraIntrinsics(**{**good, field: bad})


def test_depth_to_counts_zeroes_what_a_uint16_cannot_hold_and_writes_into_a_given_slot() -> None:
    depth = np.array(
        [[np.nan, np.inf, -np.inf, -0.5], [0.0, 1.00001, 13.107, 13.1072], [1e-5, 2.5, 7e-5, 1.0]],
        np.float32,
    )
    want = np.array([[0, 0, 0, 0], [0, 5000, 65535, 0], [0, 12500, 0, 5000]], np.uint16)
    got = depth_to_counts(depth, 5000.0)
    assert got.dtype == np.uint16 and np.array_equal(got, want)
    slot = np.full(depth.shape, 7, np.uint16)
    assert depth_to_counts(depth, 5000.0, out=slot) is slot and np.array_equal(slot, want)
    back = counts_to_depth(want, 5000.0)
    assert back.dtype == np.float32 and back[1, 1] == np.float32(1.0) and back[0, 0] == 0.0
