"""rgbdnav command line: parses, resolves config, dispatches, and maps known errors to one line.

Heavy modules (Open3D, OpenCV, GTSAM) are imported inside the commands that need them so that
``rgbdnav --help`` stays fast.
"""

from __future__ import annotations

import functools
import logging
import math
import sys
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from sensors.types import RgbdNavError

app = typer.Typer(
    name="rgbdnav",
    help="Map, localise and drive a differential-drive robot with an RGB-D camera, without ROS.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
log = logging.getLogger("rgbdnav")

ConfigOpt = Annotated[
    list[Path] | None,
    typer.Option("--config", "-c", help="YAML config file(s), applied in order over the defaults."),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", "-s", help="Override one key: section.key=value (YAML value)."),
]
Force3DofOpt = Annotated[
    bool,
    typer.Option(
        "--force-3dof",
        help="A source without wheels or /odom rides on a ground robot: planar VO (RTAB-Map's "
        "Reg/Force3DoF) and a 2-D map, instead of a handheld camera's 6-DoF poses.",
    ),
]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.")]
VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="Debug logging.")]
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Run directory to write.")]
SourceArg = Annotated[
    Path, typer.Argument(help="CARMEN log (.clf/.log[.gz]), recording folder, or world YAML.")
]
MapOpt = Annotated[Path, typer.Option("--map", "-m", help="Map bundle folder, or a Nav2 map.yaml.")]
WorldSeedOpt = Annotated[int, typer.Option(help="Seed when SOURCE is a world.")]
RrdOpt = Annotated[Path | None, typer.Option(help="Save a rerun recording (.rrd) of the run here.")]
ViewerOpt = Annotated[bool, typer.Option(help="Spawn the rerun viewer and stream the run to it.")]


def _known_errors(fn: Any) -> Any:
    """Known errors become one line on stderr and exit code 1, never a traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except RgbdNavError as err:
            typer.echo(f"error: {err}", err=True)
            raise typer.Exit(1) from None
        except OSError as err:  # unwritable --out, full disk, ...
            where = f"{err.filename}: " if err.filename else ""
            typer.echo(f"error: {where}{err.strerror or err}", err=True)
            raise typer.Exit(1) from None

    return wrapper


def _setup_logging(verbose: bool) -> None:
    from rich.console import Console
    from rich.logging import RichHandler

    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(message)s",
        handlers=[RichHandler(console=Console(stderr=True), show_time=False, show_path=False)],
        force=True,
    )


class _Progress:
    """A rich progress bar, or nothing with --quiet."""

    def __init__(self, description: str, quiet: bool) -> None:
        self.description, self.quiet = description, quiet
        self._bar: Any = None
        self._task: Any = None

    def __enter__(self) -> _Progress:
        if not self.quiet:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TimeRemainingColumn,
            )

            self._bar = Progress(
                "[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                TimeRemainingColumn(), transient=False,
            )  # fmt: skip
            self._bar.__enter__()
            self._task = self._bar.add_task(self.description, total=None)
        return self

    def __call__(self, done: int, total: int) -> None:
        if self._bar is not None:
            self._bar.update(self._task, completed=done, total=total)

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc)


def _is_world(path: Path) -> bool:
    return path.is_file() and path.suffix in (".yaml", ".yml")


def _recording_for(source: Path, cfg: Any, seed: int, quiet: bool) -> Path:
    """A recording folder as given, or the cached rendering of a world file (made if missing)."""
    from rgbdnav.cache import cached_recording_path
    from sensors.recording import Recording
    from sensors.sim.simulator import simulate

    if not source.exists():
        raise RgbdNavError(f"{source}: no such file or folder")
    if not _is_world(source):
        return source
    cached = cached_recording_path(source, cfg, seed)
    if cached.exists():
        try:
            Recording.open(cached)
            log.info("using cached rendering %s", cached)
            return cached
        except RgbdNavError as err:
            log.warning("cached rendering is unreadable (%s); rendering again", err)
    log.info("rendering %s (seed %d) into %s", source, seed, cached)
    with _Progress(f"rendering {source.stem}", quiet) as progress:
        simulate(source, cached, cfg.robot, cfg.camera, cfg.sim, seed=seed, progress=progress)
    return cached


def _echo_source(source: Path, recording: Path) -> None:
    rendered = f" (recording: {recording})" if recording != source else ""
    typer.echo(f"source      {source}{rendered}")


def _echo_outputs(outputs: dict[str, Path]) -> None:
    """One line per written file: what it is, where it is."""
    for label, path in outputs.items():
        typer.echo(f"{label:<11} {path}")


@app.command()
@_known_errors
def info(
    source_text: Annotated[
        str,
        typer.Argument(
            metavar="SOURCE", help="Recording, TUM folder, CARMEN log, bag, .oni, openni://, world."
        ),
    ],
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Say what a recording, log, bag or world holds: streams, counts, rates, duration, gaps."""
    source = Path(source_text)
    if _is_world(source):
        from sensors.sim.world import load_world

        world = load_world(source)
        walls = sum(b.name in ("wall", "lintel") for b in world.boxes)
        furniture = [b.name for b in world.boxes if b.name not in ("wall", "lintel")]
        typer.echo(f"world {world.name} ({source})")
        x0, y0, x1, y1 = world.bounds(margin=0.0)
        typer.echo(
            f"  extent        {x1 - x0:.1f} m x {y1 - y0:.1f} m, ceiling {world.ceiling_height} m"
        )
        typer.echo(f"  wall pieces   {walls}")
        typer.echo(f"  furniture     {len(furniture)}: {', '.join(furniture)}")
        typer.echo(f"  start         x={world.start[0]} y={world.start[1]} yaw={world.start[2]}")
        typer.echo(f"  route         {len(world.route)} waypoints, {world.route_length():.1f} m")
        return
    from rgbdnav.config import load_config, source_options
    from sensors.source import open_source
    from sensors.stream_stats import describe_source, format_stats_table

    src = open_source(source_text, source_options(load_config(config or [], set_ or [])))
    try:
        typer.echo(f"{source}: {src.describe()}")
        typer.echo(format_stats_table(describe_source(src)))
        if src.skipped:
            typer.echo(f"skipped while reading: {src.skipped}")
    finally:
        src.close()


@app.command()
@_known_errors
def simulate(
    world: Annotated[Path, typer.Argument(help="World YAML (see scenes/).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Recording folder to write.")],
    seed: Annotated[int, typer.Option(help="Random seed: same seed, same recording.")] = 0,
    duration: Annotated[float | None, typer.Option(help="Stop after this many seconds.")] = None,
    frames: Annotated[int | None, typer.Option(help="Stop after this many camera frames.")] = None,
    trajectory: Annotated[
        Path | None,
        typer.Option(help="Replay this TUM trajectory (z up, planar) instead of the route."),
    ] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    quiet: QuietOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    """Render a Kinect + wheel-encoder recording of a robot driving through a world."""
    _setup_logging(verbose)
    from rgbdnav.config import load_config
    from rgbdnav.run_dir import RunDir
    from sensors.sim.simulator import simulate as run_simulation

    if duration is not None and frames is not None:
        raise RgbdNavError("give --duration or --frames, not both")
    if frames is not None and frames < 1:
        raise RgbdNavError(f"--frames must be >= 1, got {frames}")
    if not world.is_file():
        raise RgbdNavError(f"{world}: no such world file")
    cfg = load_config(config or [], set_ or [])
    t0 = time.perf_counter()
    with _Progress(f"rendering {world.stem}", quiet) as progress:
        summary = run_simulation(world, out, cfg.robot, cfg.camera, cfg.sim, seed=seed,
                                 duration_s=duration, frames=frames, trajectory=trajectory,
                                 progress=progress)  # fmt: skip
    wall = time.perf_counter() - t0
    run = RunDir(out)
    run.write_config(cfg)
    run.write_summary({"command": "simulate", **summary.as_dict(), "wall_time_s": round(wall, 2),
                       "frames_per_s": round(summary.frames / wall, 2)})  # fmt: skip
    typer.echo(f"wrote {summary.frames} frames ({summary.path_length_m:.1f} m, "
               f"{summary.duration_s:.1f} s) to {out} in {wall:.1f} s")  # fmt: skip


@app.command()
@_known_errors
def odometry(
    source: Annotated[Path, typer.Argument(help="Recording folder, or a world YAML to render.")],
    out: OutOpt,
    seed: WorldSeedOpt = 0,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    vo: Annotated[bool, typer.Option(help="Run visual odometry on the RGB-D frames.")] = True,
    force_3dof: Force3DofOpt = False,
    quiet: QuietOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    """Wheel, visual and fused (EKF) odometry of a source, with drift against ground truth."""
    _setup_logging(verbose)
    from rgbdnav.commands.odometry import run_odometry
    from rgbdnav.config import load_config

    cfg = load_config(config or [], set_ or [])
    recording = _recording_for(source, cfg, seed, quiet)
    with _Progress("visual odometry", quiet or not vo) as progress:
        outputs = run_odometry(recording, out, config or [], set_ or [], vo, progress, force_3dof)
    _echo_source(source, recording)
    _echo_outputs(outputs)


@app.command("map")
@_known_errors
def map_(
    source: SourceArg,
    out: OutOpt,
    continue_: Annotated[
        Path | None,
        typer.Option("--continue", help="Map bundle to extend: relocalise in it, then map on."),
    ] = None,
    seed: WorldSeedOpt = 0,
    rrd: RrdOpt = None,
    viewer: ViewerOpt = False,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force_3dof: Force3DofOpt = False,
    quiet: QuietOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    """Pose-graph SLAM: trajectory, occupancy grid and a map bundle (Nav2 PGM/YAML + graph)."""
    _setup_logging(verbose)
    from rgbdnav.commands.map import run_map
    from rgbdnav.config import load_config

    cfg = load_config(config or [], set_ or [])
    recording = _recording_for(source, cfg, seed, quiet)
    with _Progress("mapping", quiet) as progress:
        outputs = run_map(
            recording, out, config or [], set_ or [], progress, continue_, rrd, viewer, force_3dof
        )
    _echo_source(source, recording)
    _echo_outputs(outputs)


@app.command()
@_known_errors
def localize(
    source: SourceArg,
    map_: MapOpt,
    out: OutOpt,
    initial_pose: Annotated[
        tuple[float, float, float] | None,
        typer.Option(
            "--initial-pose",
            metavar="X Y YAW",
            help="Start tracking here (map frame, m m rad); without it, relocalise globally.",
        ),
    ] = None,
    seed: WorldSeedOpt = 0,
    rrd: RrdOpt = None,
    viewer: ViewerOpt = False,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force_3dof: Force3DofOpt = False,
    gps: Annotated[
        Path | None,
        typer.Option(
            help="gps.txt fixes (t lat lon alt sigma_h) as the relocalisation prior; "
            "the map needs a geo.yaml. Default: the source's own NavSatFix/gps.txt."
        ),
    ] = None,
    quiet: QuietOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    """Localise against a saved map (no mapping): trajectory, per-scan status and confidence."""
    _setup_logging(verbose)
    from rgbdnav.commands.localize import describe, run_localize
    from rgbdnav.config import load_config
    from slam.map_bundle import load_map

    if _is_world(source):
        load_map(map_)  # refuse a bad map before spending minutes rendering the world
    cfg = load_config(config or [], set_ or [])
    recording = _recording_for(source, cfg, seed, quiet)
    with _Progress("localising", quiet) as progress:
        outputs, summary = run_localize(
            recording,
            map_,
            out,
            config or [],
            set_ or [],
            initial_pose,
            progress,
            rrd,
            viewer,
            force_3dof,
            gps,
        )
    _echo_source(source, recording)
    typer.echo(f"result      {describe(summary)}")
    _echo_outputs(outputs)


# Typer has no repeatable multi-value option, so `--goal X Y` pairs arrive as extra args.
@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
@_known_errors
def navigate(
    ctx: typer.Context,
    map_: MapOpt,
    sim: Annotated[Path, typer.Option("--sim", help="Simulator world YAML the robot drives in.")],
    out: OutOpt,
    start: Annotated[
        tuple[float, float, float] | None,
        typer.Option("--start", metavar="X Y YAW", help="True start pose (default: the world's)."),
    ] = None,
    keepout: Annotated[
        Path | None, typer.Option("--keepout", help="Keepout filter mask (Nav2 map.yaml).")
    ] = None,
    localization: Annotated[
        str | None,
        typer.Option(
            "--localization",
            help="localizer (scan-to-map + wheel odometry, the "
            "default) or groundtruth (the true simulated pose).",
        ),
    ] = None,
    goal_timeout: Annotated[
        float | None,
        typer.Option("--goal-timeout", help="Simulated seconds allowed per goal (default 60)."),
    ] = None,
    max_replans: Annotated[
        int | None, typer.Option("--max-replans", help="Replans per goal (default 5).")
    ] = None,
    waypoint_pause: Annotated[
        float | None,
        typer.Option("--waypoint-pause", help="Seconds to wait at each reached goal (default 0)."),
    ] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of wheel slip and depth noise.")] = 0,
    rrd: RrdOpt = None,
    viewer: ViewerOpt = False,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    quiet: QuietOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    """Drive to goals on a saved map in a simulated world (localiser or ground truth).

    Goals: --goal X Y [--goal X Y ...] in the map frame (metres), driven in order.
    --localization, --goal-timeout, --max-replans and --waypoint-pause override the navigate
    settings (nav.config.NavigateConfig).
    """
    _setup_logging(verbose)
    from rgbdnav.commands.navigate import describe, parse_goal_args, run_navigate

    goal = parse_goal_args(ctx.args)
    with _Progress("navigating", quiet) as progress:
        outputs, summary = run_navigate(map_, goal, sim, out, config or [], set_ or [], start,
                                        keepout, goal_timeout, max_replans, progress,
                                        localization=localization, seed=seed,
                                        waypoint_pause_s=waypoint_pause, rrd=rrd,
                                        viewer=viewer)  # fmt: skip
    typer.echo(f"result      {describe(summary)}")
    for g in summary["goals"]:
        if g["status"] != "reached":
            typer.echo(f"goal        ({g['goal'][0]:.2f}, {g['goal'][1]:.2f}) {g['status']}: "
                       f"{g['reason']}")  # fmt: skip
    _echo_outputs(outputs)


@app.command()
@_known_errors
def live(
    out: OutOpt,
    camera: Annotated[
        str, typer.Option(help="sim, or an OpenNI2 device: openni:// (first) / openni://URI.")
    ] = "sim",
    board: Annotated[
        str, typer.Option(help="sim, the board's serial port (/dev/ttyUSB0), or none.")
    ] = "sim",
    sim_world: Annotated[
        Path | None, typer.Option("--sim-world", help="World YAML for --camera/--board sim.")
    ] = Path("scenes/house.yaml"),
    map_: Annotated[
        Path | None,
        typer.Option("--map", "-m", help="Localise in this map bundle / map.yaml (no mapping)."),
    ] = None,
    duration: Annotated[
        float | None,
        typer.Option(
            help="Stop after this many seconds, counted from the first camera frame "
            "(default: Ctrl-C)."
        ),
    ] = None,
    drive: Annotated[
        str,
        typer.Option(
            help="route: drive the route/goals on the estimated pose (auto; "
            "through the nav stack, or straight at each waypoint with --set "
            "live.route_driver=direct); teleop: keyboard (manual; Tab "
            "switches to auto); idle: stay."
        ),
    ] = "route",
    goal: Annotated[
        list[str] | None,
        typer.Option(help="A waypoint X,Y for --drive route (repeat; default: the world's route)."),
    ] = None,
    rrd: RrdOpt = None,
    viewer: ViewerOpt = False,
    drill: Annotated[
        list[str] | None,
        typer.Option(
            help="Fault drill for the simulated robot, ACTION@SECONDS[:ARG]: "
            "unplug_board@5, replug_board@8, stall_camera@10:2."
        ),
    ] = None,
    repeat_route: Annotated[
        bool, typer.Option(help="Drive the route again and again (soak tests).")
    ] = False,
    seed: Annotated[int, typer.Option(help="Seed of the simulated robot.")] = 0,
    record: Annotated[
        Path | None,
        typer.Option(
            help="Also write what the robot saw (camera frames, encoder readings; the "
            "simulator's truth) as an rgbdnav recording in this folder, for "
            "`rgbdnav map` / `odometry` later."
        ),
    ] = None,
    initial_pose: Annotated[
        tuple[float, float, float] | None,
        typer.Option(
            "--initial-pose",
            metavar="X Y YAW",
            help="With --map: start tracking here (map frame, m m rad), as RViz's 2D Pose "
            "Estimate; without it the robot relocalises globally, which needs it to move.",
        ),
    ] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    quiet: QuietOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    """The live run on the robot (or the simulated robot): map, or localise with --map."""
    _setup_logging(verbose)
    from rgbdnav.live.run import Drill, LiveOptions, run_live
    from sensors.types import ConfigError

    goals = []
    for g in goal or []:
        try:
            x, y = (float(v) for v in g.split(","))
        except ValueError:
            raise ConfigError(f"--goal {g!r}: expected X,Y in metres, e.g. 4.5,1.5") from None
        goals.append((x, y))
    world = sim_world if "sim" in (camera, board) else None
    opts = LiveOptions(out=out, camera=camera, board=board, world=world,
                       config_files=config or [], overrides=set_ or [], map_bundle=map_,
                       duration_s=duration, drive=drive, goals=goals, rrd=rrd, viewer=viewer,
                       seed=seed, drills=[Drill.parse(d) for d in drill or []],
                       repeat_route=repeat_route, record=record,
                       initial_pose=initial_pose)  # fmt: skip
    outputs, summary = run_live(opts)
    lat = summary.get("latency_ms") or {"p50": "-", "p99": "-"}
    c = summary["counts"]
    typer.echo(
        f"live        {summary['mode']} for {summary['wall_s']:.1f} s: "
        f"{c.get('frames_processed', 0)} frames processed, "
        f"{c.get('frames_dropped_front_end', 0)} dropped in the front end, "
        f"latency p50 {lat['p50']} ms / p99 {lat['p99']} ms"
    )
    slam = summary.get("slam_vs_groundtruth")
    if slam:
        typer.echo(f"accuracy    ATE {slam.get('ate_rmse_m')} m against the simulator's truth")
    rec = summary.get("recording")
    if rec and "error" not in rec:
        typer.echo(
            f"recorded    {rec['frames']} frames ({rec['frames_dropped']} left out: the "
            f"writer fell behind), {rec['wheel_readings']} encoder readings"
        )
    _echo_outputs(outputs)


@app.command()
@_known_errors
def board(
    port: Annotated[str | None, typer.Argument(help="Serial port or pyserial URL.")] = None,
    emulator: Annotated[
        bool, typer.Option(help="Talk to the built-in board emulator on a pseudo-terminal.")
    ] = False,
    test_drive: Annotated[
        bool, typer.Option(help="Drive forward at 0.1 m/s for 1 s and measure it. Lift the robot!")
    ] = False,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Check an Eddie control board: firmware, battery, encoders, round-trip time."""
    from rgbdnav.commands.board import check_board
    from rgbdnav.config import load_config

    cfg = load_config(config or [], set_ or [])
    if emulator:
        from sensors.eddie_emulator import EddieEmulator

        emu = EddieEmulator(cfg.robot)
        try:
            report = check_board(emu.serve_pty(), cfg.board, cfg.robot, test_drive)
        finally:
            emu.close()
    else:
        report = check_board(port or cfg.board.port, cfg.board, cfg.robot, test_drive)
    typer.echo(report.text())


@app.command("eval")
@_known_errors
def eval_(
    trajectory: Annotated[
        Path, typer.Argument(metavar="TRAJ", help="Estimated TUM trajectory, or a run directory.")
    ],
    reference: Annotated[
        Path | None, typer.Option("--reference", "-r", help="Reference TUM trajectory (ATE, RPE).")
    ] = None,
    relations: Annotated[
        Path | None,
        typer.Option(
            help="Reference relations 't1 t2 x y z roll pitch yaw' (Kümmerle 2009 metric, planar); "
            "instead of --reference."
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Run directory to write (needed with --reference)."),
    ] = None,
    align: Annotated[
        str, typer.Option(help="Alignment: se3 (TUM ATE), sim3 (monocular), se2 (planar), none.")
    ] = "se3",
    max_diff: Annotated[
        float, typer.Option(help="Association window [s] (TUM associate.py).")
    ] = 0.02,
    delta: Annotated[float, typer.Option(help="RPE pose-pair distance.")] = 1.0,
    delta_unit: Annotated[
        str, typer.Option(help="Unit of --delta: m (along the reference) or frames.")
    ] = "m",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    verbose: VerboseOpt = False,
) -> None:
    """Score a trajectory against a reference: ATE and RPE (TUM RGB-D benchmark / evo method),
    or against reference relations (Kümmerle et al. 2009)."""
    _setup_logging(verbose)
    from rgbdnav.commands.eval import (
        format_relations_report,
        format_report,
        run_eval,
        run_relations_eval,
    )

    if (reference is None) == (relations is None):
        raise RgbdNavError("give exactly one of --reference GT and --relations FILE")
    if relations is not None:
        summary = run_relations_eval(trajectory, relations, out, max_diff_s=max_diff,
                                     config_files=config or [], overrides=set_ or [])  # fmt: skip
        typer.echo(format_relations_report(summary))
        if out is not None:
            typer.echo(f"wrote {out / 'summary.json'}")
        return
    if reference is None or out is None:  # reference is set here; the check narrows the type
        raise RgbdNavError("--reference needs --out DIR (the run directory for ate.png)")
    summary = run_eval(
        trajectory, reference, out, align=align, max_diff_s=max_diff, delta=delta,
        delta_unit=delta_unit, config_files=config or [], overrides=set_ or [],
    )  # fmt: skip
    typer.echo(format_report(summary))
    typer.echo(f"wrote {out / 'summary.json'} and {out / 'ate.png'}")


fleet_app = typer.Typer(help="Several robots' maps in one world frame.", no_args_is_help=True)
app.add_typer(fleet_app, name="fleet")


@fleet_app.command("show")
@_known_errors
def fleet_show(
    fleet_file: Annotated[Path, typer.Argument(help="Fleet file (fleet.yaml).")],
    out: OutOpt,
    verbose: VerboseOpt = False,
) -> None:
    """One picture of every robot's map and keepout mask in the world frame, and a rerun
    recording."""
    _setup_logging(verbose)
    from rgbdnav.commands.fleet import run_show

    _echo_outputs(run_show(fleet_file, out))


@fleet_app.command("align")
@_known_errors
def fleet_align(
    map_a: Annotated[Path, typer.Argument(help="Map A: bundle folder or map.yaml.")],
    map_b: Annotated[Path, typer.Argument(help="Map B, to place in A's frame.")],
    out: OutOpt,
    verbose: VerboseOpt = False,
) -> None:
    """Where B's map frame sits in A's, found without a guess; exit 1 when the maps do not
    overlap."""
    _setup_logging(verbose)
    from rgbdnav.commands.fleet import run_align
    from slam.map_align import AlignConfig

    al, outputs = run_align(map_a, map_b, out, AlignConfig())
    x, y, yaw = al.T_a_b
    typer.echo(
        f"B in A: x {x:.3f} m, y {y:.3f} m, yaw {yaw:.4f} rad "
        f"({math.degrees(yaw):.2f} deg); confidence {al.confidence:.2f}, "
        f"{al.verification.overlap_m:.0f} m of wall matched"
    )
    _echo_outputs(outputs)


@app.command()
@_known_errors
def geo(
    map_: Annotated[Path, typer.Argument(help="Map bundle (with geo.yaml) or a geo.yaml.")],
    latlon: Annotated[
        tuple[float, float] | None,
        typer.Option("--latlon", metavar="LAT LON", help="WGS84 [deg] to map x y."),
    ] = None,
    xy: Annotated[
        tuple[float, float] | None,
        typer.Option("--xy", metavar="X Y", help="Map x y [m] to WGS84 lat lon."),
    ] = None,
) -> None:
    """Convert between a map's x/y and WGS84 latitude/longitude through its geo anchor."""
    from sensors.geo import geo_anchor_of

    if (latlon is None) == (xy is None):
        raise RgbdNavError("give exactly one of --latlon LAT LON and --xy X Y")
    anchor = geo_anchor_of(map_)
    if latlon is not None:
        x, y, _ = anchor.to_map(latlon[0], latlon[1])
        typer.echo(f"x {float(x):.3f} y {float(y):.3f}")
    else:
        lat, lon, _ = anchor.to_wgs84(xy[0], xy[1])
        typer.echo(f"lat {float(lat):.8f} lon {float(lon):.8f}")


def main() -> None:
    try:
        app()
    except RgbdNavError as err:
        typer.echo(f"error: {err}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()
