"""Property tests for the readers added in session 13 (fleet.yaml, geo.yaml, gps.txt, KITTI and
EuRoC trajectories with a KITTI times file, joystick replay files, ``--board`` specs, ThunderBorg
tacho lines, ``--ros-params`` files, RealSense SDK transforms): whatever the bytes, each returns a
result or raises its documented error (an RgbdNavError subclass) -- never another exception or a
hang. The examples pinned below are the bugs the fuzzing found."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nav.joystick import parse_events
from rgbdnav.commands.export import run_content
from rgbdnav.ros_params import load_ros_params
from sensors.arduino_bridge import parse_encoder_reply
from sensors.extrinsics import chain_to_root, quaternion_matrix, robot_mount_from_tf
from sensors.geo import geo_from_dict
from sensors.gps import read_gps_txt
from sensors.motor_board import parse_device_spec
from sensors.rosbag_source import parse_sdk_transform
from sensors.thunderborg import parse_tacho_line
from sensors.tum import read_pose_table
from sensors.types import ConfigError, MapError, RgbdNavError
from slam.fleet import load_fleet
from slam.map_bundle import decode_pgm
from tests.rgbdnav.test_parsers_fuzz import YAML_ALPHABET, mutations


def examples(n: int) -> settings:
    """``n`` examples, 2 s each at most (a hang fails), no database, tmp_path reused."""
    return settings(
        max_examples=n,
        deadline=2000,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )


NUM_ALPHABET = b" \n#0123456789.-+eEnaif\t\xff"
# YAML leaves the values a hostile file may hold: mixed-type keys, huge ints, NaN, nesting.
yaml_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**400), 10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
)
yaml_value = st.recursive(
    yaml_leaf,
    lambda inner: st.one_of(
        st.lists(inner, max_size=3),
        st.dictionaries(
            st.one_of(st.integers(), st.text(max_size=12), st.none()), inner, max_size=4
        ),
    ),
    max_leaves=12,
)
GEO_KEYS = st.sampled_from(["latitude", "longitude", "altitude", "heading_deg"])


def rejects_cleanly(fn, *args, errors=(RgbdNavError,)):
    try:
        return fn(*args)
    except errors:
        return None


@examples(80)
@given(
    st.dictionaries(st.one_of(GEO_KEYS, st.integers(), st.text(max_size=5)), yaml_value, max_size=5)
)
def test_a_geo_mapping_of_any_values_is_an_anchor_or_a_map_error(data: dict) -> None:
    anchor = rejects_cleanly(geo_from_dict, data, "geo.yaml", errors=(MapError,))
    if anchor is not None:
        assert abs(anchor.latitude) <= 90 and np.isfinite(anchor.heading_deg)


FLEET = (
    b"world:\n  geo: {latitude: 52.0, longitude: 4.0}\nrobots:\n"
    b"  - name: a\n    map: m\n    T_world_map: {x: 1.0, y: -2.0, yaw: 0.5}\n"
    b"  - {name: b, map: m, geo: {latitude: 52.1, longitude: 4.1, heading_deg: 90}}\n"
)


@examples(80)
@given(mutations(FLEET, YAML_ALPHABET + b"\x00"))
def test_a_mutated_fleet_file_loads_or_is_a_map_error(tmp_path: Path, data: bytes) -> None:
    (tmp_path / "m").mkdir(exist_ok=True)
    path = tmp_path / "fleet.yaml"
    path.write_bytes(data)
    fleet = rejects_cleanly(load_fleet, path, errors=(MapError,))
    if fleet is not None:
        assert all(np.isfinite(r.T_world_map).all() for r in fleet.robots)


@examples(40)
@given(yaml_value)
def test_a_fleet_document_of_any_shape_loads_or_is_a_map_error(tmp_path: Path, doc) -> None:
    import yaml

    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump({"robots": [doc]}))
    rejects_cleanly(load_fleet, path, errors=(MapError,))


@examples(60)
@given(
    mutations(
        b"# stamp lat lon alt sigma_h\n1.0 52.0 4.0 10.0 3.0\n2.0 52.1 4.1 11 2.5\n", NUM_ALPHABET
    )
)
def test_a_mutated_gps_txt_reads_or_is_an_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "gps.txt"
    path.write_bytes(data)
    gps = rejects_cleanly(read_gps_txt, path)
    if gps is not None:
        assert (np.abs(gps.latitude) <= 90).all() and (gps.sigma_m > 0).all()


KITTI = b"1 0 0 0.5 0 1 0 0.25 0 0 1 0\n1 0 0 1.5 0 1 0 0.5 0 0 1 0\n"
EUROC = (
    b"#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
    b"q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n"
    b"1403636579758555392,4.68,-1.78,0.78,0.53,-0.15,-0.82,-0.08\n"
    b"1403636579763555584,4.68,-1.78,0.78,0.53,-0.15,-0.82,-0.08\n"
)


@examples(60)
@given(mutations(KITTI, NUM_ALPHABET), mutations(b"0.0\n0.1\n", NUM_ALPHABET))
def test_a_mutated_kitti_trajectory_and_times_file_read_or_are_an_error(
    tmp_path: Path, poses: bytes, times: bytes
) -> None:
    (tmp_path / "poses.txt").write_bytes(poses)
    (tmp_path / "times.txt").write_bytes(times)
    table = rejects_cleanly(
        read_pose_table, tmp_path / "poses.txt", "kitti", tmp_path / "times.txt"
    )
    if table is not None:
        assert np.isfinite(table.poses).all() and (np.diff(table.stamps_ns) > 0).all()


@examples(60)
@given(mutations(EUROC, NUM_ALPHABET + b","))
def test_a_mutated_euroc_trajectory_reads_or_is_an_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "data.csv"
    path.write_bytes(data)
    table = rejects_cleanly(read_pose_table, path)
    if table is not None:
        assert np.isfinite(table.poses).all()


@pytest.mark.parametrize("stamp", ["9" * 19, "9" * 5000, "1²"])
def test_a_euroc_stamp_too_large_for_int64_or_not_ascii_is_a_sensor_error(
    tmp_path: Path, stamp: str
) -> None:
    # Found by fuzz_inputs.py: OverflowError (int64), ValueError ("²" passes str.isdigit).
    path = tmp_path / "data.csv"
    path.write_bytes(EUROC.replace(b"1403636579758555392", stamp.encode()))
    with pytest.raises(RgbdNavError, match="not integer ns"):
        read_pose_table(path, "euroc")


@examples(80)
@given(mutations(b"0.0 1 0 1\n0.5 3 1 -32767\n# c\n1.25 1 0 0\n", NUM_ALPHABET))
def test_a_mutated_joystick_replay_file_parses_or_is_a_config_error(data: bytes) -> None:
    events = rejects_cleanly(
        parse_events, data.decode("utf-8", "replace"), "ev", errors=(ConfigError,)
    )
    if events:
        times = [e[0] for e in events]
        assert all(0 <= t <= 86400 for t in times) and times == sorted(times)


@pytest.mark.parametrize("line", ["nan 1 0 1", "inf 1 0 1", "-1 1 0 1", "0 1 0 99999999999"])
def test_a_replay_time_that_is_nan_inf_or_negative_is_refused_not_slept_on(line: str) -> None:
    # Found by fuzzing: NaN passed the "backwards" check, inf made replay() sleep for ever.
    with pytest.raises(ConfigError, match="ev:1"):
        parse_events(line + "\n", "ev")


SPEC_ALPHABET = "thunderborg:arduino-bridge:emulator:/dev/i2c-1ttyACM0@0x15,57600 \x00١"


@examples(100)
@given(st.text(SPEC_ALPHABET, max_size=40))
def test_any_board_spec_parses_or_is_a_config_error(spec: str) -> None:
    rejects_cleanly(parse_device_spec, spec, errors=(ConfigError,))


@examples(100)
@given(st.binary(max_size=40) | mutations(b"tacho 12.5 -3\r\n", NUM_ALPHABET))
def test_a_tacho_line_of_any_bytes_is_two_finite_rpms_or_none(line: bytes) -> None:
    rpm = parse_tacho_line(line)
    assert rpm is None or np.isfinite(rpm).all()


@examples(80)
@given(st.text(max_size=60) | st.text("[]{},:;0123456789.-eEnaif ", max_size=60))
def test_a_realsense_sdk_transform_parses_or_is_an_error(text: str) -> None:
    out = rejects_cleanly(parse_sdk_transform, text)
    if out is not None:
        assert np.isfinite(np.concatenate([np.ravel(x) for x in out])).all()


@pytest.mark.parametrize(
    "text",
    [
        "rotation=nan,0,0,0,1,0,0,0,1;translation=0,0,0",
        "rotation=1,0,0,0,1,0,0,0,1;translation=inf,0,0",
        "rotation=5,0,0,0,1,0,0,0,1;translation=0,0,0",
    ],
)
def test_a_sdk_transform_that_is_not_a_finite_rotation_is_an_error(text: str) -> None:
    # Found by fuzzing: NaN, inf and a scaled matrix were returned as the camera extrinsics.
    with pytest.raises(RgbdNavError, match="not a finite rotation"):
        parse_sdk_transform(text)


@examples(60)
@given(mutations(b"rotation=1,0,0,0,1,0,0,0,1;translation=0.015,0,0", b"0123456789.,-=;naif"))
def test_a_mutated_sdk_transform_parses_or_is_an_error(text: bytes) -> None:
    out = rejects_cleanly(parse_sdk_transform, text.decode("utf-8", "replace"))
    if out is not None:
        assert np.isfinite(np.concatenate([np.ravel(x) for x in out])).all()


ROS = (
    b"ekf_filter_node:\n  ros__parameters:\n    frequency: 30.0\n    two_d_mode: true\n"
    b"    process_noise_covariance: [0.05, 0.0, 0.0]\n"
    b"slam_toolbox:\n  ros__parameters:\n    resolution: 0.05\n    minimum_travel_distance: 0.5\n"
)


@examples(60)
@given(mutations(ROS, YAML_ALPHABET))
def test_a_mutated_ros_params_file_maps_or_is_a_config_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "p.yaml"
    path.write_bytes(data)
    rejects_cleanly(load_ros_params, [path], errors=(ConfigError,))


@examples(40)
@given(yaml_value)
def test_ros_params_of_any_shape_map_or_are_a_config_error(tmp_path: Path, params) -> None:
    import yaml

    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"ekf_filter_node": {"ros__parameters": params}}))
    rejects_cleanly(load_ros_params, [path], errors=(ConfigError,))


@pytest.mark.parametrize(
    "doc",
    [
        "robots:\n - {1: a, b: 2}\n",  # int and str keys: sorted() raised TypeError
        "robots:\n - {name: a, map: m, T_world_map: {x: 1" + "0" * 400 + "}}\n",  # OverflowError
        'robots:\n - {name: a, map: "m\\0b"}\n',  # NUL in a path: ValueError
        "world: {geo: {latitude: 1" + "0" * 400 + ", longitude: 4}}\nrobots: [{name: a, map: m}]\n",
    ],
)
def test_fleet_files_that_raised_tracebacks_are_map_errors(tmp_path: Path, doc: str) -> None:
    (tmp_path / "m").mkdir()
    path = tmp_path / "fleet.yaml"
    path.write_text(doc)
    with pytest.raises(MapError, match="fleet.yaml"):
        load_fleet(path)


P2 = b"P2\n# a comment\n3 2\n255\n0 254 205\n# mid\n0 100 255\n"
P5_16 = b"P5\n2 2\n65535\n" + bytes([0, 0, 255, 255, 1, 0, 128, 0])


@examples(100)
@given(mutations(P2, b"0123456789 \n#-+P2") | mutations(P5_16, b"\x00\xff0123456789 \n"))
def test_a_mutated_ascii_or_16_bit_pgm_decodes_or_is_a_map_error(data: bytes) -> None:
    out = rejects_cleanly(decode_pgm, data, "map.pgm", errors=(MapError,))
    if out is not None:
        pixels, maxval = out
        assert pixels.ndim == 2 and int(pixels.max(initial=0)) <= maxval


@pytest.mark.parametrize(
    "data",
    [
        b"P2\n2 1\n255\n99999999999999999999999 1\n",  # OverflowError from numpy
        b"P2\n" + b"9" * 5000 + b" 1\n255\n1 1\n",  # ValueError: int() digit limit
    ],
)
def test_pgm_numbers_too_large_for_int_are_map_errors(data: bytes) -> None:
    with pytest.raises(MapError, match="map.pgm"):
        decode_pgm(data, "map.pgm")


@examples(100)
@given(st.text(max_size=30) | st.text("0123456789 -_+\t١", max_size=30))
def test_an_encoder_reply_of_any_text_is_two_32_bit_counts_or_none(text: str) -> None:
    counts = parse_encoder_reply(text)
    assert counts is None or all(-(2**31) <= c < 2**31 for c in counts)


@pytest.mark.parametrize("reply", ["1_0 2", "١ 2", "9" * 40 + " 0", "1 2 3", "0x10 2"])
def test_an_encoder_reply_int_would_take_but_the_firmware_cannot_send_is_refused(
    reply: str,
) -> None:
    # int() took these: "1_0" as 10, Arabic-Indic digits, a 40-digit count (later int64 overflow).
    assert parse_encoder_reply(reply) is None
    assert parse_encoder_reply("123 -45") == (123, -45)


SUMMARY = (
    b'{"command": "odometry", "frame": "base_link", "source": "/nonexistent", '
    b'"map": {"path": "gone"}, "recording": {"path": "gone"}}'
)


def _odometry_run(folder: Path, summary: bytes) -> Path:
    folder.mkdir(exist_ok=True)
    (folder / "fused.tum").write_text("1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    (folder / "summary.json").write_bytes(summary)
    return folder


@examples(60)
@given(mutations(SUMMARY, b'{}[]",:0123456789.-enaifl\\u0/'))
def test_export_of_a_run_with_a_mutated_summary_reads_or_is_an_error(
    tmp_path: Path, data: bytes
) -> None:
    rejects_cleanly(run_content, _odometry_run(tmp_path / "run", data), True)


@pytest.mark.parametrize(
    "summary",
    [
        b"[" * 100_000,  # RecursionError from the JSON decoder
        b'{"command": "odometry", "source": "/' + b"a" * 5000 + b'"}',  # OSError ENAMETOOLONG
        b'{"command": "localize", "map": "/' + b"a" * 5000 + b'"}',
    ],
)
def test_export_of_a_run_whose_summary_raised_a_traceback_is_clean(
    tmp_path: Path, summary: bytes
) -> None:
    run = _odometry_run(tmp_path / "run", summary)
    (run / "trajectory.tum").write_text("1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    try:
        run_content(run, True)
    except RgbdNavError as err:
        assert "summary" in str(err)


finite_or_not = st.floats(allow_nan=True, allow_infinity=True)


@examples(100)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["base_link", "base_footprint", "camera_link", "cam_optical", "x"]),
            st.sampled_from(["base_link", "base_footprint", "camera_link", "cam_optical", "x"]),
            st.tuples(*[finite_or_not] * 3),
            st.tuples(*[finite_or_not] * 4),
        ),
        max_size=6,
    )
)
def test_a_tf_static_tree_of_any_shape_gives_a_finite_mount_or_a_value_error(edges) -> None:
    import warnings

    tree = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # NaN in, NaN out: refused below
        for child, parent, t, q in edges:
            m = np.eye(4)
            m[:3, :3], m[:3, 3] = quaternion_matrix(*q), t
            tree[child] = (parent, m)
        found = chain_to_root(tree, "cam_optical")
    if found is None:
        return
    try:
        mount = robot_mount_from_tf(found[1], optical=True)
    except ValueError:
        return
    assert all(np.isfinite(v) for v in mount.values())


def test_a_zero_quaternion_in_tf_static_is_refused_not_a_nan_camera_mount() -> None:
    # Found by fuzzing: a NaN mount passed the "turned too far" check (abs(nan) > x is False).
    m = np.eye(4)
    with np.errstate(invalid="ignore", divide="ignore"):
        m[:3, :3] = quaternion_matrix(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="not finite"):
        robot_mount_from_tf(m, optical=False)
