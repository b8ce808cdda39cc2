"""`rgbdnav navigate` as a user meets it: a 6 m x 4 m room with a box the map does not know about,
goals driven in order in the kinematic simulation, a goal in a wall or a keepout zone refused with
a reason while the run goes on, and a missing map ending in one line."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from nav.navigator import past_escape
from rgbdnav.cli import GOAL_FAILED_EXIT, app, parse_goals
from rgbdnav.nav_charts import accelerations
from sensors.sim.scan import cast_scan, depth_range_sigma
from sensors.sim.world import FloorPlan, floor_plan, load_world, world_from_dict
from sensors.tum import load_tum_trajectory
from sensors.types import ConfigError
from slam.map_bundle import save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid

runner = CliRunner()
BOX_CENTRE = (3.0, 2.0)  # [m] the box the map does not have
BOX_HALF = 0.3  # [m]
ROBOT_RADIUS = 0.23  # [m] costmap.robot_radius default
ROOM = {
    "name": "room",
    "wall_thickness": 0.1,
    "walls": [
        {"from": [0, 0], "to": [6, 0]},
        {"from": [6, 0], "to": [6, 4]},
        {"from": [6, 4], "to": [0, 4]},
        {"from": [0, 4], "to": [0, 0]},
    ],
    "start": [1.0, 2.0, 0.0],
    "route": [[5.0, 2.0]],
}


def _grid(plan: FloorPlan, values: np.ndarray) -> OccupancyGrid:
    h, w = plan.occupied.shape
    return OccupancyGrid.from_occupancy_values(
        GridGeometry(plan.resolution, plan.origin_x, plan.origin_y, w, h), values
    )


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """world.yaml (room + box), map.yaml (room only: the box is unknown to the navigator) and a
    keepout mask over the top-right corner."""
    d = tmp_path_factory.mktemp("room")
    (d / "bare.yaml").write_text(yaml.safe_dump(ROOM))
    world = dict(
        ROOM,
        furniture=[
            {"name": "box", "center": list(BOX_CENTRE), "size": [2 * BOX_HALF, 2 * BOX_HALF, 0.8]}
        ],
    )
    (d / "world.yaml").write_text(yaml.safe_dump(world))
    # The map's walls are one cell thick, as a scan-built map's are (the world's are 0.1 m).
    (d / "thin.yaml").write_text(yaml.safe_dump(dict(ROOM, wall_thickness=0.01)))
    plan = floor_plan(load_world(d / "thin.yaml"))
    save_map_yaml(_grid(plan, np.where(plan.occupied, 100, 0)), d / "map.yaml")
    x, y = (
        c.ravel()
        for c in np.meshgrid(
            plan.origin_x + (np.arange(plan.occupied.shape[1]) + 0.5) * plan.resolution,
            plan.origin_y + (np.arange(plan.occupied.shape[0]) + 0.5) * plan.resolution,
        )
    )
    keep = ((x > 4.5) & (y > 2.8)).reshape(plan.occupied.shape)
    save_map_yaml(_grid(plan, np.where(keep, 100, 0)), d / "keepout.yaml")
    return {"world": d / "world.yaml", "map": d / "map.yaml", "keepout": d / "keepout.yaml"}


def _navigate(scene: dict[str, Path], out: Path, *args: str) -> tuple[int, str, dict]:
    result = runner.invoke(
        app,
        [
            "navigate",
            "--map",
            str(scene["map"]),
            "--sim",
            str(scene["world"]),
            "--out",
            str(out),
            "-q",
            *args,
        ],
    )
    summary = {}
    if (out / "summary.json").is_file():
        summary = json.loads((out / "summary.json").read_text())
    return result.exit_code, result.output, summary


def test_two_goals_are_reached_around_a_box_missing_from_the_map(
    scene: dict[str, Path], tmp_path: Path
) -> None:
    # Facing away from the box at the start, the first plan runs straight through it; the camera
    # sees it once the robot turns, and the path is replanned around it.
    code, output, summary = _navigate(
        scene,
        tmp_path,
        "--localization",
        "groundtruth",
        "--start",
        "1.0",
        "2.0",
        str(math.pi),
        "--goal",
        "5.0,2.0",
        "--goal",
        "1.0,3.0",
    )
    assert code == 0, output
    assert "2/2 goals reached" in output
    assert [g["status"] for g in summary["goals"]] == ["reached", "reached"]
    assert summary["goals"][0]["replans"] >= 1
    for g in summary["goals"]:
        assert g["final_error_m"] <= 0.25 + 1e-6  # follower.xy_goal_tolerance
    assert summary["collisions"]["events"] == 0
    assert summary["collisions"]["min_clearance_m"] >= ROBOT_RADIUS
    assert summary["localization"]["mode"] == "groundtruth"
    assert summary["localization"]["position_error_m"]["max"] == 0.0
    for name in (
        "trajectory.tum",
        "estimated.tum",
        "commands.csv",
        "summary.json",
        "map.png",
        "velocity.png",
        "config.yaml",
    ):
        assert (tmp_path / name).is_file(), name
    _, xyz, _ = load_tum_trajectory(tmp_path / "trajectory.tum")
    x, y = xyz[:, 0], xyz[:, 1]
    d_box = np.hypot(x - BOX_CENTRE[0], y - BOX_CENTRE[1])
    assert d_box.min() > BOX_HALF + ROBOT_RADIUS - 0.05  # went around, not through
    assert summary["path_length_m"] == pytest.approx(
        float(np.hypot(np.diff(x), np.diff(y)).sum()), abs=0.01
    )
    with open(tmp_path / "commands.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(x)
    smoothed = np.array([float(r["smoothed_v_mps"]) for r in rows])
    assert np.abs(np.diff(smoothed)).max() <= 2.5 * 0.05 + 1e-6  # smoother.max_accel * period
    assert abs(smoothed[-1]) < 1e-2  # at rest at the end


def test_the_localiser_in_the_loop_drives_on_wheel_odometry_and_scan_matching(
    scene: dict[str, Path], tmp_path: Path
) -> None:
    # Default mode: the navigator only has T_map_odom from the localiser and the encoder counts
    # the board emulator reports; the wheels slip and their diameters differ from nominal.
    code, output, summary = _navigate(
        scene,
        tmp_path,
        "--start",
        "1.0",
        "2.0",
        str(math.pi),
        "--goal",
        "5.0,2.0",
        "--goal",
        "1.0,3.0",
    )
    assert code == 0, output
    assert "(localizer localisation)" in output
    loc = summary["localization"]
    assert loc["mode"] == "localizer" and "wheel odometry" in loc["description"]
    assert loc["scans"]["tracking"] >= 0.9 * summary["scans"]
    assert 0.0 < loc["position_error_m"]["max"] < 0.3  # not the truth, but close to it
    assert loc["heading_error_deg"]["max"] < 10.0
    assert summary["counts"]["reached"] == 2
    for g in summary["goals"]:  # reached by the estimate: the truth is off by at most its error
        assert g["estimated_error_m"] <= 0.25 + 1e-6
        assert g["final_error_m"] <= 0.25 + loc["position_error_m"]["max"] + 1e-3
    assert summary["collisions"]["events"] == 0
    assert summary["gospd_lines"] > 10
    # The navigate profile's localiser settings were in force (config/profiles/navigate.yaml).
    resolved = yaml.safe_load((tmp_path / "config.yaml").read_text())["localizer"]
    assert resolved["match_gate"] == 3.0 and resolved["kidnap_check_ratio"] == 0.0
    _, true_xyz, _ = load_tum_trajectory(tmp_path / "trajectory.tum")
    _, est_xyz, _ = load_tum_trajectory(tmp_path / "estimated.tum")
    err = np.hypot(*(true_xyz[:, :2] - est_xyz[:, :2]).T)
    assert float(err.max()) == pytest.approx(loc["position_error_m"]["max"], abs=1e-3)
    with open(tmp_path / "commands.csv") as f:
        rows = list(csv.DictReader(f))
    # the smoothed twist is what went to the board, as GOSPD wheel speeds [positions/s]
    m_per_pos = math.pi * 0.1524 / 36
    for r in rows[::25]:
        v, w = float(r["smoothed_v_mps"]), float(r["smoothed_w_radps"])
        assert int(r["gospd_left"]) == pytest.approx((v - 0.15 * w) / m_per_pos, abs=0.51)
        assert int(r["gospd_right"]) == pytest.approx((v + 0.15 * w) / m_per_pos, abs=0.51)


def test_waypoint_pause_waits_at_each_reached_goal(scene: dict[str, Path], tmp_path: Path) -> None:
    code, output, summary = _navigate(
        scene,
        tmp_path,
        "--localization",
        "groundtruth",
        "--waypoint-pause",
        "2",
        "--goal",
        "2.0,1.0",
    )
    assert code == 0, output
    (goal,) = summary["goals"]
    assert goal["status"] == "reached" and goal["task"] == "wait"
    with open(tmp_path / "commands.csv") as f:
        t = [float(r["t_s"]) for r in csv.DictReader(f) if r["status"] == "behavior:wait"]
    assert t[-1] - t[0] == pytest.approx(2.0, abs=0.1)


def test_navigate_with_rrd_logs_plan_paths_map_and_costmap(
    scene: dict[str, Path], tmp_path: Path
) -> None:
    rrd = tmp_path / "nav.rrd"
    code, output, _ = _navigate(
        scene, tmp_path, "--localization", "groundtruth", "--rrd", str(rrd), "--goal", "2.0,1.0"
    )
    assert code == 0, output
    data = rrd.read_bytes()
    for path in (
        b"world/plan",
        b"world/truth",
        b"world/robot/trajectory",
        b"world/map",
        b"world/costmap",
    ):
        assert path in data, path


@pytest.mark.parametrize(
    ("option", "match"),
    [
        (["--localization", "amcl"], "--localization must be one of groundtruth, localizer"),
        (["--waypoint-pause", "-1"], "--waypoint-pause must be >= 0"),
        (["--goal-timeout", "0"], "need --goal-timeout > 0"),
    ],
)
def test_a_bad_navigate_setting_is_a_one_line_error(
    scene: dict[str, Path], tmp_path: Path, option: list[str], match: str
) -> None:
    code, output, _ = _navigate(scene, tmp_path / "run", *option, "--goal", "2.0,1.0")
    assert code == 1
    assert match in output and len(output.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_a_goal_in_a_wall_is_refused_and_the_run_goes_on(
    scene: dict[str, Path], tmp_path: Path
) -> None:
    code, output, summary = _navigate(scene, tmp_path, "--goal", "0.0,2.0", "--goal", "1.5,1.0")
    assert code == GOAL_FAILED_EXIT, output  # a goal not reached
    first, second = summary["goals"]
    assert first["status"] == "refused"
    assert "wall" in first["reason"]
    assert "refused: goal (0.00, 2.00) is in a wall" in output
    assert second["status"] == "reached"
    assert summary["counts"] == {"reached": 1, "failed": 0, "refused": 1, "skipped": 0}


def test_a_goal_in_a_keepout_zone_is_refused(scene: dict[str, Path], tmp_path: Path) -> None:
    code, output, summary = _navigate(
        scene, tmp_path, "--keepout", str(scene["keepout"]), "--goal", "5.2,3.3"
    )
    assert code == GOAL_FAILED_EXIT, output  # a goal not reached
    (goal,) = summary["goals"]
    assert goal["status"] == "refused"
    assert "keepout" in goal["reason"]
    assert summary["path_length_m"] == pytest.approx(0.0, abs=1e-9)  # never moved


def test_a_missing_map_is_a_one_line_error(scene: dict[str, Path], tmp_path: Path) -> None:
    result = runner.invoke(
        app,
        [
            "navigate",
            "--map",
            str(tmp_path / "nope.yaml"),
            "--sim",
            str(scene["world"]),
            "--out",
            str(tmp_path / "run"),
            "-q",
            "--goal",
            "1,1",
        ],
    )
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "no such map" in lines[0]
    assert not (tmp_path / "run").exists()


def test_goal_arguments_are_pairs_of_numbers() -> None:
    assert parse_goals(["1,-2.5", "3e0,4"]) == [(1.0, -2.5), (3.0, 4.0)]
    # the deprecated navigate form `--goal X Y`: the Y arrives as an extra argument
    assert parse_goals(["1", "3e0"], ["-2.5", "4"]) == [(1.0, -2.5), (3.0, 4.0)]
    with pytest.raises(ConfigError, match="expected X,Y"):
        parse_goals(["1"])
    with pytest.raises(ConfigError, match="expected X,Y"):
        parse_goals(["1,2,3"])
    with pytest.raises(ConfigError, match="unexpected argument '--gaol'"):
        parse_goals(["1,2"], ["--gaol", "1,2"])


def test_old_goal_form_still_drives_with_a_deprecation_warning(
    scene: dict[str, Path], tmp_path: Path
) -> None:
    code, output, summary = _navigate(scene, tmp_path, "--goal", "1.5", "1.0")
    assert code == 0, output
    assert "--goal X Y is deprecated" in output and "1.5,1.0" in output
    assert summary["goals"][0]["goal"] == [1.5, 1.0]


def test_a_mistyped_option_is_an_error_not_ignored(scene: dict[str, Path], tmp_path: Path) -> None:
    code, output, _ = _navigate(scene, tmp_path / "run", "--goal", "1.5,1.0", "--gaol", "2,2")
    assert code == 1
    assert "unexpected argument '--gaol'" in output
    assert not (tmp_path / "run").exists()


def test_cast_scan_returns_the_wall_distance() -> None:
    occupied = np.zeros((40, 40), dtype=bool)
    occupied[:, 30] = True  # a wall at x = 3.0 .. 3.1 m
    plan = FloorPlan(occupied, 0.1, 0.0, 0.0)
    angles = np.array([-0.3, 0.0, 0.3])
    r = cast_scan(plan, np.array([1.0, 2.0, 0.0]), angles, 0.5, 4.5)
    np.testing.assert_allclose(r, 2.0 / np.cos(angles), atol=0.06)  # half a cell of marching
    assert np.isinf(cast_scan(plan, np.array([1.0, 2.0, math.pi]), angles, 0.5, 4.5)).all()
    assert np.isnan(cast_scan(plan, np.array([2.8, 2.0, 0.0]), angles[1:2], 0.5, 4.5)).all()


def test_a_door_blocked_by_an_unmapped_box_fails_after_clearing_recoveries(
    tmp_path: Path,
) -> None:
    # A wall across the room at x = 3 with one door; the world has a box in the door the map
    # does not. Each replan fails on the seen box, Nav2's recovery round starts by clearing the
    # costmap, the plan goes through the door again, the camera sees the box again...
    wall = {"from": [3, 0], "to": [3, 4], "doors": [{"at": 2.0, "width": 1.0}]}
    bare = dict(ROOM, walls=[*ROOM["walls"], wall], wall_thickness=0.01)
    save_plan = floor_plan(world_from_dict(bare))
    save_map_yaml(_grid(save_plan, np.where(save_plan.occupied, 100, 0)), tmp_path / "map.yaml")
    world = dict(
        ROOM,
        walls=[*ROOM["walls"], wall],
        furniture=[{"name": "box", "center": [3.0, 2.0], "size": [0.5, 1.2, 0.8]}],
    )
    (tmp_path / "world.yaml").write_text(yaml.safe_dump(world))
    scene = {"map": tmp_path / "map.yaml", "world": tmp_path / "world.yaml"}
    code, output, summary = _navigate(
        scene,
        tmp_path / "run",
        "--localization",
        "groundtruth",
        "--max-replans",
        "2",
        "--goal",
        "5.0,2.0",
    )
    assert code == GOAL_FAILED_EXIT, output  # a goal not reached
    (goal,) = summary["goals"]
    assert goal["status"] == "failed"
    assert "gave up after 2 replans" in goal["reason"] or "replan failed" in goal["reason"]
    assert goal["recoveries"] and goal["recoveries"][0] == "clear_costmap"
    assert summary["collisions"]["events"] == 0
    _, xyz, _ = load_tum_trajectory(tmp_path / "run" / "trajectory.tum")
    assert xyz[:, 0].max() < 3.0 - 0.25 - ROBOT_RADIUS + 0.1  # never got through the door


def test_depth_noise_grows_with_the_square_of_the_range() -> None:
    sigma = depth_range_sigma(np.array([1.0, 2.0, 4.0]), 580.0, 0.075, 0.07, 8)
    sigma_d = math.sqrt(0.07**2 + (1 / 8) ** 2 / 12)  # [px]
    np.testing.assert_allclose(sigma, np.array([1.0, 4.0, 16.0]) * sigma_d / (580 * 0.075))
    assert 0.02 < sigma[2] < 0.04  # a few cm at 4 m, as a Kinect v1


def test_velocity_chart_accelerations_are_finite_differences() -> None:
    t = np.array([0.0, 0.05, 0.1, 0.1, 0.2])
    v = np.array([0.0, 0.1, 0.3, 0.3, 0.3])
    tm, a = accelerations(t, v)
    np.testing.assert_allclose(tm, [0.025, 0.075, 0.15])  # the zero-length interval is dropped
    np.testing.assert_allclose(a, [2.0, 4.0, 0.0])


def _jumpy_localizer(jump_from: int, jump_to: int) -> type:
    """A Localizer whose answers number jump_from .. jump_to (1-based) claim to be tracking
    with map -> odom 3 m away."""
    import dataclasses

    from slam.localization import Localizer

    class Jumpy(Localizer):
        calls = 0

        def update(self, scan, odom_pose):  # type: ignore[no-untyped-def]
            r = super().update(scan, odom_pose)
            Jumpy.calls += 1
            if jump_from <= Jumpy.calls <= jump_to:
                return dataclasses.replace(
                    r,
                    status="tracking",
                    reason="matched (icp)",
                    map_to_odom=r.map_to_odom + [3.0, 0.0, 0.0],
                )
            return r

    return Jumpy


def test_the_navigator_believes_what_the_localiser_tracks(
    scene: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Whether a far answer is a jump to take is the localiser's call (localizer.match_gate,
    # tested in tests/slam): the navigator does not second-guess a "tracking" answer.
    import rgbdnav.runners.navigate as navigate_run

    monkeypatch.setattr(navigate_run, "Localizer", _jumpy_localizer(8, 10_000))
    code, output, summary = _navigate(scene, tmp_path, "--goal-timeout", "3", "--goal", "3.0,1.0")
    assert code == GOAL_FAILED_EXIT, output  # a goal not reached
    loc = summary["localization"]
    assert loc["position_error_m"]["max"] > 2.5  # the navigator believes the (wrong) 3 m
    assert loc["tracking_jumps_confirmed"] == 0  # the real localiser never jumped


def test_a_lost_localiser_is_put_back_on_odometry_with_its_last_covariance(
    scene: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import dataclasses

    import rgbdnav.runners.navigate as navigate_run
    from slam.localization import Localizer

    seeds: list[np.ndarray | None] = []
    tracked: list[np.ndarray] = []  # covariance of each tracking answer

    class Dropping(Localizer):
        calls = 0

        def update(self, scan, odom_pose):  # type: ignore[no-untyped-def]
            r = super().update(scan, odom_pose)
            Dropping.calls += 1
            if Dropping.calls in (8, 9):
                return dataclasses.replace(r, status="lost", reason="lost (test)")
            tracked.append(r.covariance)
            return r

        def set_initial_pose(self, pose, covariance=None):  # type: ignore[no-untyped-def]
            seeds.append(None if covariance is None else np.array(covariance))
            super().set_initial_pose(pose, covariance)

    monkeypatch.setattr(navigate_run, "Localizer", Dropping)
    code, output, summary = _navigate(scene, tmp_path, "--goal", "3.0,1.0")
    assert code == 0, output
    loc = summary["localization"]
    assert loc["reseeded_from_odometry"] == 2
    # The start pose comes with the default covariance; both reseeds with the last tracked one,
    # not a search-window-wide one that would let the next match pull it anywhere.
    assert seeds[0] is None and len(seeds) == 3
    for cov in seeds[1:]:
        np.testing.assert_array_equal(cov, tracked[6])  # answer 7, the last before the drop
    assert loc["position_error_m"]["max"] < 0.3
    assert summary["goals"][0]["status"] == "reached"


def _biased_localizer(bias_m: float) -> type:
    """A Localizer whose tracking answers put the robot ``bias_m`` further along the map's x
    than its own estimate (as narrow matches of moved furniture can, scan after scan) until a
    settle's wide match (``match_recent``) has answered."""
    import dataclasses

    from slam.localization import Localizer

    class Biased(Localizer):
        settled = False

        def update(self, scan, odom_pose):  # type: ignore[no-untyped-def]
            r = super().update(scan, odom_pose)
            if Biased.settled or r.status != "tracking":
                return r
            shift = np.array([bias_m, 0.0, 0.0])
            return dataclasses.replace(r, pose=r.pose + shift, map_to_odom=r.map_to_odom + shift)

        def match_recent(self, n_scans):  # type: ignore[no-untyped-def]
            Biased.settled = True
            return super().match_recent(n_scans)

    return Biased


@pytest.mark.parametrize("settle", [True, False])
def test_a_goal_settle_turns_in_place_and_drives_on_to_the_corrected_goal(
    scene: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, settle: bool
) -> None:
    # The estimate is 0.3 m ahead of the truth when the goal checker (0.1 m) says "reached".
    # With the navigate profile's settle the robot turns in place, the wide match puts the
    # estimate back on the truth, and the next control cycle drives the last 0.3 m.
    import rgbdnav.runners.navigate as navigate_run

    monkeypatch.setattr(navigate_run, "Localizer", _biased_localizer(0.3))
    spin = "6.0" if settle else "0.0"
    code, output, summary = _navigate(
        scene,
        tmp_path,
        "--set",
        "follower.xy_goal_tolerance=0.1",
        "--set",
        f"navigate.goal_settle_spin={spin}",
        "--goal",
        "3.0,1.0",
    )
    assert code == 0, output
    goal = summary["goals"][0]
    assert goal["status"] == "reached" and goal["estimated_error_m"] <= 0.1 + 1e-6
    with open(tmp_path / "commands.csv") as f:
        statuses = {r["status"] for r in csv.DictReader(f)}
    if settle:
        assert len(goal["settles"]) == 1 and goal["settles"][0].startswith("wide match of")
        assert summary["localization"]["settles"] == 1
        assert "behavior:spin" in statuses
        assert goal["final_error_m"] < 0.2
    else:
        assert "settles" not in goal and "behavior:spin" not in statuses
        assert goal["final_error_m"] > 0.2  # the bias stays in the truth
    assert summary["collisions"]["events"] == 0


def test_a_run_of_gated_matches_while_driving_settles_then_replans(
    scene: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # navigate.settle_on_gated_scans (15 in the navigate profile): a localiser whose matches the
    # gate has held back that long disagrees with its scans; the robot settles on the way.
    import rgbdnav.runners.navigate as navigate_run
    from slam.localization import Localizer

    class Contested(Localizer):
        calls = 0

        def update(self, scan, odom_pose):  # type: ignore[no-untyped-def]
            Contested.calls += 1
            return super().update(scan, odom_pose)

        @property
        def gated_streak(self) -> int:
            return 15 if Contested.calls == 6 else 0  # the 6th scan, while driving

    monkeypatch.setattr(navigate_run, "Localizer", Contested)
    code, output, summary = _navigate(scene, tmp_path, "--goal", "5.0,2.0")
    assert code == 0, output
    goal = summary["goals"][0]
    assert goal["status"] == "reached"
    assert len(goal["settles"]) == 2  # on the way, then at the goal
    assert all(r.startswith("wide match of") for r in goal["settles"])
    assert summary["collisions"]["events"] == 0
    Contested.calls = 0  # the same disagreement, with settling while driving off
    code, output, summary = _navigate(
        scene, tmp_path / "off", "--set", "navigate.settle_on_gated_scans=0", "--goal", "5.0,2.0"
    )
    assert code == 0, output
    assert len(summary["goals"][0]["settles"]) == 1  # at the goal only


def test_past_escape_drops_only_the_leading_blocked_points() -> None:
    """The planner's way out of the inflated band is blocked by design: the navigator must not
    take it for a new obstacle, but a blocked point further on still counts."""
    xy = np.arange(12.0).reshape(6, 2)
    ok = np.array([False, False, True, True, False, True])
    np.testing.assert_array_equal(past_escape(xy, ok), xy[2:])
    np.testing.assert_array_equal(past_escape(xy, np.ones(6, dtype=bool)), xy)
    assert len(past_escape(xy, np.zeros(6, dtype=bool))) == 0


def test_replan_frequency_plans_again_while_driving(
    scene: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """navigate.replan_frequency (Nav2's rate-controlled ComputePathToPose): about one plan per
    simulated second on top of the event-driven ones, none of which counts as a replan."""
    from nav.planner import GridPlanner

    calls: list[int] = []
    plan = GridPlanner.plan

    def counting(self: GridPlanner, *args: object, **kwargs: object) -> object:
        calls.append(1)
        return plan(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(GridPlanner, "plan", counting)
    plans = {}
    for hz in (0.0, 1.0):
        calls.clear()
        code, output, summary = _navigate(
            scene,
            tmp_path / f"hz{hz:g}",
            "--localization",
            "groundtruth",
            "--set",
            f"navigate.replan_frequency={hz}",
            "--goal",
            "1.0,3.4",
        )
        assert code == 0, output
        (goal,) = summary["goals"]
        assert goal["status"] == "reached" and summary["collisions"]["events"] == 0
        plans[hz] = (len(calls), goal["replans"], goal["time_s"])
    n0, replans0, _ = plans[0.0]
    n1, replans1, t1 = plans[1.0]
    assert n1 - (1 + replans1) >= math.floor(t1) - 1 > 0
    assert n0 == 1 + replans0
