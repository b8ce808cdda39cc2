"""The live run's nav-driven auto mode (rgbdnav.live.nav) and its bounded bookkeeping
(rgbdnav.live.stats), on hand-built maps and a perfect unicycle: no simulator process."""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rgbdnav.config import Config
from rgbdnav.live.nav import LiveNavigator, MapSnapshot, near_edge
from rgbdnav.live.stats import FrameWindows, Reservoir, Timeline, TrackWriter, tame_malloc
from sensors.types import LaserScan
from slam.occupancy_grid import GridGeometry, OccupancyGrid

RES = 0.05  # [m/cell]
DT_NS = 100_000_000  # [ns] the live controller's 10 Hz


def two_rooms() -> OccupancyGrid:
    """6 m x 4 m, outer walls, and a wall at x = 3 m with a 1 m door at y = 2.5 .. 3.5 m."""
    g = GridGeometry(RES, 0.0, 0.0, 120, 80)
    v = np.zeros(g.shape, dtype=np.int8)
    v[:2, :] = v[-2:, :] = v[:, :2] = v[:, -2:] = 100
    v[:, 59:61] = 100
    v[50:70, 59:61] = 0  # the door
    return OccupancyGrid.from_occupancy_values(g, v)


def drive(
    nav: LiveNavigator, pose: np.ndarray, seconds: float, walls: np.ndarray
) -> tuple[np.ndarray, float]:
    """A perfect unicycle under the navigator's commands; (final pose, least wall clearance)."""
    wall_xy = np.argwhere(walls)[:, ::-1] * RES + RES / 2  # cell centres (x, y)
    least = math.inf
    t = 0
    for _ in range(int(seconds * 1e9 / DT_NS)):
        v, w = nav.tick(t, pose)
        dt = DT_NS / 1e9
        pose = pose + np.array(
            [
                v * dt * math.cos(pose[2] + w * dt / 2),
                v * dt * math.sin(pose[2] + w * dt / 2),
                w * dt,
            ]
        )
        least = min(least, float(np.hypot(*(wall_xy - pose[:2]).T).min()))
        t += DT_NS
        if nav.done:
            break
    return pose, least


def test_the_navigator_plans_through_the_door_and_reaches_every_waypoint() -> None:
    grid = two_rooms()
    route = np.array([[4.5, 1.0], [4.5, 3.2], [1.0, 3.0]])
    nav = LiveNavigator(
        Config(),
        route,
        np.array([1.0, 1.0, 0.0]),
        static_map=(grid, 0.65, 0.25),
        plan_in_thread=False,
    )
    pose, least = drive(nav, np.array([1.0, 1.0, 0.0]), 150.0, grid.occupied_mask())
    assert nav.done and nav.counts["waypoints_reached"] == 3
    assert not any(k.startswith("waypoints_skipped") for k in nav.counts)
    assert math.hypot(*(pose[:2] - route[-1])) <= Config().follower.xy_goal_tolerance
    # The footprint (0.23 m) never touched a wall; the door leaves 0.27 m each side of centre.
    assert least > Config().costmap.robot_radius
    # Speeds stayed within the live limits (the smoother clamps to live.max_*).
    assert nav.cfg.smoother.max_velocity[0] == pytest.approx(Config().live.max_linear_speed)


def test_an_unreachable_waypoint_is_skipped_and_the_route_goes_on() -> None:
    grid = two_rooms()
    route = np.array([[3.0, 1.0], [1.0, 3.0]])  # the first is inside the wall
    cfg = replace(Config(), live=replace(Config().live, waypoint_timeout=20.0))
    nav = LiveNavigator(
        cfg, route, np.array([1.0, 1.0, 0.0]), static_map=(grid, 0.65, 0.25), plan_in_thread=False
    )
    drive(nav, np.array([1.0, 1.0, 0.0]), 120.0, grid.occupied_mask())
    assert nav.done and nav.counts["waypoints_reached"] == 1
    skipped = nav.counts["waypoints_skipped_no_plan"] + nav.counts["waypoints_skipped_timeout"]
    assert skipped == 1


def test_while_mapping_unknown_space_is_traversable_and_snapshots_become_costmaps() -> None:
    nav = LiveNavigator(Config(), np.array([[3.0, 0.0]]), np.zeros(3), plan_in_thread=False)
    nav.start()
    try:
        # Nothing mapped yet: the plan goes straight through unknown space.
        v, w = nav.tick(0, np.zeros(3))
        assert nav.path is not None and nav.counts["nav_plans"] == 1
        # Keyframes seeing a wall 2 m ahead: the builder thread turns them into a static layer.
        angles = np.linspace(-0.5, 0.5, 101)
        ranges = (2.0 / np.cos(angles)).astype(np.float32)
        scan = LaserScan(1, float(angles[0]), float(angles[1] - angles[0]), ranges, 0.45, 4.0)
        nav.set_map(MapSnapshot(np.zeros((5, 3)), (scan,) * 5))
        deadline = time.monotonic() + 10.0
        while nav.counts["nav_map_builds"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        nav.tick(DT_NS, np.zeros(3))  # installs it
        assert int(nav.costmap.cost_at(2.0, 0.0)) == 254  # the wall is lethal
        assert int(nav.costmap.cost_at(1.0, 0.0)) == 0  # seen free
        assert int(nav.costmap.cost_at(-1.0, 0.0)) == 255  # behind: still unknown
        # A new keyframe only: integrated into the last grid; a moved one (a loop closure): all.
        for poses, incremental in ((np.zeros((6, 3)), 1), (np.full((7, 3), 0.2), 1)):
            builds = nav.counts["nav_map_builds"]
            nav.set_map(MapSnapshot(poses, (scan,) * len(poses)))
            deadline = time.monotonic() + 10.0
            while nav.counts["nav_map_builds"] == builds and time.monotonic() < deadline:
                time.sleep(0.01)
            assert nav.counts["nav_map_builds_incremental"] == incremental
    finally:
        nav.close()


def test_a_snapshot_that_cannot_be_integrated_is_counted_and_the_builder_goes_on() -> None:
    nav = LiveNavigator(Config(), np.array([[3.0, 0.0]]), np.zeros(3), plan_in_thread=False)
    nav.start()
    try:
        angles = np.linspace(-0.5, 0.5, 101)
        scan = LaserScan(
            1,
            float(angles[0]),
            float(angles[1] - angles[0]),
            (2.0 / np.cos(angles)).astype(np.float32),
            0.45,
            4.0,
        )
        nav.set_map(MapSnapshot(np.zeros((3, 3)), (scan,) * 5))  # 3 poses for 5 scans
        deadline = time.monotonic() + 10.0
        while nav.counts["nav_map_build_errors"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert nav.counts["nav_map_build_errors"] == 1 and nav.counts["nav_map_builds"] == 0
        nav.set_map(MapSnapshot(np.zeros((5, 3)), (scan,) * 5))  # a good one still builds
        deadline = time.monotonic() + 10.0
        while nav.counts["nav_map_builds"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert nav.counts["nav_map_builds"] == 1
    finally:
        nav.close()


def test_the_costmap_grows_when_the_robot_nears_its_edge() -> None:
    nav = LiveNavigator(Config(), np.array([[1.0, 0.0]]), np.zeros(3), plan_in_thread=False)
    far = np.array([30.0, 0.0, 0.0])
    assert near_edge(nav.geometry, far[None, :2], 1.0)
    nav.tick(0, far)
    assert not near_edge(nav.geometry, far[None, :2], 1.0)
    assert nav.counts["nav_costmap_regrown"] == 1


def test_a_reservoir_keeps_a_bounded_uniform_sample_with_exact_count_and_max() -> None:
    r = Reservoir(1000, seed=0)
    values = np.arange(100_000, dtype=float)
    for v in values:
        r.add(v)
    assert len(r.values()) == 1000 and r.count == 100_000 and r.max == 99_999
    assert r.percentile(50) == pytest.approx(50_000, rel=0.05)
    assert r.percentile(99) == pytest.approx(99_000, rel=0.01)


def test_a_track_is_streamed_in_full_and_thinned_in_memory(tmp_path: Path) -> None:
    tw = TrackWriter(tmp_path / "t.tum", spacing_m=0.05, capacity=100)
    n = 5000
    for k in range(n):  # 0.01 m steps: 50 m
        tw.add(10**9 + k * 10**7, 0.01 * k, 0.0, 0.1)
    tw.close()
    back = tw.load()
    assert len(back) == n and back[-1, 1] == pytest.approx(0.01 * (n - 1))
    assert back[0, 3] == pytest.approx(0.1) and int(back[1, 0]) == 10**9 + 10**7
    assert len(tw.thinned()) < 100


def test_a_streamed_track_reaches_the_file_before_it_is_closed(tmp_path: Path) -> None:
    # A kill -9 never reaches close(): the first row and every second's rows are flushed.
    tw = TrackWriter(tmp_path / "t.tum", spacing_m=0.05)
    tw.add(10**9, 1.0, 2.0, 0.0)
    on_disk = np.loadtxt(tmp_path / "t.tum", comments="#", ndmin=2)
    assert len(on_disk) == 1 and on_disk[0, 1] == pytest.approx(1.0)
    tw._flushed_at -= 2.0  # a second and more later
    tw.add(2 * 10**9, 3.0, 2.0, 0.0)
    assert len(np.loadtxt(tmp_path / "t.tum", comments="#", ndmin=2)) == 2
    tw.close()


def test_a_timeline_halves_instead_of_growing() -> None:
    tl = Timeline(capacity=64)
    for k in range(10_000):
        tl.add(float(k), 1.0)
    assert len(tl.points) < 64 and tl.points[0][0] == 0.0


def test_frame_windows_keep_cumulative_counts_and_each_windows_p99() -> None:
    fw = FrameWindows(capacity=8)
    for ms in range(1, 101):  # 1..100 ms in the first window
        fw.add(float(ms))
    fw.sample(5.0, processed=100, dropped=0)
    fw.sample(10.0, processed=100, dropped=3)  # nothing processed, 3 dropped meanwhile
    fw.add(400.0)
    fw.sample(15.0, processed=101, dropped=3)
    assert fw.points[0] == (5.0, [100, 0, 99.01])
    assert fw.points[1] == (10.0, [100, 3, None])
    assert fw.points[2] == (15.0, [101, 3, 400.0])
    for k in range(4, 100):  # halved, never longer than capacity; the counts stay cumulative
        fw.sample(5.0 * k, processed=101 + k, dropped=3 + k)
    assert len(fw.points) < 8 and fw.points[-1] == (495.0, [200, 102, None])  # the run's totals


def test_with_the_planner_on_its_own_thread_the_tick_never_waits_for_a_plan() -> None:
    grid = two_rooms()
    nav = LiveNavigator(
        Config(), np.array([[4.5, 1.0]]), np.array([1.0, 1.0, 0.0]), static_map=(grid, 0.65, 0.25)
    )
    nav.start()
    try:
        pose = np.array([1.0, 1.0, 0.0])
        assert nav.tick(0, pose) == (0.0, 0.0) and nav.path is None  # asked, not waited for
        deadline = time.monotonic() + 10.0
        t = 0
        while nav.path is None and time.monotonic() < deadline:
            time.sleep(0.01)
            t += DT_NS
            nav.tick(t, pose)
        assert nav.path is not None and nav.counts["nav_plans"] == 1
    finally:
        nav.close()


def test_malloc_is_tamed_on_glibc_and_left_alone_when_asked() -> None:
    import platform

    assert tame_malloc(0, 0) is False  # nothing asked: nothing done
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert tame_malloc(8, 32 << 20) is True  # glibc's own limits: harmless to the suite


def test_a_keepout_mask_closes_the_door_in_every_costmap_the_navigator_installs() -> None:
    from nav.costmap import LETHAL

    grid = two_rooms()
    zone_geom = GridGeometry(RES, 2.8, 2.4, 8, 24)  # over the door (x 2.8-3.2, y 2.4-3.6)
    zone = OccupancyGrid.from_occupancy_values(zone_geom, np.full(zone_geom.shape, 100, np.int8))
    nav = LiveNavigator(
        Config(),
        np.array([[4.5, 3.0]]),
        np.array([1.0, 1.0, 0.0]),
        static_map=(grid, 0.65, 0.25),
        plan_in_thread=False,
        keepout=zone,
    )

    def door_cost() -> int:
        r, c = nav.geometry.world_to_cell(3.0, 3.0)
        return int(nav.nav.costmap.master()[r, c])

    assert door_cost() == LETHAL
    nav.tick(0, np.array([30.0, 1.0, 0.0]))  # far out: a new, larger costmap
    assert nav.counts["nav_costmap_regrown"] == 1 and door_cost() == LETHAL
    free = LiveNavigator(
        Config(),
        np.array([[4.5, 3.0]]),
        np.array([1.0, 1.0, 0.0]),
        static_map=(grid, 0.65, 0.25),
        plan_in_thread=False,
    )
    r, c = free.geometry.world_to_cell(3.0, 3.0)
    assert int(free.nav.costmap.master()[r, c]) < LETHAL  # the open door without the mask
