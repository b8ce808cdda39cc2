"""ROS 2 parameter files (``node: ros__parameters: ...``) mapped onto rgbdnav's configuration.

``--ros-params FILE`` reads the files robot_localization, slam_toolbox, AMCL and Nav2 users
already have. Our sections use the upstream names, so a parameter maps to the same key of the
section that owns the node: ``ekf_filter_node`` -> ``ekf``, ``slam_toolbox`` -> ``mapper``,
``amcl`` -> ``localizer``, ``global_costmap`` -> ``costmap``, ``controller_server``'s
RegulatedPurePursuit ``FollowPath`` -> ``follower``, ``planner_server``'s Navfn ``GridBased`` ->
``planner``, ``velocity_smoother`` -> ``smoother``, ``collision_monitor`` keeps its name. A few
need converting (a 15x15 covariance -> its diagonal, ``odom0``/``imu0`` topics -> ``topics``).
Everything else is listed as ignored, with the reason. The result is a list of
``section.key=value`` overrides applied over ``--config`` and under ``--set``; every value is
validated here so a bad one is an error naming the file, node and parameter.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sensors.config import build_section
from sensors.safe_yaml import read_yaml
from sensors.types import ConfigError

PARAMS_KEY = "ros__parameters"
RPP_PLUGIN = "RegulatedPurePursuitController"
NAVFN_PLUGIN = "NavfnPlanner"
STATE_SIZE = 15  # robot_localization's state vector
NO_ROS = "rgbdnav has no ROS graph: topics, frames, QoS, clocks"
# Keys every node may carry, and why they have no counterpart.
COMMON_IGNORED: Mapping[str, str] = {
    "use_sim_time": NO_ROS,
    "plugin": "plugin name (checked where it matters)",
    "enabled": "layer/plugin switch: rgbdnav's pipeline is fixed",
}


@dataclass(frozen=True)
class Row:
    """One parameter's fate: ``target`` (``section.key``) when applied, else ``reason``."""

    file: str
    node: str
    key: str
    value: Any
    target: str = ""
    reason: str = ""


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def parameter_blocks(data: Any, path: Path) -> list[tuple[str, dict[str, Any]]]:
    """(node name, flattened parameters) per ``ros__parameters`` block; the node name is the
    last path component (``/ns/ekf_filter_node`` -> ekf_filter_node; ``/**`` stays)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: not a ROS 2 parameter file (top level is not a mapping)")
    blocks: list[tuple[str, dict[str, Any]]] = []

    def walk(node: Mapping[str, Any], names: list[str]) -> None:
        for k, v in node.items():
            if k == PARAMS_KEY:
                if not isinstance(v, Mapping):
                    raise ConfigError(f"{path}: {'/'.join(names)}: {PARAMS_KEY} is not a mapping")
                name = names[-1] if names else "/**"
                short = name if name == "/**" else name.rsplit("/", 1)[-1] or name
                blocks.append((short, _flatten(v)))
            elif isinstance(v, Mapping):
                walk(v, [*names, str(k)])

    walk(data, [])
    if not blocks:
        raise ConfigError(
            f"{path}: no '{PARAMS_KEY}' block; a ROS 2 parameter file looks like "
            "'node_name: {ros__parameters: {...}}'"
        )
    return blocks


def _diagonal(value: Any, what: str) -> tuple[list[float], str]:
    """A robot_localization covariance: 15 diagonal values or a 15x15 row-major matrix."""
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):  # a string, a ragged list, a mapping
        raise ConfigError(f"{what}: expected a list of numbers, got {value!r:.60}") from None
    if a.size == STATE_SIZE:
        return a.tolist(), ""
    if a.size != STATE_SIZE * STATE_SIZE:
        raise ConfigError(
            f"{what}: expected 15x15 = 225 values (or a 15-value diagonal), got {a.size}"
        )
    m = a.reshape(STATE_SIZE, STATE_SIZE)
    off = m - np.diag(np.diag(m))
    note = " (off-diagonal terms dropped: our Q is diagonal)" if np.any(off != 0) else ""
    return np.diag(m).tolist(), note


def _fields(section: type) -> set[str]:
    return {f.name for f in dataclasses.fields(section)}


# --- per node kind: key -> (section.key, value) or a reason ----------------------------------

EKF_REASONS: Mapping[str, str] = {
    "map_frame": "one odom-frame EKF; map -> odom comes from the mapper/localiser",
    "publish_acceleration": "acceleration is not published",
    "transform_time_offset": NO_ROS,
    "transform_timeout": NO_ROS,
    "print_diagnostics": NO_ROS,
    "debug": NO_ROS,
    "debug_out_file": NO_ROS,
    "use_control": "control input (cmd_vel) prediction not implemented",
    "stamped_control": "control input (cmd_vel) prediction not implemented",
    "control_timeout": "control input (cmd_vel) prediction not implemented",
    "control_config": "control input (cmd_vel) prediction not implemented",
    "acceleration_limits": "control input (cmd_vel) prediction not implemented",
    "deceleration_limits": "control input (cmd_vel) prediction not implemented",
    "acceleration_gains": "control input (cmd_vel) prediction not implemented",
    "deceleration_gains": "control input (cmd_vel) prediction not implemented",
    "dynamic_process_noise_covariance": "Q does not scale with velocity here",
    "imu0_remove_gravitational_acceleration": "only the IMU's angular velocity z is fused",
    "reset_on_time_jump": NO_ROS,
    "permit_corrected_publication": NO_ROS,
}


def _ekf(key: str, value: Any, what: str) -> tuple[str, Any, str] | str:
    from slam.config import EkfConfig

    if key in ("odom0", "imu0"):
        topic = str(value)  # a relative ROS name resolves in the root namespace of a bag
        return "topics." + key[:-1], topic if topic.startswith("/") else "/" + topic, ""
    if key in ("process_noise_covariance", "initial_estimate_covariance"):
        diag, note = _diagonal(value, what)
        return f"ekf.{key}", diag, note
    if key in _fields(EkfConfig):
        return f"ekf.{key}", value, ""
    if key in EKF_REASONS:
        return EKF_REASONS[key]
    head = key.split("_", 1)[0]
    if head[:-1] in ("odom", "imu", "pose", "twist") and head[-1:].isdigit():
        if key.endswith(("_queue_size", "_nodelay")):
            return NO_ROS
        return f"input {head}: rgbdnav fuses odom0 (wheels), imu0 (gyro) and its own vo0"
    return "not a robot_localization parameter rgbdnav implements"


SLAM_REASONS: Mapping[str, str] = {
    "transform_timeout": NO_ROS,
    "transform_publish_period": NO_ROS,
    "tf_buffer_duration": NO_ROS,
    "map_update_interval": NO_ROS,
    "debug_logging": NO_ROS,
    "stack_size_to_use": NO_ROS,
    "enable_interactive_mode": NO_ROS,
    "use_map_saver": "`map` always writes the map bundle",
    "solver_plugin": "the pose graph is optimised with GTSAM",
    "mode": "mapping vs localization is the verb: `map` or `localize`",
    "map_file_name": "`map --continue BUNDLE` extends a saved map",
    "map_start_pose": "`map --continue BUNDLE` extends a saved map",
    "map_start_at_dock": "`map --continue BUNDLE` extends a saved map",
    "use_scan_matching": "scans are always matched",
    "throttle_scans": "every scan is offered to the mapper",
}


def _by_name(section: str, section_type: type, reasons: Mapping[str, str], default: str) -> Any:
    def mapper(key: str, value: Any, what: str) -> tuple[str, Any, str] | str:
        if key in _fields(section_type):
            return f"{section}.{key}", value, ""
        if key.startswith("ceres_"):
            return "the pose graph is optimised with GTSAM"
        if key.endswith(("_frame", "_frame_id", "_topic", "_timeout")) or key in reasons:
            return reasons.get(key, NO_ROS)
        return default

    return mapper


def _costmap(node: str) -> Any:
    from nav.config import CostmapConfig

    def mapper(key: str, value: Any, what: str) -> tuple[str, Any, str] | str:
        leaf = key.rsplit(".", 1)[-1]
        if node == "local_costmap":
            return "one costmap (the global one) plans and follows; local_costmap not used"
        if leaf == "footprint":
            return "polygon footprints not implemented; robot_radius is used"
        if leaf in _fields(CostmapConfig):
            return f"costmap.{leaf}", value, ""
        if leaf.endswith(("_frame", "_topic", "_frequency")) or leaf in ("topic", "data_type"):
            return NO_ROS
        return "costmap layer parameter rgbdnav does not have"

    return mapper


def _controller(blocks: Mapping[str, Any]) -> Any:
    from nav.config import FollowerConfig

    plugin = str(blocks.get("FollowPath.plugin", ""))

    def mapper(key: str, value: Any, what: str) -> tuple[str, Any, str] | str:
        leaf = key.rsplit(".", 1)[-1]
        if key == "controller_frequency":
            return "follower.controller_frequency", value, ""
        if key.startswith("FollowPath."):
            if RPP_PLUGIN not in plugin:
                return f"controller plugin {plugin or '?'}: rgbdnav follows with RPP only"
            if leaf in _fields(FollowerConfig):
                return f"follower.{leaf}", value, ""
            return "RPP parameter rgbdnav does not implement"
        if leaf in ("xy_goal_tolerance", "yaw_goal_tolerance"):
            return f"follower.{leaf}", value, ""
        return "controller_server parameter rgbdnav does not implement"

    return mapper


def _planner(blocks: Mapping[str, Any]) -> Any:
    from nav.config import PlannerConfig

    plugin = str(blocks.get("GridBased.plugin", ""))

    def mapper(key: str, value: Any, what: str) -> tuple[str, Any, str] | str:
        leaf = key.rsplit(".", 1)[-1]
        if key.startswith("GridBased."):
            if NAVFN_PLUGIN not in plugin:
                return f"planner plugin {plugin or '?'}: rgbdnav plans like NavFn only"
            if leaf in _fields(PlannerConfig):
                return f"planner.{leaf}", value, ""
        return "planner_server parameter rgbdnav does not implement"

    return mapper


def _collision_monitor(blocks: Mapping[str, Any]) -> Any:
    def mapper(key: str, value: Any, what: str) -> tuple[str, Any, str] | str:
        name, _, leaf = key.rpartition(".")
        if leaf == "slowdown_ratio" and blocks.get(f"{name}.action_type") == "slowdown":
            return "collision_monitor.slowdown_ratio", value, ""
        if leaf in ("points", "radius", "type", "action_type"):
            return "zone shapes: rgbdnav's boxes are the footprint + collision_monitor.*_distance"
        if leaf.endswith(("_frame_id", "_topic", "_timeout", "topic")):
            return NO_ROS
        return "collision_monitor parameter rgbdnav does not implement"

    return mapper


def _mapper_for(node: str, params: Mapping[str, Any]) -> tuple[Any, str]:
    """(key mapper, kind) for a node, or (None, reason) for nodes rgbdnav does not map."""
    from nav.config import SmootherConfig
    from slam.config import LocalizerConfig, MapperConfig

    if node == "/**":
        return _wildcard, "all nodes"
    if "ekf" in node or "ukf" in node:
        return _ekf, "robot_localization"
    if "slam_toolbox" in node:
        return _by_name(
            "mapper",
            MapperConfig,
            SLAM_REASONS,
            "slam_toolbox parameter rgbdnav does not implement",
        ), "slam_toolbox"
    if node == "amcl":
        pf = "rgbdnav localises by scan-to-map matching, not a particle filter"
        return _by_name("localizer", LocalizerConfig, {}, pf), "AMCL"
    if node in ("global_costmap", "local_costmap"):
        return _costmap(node), "Nav2 costmap"
    if node == "controller_server":
        return _controller(params), "Nav2 controller"
    if node == "planner_server":
        return _planner(params), "Nav2 planner"
    if node == "velocity_smoother":
        return _by_name(
            "smoother", SmootherConfig, {}, "velocity_smoother parameter rgbdnav does not implement"
        ), "Nav2 velocity_smoother"
    if node == "collision_monitor":
        return _collision_monitor(params), "Nav2 collision_monitor"
    return None, f"node {node}: no rgbdnav counterpart"


def _validate(layer: Mapping[str, Mapping[str, Any]], source: str) -> None:
    """Build each section from one file's mapped keys, so a bad value names the file."""
    from rgbdnav.config import SECTIONS

    for section, values in layer.items():
        try:
            build_section(SECTIONS[section], values, section)
        except ConfigError as err:
            raise ConfigError(f"{source}: {err}") from None


def _wildcard(key: str, value: Any, what: str) -> tuple[str, Any, str] | str:
    """``/**`` applies to every node: a key only one of our ROS-named sections has maps."""
    from rgbdnav.config import SECTIONS

    owners = [s for s in ("ekf", "mapper", "localizer") if key in _fields(SECTIONS[s])]
    if len(owners) == 1:
        return f"{owners[0]}.{key}", value, ""
    if owners:
        return f"/** key in several sections ({', '.join(owners)}): set it under its node"
    return "no rgbdnav counterpart"


def load_ros_params(paths: Iterable[Path]) -> tuple[list[str], list[Row]]:
    """``section.key=value`` overrides (in file order, later files win) and a row per key."""
    overrides: list[str] = []
    rows: list[Row] = []
    for path in paths:
        data = read_yaml(
            path,
            ConfigError,
            "ROS parameter file",
            "{source}: line {line} is not valid YAML ({problem})",
        )
        layer: dict[str, dict[str, Any]] = {}
        for node, params in parameter_blocks(data, path):
            mapper, kind = _mapper_for(node, params)
            if mapper is None:
                rows.append(Row(path.name, node, f"({len(params)} keys)", "", reason=kind))
                continue
            for key, value in params.items():
                what = f"{path}: {node}: {key}"
                if key in COMMON_IGNORED or key.endswith(".plugin"):
                    rows.append(
                        Row(
                            path.name,
                            node,
                            key,
                            value,
                            reason=COMMON_IGNORED.get(key.rsplit(".", 1)[-1], "plugin name"),
                        )
                    )
                    continue
                result = mapper(key, value, what)
                if isinstance(result, str):
                    rows.append(Row(path.name, node, key, value, reason=result))
                    continue
                target, mapped, note = result
                section, name = target.split(".", 1)
                layer.setdefault(section, {})[name] = mapped
                overrides.append(f"{target}={json.dumps(mapped)}")
                rows.append(Row(path.name, node, key, value, target=target + note))
        _validate(layer, f"{path} (--ros-params)")
    return overrides, rows


def _short(value: Any, width: int = 28) -> str:
    text = json.dumps(value) if not isinstance(value, str) else value
    return text if len(text) <= width else text[: width - 3] + "..."


def format_table(rows: Iterable[Row]) -> str:
    """Applied keys one a line (-> section.key); ignored keys grouped by node and reason."""
    rows = list(rows)
    applied = [r for r in rows if r.target]
    ignored: dict[tuple[str, str], list[str]] = {}
    for r in rows:
        if not r.target:
            ignored.setdefault((r.node, r.reason), []).append(r.key)
    n_ignored = len(rows) - len(applied)
    lines = [f"ros-params: {len(applied)} applied, {n_ignored} ignored"]
    for r in applied:
        lines.append(f"  applied  {r.node}.{r.key} = {_short(r.value)} -> {r.target}")
    for (node, reason), keys in ignored.items():
        lines.append(f"  ignored  {node}: {', '.join(keys)} ({reason})")
    return "\n".join(lines)
