"""Ground-truth robot motion for the simulator and the encoder and gyro readings it causes.

The robot drives a waypoint route with a unicycle controller under speed and acceleration
limits (or replays a recorded trajectory). Encoders see that motion through the robot's *true*
geometry (wheel diameters and track that differ from the nominal ones), slip and gear backlash,
and report whole positions (36 per revolution on Eddie); odometry later integrates them with the
*nominal* geometry, which is where the drift comes from.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensors.config import RobotConfig, SimConfig
from sensors.sim.world import World
from sensors.tum import load_trajectory
from sensors.types import NS_PER_S, WorldError

HEADING_GAIN = 2.5  # [1/s] angular speed per radian of heading error
TURN_IN_PLACE_ANGLE = 0.35  # [rad] heading errors above this stop forward motion
SETTLE_TIME = 1.0  # [s] the robot stands still at the end of the route
ROUTE_TIME_FACTOR = 6.0  # give up when the route takes this many times its ideal duration
REPLAY_SMOOTHING = 0.1  # [s] moving-average window over replayed mocap poses


@dataclass(frozen=True, eq=False)
class Trajectory:
    """base_link in the world at the physics rate, with its body velocities."""

    t_ns: np.ndarray  # (M,) int64 [ns], starts at 0
    x: np.ndarray  # (M,) [m]
    y: np.ndarray  # (M,) [m]
    yaw: np.ndarray  # (M,) [rad], unwrapped (continuous)
    v: np.ndarray  # (M,) [m/s] forward speed over the step that *ends* at sample i
    w: np.ndarray  # (M,) [rad/s]

    @property
    def duration_s(self) -> float:
        return float(self.t_ns[-1] - self.t_ns[0]) / NS_PER_S

    def length_m(self) -> float:
        return float(np.hypot(np.diff(self.x), np.diff(self.y)).sum())

    def truncated(self, duration_s: float) -> Trajectory:
        keep = self.t_ns <= self.t_ns[0] + int(round(duration_s * NS_PER_S))
        return Trajectory(*(a[keep] for a in (self.t_ns, self.x, self.y, self.yaw, self.v, self.w)))

    def interpolate(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pose at arbitrary times (clamped to the trajectory's span)."""
        t = np.asarray(t_ns, dtype=np.float64)
        tt = self.t_ns.astype(np.float64)
        return np.interp(t, tt, self.x), np.interp(t, tt, self.y), np.interp(t, tt, self.yaw)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def drive_route(world: World, sim: SimConfig) -> Trajectory:
    """Drive ``world.route`` from ``world.start``: turn in place towards the next waypoint when the
    heading error is large, otherwise drive forward while steering; slow down before waypoints
    that need a sharp turn. Deterministic."""
    dt = 1.0 / sim.physics_rate
    x, y, th = world.start
    v = w = 0.0
    route = world.route
    ideal = (
        world.route_length() / sim.max_linear_speed + len(route) * math.pi / sim.max_angular_speed
    )
    max_steps = int(ROUTE_TIME_FACTOR * ideal / dt) + 1
    out = [(x, y, th, v, w)]
    i, settle = 0, 0
    for _ in range(max_steps):
        if i < len(route):
            dx, dy = route[i, 0] - x, route[i, 1] - y
            dist = math.hypot(dx, dy)
            if dist < sim.waypoint_tolerance:
                i += 1
                continue
            err = _wrap(math.atan2(dy, dx) - th)
            w_cmd = max(-sim.max_angular_speed, min(sim.max_angular_speed, HEADING_GAIN * err))
            if abs(err) > TURN_IN_PLACE_ANGLE:
                v_cmd = 0.0
            else:
                # Brake so the robot arrives slowly where the next leg needs a sharp turn.
                turn_next = (
                    i + 1 < len(route)
                    and abs(
                        _wrap(
                            math.atan2(route[i + 1, 1] - route[i, 1], route[i + 1, 0] - route[i, 0])
                            - math.atan2(dy, dx)
                        )
                    )
                    > TURN_IN_PLACE_ANGLE
                )
                reach = dist if (turn_next or i + 1 == len(route)) else math.inf
                v_cmd = min(sim.max_linear_speed, math.sqrt(2 * sim.max_linear_accel * reach))
                v_cmd *= math.cos(err)
        else:
            v_cmd = w_cmd = 0.0
            settle += 1
            if settle * dt >= SETTLE_TIME:
                break
        v += max(-sim.max_linear_accel * dt, min(sim.max_linear_accel * dt, v_cmd - v))
        w += max(-sim.max_angular_accel * dt, min(sim.max_angular_accel * dt, w_cmd - w))
        # Midpoint (second-order) integration of the unicycle over one step.
        x += v * dt * math.cos(th + w * dt / 2)
        y += v * dt * math.sin(th + w * dt / 2)
        th += w * dt
        out.append((x, y, th, v, w))
    else:
        raise WorldError(
            f"{world.source}: the robot did not finish the route within {max_steps * dt:.0f} s "
            f"(stuck before waypoint {i}: {route[min(i, len(route) - 1)].tolist()})"
        )
    arr = np.array(out)
    t_ns = np.round(np.arange(len(arr)) * dt * NS_PER_S).astype(np.int64)
    return Trajectory(t_ns, arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4])


def replay_tum(path: str | Path, robot: RobotConfig, sim: SimConfig) -> Trajectory:
    """A recorded camera trajectory (TUM, z up, planar motion, e.g. the TUM fr2/pioneer mocap)
    -> base_link trajectory at the physics rate, starting at t = 0."""
    stamps, xyz, quat = load_trajectory(path)
    if len(stamps) < 2:
        raise WorldError(f"{path}: a trajectory to replay needs at least 2 poses")
    qx, qy, qz, qw = quat.T
    # Third column of the rotation matrix: the optical axis (camera z) in the world.
    zx = 2 * (qx * qz + qw * qy)
    zy = 2 * (qy * qz - qw * qx)
    cam_yaw = np.unwrap(np.arctan2(zy, zx))
    yaw = cam_yaw  # camera looks along base_link x when camera_yaw = 0
    bx = xyz[:, 0] - (np.cos(yaw) * robot.camera_x - np.sin(yaw) * robot.camera_y)
    by = xyz[:, 1] - (np.sin(yaw) * robot.camera_x + np.cos(yaw) * robot.camera_y)
    t_rel = (stamps - stamps[0]).astype(np.float64) / NS_PER_S
    dt = 1.0 / sim.physics_rate
    t = np.arange(0.0, t_rel[-1], dt)
    x, y, th = (np.interp(t, t_rel, a) for a in (bx, by, yaw))
    k = max(1, int(round(REPLAY_SMOOTHING / dt)))
    if k > 1 and len(t) > 2 * k:
        kernel = np.ones(k) / k
        x, y, th = (
            np.convolve(np.pad(a, (k // 2, k - 1 - k // 2), mode="edge"), kernel, "valid")
            for a in (x, y, th)
        )
    v, w = body_velocities(x, y, th, dt)
    return Trajectory(np.round(t * NS_PER_S).astype(np.int64), x, y, th, v, w)


def body_velocities(
    x: np.ndarray, y: np.ndarray, yaw: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Forward speed and yaw rate over each step (sample i holds the step ending at i)."""
    dth = np.diff(yaw)
    ds = np.hypot(np.diff(x), np.diff(y))
    heading = np.arctan2(np.diff(y), np.diff(x))
    forward = np.cos(heading - (yaw[:-1] + dth / 2))
    v = np.concatenate([[0.0], np.sign(forward) * ds / dt])
    w = np.concatenate([[0.0], dth / dt])
    return v, w


def wheel_travel(traj: Trajectory, track_width: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground distance [m] each wheel covers per physics step for a given (true) track width."""
    dth = np.diff(traj.yaw)
    ds = np.hypot(np.diff(traj.x), np.diff(traj.y)) * np.sign(
        traj.v[1:] + 1e-12 * (traj.v[1:] == 0)
    )
    return ds - dth * track_width / 2, ds + dth * track_width / 2


def _backlash(angle: np.ndarray, play: float) -> np.ndarray:
    """Motor-side angle for a wheel angle seen through gear play: the motor leads the wheel by
    half the play in the direction of the last motion, and crosses the play on reversal."""
    if play <= 0 or len(angle) < 2:
        return angle
    step = np.sign(np.diff(angle))
    idx = np.where(step != 0, np.arange(len(step)), -1)
    last = np.maximum.accumulate(idx)  # index of the last non-zero step so far
    direction = np.where(last >= 0, step[np.maximum(last, 0)], 0.0)
    return angle + np.concatenate([[0.0], direction]) * play / 2


def correlated_noise(
    n: int, sigma: float, tau: float, dt: float, rng: np.random.Generator
) -> np.ndarray:
    """Stationary first-order Gauss-Markov (AR(1)) samples with std ``sigma`` and correlation
    time ``tau`` [s]: x_k = a x_(k-1) + sqrt(1 - a^2) sigma n_k, a = exp(-dt / tau).

    The recursion runs as a plain loop, the same operations as ``scipy.signal.lfilter([1],
    [1, -a], ...)`` and so the same bits (tested): importing scipy.signal cost ~1.5 s of CPU
    on the start-up path of every world run, before the renderer could start."""
    if n == 0:
        return np.zeros(0)
    a = math.exp(-dt / tau)
    white = rng.standard_normal(n) * sigma * math.sqrt(1 - a * a)
    white[0] = sigma * rng.standard_normal()  # start in the stationary distribution
    out = white.tolist()
    x = 0.0
    for k, w in enumerate(out):
        x = w + a * x
        out[k] = x
    return np.array(out)


def diff_drive_step(
    pose: np.ndarray, d_left: float, d_right: float, track_width: float
) -> np.ndarray:
    """Midpoint integration of the wheels' ground travel (d_left, d_right [m]) on a track [m]:
    ds = (dR + dL) / 2, dtheta = (dR - dL) / track, x += ds cos(theta + dtheta / 2)."""
    ds = 0.5 * (d_left + d_right)
    dth = (d_right - d_left) / track_width
    mid = pose[2] + 0.5 * dth
    return np.array(
        [pose[0] + ds * math.cos(mid), pose[1] + ds * math.sin(mid), float(_wrap(pose[2] + dth))]
    )


def gauss_markov_step(
    x: np.ndarray, sigma: float, tau_s: float, dt_s: float, noise: np.ndarray
) -> np.ndarray:
    """One AR(1) step with stationary std ``sigma`` and correlation time ``tau_s`` [s]:
    x' = a x + sqrt(1 - a^2) sigma n, a = exp(-dt / tau); ``noise`` is standard normal."""
    a = math.exp(-dt_s / tau_s)
    return a * x + math.sqrt(1.0 - a * a) * sigma * noise


def encoder_counts(
    traj: Trajectory, robot: RobotConfig, sim: SimConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative encoder positions (left, right) at every physics sample, starting at 0."""
    true_track = robot.track_width * (1 + sim.track_width_error)
    s_left, s_right = wheel_travel(traj, true_track)
    counts = []
    dt = 1.0 / sim.physics_rate
    for s, err in ((s_left, sim.wheel_diameter_error[0]), (s_right, sim.wheel_diameter_error[1])):
        slip = 1 + correlated_noise(len(s), sim.wheel_slip, sim.slip_correlation_time, dt, rng)
        true_radius = robot.wheel_diameter * (1 + err) / 2
        wheel_angle = np.concatenate([[0.0], np.cumsum(s * slip)]) / true_radius
        motor = _backlash(wheel_angle, sim.backlash)
        counts.append(np.floor(motor / (2 * math.pi / robot.ticks_per_revolution) + 1e-9))
    return counts[0].astype(np.int64), counts[1].astype(np.int64)


def sample_times(duration_ns: int, rate_hz: float) -> np.ndarray:
    """Nominal sample times 0, 1/rate, ... within [0, duration]."""
    period = NS_PER_S / rate_hz
    n = int(duration_ns // period) + 1
    return np.round(np.arange(n) * period).astype(np.int64)


def blocked_step(
    pose: np.ndarray,
    d_left: float,
    d_right: float,
    track_width: float,
    is_free: Callable[[float, float], bool],
    wheel_slip: float,
) -> tuple[np.ndarray, float, float, str]:
    """One physics step of a round robot that may run into something.

    The wheels want to travel (``d_left``, ``d_right``) [m] (:func:`diff_drive_step`); the body
    stays where ``is_free(x, y)`` (the footprint's centre keeps its clearance). Returns (new pose,
    left and right encoder travel [m], outcome):

    - ``"free"``: the whole motion; the encoders see the commanded travel.
    - ``"slid"``: the full motion is blocked but its x or y part alone is not (the larger one
      wins): the robot slides along the wall, turning as commanded. The wheels roll by the
      achieved forward motion ``ds_a = d_a . (cos th_mid, sin th_mid)``; the sideways part is
      skid the encoders never see.
    - ``"blocked"``: neither part is free; the robot only turns (always possible for a round
      robot in a free cell).

    When blocked, a real wheel mostly stalls against the obstacle (the motor's current limit) and
    slips a little: the encoders advance by the achieved travel plus ``wheel_slip`` (0..1) of
    the travel that was refused, ``d_enc = d_a + wheel_slip (d - d_a)``.
    """
    full = diff_drive_step(pose, d_left, d_right, track_width)
    if is_free(float(full[0]), float(full[1])):
        return full, d_left, d_right, "free"
    x, y = float(pose[0]), float(pose[1])
    dth = (d_right - d_left) / track_width
    mid = float(pose[2]) + 0.5 * dth
    candidates = [(abs(full[0] - x), full[0], y), (abs(full[1] - y), x, full[1])]
    candidates.sort(key=lambda c: -c[0])
    new, outcome = np.array([x, y, full[2]]), "blocked"
    for size, cx, cy in candidates:
        if size > 0.0 and is_free(float(cx), float(cy)):
            new, outcome = np.array([cx, cy, full[2]]), "slid"
            break
    ds_a = (new[0] - x) * math.cos(mid) + (new[1] - y) * math.sin(mid)  # [m] achieved forward
    half_turn = 0.5 * dth * track_width
    a_left, a_right = ds_a - half_turn, ds_a + half_turn  # [m] what the body let them roll
    enc_left = a_left + wheel_slip * (d_left - a_left)
    enc_right = a_right + wheel_slip * (d_right - a_right)
    return new, enc_left, enc_right, outcome
