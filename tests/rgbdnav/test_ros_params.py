"""--ros-params: ROS 2 parameter files shaped like the shipped ones (robot_localization's
params/ekf.yaml, slam_toolbox's mapper_params_online_async.yaml, an excerpt of Nav2's
nav2_params.yaml with RPP, velocity_smoother and collision_monitor) mapped onto our config."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.config import load_config
from rgbdnav.ros_params import format_table, load_ros_params
from sensors.types import ConfigError
from tests.bagtools import MS, T0, write_bag

HERE = Path(__file__).resolve().parent
PARAMS = HERE / "ros_params"
EKF, SLAM, NAV2 = (
    PARAMS / "ekf.yaml",
    PARAMS / "mapper_params_online_async.yaml",
    PARAMS / "nav2_params.yaml",
)


def reasons(rows, node):
    return {r.key: r.reason for r in rows if r.node == node and not r.target}


def test_robot_localization_ekf_yaml_maps_its_15x15_covariance_and_inputs():
    overrides, rows = load_ros_params([EKF])
    cfg = load_config(overrides=overrides)
    q = (
        0.05,
        0.05,
        0.06,
        0.03,
        0.03,
        0.06,
        0.025,
        0.025,
        0.04,
        0.01,
        0.01,
        0.02,
        0.01,
        0.01,
        0.015,
    )
    assert cfg.ekf.process_noise_covariance == pytest.approx(q)
    assert cfg.ekf.initial_estimate_covariance == pytest.approx((1e-9,) * 15)
    assert cfg.ekf.frequency == 30.0 and cfg.ekf.sensor_timeout == 0.1
    assert cfg.ekf.two_d_mode is False
    assert cfg.ekf.odom0_config == (True, True) + (False,) * 9 + (True,) + (False,) * 3
    assert cfg.ekf.imu0_relative is True and cfg.ekf.odom0_pose_rejection_threshold == 5.0
    # odom0 / imu0 name the topics (relative names resolve in the root namespace)
    assert cfg.topics.odom == "/example/odom" and cfg.topics.imu == "/example/imu"
    why = reasons(rows, "ekf_filter_node")
    assert "map -> odom" in why["map_frame"]
    assert "odom0" in why["odom1"] and "odom0" in why["twist0_config"]
    assert "cmd_vel" in why["use_control"]
    assert "ROS graph" in why["odom0_queue_size"]


def test_slam_toolbox_mapper_params_map_onto_the_mapper():
    overrides, rows = load_ros_params([SLAM])
    cfg = load_config(overrides=overrides)
    m = cfg.mapper
    assert (m.resolution, m.max_laser_range) == (0.05, 20.0)
    assert (m.minimum_travel_distance, m.minimum_travel_heading) == (0.5, 0.5)
    assert (m.loop_search_maximum_distance, m.loop_match_minimum_chain_size) == (3.0, 10)
    assert m.loop_search_space_dimension == 8.0 and m.minimum_time_interval == 0.5
    why = reasons(rows, "slam_toolbox")
    assert "GTSAM" in why["solver_plugin"] and "GTSAM" in why["ceres_loss_function"]
    assert "`map` or `localize`" in why["mode"]


def test_nav2_params_map_costmap_rpp_smoother_collision_monitor_and_amcl():
    overrides, rows = load_ros_params([NAV2])
    cfg = load_config(overrides=overrides)
    assert (cfg.costmap.inflation_radius, cfg.costmap.cost_scaling_factor) == (0.55, 3.0)
    assert cfg.costmap.robot_radius == 0.22 and cfg.costmap.obstacle_max_range == 2.5
    assert cfg.follower.desired_linear_vel == 0.5 and cfg.follower.lookahead_dist == 0.6
    assert cfg.follower.controller_frequency == 20.0 and cfg.follower.xy_goal_tolerance == 0.25
    assert cfg.smoother.max_velocity == (0.26, 0.0, 1.0)
    assert cfg.smoother.max_decel == (-2.5, 0.0, -3.2)
    assert cfg.collision_monitor.slowdown_ratio == 0.3
    assert (cfg.localizer.alpha1, cfg.localizer.update_min_d) == (0.2, 0.25)
    assert cfg.planner.tolerance == 0.5 and cfg.planner.allow_unknown is True
    assert "particle filter" in reasons(rows, "amcl")["max_particles"]
    assert "local_costmap not used" in reasons(rows, "local_costmap")["robot_radius"]
    assert "ROS graph" in reasons(rows, "/**")["use_sim_time"]
    assert "no rgbdnav counterpart" in reasons(rows, "bt_navigator")["(5 keys)"]
    table = format_table(rows)
    assert "applied  global_costmap.inflation_layer.inflation_radius = 0.55 -> costmap." in table
    assert "ignored  amcl: alpha5, " in table


def test_a_dwb_controller_is_ignored_whole_and_a_wildcard_key_finds_its_section(tmp_path):
    path = tmp_path / "dwb.yaml"
    path.write_text(
        "/**:\n  ros__parameters:\n    frequency: 15.0\n"
        "controller_server:\n  ros__parameters:\n    FollowPath:\n"
        '      plugin: "dwb_core::DWBLocalPlanner"\n      max_vel_x: 0.26\n'
        "      xy_goal_tolerance: 0.25\n"
    )
    overrides, rows = load_ros_params([path])
    assert overrides == ["ekf.frequency=15.0"]
    why = reasons(rows, "controller_server")
    assert (
        "dwb_core::DWBLocalPlanner" in why["FollowPath.max_vel_x"]
        and "RPP" in why["FollowPath.max_vel_x"]
    )


def test_layers_config_files_then_ros_params_then_set(tmp_path):
    mine = tmp_path / "mine.yaml"
    mine.write_text("ekf:\n  frequency: 10.0\ncostmap:\n  inflation_radius: 0.3\n")
    overrides, _ = load_ros_params([EKF, NAV2])
    cfg = load_config([mine], [*overrides, "costmap.inflation_radius=0.7"])
    assert cfg.ekf.frequency == 30.0  # --ros-params over --config
    assert cfg.costmap.inflation_radius == 0.7  # --set over --ros-params


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "ekf_filter_node:\n  ros__parameters:\n    process_noise_covariance: "
            + str([0.1] * 100),
            "expected 15x15 = 225 values (or a 15-value diagonal), got 100",
        ),
        (
            "ekf_filter_node:\n  ros__parameters:\n    frequency: -5.0\n",
            "ekf.frequency: -5.0 Hz is out of range",
        ),
        (  # the fuzz test's find: a mutated list read as a string
            "ekf_filter_node:\n  ros__parameters:\n    process_noise_covariance: 0.05, 0.0]\n",
            "process_noise_covariance: expected a list of numbers, got '0.05, 0.0]'",
        ),
        ("ekf:\n  frequency: 30\n", "no 'ros__parameters' block"),
        ("ekf_filter_node:\n  ros__parameters: [1, 2]\n", "ros__parameters is not a mapping"),
    ],
)
def test_bad_parameter_files_are_one_error_naming_the_file(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        load_ros_params([path])
    assert str(path) in str(err.value)


def write_odom_bag(path: Path) -> None:
    with write_bag(path, "mcap") as bag:
        for k in range(20):
            t = T0 + k * 100 * MS
            bag.write("/odom", "nav_msgs/msg/Odometry", t, bag.odometry(t, 0.05 * k, 0.0, 0.0))


def test_cli_odometry_with_robot_localizations_file(tmp_path):
    bag = tmp_path / "odom_bag"
    write_odom_bag(bag)
    runner = CliRunner()
    # As shipped, the file names example/odom and example/imu: the bag has neither.
    result = runner.invoke(
        app, ["odometry", str(bag), "-o", str(tmp_path / "a"), "-q", "--ros-params", str(EKF)]
    )
    assert result.exit_code == 1
    assert "error: " in result.output and "odom topic /example/odom is not in the bag" in (
        result.output
    )
    mine = tmp_path / "ekf.yaml"
    text = EKF.read_text().replace("example/odom\n", "odom\n").replace("imu0: example/imu", "")
    mine.write_text(text.replace("imu0_config", "imu1_config"))
    out = tmp_path / "b"
    result = runner.invoke(
        app,
        [
            "odometry",
            str(bag),
            "-o",
            str(out),
            "-q",
            "--ros-params",
            str(mine),
            "--set",
            "ekf.imu0_config=[" + ",".join(["false"] * 15) + "]",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "ros-params: " in result.output and "-> ekf.process_noise_covariance" in result.output
    config = (out / "config.yaml").read_text()
    assert "odom: /odom" in config and "frequency: 30.0" in config
    assert (out / "summary.json").is_file()
