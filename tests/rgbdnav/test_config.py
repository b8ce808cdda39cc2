"""The config loader: shipped defaults, layering, and errors that name the offending key."""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from rgbdnav.config import (
    REPO_CONFIG_DIR,
    SECTIONS,
    Config,
    config_to_dict,
    load_config,
    write_config,
)
from rgbdnav.config_docs import render_eddie_yaml, render_section_yaml
from sensors.types import ConfigError


def write_text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def write_yaml(path: Path, data: object) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# --- shipped defaults -------------------------------------------------------------------------


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_shipped_section_file_equals_code_defaults(section: str) -> None:
    path = REPO_CONFIG_DIR / f"{section}.yaml"
    data = yaml.safe_load(path.read_text())
    assert list(data) == [section]
    assert set(data[section]) == {f.name for f in dataclasses.fields(SECTIONS[section])}
    assert load_config([path]) == Config()


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_shipped_section_file_is_up_to_date_with_generator(section: str) -> None:
    path = REPO_CONFIG_DIR / f"{section}.yaml"
    assert path.read_text() == render_section_yaml(section, SECTIONS[section]())


def test_all_shipped_files_together_equal_code_defaults() -> None:
    files = sorted(REPO_CONFIG_DIR.glob("*.yaml"))
    assert {p.stem for p in files} == set(SECTIONS)
    assert load_config(files) == Config()


def test_every_field_has_a_doc_or_unit_in_the_shipped_yaml() -> None:
    for section in SECTIONS:
        text = (REPO_CONFIG_DIR / f"{section}.yaml").read_text()
        body = [ln for ln in text.splitlines() if ln.startswith("  ")]
        assert all("# [" in ln for ln in body), section


def test_eddie_profile_loads_with_eddie_geometry_and_kinect_intrinsics() -> None:
    path = REPO_CONFIG_DIR / "robots" / "eddie.yaml"
    assert path.read_text() == render_eddie_yaml()
    cfg = load_config([path])
    assert cfg.robot.wheel_diameter == pytest.approx(0.1524)
    assert cfg.robot.ticks_per_revolution == 36
    assert cfg.robot.track_width == pytest.approx(0.3)
    assert (cfg.camera.width, cfg.camera.height, cfg.camera.rate) == (640, 480, 30.0)
    assert cfg.camera.fx == cfg.camera.fy == pytest.approx(525.0)
    assert (cfg.camera.depth_min, cfg.camera.depth_max) == (0.5, 4.5)


def test_defaults_follow_upstream_ros_values() -> None:
    cfg = Config()
    assert cfg.ekf.frequency == 30.0 and cfg.ekf.sensor_timeout == 0.1 and cfg.ekf.two_d_mode
    assert cfg.ekf.process_noise_covariance[:3] == (0.05, 0.05, 0.06)
    assert cfg.ekf.initial_estimate_covariance == (1e-9,) * 15
    assert cfg.mapper.resolution == 0.05 and cfg.mapper.minimum_travel_distance == 0.5
    assert cfg.costmap.inflation_radius == 0.55
    assert cfg.smoother.max_velocity == (0.5, 0.0, 2.5)
    assert cfg.smoother.max_decel == (-2.5, 0.0, -3.2)
    assert cfg.follower.lookahead_dist == 0.6 and cfg.follower.rotate_to_heading_min_angle == 0.785


# --- errors name the file and the key path ----------------------------------------------------


def test_unknown_key_names_file_and_section_key(tmp_path: Path) -> None:
    path = write_yaml(tmp_path / "ekf.yaml", {"ekf": {"frequncy": 10.0}})
    with pytest.raises(ConfigError, match=r"ekf\.yaml: ekf\.frequncy: unknown key .*frequency"):
        load_config([path])


def test_unknown_section_is_rejected(tmp_path: Path) -> None:
    path = write_yaml(tmp_path / "bad.yaml", {"ekff": {"frequency": 10.0}})
    with pytest.raises(ConfigError, match=r"bad\.yaml: ekff: unknown section"):
        load_config([path])


def test_wrong_type_names_key_path(tmp_path: Path) -> None:
    path = write_yaml(tmp_path / "ekf.yaml", {"ekf": {"frequency": "fast"}})
    with pytest.raises(ConfigError, match=r"ekf\.yaml: ekf\.frequency: expected a number"):
        load_config([path])


def test_wrong_literal_choice_lists_the_choices() -> None:
    with pytest.raises(ConfigError, match=r"smoother\.feedback: 'HALF_LOOP' is not one of"):
        load_config(overrides=["smoother.feedback=HALF_LOOP"])


@pytest.mark.parametrize(
    ("override", "pattern"),
    [
        ("camera.fx=-1", r"camera\.fx: -1(\.0)? px is out of range \(must be > 0\.0 px\)"),
        (
            "robot.wheel_diameter=0",
            r"robot\.wheel_diameter: 0(\.0)? m is out of range \(must be > 0",
        ),
        ("smoother.max_decel=[-2.5, 0.5, -3.2]", r"smoother\.max_decel\[1\]: 0\.5 .* <= 0\.0"),
        # A cell of 1e12 m made a one-cell map without a word.
        (
            "mapper.resolution=1e12",
            r"mapper\.resolution: 10+\.0 m/cell is out of range \(must be <= 1\.0",
        ),
        # Session 17's keys: a negative window or allowance is refused, not read as "off".
        (
            "ekf.odom0_still_window=-1",
            r"ekf\.odom0_still_window: -1(\.0)? s is out of range \(must be >= 0\.0 s\)",
        ),
        (
            "navigate.collision_hold_allowance=-2",
            r"navigate\.collision_hold_allowance: -2(\.0)? s is out of range \(must be >= 0\.0",
        ),
    ],
)
def test_out_of_range_value_names_key_and_range(override: str, pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        load_config(overrides=[override])


def test_config_vector_with_14_elements_is_rejected(tmp_path: Path) -> None:
    path = write_yaml(tmp_path / "ekf.yaml", {"ekf": {"odom0_config": [True] * 14}})
    with pytest.raises(ConfigError, match=r"ekf\.odom0_config: expected 15 values, got 14"):
        load_config([path])


def test_config_vector_with_a_non_bool_names_the_element(tmp_path: Path) -> None:
    path = write_yaml(tmp_path / "ekf.yaml", {"ekf": {"imu0_config": [False] * 14 + [1]}})
    with pytest.raises(ConfigError, match=r"ekf\.imu0_config\[14\]: expected true/false"):
        load_config([path])


@pytest.mark.parametrize(
    ("overrides", "pattern"),
    [
        (["follower.min_lookahead_dist=1.0"], r"follower: min_lookahead_dist \(1\.0\) must not"),
        (["depth_to_scan.min_height=2.0"], r"depth_to_scan: min_height \(2\.0\) must be below"),
        (["depth_to_scan.range_min=5.0"], r"depth_to_scan: range_min \(5\.0\) must be below"),
        (["mapper.free_thresh=0.7"], r"mapper: free_thresh \(0\.7\) must be below occupied"),
        (["smoother.min_velocity=[1.0, 0.0, -2.5]"], r"smoother: min_velocity\[0\] \(1\.0\)"),
        (["follower.allow_reversing=true"], r"follower: use_rotate_to_heading and allow_rev"),
        (["ekf.smooth_lagged_data=true"], r"ekf: smooth_lagged_data needs history_length"),
    ],
)
def test_cross_field_validation_failure_is_reported(overrides: list[str], pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        load_config(overrides=overrides)


def test_cross_field_check_sees_values_from_earlier_layers(tmp_path: Path) -> None:
    path = write_yaml(tmp_path / "f.yaml", {"follower": {"max_lookahead_dist": 2.0}})
    cfg = load_config([path], overrides=["follower.min_lookahead_dist=1.5"])
    assert (cfg.follower.min_lookahead_dist, cfg.follower.max_lookahead_dist) == (1.5, 2.0)


# --- layering ---------------------------------------------------------------------------------


def test_set_overrides_win_over_files_which_win_over_defaults(tmp_path: Path) -> None:
    first = write_yaml(tmp_path / "a.yaml", {"ekf": {"frequency": 10.0, "sensor_timeout": 0.5}})
    second = write_yaml(tmp_path / "b.yaml", {"ekf": {"frequency": 15.0}})
    cfg = load_config([first, second], overrides=["ekf.frequency=20"])
    assert cfg.ekf.frequency == 20.0  # --set beats both files
    assert cfg.ekf.sensor_timeout == 0.5  # first file beats the default
    assert cfg.ekf.two_d_mode is Config().ekf.two_d_mode  # untouched keys keep defaults
    assert load_config([first, second]).ekf.frequency == 15.0  # later file beats earlier


def test_base_layer_sits_between_defaults_and_files(tmp_path: Path) -> None:
    base = {"camera": {"fx": 500.0, "fy": 501.0}}
    path = write_yaml(tmp_path / "cam.yaml", {"camera": {"fx": 510.0}})
    cfg = load_config([path], base=base)
    assert (cfg.camera.fx, cfg.camera.fy) == (510.0, 501.0)


def test_integer_override_for_float_key_becomes_float() -> None:
    cfg = load_config(overrides=["costmap.inflation_radius=1"])
    assert isinstance(cfg.costmap.inflation_radius, float)
    assert cfg.costmap.inflation_radius == 1.0


@pytest.mark.parametrize("bad", ["ekf.frequency", "frequency=30", "=30", "ekf.=30"])
def test_set_syntax_error_explains_the_expected_form(bad: str) -> None:
    with pytest.raises(ConfigError, match=r"--set .*expected section\.key=value"):
        load_config(overrides=[bad])


def test_set_value_that_is_not_yaml_is_reported() -> None:
    with pytest.raises(ConfigError, match=r"--set 'ekf\.frequency=\[1, ': value is not valid"):
        load_config(overrides=["ekf.frequency=[1, "])


def test_set_unknown_key_names_the_override() -> None:
    with pytest.raises(ConfigError, match=r"--set ekf\.nope=1: ekf\.nope: unknown key"):
        load_config(overrides=["ekf.nope=1"])


def test_invalid_yaml_file_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("ekf:\n  frequency: [1, 2\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml: line \d+ is not valid YAML"):
        load_config([path])


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read config file"):
        load_config([tmp_path / "nope.yaml"])


# --- hostile files and values ----------------------------------------------------------------


def test_a_config_that_is_not_utf8_is_a_config_error_naming_the_byte(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes("camera:\n  fx: 525 # \u00b5m\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1\.yaml: config file is not UTF-8 text \(byte"):
        load_config([path])


@pytest.mark.parametrize(
    "text",
    [
        "[" * 5000 + "]" * 5000,
        "a:\n" + "".join(" " * i + "b:\n" for i in range(1, 200)) + " " * 200 + "1\n",
    ],
)
def test_deeply_nested_yaml_is_an_error_not_a_recursion_error(tmp_path: Path, text: str) -> None:
    path = tmp_path / "deep.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"deep\.yaml: line \d+: nested deeper than 64"):
        load_config([path])


def test_a_yaml_alias_bomb_is_refused_at_once_with_a_short_message(tmp_path: Path) -> None:
    lines = ["a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    for prev, name in zip("abcdefgh", "bcdefghi", strict=True):
        lines.append(f"{name}: &{name} [{', '.join(['*' + prev] * 9)}]")
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines + ["ekf: *i"]) + "\n")
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match="more than 1000000 nodes") as info:
        load_config([path])
    assert time.perf_counter() - t0 < 2.0 and len(str(info.value)) < 300


def test_a_small_alias_that_expands_to_a_big_value_is_quoted_short() -> None:
    with pytest.raises(ConfigError, match=r"ekf\.frequency: expected a number") as info:
        load_config(overrides=["ekf.frequency=[" + ", ".join(["x" * 50] * 2000) + "]"])
    assert len(str(info.value)) < 300


def test_a_duplicate_key_is_an_error_naming_the_key_and_line(tmp_path: Path) -> None:
    path = write_text(tmp_path / "dup.yaml", "ekf:\n  frequency: 30\n  frequency: 50\n")
    with pytest.raises(ConfigError, match=r"dup\.yaml: line 3: duplicate key 'frequency'"):
        load_config([path])
    path = write_text(tmp_path / "dup2.yaml", "ekf: {}\nmapper: {}\nekf: {}\n")
    with pytest.raises(ConfigError, match=r"line 3: duplicate key 'ekf'"):
        load_config([path])


@pytest.mark.parametrize(("typed", "value"), [("1e12", 1e12), ("5E2", 500.0), ("5.25e2", 525.0)])
def test_numbers_typed_with_an_exponent_and_no_dot_are_numbers(typed: str, value: float) -> None:
    assert load_config(overrides=[f"camera.fx={typed}"]).camera.fx == value
    assert load_config(overrides=["camera.baseline=75e-3"]).camera.baseline == 0.075


@pytest.mark.parametrize("typed", [".nan", ".inf", "-.inf", "1" + "0" * 400])
def test_a_number_that_is_not_finite_is_refused_where_a_range_would_let_it_pass(
    typed: str,
) -> None:
    with pytest.raises(ConfigError, match=r"camera\.fx: expected a finite number"):
        load_config(overrides=[f"camera.fx={typed}"])


@pytest.mark.parametrize("value", ["", "' '"])
def test_an_empty_topic_name_is_an_error_not_a_stream_silently_dropped(value: str) -> None:
    with pytest.raises(ConfigError, match=r"topics: rgb: empty topic name"):
        load_config(overrides=[f"topics.rgb={value}"])


def test_a_yaml_file_that_is_not_a_regular_file_is_refused_without_blocking(
    tmp_path: Path,
) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match=r"fifo\.yaml: cannot read config file \(not a regular"):
        load_config([fifo])
    with pytest.raises(ConfigError, match=r"/dev/zero: cannot read config file"):
        load_config(["/dev/zero"])


# --- writing ----------------------------------------------------------------------------------


def test_write_config_round_trips_defaults(tmp_path: Path) -> None:
    out = tmp_path / "resolved.yaml"
    write_config(Config(), out)
    assert load_config([out]) == Config()


def test_write_config_round_trips_overridden_values(tmp_path: Path) -> None:
    cfg = load_config(
        overrides=[
            "ekf.initial_estimate_covariance=" + str([1e-3] * 15),
            "smoother.feedback=CLOSED_LOOP",
            "vo.min_inliers=25",
            "board.port=/dev/ttyACM0",
            "mapper.robust_kernel=cauchy",
        ]
    )
    out = tmp_path / "resolved.yaml"
    write_config(cfg, out)
    again = load_config([out])
    assert again == cfg
    assert config_to_dict(again) == config_to_dict(cfg)


def test_non_string_keys_are_reported_as_unknown_keys() -> None:
    keys: dict[Any, Any] = {1: 2.0, "nope": 3.0}  # YAML allows non-string keys
    with pytest.raises(ConfigError, match=r"scene: ekf\.1: unknown key"):
        load_config(base={"ekf": keys})


def test_vo_advanced_is_a_nested_section_reachable_from_files_and_set(tmp_path: Path) -> None:
    # Issue #10: the ORB + PnP pipeline's constants (VoTuning) are config, not code.
    from slam.visual_odometry import VisualOdometry

    f = tmp_path / "vo.yaml"
    f.write_text("vo:\n  advanced:\n    knn: 3\n    pnp_method: magsac\n")
    cfg = load_config([f], ["vo.advanced.fast_threshold=10", "vo.advanced.knn=4"])
    adv = cfg.vo.advanced
    assert (adv.fast_threshold, adv.knn, adv.pnp_method) == (10, 4, "magsac")  # merged by key
    assert adv.orb_levels == 6  # untouched keys keep their defaults
    from sensors.types import CameraIntrinsics

    vo = VisualOdometry(CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5), cfg.vo)
    assert vo.tuning.fast_threshold == 10  # it reaches the pipeline
    with pytest.raises(ConfigError, match=r"vo\.advanced\.fast_treshold: unknown key"):
        load_config([], ["vo.advanced.fast_treshold=10"])
    with pytest.raises(ConfigError, match=r"vo\.advanced\.knn"):
        load_config([], ["vo.advanced.knn=0"])
    with pytest.raises(ConfigError, match=r"vo\.advanced: expected a mapping"):
        load_config([], ["vo.advanced=3"])
