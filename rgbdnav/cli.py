"""rgbdnav command line: parses, resolves config, dispatches, and maps known errors to one line.

Heavy modules (Open3D, OpenCV, GTSAM) are imported inside the commands that need them so that
``rgbdnav --help`` stays fast.
"""

from __future__ import annotations

import functools
import inspect
import logging
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer

from rgbdnav.stop_signals import StopSignals
from sensors.types import RgbdNavError

app = typer.Typer(
    name="rgbdnav",
    help="Map, localise and drive a differential-drive robot with an RGB-D camera, without ROS.",
    no_args_is_help=True,
    add_completion=True,  # --install-completion / --show-completion (bash, zsh, fish, pwsh)
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
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
QuietOpt = Annotated[
    bool, typer.Option("--quiet", "-q", help="No progress bars; log warnings and errors only.")
]


RosParamsOpt = Annotated[
    list[Path] | None,
    typer.Option(
        "--ros-params",
        help="ROS 2 parameter YAML (robot_localization, slam_toolbox, AMCL, Nav2), repeatable: "
        "what rgbdnav implements is applied over --config, a table says what was ignored.",
    ),
]


def _topic_opt(role: str) -> Any:
    return typer.Option(f"--{role}-topic", help=f"Bag topic of the {role} stream.")


RgbTopicOpt = Annotated[str | None, _topic_opt("rgb")]
DepthTopicOpt = Annotated[str | None, _topic_opt("depth")]
InfoTopicOpt = Annotated[
    str | None, typer.Option("--info-topic", help="Bag topic of the colour CameraInfo.")
]
OdomTopicOpt = Annotated[str | None, _topic_opt("odom")]
ImuTopicOpt = Annotated[str | None, _topic_opt("imu")]
VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="Debug logging.")]
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Run directory to write.")]
SourceArg = Annotated[
    Path,
    typer.Argument(
        help="ROS bag (ROS 1 .bag, rosbag2 folder, .db3, .mcap), recording or TUM RGB-D folder, "
        "CARMEN log (.clf/.log[.gz]), or world YAML."
    ),
]
MapOpt = Annotated[Path, typer.Option("--map", "-m", help="Map bundle folder, or a Nav2 map.yaml.")]
WorldSeedOpt = Annotated[int, typer.Option(help="Seed when SOURCE is a world.")]
RrdOpt = Annotated[Path | None, typer.Option(help="Save a rerun recording (.rrd) of the run here.")]
ViewerOpt = Annotated[bool, typer.Option(help="Spawn the rerun viewer and stream the run to it.")]
FormatOpt = Annotated[
    str,
    typer.Option(
        "--format",
        help="Also write each trajectory as kitti (NAME.kitti.txt + NAME.times.txt) or euroc "
        "(NAME.euroc.csv) beside its NAME.tum.",
    ),
]
GoalOpt = Annotated[
    list[str] | None,
    typer.Option("--goal", "-g", metavar="X,Y", help="A goal in the map frame [m]; repeat."),
]
GOAL_FAILED_EXIT = 3  # exit status when a navigation goal was not reached (1: error, 2: usage)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            typer.echo(f"rgbdnav {version('rgbdnav')}")
        except PackageNotFoundError:  # run from a source tree that was never installed
            typer.echo("rgbdnav (not installed)")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool | None,
        typer.Option("--version", callback=_version, is_eager=True, help="Print the version."),
    ] = None,
) -> None:
    """Map, localise and drive a differential-drive robot with an RGB-D camera, without ROS."""


def _given(ctx: typer.Context, name: str) -> bool:
    """Whether the user typed option ``name`` (a parameter name), not just its default. By
    the enum's name: typer >= 0.20 vendors click, so click's own ParameterSource is another
    class."""
    source = ctx.get_parameter_source(name)
    return source is not None and source.name != "DEFAULT"


def _refuse_unused(ctx: typer.Context, why: str, *names: str) -> None:
    """An option that would be ignored here is an error, not silence."""
    given = [f"--{n.rstrip('_').replace('_', '-')}" for n in names if _given(ctx, n)]
    if given:
        raise RgbdNavError(f"{', '.join(given)}: {why}; it would be ignored here")


def _check_format(fmt: str) -> None:
    from sensors.tum import TRAJECTORY_FORMATS

    if fmt not in TRAJECTORY_FORMATS:
        raise RgbdNavError(f"--format {fmt!r}: use one of {', '.join(TRAJECTORY_FORMATS)}")


def _write_formats(out: Path, fmt: str) -> None:
    """``--format``: every TUM trajectory of the run folder written again in ``fmt``."""
    from sensors.tum import convert_tum_files

    written = convert_tum_files(out, fmt)
    if written:
        typer.echo(f"{fmt:<11} {', '.join(p.name for p in written)}")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def parse_goals(values: Sequence[str], extra: Sequence[str] = ()) -> list[tuple[float, float]]:
    """``--goal X,Y`` values -> goals (the one syntax of navigate and live). The older
    ``navigate --goal X Y`` form arrives as a lone X plus a stray Y in ``extra``: accepted for
    this release with a deprecation warning."""
    from sensors.types import ConfigError

    goals: list[tuple[float, float]] = []
    stray = list(extra)
    for value in values:
        parts = value.split(",")
        if len(parts) == 1 and stray and _is_number(stray[0]):
            log.warning(
                "--goal X Y is deprecated and goes in the next release; write --goal %s,%s",
                value,
                stray[0],
            )
            parts.append(stray.pop(0))
        try:
            x, y = (float(v) for v in parts)
        except ValueError:
            raise ConfigError(f"--goal {value!r}: expected X,Y in metres, e.g. 4.5,1.5") from None
        goals.append((x, y))
    if stray:
        raise ConfigError(f"unexpected argument {stray[0]!r} (goals are --goal X,Y)")
    return goals


def _known_errors(fn: Any) -> Any:
    """Known errors become one line on stderr and exit code 1, never a traceback. A run
    directory the command had started is not left without its summary.json: it says why."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except RgbdNavError as err:
            message = str(err)
        except OSError as err:  # unwritable --out, full disk, ...
            where = f"{err.filename}: " if err.filename else ""
            message = f"{where}{err.strerror or err}"
        except KeyboardInterrupt:  # a second Ctrl-C: no outputs, but say so in the run folder
            _failed_run_summary(kwargs.get("out"), fn.__name__.rstrip("_"), "interrupted")
            raise
        _failed_run_summary(kwargs.get("out"), fn.__name__.rstrip("_"), message)
        typer.echo(f"error: {message}", err=True)
        raise typer.Exit(1) from None

    return wrapper


def _end_if_stopped(stop: StopSignals, kept: str) -> None:
    """A run a signal stopped early exits with the shell's code for it, after its outputs."""
    if stop.signum is not None:
        typer.echo(f"interrupted by {stop.name}: {kept}", err=True)
        raise typer.Exit(stop.exit_code)


def _failed_run_summary(out: Any, command: str, message: str) -> None:
    """A started run directory (its config.yaml written) without summary.json gets one that
    records the failure; any other folder named by --out is left alone."""
    if not isinstance(out, Path) or not (out / "config.yaml").is_file():
        return
    if (out / "summary.json").exists():
        return
    from rgbdnav.run_dir import RunDir

    try:
        RunDir(out).write_summary({"command": command, "status": "failed", "error": message})
    except OSError:
        pass  # the original error is what the user needs to see


def _topic_flags(
    rgb: str | None, depth: str | None, info: str | None, odom: str | None, imu: str | None
) -> dict[str, str | None]:
    """The --*-topic flags by the ``topics`` key each sets."""
    return {"rgb": rgb, "depth": depth, "camera_info": info, "odom": odom, "imu": imu}


def _settings(
    set_: list[str] | None,
    ros_params: list[Path] | None = None,
    topics: dict[str, str | None] | None = None,
) -> list[str]:
    """--ros-params (lowest), then --*-topic flags, then --set as ``section.key=value`` texts."""
    import json

    out: list[str] = []
    if ros_params:
        from rgbdnav.ros_params import format_table, load_ros_params

        overrides, rows = load_ros_params(ros_params)
        typer.echo(format_table(rows))
        out += overrides
    for role, topic in (topics or {}).items():
        if topic is not None:
            out.append(f"topics.{role}={json.dumps(topic)}")
    return out + list(set_ or [])


def _setup_logging(verbose: bool, quiet: bool = False) -> None:
    from rich.console import Console
    from rich.logging import RichHandler

    if verbose and quiet:
        raise RgbdNavError("give --verbose or --quiet, not both")
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO,
        format="%(message)s",
        handlers=[RichHandler(console=Console(stderr=True), show_time=False, show_path=False)],
        force=True,
    )


@dataclass(frozen=True)
class Shared:
    """The options verbs share, resolved once by :func:`_shared_options`."""

    config: list[Path]  # --config files, in order
    overrides: list[str]  # --ros-params, then --*-topic, then --set: section.key=value texts
    quiet: bool


_TOPIC_OPTS = {
    "rgb_topic": RgbTopicOpt,
    "depth_topic": DepthTopicOpt,
    "info_topic": InfoTopicOpt,
    "odom_topic": OdomTopicOpt,
    "imu_topic": ImuTopicOpt,
}


def _shared_options(*, config: bool = True, ros_params: bool = True, topics: bool = False) -> Any:
    """Give a verb the options verbs share, defined once: --config/--set, --ros-params, the
    --*-topic flags (each group on request), --quiet and --verbose. They are added to the verb's
    signature (where typer reads options), resolved (logging set up, overrides merged) and handed
    to the verb as one ``shared: Shared``."""
    extra: list[tuple[str, Any, Any]] = []
    if config:
        extra += [("config", ConfigOpt, None), ("set_", SetOpt, None)]
    if ros_params:
        extra.append(("ros_params", RosParamsOpt, None))
    if topics:
        extra += [(name, opt, None) for name, opt in _TOPIC_OPTS.items()]
    extra += [("quiet", QuietOpt, False), ("verbose", VerboseOpt, False)]

    def decorate(fn: Any) -> Any:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            given = {name: kwargs.pop(name) for name, _, _ in extra}
            flags = _topic_flags(*(given[name] for name in _TOPIC_OPTS)) if topics else None
            overrides = _settings(given.get("set_"), given.get("ros_params"), flags)
            _setup_logging(given["verbose"], given["quiet"])
            shared = Shared(list(given.get("config") or []), overrides, given["quiet"])
            return fn(*args, shared=shared, **kwargs)

        signature = inspect.signature(fn, eval_str=True)
        own = [p for p in signature.parameters.values() if p.name != "shared"]
        added = [
            inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=opt)
            for name, opt, default in extra
        ]
        wrapper.__signature__ = signature.replace(parameters=own + added)  # type: ignore[attr-defined]
        return wrapper

    return decorate


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
                "[progress.description]{task.description}",
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                transient=False,
            )
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
    from rgbdnav.cache import is_world

    return is_world(path)


def _echo_source(source: Path) -> None:
    typer.echo(f"source      {source}")


def _echo_outputs(outputs: dict[str, Path]) -> None:
    """One line per written file: what it is, where it is."""
    for label, path in outputs.items():
        typer.echo(f"{label:<11} {path}")


@app.command()
@_known_errors
@_shared_options(topics=True)
def info(
    source_text: Annotated[
        str,
        typer.Argument(
            metavar="SOURCE",
            help="Recording, TUM folder, CARMEN log, bag, .oni, world, or a camera URI "
            "(realsense://, freenect://, openni://).",
        ),
    ],
    *,
    shared: Shared,
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

    cfg = load_config(shared.config, shared.overrides)
    src = open_source(source_text, source_options(cfg, require_topics=False))
    try:
        typer.echo(f"{source_text}: {src.describe()}")
        typer.echo(format_stats_table(describe_source(src)))
        if hasattr(src, "static_extrinsics"):
            from rgbdnav.config import camera_mount

            try:
                _, mount = camera_mount(src, shared.config, shared.overrides)
            except RgbdNavError as err:  # info describes; the commands refuse
                mount = {"source": "config", "note": f"tf_static not usable: {err}"}
            shown = ", ".join(f"{k}={v:g}" for k, v in mount.items() if k.startswith("camera_"))
            label = getattr(src, "mount_source", "/tf_static chain")
            where = mount.get("chain") or mount.get("note") or f"no usable {label}"
            typer.echo(
                f"extrinsics  from {mount['source']} ({where}){': ' + shown if shown else ''}"
            )
        if src.skipped:
            typer.echo(f"skipped while reading: {src.skipped}")
    finally:
        src.close()


@app.command()
@_known_errors
@_shared_options()
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
    *,
    shared: Shared,
) -> None:
    """Render a Kinect + wheel-encoder recording of a robot driving through a world."""
    from rgbdnav.config import load_config
    from rgbdnav.run_dir import RunDir
    from sensors.sim.simulator import simulate as run_simulation

    if duration is not None and frames is not None:
        raise RgbdNavError("give --duration or --frames, not both")
    if frames is not None and frames < 1:
        raise RgbdNavError(f"--frames must be >= 1, got {frames}")
    if not world.is_file():
        raise RgbdNavError(f"{world}: no such world file")
    cfg = load_config(shared.config, shared.overrides)
    t0 = time.perf_counter()
    with _Progress(f"rendering {world.stem}", shared.quiet) as progress:
        summary = run_simulation(
            world,
            out,
            cfg.robot,
            cfg.camera,
            cfg.sim,
            seed=seed,
            duration_s=duration,
            frames=frames,
            trajectory=trajectory,
            progress=progress,
        )
    wall = time.perf_counter() - t0
    run = RunDir(out)
    run.write_config(cfg)
    run.write_summary(
        {
            "command": "simulate",
            **summary.as_dict(),
            "wall_time_s": round(wall, 2),
            "frames_per_s": round(summary.frames / wall, 2),
        }
    )
    typer.echo(
        f"wrote {summary.frames} frames ({summary.path_length_m:.1f} m, "
        f"{summary.duration_s:.1f} s) to {out} in {wall:.1f} s"
    )


@app.command()
@_known_errors
@_shared_options(topics=True)
def odometry(
    ctx: typer.Context,
    source: SourceArg,
    out: OutOpt,
    seed: WorldSeedOpt = 0,
    vo: Annotated[bool, typer.Option(help="Run visual odometry on the RGB-D frames.")] = True,
    force_3dof: Force3DofOpt = False,
    fmt: FormatOpt = "tum",
    *,
    shared: Shared,
) -> None:
    """Wheel, visual and fused (EKF) odometry of a source, with drift against ground truth."""
    _check_format(fmt)
    if not _is_world(source):
        _refuse_unused(ctx, "only with a world SOURCE (it seeds the rendering)", "seed")
    from rgbdnav.commands.odometry import run_odometry

    stop = StopSignals("no more frames are read; the odometry of what was read is being saved")
    with stop, _Progress("visual odometry", shared.quiet or not vo) as progress:
        outputs = run_odometry(
            source, out, shared.config, shared.overrides, vo, progress, force_3dof, seed, stop
        )
    _echo_source(source)
    _echo_outputs(outputs)
    _write_formats(out, fmt)
    _end_if_stopped(stop, "the trajectories hold what was read before it")


@app.command("map")
@_known_errors
@_shared_options(topics=True)
def map_(
    ctx: typer.Context,
    source: SourceArg,
    out: OutOpt,
    continue_: Annotated[
        Path | None,
        typer.Option("--continue", help="Map bundle to extend: relocalise in it, then map on."),
    ] = None,
    seed: WorldSeedOpt = 0,
    rrd: RrdOpt = None,
    viewer: ViewerOpt = False,
    force_3dof: Force3DofOpt = False,
    fmt: FormatOpt = "tum",
    *,
    shared: Shared,
) -> None:
    """Pose-graph SLAM: trajectory, occupancy grid and a map bundle (Nav2 PGM/YAML + graph)."""
    _check_format(fmt)
    if not _is_world(source):
        _refuse_unused(ctx, "only with a world SOURCE (it seeds the rendering)", "seed")
    from rgbdnav.runners.map import run_map

    # A world is rendered straight into the front end (no recording on disk). Ctrl-C or SIGTERM
    # stops the reading; what was read is mapped and saved (a second one aborts).
    stop = StopSignals("no more frames are read; the map of what was read is being saved")
    with stop, _Progress("mapping", shared.quiet) as progress:
        outputs = run_map(
            source,
            out,
            shared.config,
            shared.overrides,
            progress,
            continue_,
            rrd,
            viewer,
            force_3dof,
            seed,
            stop,
        )
    _echo_source(source)
    _echo_outputs(outputs)
    _write_formats(out, fmt)
    _end_if_stopped(stop, "the map holds what was read before it")


@app.command()
@_known_errors
@_shared_options(topics=True)
def localize(
    ctx: typer.Context,
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
    force_3dof: Force3DofOpt = False,
    fmt: FormatOpt = "tum",
    gps: Annotated[
        Path | None,
        typer.Option(
            help="gps.txt fixes (t lat lon alt sigma_h) as the relocalisation prior; "
            "the map needs a geo.yaml. Default: the source's own NavSatFix/gps.txt."
        ),
    ] = None,
    *,
    shared: Shared,
) -> None:
    """Localise against a saved map (no mapping): trajectory, per-scan status and confidence."""
    _check_format(fmt)
    if not _is_world(source):
        _refuse_unused(ctx, "only with a world SOURCE (it seeds the rendering)", "seed")
    from rgbdnav.runners.localize import describe, run_localize
    from slam.map_bundle import load_map

    if _is_world(source):
        load_map(map_)  # refuse a bad map before spending minutes rendering the world
    stop = StopSignals("no more frames are read; the poses of what was read are being saved")
    with stop, _Progress("localising", shared.quiet) as progress:
        outputs, summary = run_localize(
            source,
            map_,
            out,
            shared.config,
            shared.overrides,
            initial_pose,
            progress,
            rrd,
            viewer,
            force_3dof,
            gps,
            seed,
            stop,
        )
    _echo_source(source)
    typer.echo(f"result      {describe(summary)}")
    _echo_outputs(outputs)
    _write_formats(out, fmt)
    _end_if_stopped(stop, "the trajectory holds what was read before it")


# Extra args: the Y of the deprecated `--goal X Y` form (see parse_goals).
@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
@_known_errors
@_shared_options()
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
    goal_: GoalOpt = None,
    rrd: RrdOpt = None,
    viewer: ViewerOpt = False,
    fmt: FormatOpt = "tum",
    *,
    shared: Shared,
) -> None:
    """Drive to goals on a saved map in a simulated world (localiser or ground truth).

    Goals: --goal X,Y [--goal X,Y ...] in the map frame (metres), driven in order; the exit
    status is 3 when a goal was not reached. --localization, --goal-timeout, --max-replans and
    --waypoint-pause override the navigate settings (nav.config.NavigateConfig).
    """
    _check_format(fmt)
    from rgbdnav.runners.navigate import describe, run_navigate

    goal = parse_goals(goal_ or [], ctx.args)
    with _Progress("navigating", shared.quiet) as progress:
        outputs, summary = run_navigate(
            map_,
            goal,
            sim,
            out,
            shared.config,
            shared.overrides,
            start,
            keepout,
            goal_timeout,
            max_replans,
            progress,
            localization=localization,
            seed=seed,
            waypoint_pause_s=waypoint_pause,
            rrd=rrd,
            viewer=viewer,
        )
    typer.echo(f"result      {describe(summary)}")
    failed = [g for g in summary["goals"] if g["status"] != "reached"]
    for g in failed:
        typer.echo(
            f"goal        ({g['goal'][0]:.2f}, {g['goal'][1]:.2f}) {g['status']}: {g['reason']}"
        )
    _echo_outputs(outputs)
    _write_formats(out, fmt)
    if failed:
        raise typer.Exit(GOAL_FAILED_EXIT)


@app.command()
@_known_errors
@_shared_options()
def live(
    ctx: typer.Context,
    out: OutOpt,
    camera: Annotated[
        str,
        typer.Option(
            help="sim, or a camera: realsense://[SERIAL|FILE.db3], freenect://[N], openni://[URI]."
        ),
    ] = "sim",
    board: Annotated[
        str,
        typer.Option(
            help="sim, a device spec (eddie:/dev/ttyUSB0, thunderborg:/dev/i2c-1@0x15, "
            "arduino-bridge:/dev/ttyACM0@57600), emulator:KIND (the simulated robot driven "
            "through that board emulator), or none."
        ),
    ] = "sim",
    sim_world: Annotated[
        Path,
        typer.Option("--sim-world", help="World YAML for --camera/--board sim."),
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
        typer.Option(
            "--goal",
            "-g",
            metavar="X,Y",
            help="A waypoint for --drive route (repeat; default: the world's route); the exit "
            "status is 3 when one was not reached.",
        ),
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
    joystick: Annotated[
        str | None,
        typer.Option(
            help="Joystick teleop from this evdev device (/dev/input/eventN; extra "
            "'joystick'): hold BTN_TL to drive, START switches manual/auto."
        ),
    ] = None,
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
    robot: Annotated[
        str | None,
        typer.Option(
            help="This robot's name in a fleet: the run goes to OUT/NAME/. Run one process per "
            "robot; `rgbdnav world-view OUT` draws them all in the world frame."
        ),
    ] = None,
    start: Annotated[
        tuple[float, float, float] | None,
        typer.Option(
            "--start",
            metavar="X Y YAW",
            help="The simulated robot's true start in the world (default: the world's start).",
        ),
    ] = None,
    fleet: Annotated[
        Path | None,
        typer.Option(
            help="Fleet file (fleet.yaml) with --robot NAME: localise in that robot's map "
            "(default --map), placed in the world by its T_world_map (or geo anchors), with "
            "its keepout mask; world-view then draws the run where the fleet puts it.",
        ),
    ] = None,
    fmt: FormatOpt = "tum",
    *,
    shared: Shared,
) -> None:
    """The live run on the robot (or the simulated robot): map, or localise with --map."""
    _check_format(fmt)
    from rgbdnav.live.run import Drill, LiveOptions, run_live

    if robot is not None:
        if not robot.replace("-", "").replace("_", "").isalnum():
            raise RgbdNavError(f"--robot {robot!r}: use letters, digits, - and _ (a folder name)")
        out = out / robot
    if start is not None and "sim" not in (camera, board):
        raise RgbdNavError("--start places the simulated robot; a real robot starts where it is")
    goals = parse_goals(goal or [])
    if "sim" not in (camera, board):  # (--drill and --initial-pose: checked by LiveRun)
        _refuse_unused(ctx, "only with --camera sim or --board sim", "sim_world", "seed")
    if drive != "route":
        _refuse_unused(ctx, f"only with --drive route, not {drive}", "goal", "repeat_route")
    world = sim_world if "sim" in (camera, board) else None
    opts = LiveOptions(
        out=out,
        camera=camera,
        board=board,
        world=world,
        config_files=shared.config,
        overrides=shared.overrides,
        map_bundle=map_,
        duration_s=duration,
        drive=drive,
        goals=goals,
        rrd=rrd,
        viewer=viewer,
        seed=seed,
        drills=[Drill.parse(d) for d in drill or []],
        repeat_route=repeat_route,
        record=record,
        joystick=joystick,
        initial_pose=initial_pose,
        robot=robot,
        start=start,
        fleet=fleet,
    )
    outputs, summary = run_live(opts)
    _write_formats(out, fmt)
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
    reached = summary["counts"].get("waypoints_reached", 0)
    if goals and not repeat_route and reached < len(goals):
        typer.echo(f"goals       {reached} of {len(goals)} reached", err=True)
        raise typer.Exit(GOAL_FAILED_EXIT)


@app.command("world-view")
@_known_errors
@_shared_options(config=False, ros_params=False)
def world_view(
    runs: Annotated[
        list[Path], typer.Argument(help="Robot run folders (live --robot), or folders of them.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Picture to write (PNG).")],
    *,
    shared: Shared,
) -> None:
    """Every robot's own map and path in the world frame, in one picture."""
    from rgbdnav.live.world_view import robot_runs
    from rgbdnav.live.world_view import world_view as draw

    found = robot_runs(runs)
    for name, d in draw(found, out).items():
        x, y, yaw = d["T_world_map"]
        typer.echo(
            f"{name:<11} {d['occupied_cells']} occupied cells, {d['path_poses']} poses; "
            f"world -> {name}/map: x={x:g} y={y:g} yaw={yaw:g}"
        )
    typer.echo(f"picture     {out}")


@app.command()
@_known_errors
@_shared_options()
def board(
    port: Annotated[
        str | None,
        typer.Argument(
            help="Device spec: eddie:/dev/ttyUSB0 (or a bare port), "
            "thunderborg:/dev/i2c-1@0x15[,TACHO_PORT], "
            "arduino-bridge:/dev/ttyACM0@57600."
        ),
    ] = None,
    emulator: Annotated[
        bool,
        typer.Option(
            help="Talk to a built-in emulator instead; the argument names which: eddie "
            "(default), thunderborg or arduino-bridge."
        ),
    ] = False,
    test_drive: Annotated[
        bool, typer.Option(help="Drive forward at 0.1 m/s for 1 s and measure it. Lift the robot!")
    ] = False,
    *,
    shared: Shared,
) -> None:
    """Check a motor board: which board, firmware, battery, odometry, round-trip time."""
    from rgbdnav.commands.board import check_board
    from rgbdnav.config import load_config
    from sensors.boards import open_board

    cfg = load_config(shared.config, shared.overrides)
    spec = f"emulator:{port or 'eddie'}" if emulator else (port or cfg.board.port)
    with open_board(spec, cfg) as motor_board:
        report = check_board(motor_board, spec, test_drive)
    typer.echo(report.text())


@app.command("eval")
@_known_errors
@_shared_options()
def eval_(
    ctx: typer.Context,
    trajectory: Annotated[
        Path,
        typer.Argument(
            metavar="TRAJ",
            help="Estimated trajectory (TUM, KITTI or EuRoC CSV, detected), or a run directory.",
        ),
    ],
    reference: Annotated[
        Path | None,
        typer.Option("--reference", "-r", help="Reference trajectory, any format (ATE, RPE)."),
    ] = None,
    times: Annotated[
        Path | None,
        typer.Option(
            help="KITTI times file of TRAJ (default: NAME.times.txt or times.txt beside)."
        ),
    ] = None,
    reference_times: Annotated[
        Path | None,
        typer.Option(help="KITTI times file of --reference (default: found beside it)."),
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
        typer.Option("--out", "-o", help="Also write summary.json (and ate.png) to this folder."),
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
    *,
    shared: Shared,
) -> None:
    """Score a trajectory against a reference: ATE and RPE (TUM RGB-D benchmark / evo method),
    or against reference relations (Kümmerle et al. 2009). Prints the result; --out also
    writes it."""
    from rgbdnav.runners.eval import (
        format_relations_report,
        format_report,
        run_eval,
        run_relations_eval,
    )

    if (reference is None) == (relations is None):
        raise RgbdNavError("give exactly one of --reference GT and --relations FILE")
    if relations is not None:
        _refuse_unused(
            ctx,
            "only with --reference, not --relations",
            "align",
            "delta",
            "delta_unit",
            "reference_times",
        )
        summary = run_relations_eval(
            trajectory,
            relations,
            out,
            max_diff_s=max_diff,
            config_files=shared.config,
            overrides=shared.overrides,
            estimate_times=times,
        )
        typer.echo(format_relations_report(summary))
        if out is not None:
            typer.echo(f"wrote {out / 'summary.json'}")
        return
    if reference is None:  # exactly one of the two, checked above; this narrows the type
        raise RgbdNavError("give --reference GT")
    summary = run_eval(
        trajectory,
        reference,
        out,
        align=align,
        max_diff_s=max_diff,
        delta=delta,
        delta_unit=delta_unit,
        config_files=shared.config,
        overrides=shared.overrides,
        estimate_times=times,
        reference_times=reference_times,
    )
    typer.echo(format_report(summary))
    if out is not None:
        typer.echo(f"wrote {out / 'summary.json'} and {out / 'ate.png'}")


@app.command("export")
@_known_errors
@_shared_options(config=False, ros_params=False)
def export(
    run: Annotated[Path, typer.Argument(metavar="RUN_DIR", help="A run folder (map, live, ...).")],
    to: Annotated[str, typer.Option("--to", help="Output format: mcap (rosbag2 folder).")],
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Bag folder to write (default RUN_DIR/rosbag2)."),
    ] = None,
    images: Annotated[bool, typer.Option(help="Include the run's colour and depth images.")] = True,
    *,
    shared: Shared,
) -> None:
    """A run as a rosbag2/MCAP folder (/tf, /tf_static, /map, /scan, /odom, Path, images) for
    Foxglove or `ros2 bag play` into RViz."""
    from rgbdnav.commands.export import run_export

    result = run_export(run, to, out, images)
    if not shared.quiet:
        for topic, n in result["counts"].items():
            typer.echo(f"{topic:<42} {n} messages")
    typer.echo(f"bag         {result['out']}")


@app.command()
@_known_errors
@_shared_options(ros_params=False)
def batch(
    verb: Annotated[str, typer.Argument(help="map, localize or eval: the verb run per source.")],
    sources: Annotated[
        list[Path],
        typer.Argument(help="Sources (logs, recordings, worlds; for eval: trajectories or runs)."),
    ],
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Batch folder: DIR/<source-name>/ + report.")
    ],
    scheduler: Annotated[
        str | None,
        typer.Option(help="Address of a running Dask scheduler (default: a LocalCluster)."),
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="LocalCluster worker processes (default: one per core).")
    ] = None,
    map_: Annotated[
        Path | None, typer.Option("--map", "-m", help="localize: the map every source uses.")
    ] = None,
    reference: Annotated[
        Path | None, typer.Option("--reference", "-r", help="eval: reference TUM trajectory.")
    ] = None,
    relations: Annotated[
        Path | None, typer.Option(help="eval: Kümmerle relations file, instead of --reference.")
    ] = None,
    align: Annotated[str, typer.Option(help="eval --reference: se3, sim3, se2, none.")] = "se3",
    seed: WorldSeedOpt = 0,
    force_3dof: Force3DofOpt = False,
    *,
    shared: Shared,
) -> None:
    """Run map, localize or eval on many sources at once on Dask: one task per source, a report
    per source (accuracy, time, memory); finished sources are skipped on a rerun."""
    from rgbdnav.commands.batch import BatchOptions, accuracy_text, run_batch

    opts = BatchOptions(
        verb=verb,
        out=out,
        config_files=tuple(shared.config),
        overrides=tuple(shared.overrides),
        map_bundle=map_,
        reference=reference,
        relations=relations,
        align=align,
        seed=seed,
        force_3dof=force_3dof,
    )

    def echo(row: dict) -> None:
        status = "done*" if row.get("resumed") else row["status"]
        what = row["error"] if row["error"] else accuracy_text(row["accuracy"])
        typer.echo(f"{status:<7} {row['name']:<24} {row.get('wall_s', '-'):>7} s  {what}")

    result = run_batch(sources, opts, scheduler, workers, on_row=echo)
    typer.echo(
        f"{len(result.rows) - result.failed} done ({result.skipped} skipped as done "
        f"before, marked *), {result.failed} failed; report {out / 'report.md'}"
    )
    if result.failed:
        raise typer.Exit(1)


fleet_app = typer.Typer(help="Several robots' maps in one world frame.", no_args_is_help=True)
app.add_typer(fleet_app, name="fleet")


@fleet_app.command("show")
@_known_errors
@_shared_options(config=False, ros_params=False)
def fleet_show(
    fleet_file: Annotated[Path, typer.Argument(help="Fleet file (fleet.yaml).")],
    out: OutOpt,
    *,
    shared: Shared,
) -> None:
    """One picture of every robot's map and keepout mask in the world frame, and a rerun
    recording."""
    from rgbdnav.commands.fleet import run_show

    _echo_outputs(run_show(fleet_file, out))


@fleet_app.command("align")
@_known_errors
@_shared_options(ros_params=False)
def fleet_align(
    map_a: Annotated[Path, typer.Argument(help="Map A: bundle folder or map.yaml.")],
    map_b: Annotated[Path, typer.Argument(help="Map B, to place in A's frame.")],
    out: OutOpt,
    *,
    shared: Shared,
) -> None:
    """Where B's map frame sits in A's, found without a guess; exit 1 when the maps do not
    overlap. Tunables: the ``align`` section (``--set align.min_overlap_m=10``)."""
    from rgbdnav.commands.fleet import run_align
    from rgbdnav.config import load_config

    cfg = load_config(shared.config, shared.overrides)
    al, outputs = run_align(map_a, map_b, out, cfg.align)
    x, y, yaw = al.T_a_b
    typer.echo(
        f"B in A: x {x:.3f} m, y {y:.3f} m, yaw {yaw:.4f} rad "
        f"({math.degrees(yaw):.2f} deg); confidence {al.confidence:.2f}, "
        f"{al.verification.overlap_m:.0f} m of wall matched"
    )
    _echo_outputs(outputs)


@app.command()
@_known_errors
@_shared_options(config=False, ros_params=False)
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
    *,
    shared: Shared,
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
        assert xy is not None  # exactly one of the two, checked above
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
