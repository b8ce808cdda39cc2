"""The whole resolved configuration: defaults < YAML files (in order) < ``--set key=value``.

Every section is a frozen dataclass owned by the layer that uses it (``sensors.config``,
``slam.config``, ``nav.config``); this module only composes them, reads YAML and applies
overrides. Errors name the file and the full key path, e.g. ``ekf.yaml: ekf.frequency: ...``.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from nav.config import (
    CollisionMonitorConfig,
    CostmapConfig,
    FollowerConfig,
    NavigateConfig,
    PlannerConfig,
    SmootherConfig,
)
from nav.joystick import JoystickConfig
from sensors.atomic import atomic_write_text
from sensors.config import (
    BoardConfig,
    BridgeConfig,
    CameraConfig,
    RobotConfig,
    SimConfig,
    SyncConfig,
    ThunderBorgConfig,
    TopicsConfig,
    build_section,
    param,
    section_to_dict,
    short_repr,
)
from sensors.safe_yaml import load_yaml, read_yaml
from sensors.source import SourceOptions
from sensors.types import ConfigError, RgbdNavError
from slam.config import (
    AlignConfig,
    DepthToScanConfig,
    EkfConfig,
    LocalizerConfig,
    MapperConfig,
    VoConfig,
)

SHOWN_OVERRIDE_CHARS = 80  # [chars] of a --set quoted in its error
REPO_CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"


@dataclass(frozen=True)
class LiveConfig:
    """The live run: queues, stall detection, checkpoints and route driving (`rgbdnav live`)."""

    frame_queue_size: int = param(4, ge=1, doc="camera frames waiting for the front end")
    scan_queue_size: int = param(64, ge=1, doc="scans waiting for the mapper")
    camera_stall_timeout: float = param(
        1.0, unit="s", gt=0.0, doc="no frame for this long: a camera stall (mapping pauses)"
    )
    checkpoint_period: float = param(
        30.0, unit="s", gt=0.0, doc="the map bundle is saved this often (and on exit)"
    )
    first_checkpoint_after: float = param(
        2.0, unit="s", gt=0.0, doc="the first save comes this soon after mapping starts"
    )
    control_rate: float = param(10.0, unit="Hz", gt=0.0, doc="velocity commands to the board")
    pose_before_vo: bool = param(
        True, doc="a frame's pose leaves before its VO is fused (VO corrects the next frames)"
    )
    skip_vo_when_behind: bool = param(
        True, doc="frames waiting: skip VO on this one instead of dropping the next frame"
    )
    ekf_history_length: float = param(
        2.0, unit="s", gt=0.0, doc="EKF history for late frames (smooth_lagged_data forced on)"
    )
    visualize_every: int = param(3, ge=1, doc="draw every n-th frame and scan")
    visualize_queue_size: int = param(8, ge=1, doc="drawing jobs queued before they are dropped")
    max_linear_speed: float = param(0.3, unit="m/s", gt=0.0, doc="--drive route forward speed")
    max_angular_speed: float = param(0.6, unit="rad/s", gt=0.0, doc="--drive route turn rate")
    turn_in_place_angle: float = param(
        0.6, unit="rad", gt=0.0, doc="turn on the spot while the heading error is larger"
    )
    heading_gain: float = param(1.5, unit="1/s", gt=0.0, doc="turn rate per heading error")
    waypoint_tolerance: float = param(0.2, unit="m", gt=0.0, doc="a route waypoint is reached")
    board_kill_switch: int = param(
        1, unit="s", ge=0, le=26, doc="WATCH: board stops the motors without commands (0 = off)"
    )
    obstacle_memory: float = param(
        5.0,
        unit="s",
        gt=0.0,
        doc="scans of this long ago replayed into the obstacle layer of each new live costmap",
    )
    sim_initial_pose: bool = param(
        True,
        doc="--map with the simulated robot: it is told its true start (as --initial-pose); "
        "false: it relocalises globally, with the GPS prior when the world has a geo anchor",
    )
    blocked_timeout: float = param(
        5.0, unit="s", gt=0.0, doc="direct driver: a waypoint blocked this long is skipped"
    )
    teleop_key_timeout: float = param(
        0.6, unit="s", gt=0.0, doc="manual mode stops when no key came for this long (key_timeout)"
    )
    route_driver: Literal["nav", "direct"] = param(
        "nav",
        doc="auto mode: nav = waypoints as goals for costmap, planner, RPP, behaviours and "
        "smoother; direct = steer straight at each waypoint (no planner)",
    )
    waypoint_timeout: float = param(
        60.0, unit="s", gt=0.0, doc="nav driver: a waypoint not reached in this long is skipped"
    )
    replan_period: float = param(
        1.0, unit="s", gt=0.0, doc="nav driver: plan again from the estimate this often"
    )
    nav_map_period: float = param(
        1.0,
        unit="s",
        gt=0.0,
        doc="nav driver: the costmap's static layer is rebuilt from the "
        "mapper's keyframes this often (in a background thread)",
    )
    nav_map_margin: float = param(
        2.0, unit="m", ge=0.0, doc="nav driver: costmap = start, route and robot grown by this"
    )
    mapper_rate: float = param(
        10.0,
        unit="Hz",
        ge=0.0,
        doc="scans handed to the mapper or localiser at most this often "
        "(0 = every frame): a third of the mapper's CPU at 30 Hz, and each scan the mapper "
        "tracks stays in its memory (~350 B)",
    )
    malloc_arena_max: int = param(
        2,
        ge=0,
        doc="glibc malloc arenas at most (0 = glibc default, 8 per core): per-thread "
        "arenas keep freed memory and RSS creeps in long runs",
    )
    malloc_mmap_threshold: int = param(
        1048576,
        unit="B",
        ge=0,
        doc="glibc: blocks this large are mmap'ed and returned on free "
        "(0 = glibc's dynamic threshold, which grows to 32 MB and lets RSS creep)",
    )
    stats_reservoir: int = param(
        20000, ge=100, doc="latency samples kept for the percentiles (uniform reservoir sample)"
    )
    track_decimation: float = param(
        0.05,
        unit="m",
        ge=0.0,
        doc="trajectory kept in memory for drawing: a point per this "
        "much travel (the full trajectories are streamed to the run directory)",
    )


@dataclass(frozen=True)
class Config:
    robot: RobotConfig = field(default_factory=RobotConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    sync: SyncConfig = field(default_factory=SyncConfig)
    ekf: EkfConfig = field(default_factory=EkfConfig)
    vo: VoConfig = field(default_factory=VoConfig)
    depth_to_scan: DepthToScanConfig = field(default_factory=DepthToScanConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)
    align: AlignConfig = field(default_factory=AlignConfig)
    costmap: CostmapConfig = field(default_factory=CostmapConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    follower: FollowerConfig = field(default_factory=FollowerConfig)
    smoother: SmootherConfig = field(default_factory=SmootherConfig)
    navigate: NavigateConfig = field(default_factory=NavigateConfig)
    collision_monitor: CollisionMonitorConfig = field(default_factory=CollisionMonitorConfig)
    board: BoardConfig = field(default_factory=BoardConfig)
    thunderborg: ThunderBorgConfig = field(default_factory=ThunderBorgConfig)
    arduino_bridge: BridgeConfig = field(default_factory=BridgeConfig)
    joystick: JoystickConfig = field(default_factory=JoystickConfig)
    topics: TopicsConfig = field(default_factory=TopicsConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    live: LiveConfig = field(default_factory=LiveConfig)


# Annotations are strings under `from __future__ import annotations`; read types off an instance.
SECTIONS: dict[str, type] = {
    f.name: type(getattr(Config(), f.name)) for f in dataclasses.fields(Config)
}


def config_to_dict(cfg: Config) -> dict[str, dict[str, Any]]:
    return {name: section_to_dict(getattr(cfg, name)) for name in SECTIONS}


def _read_yaml(path: Path) -> dict[str, Any]:
    data = read_yaml(
        path, ConfigError, "config file", "{source}: line {line} is not valid YAML ({problem})"
    )
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping of sections")
    return data


def _merge_layer(
    merged: dict[str, dict[str, Any]], layer: Mapping[str, Any], source: str
) -> dict[str, dict[str, Any]]:
    """Overlay one file's sections on ``merged``, checking every section and key as we go."""
    out = {k: dict(v) for k, v in merged.items()}
    for section, values in layer.items():
        if section not in SECTIONS:
            raise ConfigError(
                f"{source}: {section}: unknown section (valid: {', '.join(SECTIONS)})"
            )
        if values is None:
            continue
        if not isinstance(values, Mapping):
            raise ConfigError(
                f"{source}: {section}: expected a mapping of keys, got {short_repr(values)}"
            )
        out[section] = _deep_merge(out[section], values)
        # Validate now so the error names the file that introduced the bad value.
        try:
            build_section(SECTIONS[section], out[section], section)
        except ConfigError as err:
            raise ConfigError(f"{source}: {err}") from None
    return out


def _deep_merge(base: Mapping[str, Any], layer: Mapping[str, Any]) -> dict[str, Any]:
    """``layer`` over ``base``; nested sections (``vo.advanced``) merge key by key."""
    out = dict(base)
    for key, value in layer.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _shown(text: str) -> str:
    return text if len(text) <= SHOWN_OVERRIDE_CHARS else text[:SHOWN_OVERRIDE_CHARS] + "..."


def parse_override(text: str) -> tuple[str, str, Any]:
    """``"ekf.frequency=30"`` -> ("ekf", "frequency", 30); the value is parsed as YAML. A nested
    key (``vo.advanced.fast_threshold=10``) keeps its dots in the name."""
    key, sep, raw = text.partition("=")
    section, dot, name = key.strip().partition(".")
    if not sep or not dot or not section or not name:
        raise ConfigError(
            f"--set {_shown(text)!r}: expected section.key=value, e.g. ekf.frequency=30"
        )
    invalid = "{source}: value is not valid YAML ({problem})"
    source = f"--set {_shown(text)!r}"
    value = load_yaml(raw, source, ConfigError, invalid) if raw.strip() else ""
    return section, name, value


def load_config(
    files: Iterable[str | os.PathLike[str]] = (),
    overrides: Iterable[str] = (),
    base: Mapping[str, Mapping[str, Any]] | None = None,
) -> Config:
    """Resolve defaults < ``base`` (e.g. a recording's scene.yaml) < files < overrides."""
    merged: dict[str, dict[str, Any]] = {name: {} for name in SECTIONS}
    if base:
        merged = _merge_layer(merged, base, "scene")
    for f in files:
        path = Path(f)
        merged = _merge_layer(merged, _read_yaml(path), str(path))
    for text in overrides:
        section, name, value = parse_override(text)
        for part in reversed(name.split(".")[1:]):
            value = {part: value}
        name = name.split(".")[0]
        merged = _merge_layer(merged, {section: {name: value}}, f"--set {_shown(text)}")
    return Config(**{s: build_section(SECTIONS[s], merged[s], s) for s in SECTIONS})


def write_config(cfg: Config, path: Path) -> None:
    """Write the resolved config as YAML, atomically."""
    text = "# rgbdnav resolved configuration\n" + yaml.safe_dump(
        config_to_dict(cfg), sort_keys=False, default_flow_style=None
    )
    atomic_write_text(path, text)


def source_options(cfg: Config, strict: bool = False, require_topics: bool = True) -> SourceOptions:
    """What adapters need from the configuration (rosbag topics, robot, camera).
    ``require_topics=False`` (``info``) describes a bag whose topics do not resolve."""
    return SourceOptions(
        topics=section_to_dict(cfg.topics),
        robot=cfg.robot,
        camera=cfg.camera,
        strict=strict,
        sync=cfg.sync,
        require_topics=require_topics,
    )


def initial_pose_array(values: Sequence[float]) -> np.ndarray:
    """``--initial-pose X Y YAW`` as a (3,) array, or a one-line error."""
    init = np.asarray(values, dtype=np.float64)
    if init.shape != (3,) or not np.all(np.isfinite(init)):
        raise ConfigError(f"--initial-pose needs three finite numbers X Y YAW, got {list(values)}")
    return init


def user_keys(
    files: Iterable[str | os.PathLike[str]] = (), overrides: Iterable[str] = ()
) -> set[str]:
    """``section.key`` names the user's config files and ``--set`` overrides set."""
    keys: set[str] = set()
    for f in files:
        for section, values in _read_yaml(Path(f)).items():
            if isinstance(values, Mapping):
                keys |= {f"{section}.{k}" for k in values}
    for text in overrides:
        section, name, _ = parse_override(text)
        keys.add(f"{section}.{name}")
    return keys


def camera_mount(
    src: Any,
    files: Sequence[str | os.PathLike[str]],
    overrides: Sequence[str],
    base: Mapping[str, Mapping[str, Any]] | None = None,
) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    """(``base`` with the camera mount the source gives, summary entry): a bag's ``/tf_static``
    (all of it), or a device's own measure (``mount_source``: a Kinect's accelerometer pitch).

    The source's values go in the lowest layer, and only when neither the config files,
    ``--set`` nor ``base`` set any of the ``robot.camera_*`` keys it gives: the config wins,
    whole, over what the source gives.
    """
    from sensors.extrinsics import MOUNT_KEYS

    out = {k: dict(v) for k, v in (base or {}).items()}
    static = getattr(src, "static_extrinsics", None)
    label = str(getattr(src, "mount_source", "tf_static"))
    if static is None:
        return out, {"source": "config"}
    set_by_user = sorted(
        k
        for k in user_keys(files, overrides) | {f"robot.{k}" for k in out.get("robot", {})}
        if k in {f"robot.{m}" for m in MOUNT_KEYS}
    )
    try:
        found = static()
    except RgbdNavError as err:
        if not set_by_user:
            raise
        return out, {"source": "config", "note": f"{label} not usable: {err}"}
    if found is None:
        return out, {"source": "config"}
    mount, chain = found
    clash = [k for k in set_by_user if k.removeprefix("robot.") in mount]
    if clash:
        note = f"{label} {chain} not used: the config sets {', '.join(clash)}"
        return out, {"source": "config", "note": note}
    out.setdefault("robot", {}).update(mount)
    values = {k: round(v, 4) for k, v in mount.items()}
    return out, {"source": label, "chain": chain, **values}
