"""Planar EKF with robot_localization semantics: fuses wheel odometry, visual odometry and a gyro
into ``odom -> base_link``.

State (two_d_mode subset of robot_localization's 15-vector, world-frame pose, body-frame rates)::

    x = [x, y, yaw, vx, vy, vyaw]        [m, m, rad, m/s, m/s, rad/s]

Layout follows filterpy: pure kernels (:func:`predict`, :func:`update`, :func:`innovate`) over
arrays, and a thin stateful shell (:class:`PlanarEkf`) that turns sensor messages into
measurements, gates them, keeps the history for late data and reports what it did.
:func:`fuse` runs a whole log offline.

robot_localization behaviour reproduced here (see the module-level notes on each function):

* ``*_config`` vectors pick the measured variables; a pose message updates x/y/yaw, a twist
  message vx/vy/vyaw, each as its own update with its own Mahalanobis gate.
* ``*_rejection_threshold`` is in standard deviations: a measurement is rejected when its squared
  Mahalanobis distance (NIS) reaches ``threshold**2``.
* ``*_differential``: consecutive poses of a sensor are differenced (``prev^-1 * cur``), turned
  into a body-frame velocity and fused into vx/vy/vyaw where the pose flags were set.
* ``*_relative``: the first pose of a sensor is removed from all its later poses.
* ``process_noise_covariance`` is per second: ``P += dt * Q``.
* ``sensor_timeout``: without data for that long the filter only predicts and says so.
* ``smooth_lagged_data`` / ``history_length``: a measurement older than the filter time is
  fused by reverting to the last state at or before it and re-filtering everything since.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from bisect import bisect_right
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from operator import attrgetter
from typing import NamedTuple

import numpy as np

from sensors.config import RobotConfig
from sensors.types import NS_PER_S, ImuSample, Odometry2D, Pose2, RgbdNavError
from slam.config import STATE_NAMES, EkfConfig
from slam.diff_drive import WheelErrorModel, wheel_increments
from slam.geometry import between as se2_between
from slam.geometry import rotate_covariance, wrap_angle

log = logging.getLogger(__name__)

# 1. State layout.
X, Y, YAW, VX, VY, VYAW, GYRO_BIAS = range(7)
STATE_DIM = 7  # the planar state and the gyro's z bias [rad/s]
PLANAR_NAMES = ("x", "y", "yaw", "vx", "vy", "vyaw")
PLANAR_INDEX = tuple(STATE_NAMES.index(n) for n in PLANAR_NAMES)  # into the 15-vectors
POSE_IDX = np.array([X, Y, YAW])
TWIST_IDX = np.array([VX, VY, VYAW])

# 2. Named constants (physics / numerics, not tunables).
MIN_MEASUREMENT_VARIANCE = 1e-9  # [unit^2] floor on R's diagonal, as robot_localization does
NONHOLONOMIC_VY_VARIANCE = 1e-4  # [(m/s)^2] sigma 1 cm/s on the vy = 0 pseudo-measurement
QUANTISATION_FACTOR = 1.0 / 6.0  # var of the difference of two readings rounded to 1 tick [tick^2]
# Wheel twist variance from the mean travel over this long (wheel_twist_inputs): long enough that
# a measurement's weight no longer follows its own tick count (an Eddie tick is 13 mm, so at
# 0.3 m/s most 20 ms intervals count 0 or 1), short against a stop-and-go cycle. Distance lost
# by a wheel-only filter at 0.3 m/s: 10.5 % with the interval's own count, 1.5 % at 0.1 s,
# 0.6 % at 0.5 s (tests/slam/test_ekf.py); house route fused: 3 % -> 0.1 %.
WHEEL_VARIANCE_WINDOW_S = 0.5  # [s]

Residual = Callable[[np.ndarray, np.ndarray], np.ndarray]


class EkfError(RgbdNavError):
    """The EKF was asked for something it cannot give (e.g. a state before its history)."""


# --- kernels ----------------------------------------------------------------------------------


def angle_residual(angle_rows: np.ndarray) -> Residual:
    """A residual ``a - b`` with the rows flagged in ``angle_rows`` wrapped into [-pi, pi)."""
    rows = np.asarray(angle_rows, dtype=bool)

    def residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        r = np.asarray(a, dtype=np.float64) - b
        if rows.any():
            r[rows] = (r[rows] + math.pi) % (2 * math.pi) - math.pi
        return r

    return residual


def transition(x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity planar motion f(x, dt) and its Jacobian F = df/dx.

    With c = cos(yaw), s = sin(yaw) and body-frame velocities (robot_localization's model with
    roll = pitch = 0 and no acceleration states)::

        x'    = x + (vx c - vy s) dt
        y'    = y + (vx s + vy c) dt
        yaw'  = yaw + vyaw dt
        v*'   = v*

        F = I + [[0, 0, -(vx s + vy c) dt, c dt, -s dt, 0 ],
                 [0, 0,  (vx c - vy s) dt, s dt,  c dt, 0 ],
                 [0, 0,  0,                0,     0,    dt],
                 [0 ...                                   ]]
    """
    c, s = math.cos(x[YAW]), math.sin(x[YAW])
    vx, vy = x[VX], x[VY]
    xn = x.copy()
    xn[X] += (vx * c - vy * s) * dt
    xn[Y] += (vx * s + vy * c) * dt
    xn[YAW] = wrap_angle(x[YAW] + x[VYAW] * dt)
    f = np.eye(len(x))  # the gyro bias (when present) is a random walk: F = 1 there
    f[X, YAW] = -(vx * s + vy * c) * dt
    f[X, VX], f[X, VY] = c * dt, -s * dt
    f[Y, YAW] = (vx * c - vy * s) * dt
    f[Y, VX], f[Y, VY] = s * dt, c * dt
    f[YAW, VYAW] = dt
    return xn, f


def predict(
    x: np.ndarray, P: np.ndarray, dt: float, Q: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Propagate (x, P) by ``dt`` [s]: x = f(x), P = F P F^T + dt Q.

    ``Q`` is the process noise *per second* (robot_localization's process_noise_covariance is
    scaled by the time step the same way).
    """
    xn, f = transition(x, dt)
    Pn = f @ P @ f.T + dt * Q
    return xn, (Pn + Pn.T) / 2  # exact symmetry despite round-off


def innovate(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    residual_fn: Residual = np.subtract,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Innovation y = z - Hx (through ``residual_fn``), its covariance S = H P H^T + R and the
    normalised innovation squared NIS = y^T S^-1 y (the squared Mahalanobis distance)."""
    y = residual_fn(z, H @ x)
    S = H @ P @ H.T + R
    nis = float(y @ np.linalg.solve(S, y))
    return y, S, nis


def update(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    residual_fn: Residual = np.subtract,
    rows: np.ndarray | None = None,
    known: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Kalman update -> (x, P, innovation, S, nis).

    K = P H^T S^-1;  x += K y;  Joseph form P = (I - K H) P (I - K H)^T + K R K^T, which stays
    symmetric positive semi-definite for any gain (unlike (I - K H) P), then symmetrised against
    round-off. With ``rows`` and ``known``, the gain of those state rows is the one they would
    have if state ``known`` were exact: their covariance conditioned on it,
    ``P[r] - P[r, k] P[k] / P[k, k]``, so they take no share of its correction (the Joseph form
    keeps P the covariance of that estimate).
    """
    y, S, nis = innovate(x, P, z, H, R, residual_fn)
    K = np.linalg.solve(S, H @ P).T  # = P H^T S^-1, S and P symmetric
    if rows is not None and known is not None and P[known, known] > 0:
        pr = P[rows] - np.outer(P[rows, known], P[known]) / P[known, known]
        K[rows] = np.linalg.solve(S, H @ pr.T).T
    xn = x + K @ y
    ikh = np.eye(len(x)) - K @ H
    Pn = ikh @ P @ ikh.T + K @ R @ K.T
    return xn, (Pn + Pn.T) / 2, y, S, nis


def pose_update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`update` for a direct planar pose measurement (x, y, yaw; H = I): the yaw residual
    and the updated yaw wrapped. Scan-match fusion in the mapper and the localiser."""
    xn, Pn, _, _, _ = update(x, P, z, np.eye(3), R, angle_residual(np.array([False, False, True])))
    xn[2] = wrap_angle(xn[2])
    return xn, Pn


def passes_gate(nis: float, threshold_sigma: float) -> bool:
    """robot_localization's checkMahalanobisThreshold: accept while NIS < threshold^2."""
    return nis < threshold_sigma * threshold_sigma


# --- inputs -----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PoseInput:
    """A pose measurement of base_link in the sensor's own world frame (e.g. VO's odom)."""

    stamp_ns: int  # [ns]
    pose: Pose2
    covariance: np.ndarray  # (3, 3) over x [m], y [m], yaw [rad]
    valid: bool = True  # False = the sensor failed on this frame (e.g. VO lost): skipped


@dataclass(frozen=True, eq=False)
class TwistInput:
    """A body-frame velocity measurement of base_link."""

    stamp_ns: int  # [ns]
    vx: float  # [m/s]
    vy: float  # [m/s]
    vyaw: float  # [rad/s]
    covariance: np.ndarray  # (3, 3) over vx, vy, vyaw
    valid: bool = True


@dataclass(frozen=True, eq=False)
class GyroBiasInput:
    """A direct measurement of the gyro z bias: the mean gyro reading while the robot stood
    still (slam.front_end: the wheels unchanged), fused as sensor ``imu0``."""

    stamp_ns: int  # [ns]
    bias: float  # [rad/s]
    variance: float  # [(rad/s)^2] of the mean
    # The textbook update: the pose takes its share of the bias's correction. For a robot
    # that has not moved yet (start-up): its heading error is the unknown bias's alone, and
    # without a path behind it nothing can step sideways.
    moves_pose: bool = False
    valid: bool = True


Message = PoseInput | TwistInput | ImuSample | Odometry2D | GyroBiasInput
DEFAULT_WHEEL_ERROR = WheelErrorModel()


def motion_twist(stamp_ns: int, delta: Pose2, covariance: np.ndarray, dt_s: float) -> TwistInput:
    """A planar motion (dx, dy, dyaw) measured over ``dt_s`` (e.g. one VO frame pair) as a
    body twist: v = delta / dt, its covariance scaled by 1 / dt^2."""
    return TwistInput(
        stamp_ns,
        delta.x / dt_s,
        delta.y / dt_s,
        delta.yaw / dt_s,
        np.asarray(covariance, dtype=np.float64) / dt_s**2,
    )


MAX_SPREAD_STEPS = 8  # a gap is cut into at most this many steps (interval_twists)


def interval_twists(
    start_ns: int,
    end_ns: int,
    mean: TwistInput,
    marks_ns: Sequence[int] = (),
    max_step_s: float | None = None,
) -> list[TwistInput]:
    """A body twist ``mean`` measured as the mean velocity over ``(start_ns, end_ns]`` (with the
    covariance of that mean) as one twist per step of the interval: at every stamp of
    ``marks_ns`` inside it and at ``end_ns``, with any gap longer than ``max_step_s`` between
    consecutive stamps cut into equal steps. Each of the k twists carries k times the mean's
    covariance, so together they hold the information of one measurement.

    Why: an EKF fusing a twist at the end of its interval corrects the velocity only from then
    on; over the interval the pose follows the velocity the filter had before. After a gap
    (a board reply that came a second late, frames the front end skipped or dropped while the
    robot spun at 35 deg/s) the heading then misses most of the turn made in the gap: a live
    soak lost 24 deg in one 5 s spin this way, although the wheels had counted the turn to
    within 2 deg."""
    stamps = sorted({int(s) for s in marks_ns if start_ns < s < end_ns} | {int(end_ns)})
    if max_step_s is not None and max_step_s > 0 and end_ns > start_ns:
        # Each piece older than the filter's newest state costs a re-filter of the history
        # after it: a 2 s gap in 1/30 s steps took 0.2 s here; at most MAX_SPREAD_STEPS cuts.
        step_ns = max(max_step_s * NS_PER_S, (end_ns - start_ns) / MAX_SPREAD_STEPS)
        cut: list[int] = []
        prev = int(start_ns)
        for s in stamps:
            n = max(1, math.ceil((s - prev) / step_ns - 1e-9))
            cut.extend(prev + (s - prev) * i // n for i in range(1, n + 1))
            prev = s
        stamps = cut
    k = len(stamps)
    cov = np.asarray(mean.covariance, dtype=np.float64) * k
    return [replace(mean, stamp_ns=s, covariance=cov) for s in stamps]


def spanning_motion_twists(
    skipped_ns: Sequence[int],
    stamp_ns: int,
    delta: Pose2,
    covariance: np.ndarray,
    dt_s: float,
    max_step_s: float | None = None,
) -> list[TwistInput]:
    """A planar motion measured over ``dt_s`` that spans frames it skipped (``skipped_ns``, the
    stamps in between; a live front end behind skips VO on frames) as the span's mean velocity
    at each skipped stamp and at ``stamp_ns`` (:func:`interval_twists`; also every
    ``max_step_s`` where frames were dropped, not skipped). On the house recording with VO
    skipped on 15 % of the frames in bursts of 1-4, the live settings' fused ATE is 0.299 m with
    one twist at the span's end and 0.123 m this way (0.134 m with VO on every frame):
    ``bench/bench_vo_gaps.py``."""
    one = motion_twist(stamp_ns, delta, covariance, dt_s)
    return interval_twists(stamp_ns - round(dt_s * NS_PER_S), stamp_ns, one, skipped_ns, max_step_s)


def wheel_twist_inputs(
    stamps_ns: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    robot: RobotConfig,
    model: WheelErrorModel = DEFAULT_WHEEL_ERROR,
    vy_variance: float = NONHOLONOMIC_VY_VARIANCE,
    variance_window_s: float = WHEEL_VARIANCE_WINDOW_S,
    last_only: bool = False,
    max_interval_s: float | None = None,
) -> list[TwistInput]:
    """Encoder counts -> one :class:`TwistInput` per interval, stamped at its end (only the
    last interval's with ``last_only``: live, one new reading at a time).

    Per interval of dt with wheel travels dR, dL [m], tick length q [m] and track b::

        v = (dR + dL) / (2 dt),  w = (dR - dL) / (b dt),  vy = 0 (non-holonomic)
        var(dR) = k_r <|dR|> + q^2/6,  var(dL) = k_l <|dL|> + q^2/6  (error model + quantisation)
        var(v) = (var dR + var dL) / (4 dt^2),  var(w) = (var dR + var dL) / (b^2 dt^2)
        cov(v, w) = (var dR - var dL) / (2 b dt^2)

    ``<|d|>`` is the mean travel per interval over the intervals ending within the last
    ``variance_window_s`` (causal). The interval's own travel would make each measurement's
    weight depend on its own noise: an interval that happened to count fewer ticks (or none,
    crawling) is trusted more than one that counted more, and the filter's speed comes out low
    (measured on the house route: fused distance 3 % short, 0.1 % with the window).
    Pass a few earlier readings for the window to act on (e.g. live, one new reading at a time).
    An interval longer than ``max_interval_s`` (a reading that came late) is spread over its
    span (:func:`interval_twists`) instead of one twist at its end.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    ds, dth = wheel_increments(left, right, robot)
    dt = np.diff(stamps) / NS_PER_S
    b = robot.track_width
    d_right, d_left = ds + b * dth / 2, ds - b * dth / 2
    quant = QUANTISATION_FACTOR * robot.metres_per_tick**2
    # Causal window mean of |travel| per interval (cumulative sums: no loop over intervals).
    ends = stamps[1:]
    idx = np.arange(len(ends))
    first = np.minimum(
        np.searchsorted(ends, ends - int(variance_window_s * NS_PER_S), side="right"), idx
    )  # always the interval itself
    count = idx + 1 - first

    def window_mean(d: np.ndarray) -> np.ndarray:
        c = np.concatenate([[0.0], np.cumsum(np.abs(d))])
        return (c[1:] - c[first]) / count

    var_r = model.k_right * window_mean(d_right) + quant
    var_l = model.k_left * window_mean(d_left) + quant
    cov = np.zeros((len(dt), 3, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        cov[:, 0, 0] = (var_r + var_l) / (4 * dt**2)
        cov[:, 2, 2] = (var_r + var_l) / (b * dt) ** 2
        cov[:, 0, 2] = cov[:, 2, 0] = (var_r - var_l) / (2 * b * dt**2)
        v, w = ds / dt, dth / dt
    cov[:, 1, 1] = vy_variance
    ok = dt > 0
    out: list[TwistInput] = []
    for i in range(len(dt) - 1 if last_only and len(dt) else 0, len(dt)):
        end = int(stamps[i + 1])
        tw = TwistInput(end, float(v[i]), 0.0, float(w[i]), cov[i], valid=bool(ok[i]))
        if ok[i] and max_interval_s is not None and dt[i] > max_interval_s:
            out.extend(interval_twists(int(stamps[i]), end, tw, (), max_interval_s))
        else:
            out.append(tw)
    return out


# --- sensors and measurements ------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SensorSpec:
    """One robot_localization input (odom0, vo0, imu0) reduced to the planar state."""

    name: str
    pose_mask: np.ndarray  # (3,) bool over x, y, yaw
    twist_mask: np.ndarray  # (3,) bool over vx, vy, vyaw
    differential: bool
    relative: bool
    pose_threshold: float  # [sigma]
    twist_threshold: float  # [sigma]


SENSOR_NAMES = ("odom0", "vo0", "imu0")


def sensor_specs(cfg: EkfConfig) -> dict[str, SensorSpec]:
    """Map each ``<sensor>_config`` 15-vector onto (x, y, yaw | vx, vy, vyaw).

    Planar only: with two_d_mode false, flags on z, roll, pitch or their rates cannot be honoured
    and raise :class:`EkfError`; in two_d_mode they are ignored, as robot_localization does.
    """
    out = {}
    for name in SENSOR_NAMES:
        flags = np.array(getattr(cfg, f"{name}_config"), dtype=bool)
        planar = flags[list(PLANAR_INDEX)]
        if not cfg.two_d_mode and flags.sum() != planar.sum():
            raise EkfError(f"{name}_config sets 3D variables but the planar EKF needs two_d_mode")
        out[name] = SensorSpec(
            name,
            planar[:3].copy(),
            planar[3:].copy(),
            bool(getattr(cfg, f"{name}_differential")),
            bool(getattr(cfg, f"{name}_relative")),
            float(getattr(cfg, f"{name}_pose_rejection_threshold")),
            float(getattr(cfg, f"{name}_twist_rejection_threshold")),
        )
    return out


@dataclass(frozen=True, eq=False)
class Measurement:
    """A measurement ready for the filter: rows ``idx`` of the state, in state units."""

    stamp_ns: int  # [ns]
    sensor: str
    kind: str  # "pose" or "twist"
    idx: np.ndarray  # (m,) int state indices
    z: np.ndarray  # (m,)
    R: np.ndarray  # (m, m)
    threshold: float  # [sigma]
    gyro: bool = False  # from a gyro: its vyaw row reads vyaw + the gyro bias state
    moves_pose: bool = False  # a bias measurement that may move the pose (GyroBiasInput)


@dataclass(frozen=True)
class UpdateResult:
    """What one measurement did: NIS, dof, whether the gate let it through, and why not."""

    stamp_ns: int  # [ns]
    sensor: str
    kind: str
    accepted: bool
    nis: float  # y^T S^-1 y (nan when not computed)
    dof: int
    # "", "initialised", "rejected", "late_refiltered", "dropped_late", "before_start", ...
    reason: str = ""


@dataclass
class _SensorStats:
    received: int = 0
    fused: int = 0
    rejected: int = 0
    invalid: int = 0  # messages flagged invalid by the sensor (VO lost): skipped
    dropped_late: int = 0  # older than the filter and not recoverable from history
    before_start: int = 0  # at or before the instant the filter started without a measurement
    refiltered: int = 0  # late measurements fused by re-filtering from history
    timeouts: int = 0  # times the sensor went silent for longer than sensor_timeout


@dataclass(frozen=True)
class EkfStats:
    """Counters per sensor (a snapshot) and the number of predict-only outputs."""

    sensors: Mapping[str, Mapping[str, int]]
    timed_out_outputs: int = 0
    stale_sensors: tuple[str, ...] = ()

    def total(self, key: str) -> int:
        return sum(s[key] for s in self.sensors.values())


@dataclass
class _Entry:
    """Filter state right after ``meas`` was processed (or the initial state when None)."""

    stamp_ns: int
    x: np.ndarray
    P: np.ndarray
    meas: Measurement | None
    accepted: bool


_STAMP = attrgetter("stamp_ns")  # a history entry's sort key (bisect on the list itself)


def _observation(m: Measurement) -> np.ndarray:
    """H of a measurement: ones at its state rows (a gyro's vyaw also sees the gyro bias)."""
    H = np.zeros((len(m.idx), STATE_DIM))
    H[np.arange(len(m.idx)), m.idx] = 1.0
    if m.gyro:
        H[m.idx == VYAW, GYRO_BIAS] = 1.0
    return H


def _cov3(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float64).reshape(3, 3)
    return (c + c.T) / 2


# --- the filter -------------------------------------------------------------------------------


class PlanarEkf:
    """Thin stateful shell: per-sensor preprocessing, gating, history and outputs.

    Use :meth:`process` with messages in arrival order and :meth:`state_at` for outputs. The
    filter starts at the first measurement: measured variables are copied into the state (as
    robot_localization does), the rest stay at ``x0``; P starts at initial_estimate_covariance.

    A twist or gyro update moves the pose (x, y, yaw) only as it would if the gyro bias were
    known (robot_localization has no bias state): the bias remembers the whole run, and through
    its cross-covariance with the pose the textbook update turned every VO or wheel yaw-rate
    innovation into a retroactive jump, sideways by up to 3.4 cm on the house route, which a
    differential drive cannot make and the odom frame must not (REP-105: continuous). The rates'
    own short-memory correction of the pose is kept. ``twist_moves_pose`` restores the textbook
    update for comparison (docs/design/ekf_lateral.md).
    """

    twist_moves_pose = False  # True: the textbook update (bench/diag_ekf_lateral.py --textbook)

    def __init__(
        self,
        cfg: EkfConfig,
        gyro_z_variance: float = 1e-4,
        x0: np.ndarray | None = None,
    ) -> None:
        if (err := cfg.validate()) is not None:
            raise EkfError(err)
        self.cfg = cfg
        self.specs = sensor_specs(cfg)
        self.gyro_z_variance = gyro_z_variance  # [(rad/s)^2] ImuSample carries no covariance
        # The gyro bias is a random walk: without it a biased gyro, trusted for yaw rate, turns
        # the whole fused heading (robot_localization has no such state; users subtract it).
        self.Q = np.diag(
            np.append(
                np.asarray(cfg.process_noise_covariance, dtype=np.float64)[list(PLANAR_INDEX)],
                cfg.imu0_gyro_bias_process_noise,
            )
        )
        self.P0 = np.diag(
            np.append(
                np.asarray(cfg.initial_estimate_covariance, dtype=np.float64)[list(PLANAR_INDEX)],
                cfg.imu0_gyro_bias_initial_variance,
            )
        )
        self.x = np.zeros(STATE_DIM) if x0 is None else np.asarray(x0, dtype=np.float64).copy()
        self.P = self.P0.copy()
        self.t_ns: int | None = None  # time of the last processed measurement
        self.timeout_ns = int(round(cfg.sensor_timeout * NS_PER_S))
        self.history_ns = int(round(cfg.history_length * NS_PER_S))
        self._history: list[_Entry] = []
        self._stats = {n: _SensorStats() for n in SENSOR_NAMES}
        self._last_seen: dict[str, int] = {}
        self._stale: set[str] = set()
        self._prev_pose: dict[str, tuple[int, Pose2, np.ndarray]] = {}
        self._first_pose: dict[str, Pose2] = {}
        self.timed_out_outputs = 0

    def start(self, stamp_ns: int) -> None:
        """Start the filter at ``x0`` at ``stamp_ns`` without a measurement: the odom frame is
        where the robot is now (REP-105). For a front end whose only motion input is a twist
        (VO): its first twist would otherwise set the pose at the twist's end, losing the
        first pair's motion. No effect once the filter has a state."""
        if self.t_ns is None:
            self.t_ns = int(stamp_ns)
            self._history.append(_Entry(self.t_ns, self.x.copy(), self.P.copy(), None, True))

    # 1. Messages -> measurements (per sensor, in arrival order, like robot_localization's
    #    callbacks: differential and relative state depends on what that sensor sent before).

    def _measurements(self, sensor: str, msg: Message) -> list[Measurement]:
        spec = self.specs[sensor]
        if isinstance(msg, Odometry2D):
            msg = PoseInput(msg.stamp_ns, msg.pose, msg.covariance)
        if isinstance(msg, ImuSample):
            # A gyro measures vyaw (+ its bias) only: the nan rows are never fused.
            cov = np.diag([1.0, 1.0, self.gyro_z_variance])
            z = np.array([math.nan, math.nan, msg.gyro_z])
            made = self._make(
                sensor, msg.stamp_ns, "twist", spec.twist_mask, z, cov, spec.twist_threshold
            )
            return [dataclasses.replace(m, gyro=True) for m in made]
        if isinstance(msg, GyroBiasInput):
            var = max(msg.variance, MIN_MEASUREMENT_VARIANCE)
            return [
                Measurement(
                    int(msg.stamp_ns),
                    sensor,
                    "bias",
                    np.array([GYRO_BIAS]),
                    np.array([msg.bias]),
                    np.array([[var]]),
                    spec.twist_threshold,
                    moves_pose=msg.moves_pose,
                )
            ]
        if isinstance(msg, TwistInput):
            z = np.array([msg.vx, msg.vy, msg.vyaw])
            return self._make(
                sensor,
                msg.stamp_ns,
                "twist",
                spec.twist_mask,
                z,
                _cov3(msg.covariance),
                spec.twist_threshold,
            )
        if not isinstance(msg, PoseInput):
            raise EkfError(f"{sensor}: cannot fuse a {type(msg).__name__}")
        cov = _cov3(msg.covariance)
        if spec.differential:
            return self._differential(spec, msg, cov)
        pose = msg.pose
        if spec.relative:
            first = self._first_pose.setdefault(sensor, pose)
            pose = se2_between(first, pose)
            cov = rotate_covariance(cov, -first.yaw)
        z = np.array([pose.x, pose.y, pose.yaw])
        return self._make(sensor, msg.stamp_ns, "pose", spec.pose_mask, z, cov, spec.pose_threshold)

    def _differential(self, spec: SensorSpec, msg: PoseInput, cov: np.ndarray) -> list[Measurement]:
        """Pose -> body-frame twist: delta = prev^-1 * cur over dt = t - t_prev.

        ``z = (dx, dy, dyaw) / dt`` in the previous body frame, fused into vx, vy, vyaw where the
        x, y, yaw flags were set. Covariance: both poses' errors rotated into that frame,
        ``R = Rot (S_prev + S_cur) Rot^T / dt^2`` (independent pose errors; robot_localization
        instead uses ``(S_prev + S_cur) * dt``, which is not in velocity units).
        """
        prev = self._prev_pose.get(spec.name)
        self._prev_pose[spec.name] = (msg.stamp_ns, msg.pose, cov)
        if prev is None:
            return []
        t_prev, p_prev, c_prev = prev
        dt = (msg.stamp_ns - t_prev) / NS_PER_S
        if dt <= 0:
            return []
        d = se2_between(p_prev, msg.pose)
        R = rotate_covariance(c_prev + cov, -p_prev.yaw) / dt**2
        z = np.array([d.x, d.y, d.yaw]) / dt
        return self._make(
            spec.name, msg.stamp_ns, "twist", spec.pose_mask, z, R, spec.pose_threshold
        )

    @staticmethod
    def _make(
        sensor: str,
        stamp_ns: int,
        kind: str,
        mask: np.ndarray,
        z: np.ndarray,
        R: np.ndarray,
        threshold: float,
    ) -> list[Measurement]:
        rows = np.flatnonzero(mask & np.isfinite(z))  # nan/inf values are excluded, as upstream
        if rows.size == 0:
            return []
        r = R[np.ix_(rows, rows)].copy()
        d = np.abs(np.diag(r))
        np.fill_diagonal(r, np.maximum(d, MIN_MEASUREMENT_VARIANCE))
        base = POSE_IDX if kind == "pose" else TWIST_IDX
        return [Measurement(int(stamp_ns), sensor, kind, base[rows], z[rows], r, threshold)]

    # 2. The filter proper.

    def _apply(self, m: Measurement) -> UpdateResult:
        """Predict to the measurement's time, gate, update; record the state in the history."""
        st = self._stats[m.sensor]
        if self.t_ns is None:
            # robot_localization (FilterBase::processMeasurement): the first measurement sets
            # the measured variables and their covariance. Left at initial_estimate_covariance
            # (1e-9), a first wheel yaw rate was taken as exact and the gyro's first sample
            # beside it set the gyro bias to the wheel's noise.
            self.x[m.idx] = m.z
            self.P[np.ix_(m.idx, m.idx)] = m.R
            self.x[YAW] = wrap_angle(self.x[YAW])
            self.t_ns = m.stamp_ns
            self._history.append(_Entry(m.stamp_ns, self.x.copy(), self.P.copy(), m, True))
            st.fused += 1
            return UpdateResult(
                m.stamp_ns, m.sensor, m.kind, True, math.nan, len(m.idx), "initialised"
            )
        dt = (m.stamp_ns - self.t_ns) / NS_PER_S
        x, P = (self.x, self.P) if dt <= 0 else predict(self.x, self.P, dt, self.Q)
        H = _observation(m)
        textbook = self.twist_moves_pose or m.moves_pose
        bias_known = POSE_IDX if m.kind in ("twist", "bias") and not textbook else None
        xu, Pu, _, _, nis = update(
            x, P, m.z, H, m.R, angle_residual(m.idx == YAW), bias_known, GYRO_BIAS
        )
        accepted = passes_gate(nis, m.threshold)
        if accepted:
            xu[YAW] = wrap_angle(xu[YAW])
            self.x, self.P = xu, Pu
            st.fused += 1
        else:
            self.x, self.P = x, P  # the prediction stands, the correction is dropped
            st.rejected += 1
        self.t_ns = max(self.t_ns, m.stamp_ns)
        self._history.append(_Entry(m.stamp_ns, self.x.copy(), self.P.copy(), m, accepted))
        return UpdateResult(
            m.stamp_ns, m.sensor, m.kind, accepted, nis, len(m.idx), "" if accepted else "rejected"
        )

    def _prune_history(self) -> None:
        """Keep the states needed to revert up to history_length back (plus one before it)."""
        assert self.t_ns is not None
        keep_from = self.t_ns - self.history_ns if self.cfg.smooth_lagged_data else self.t_ns
        i = bisect_right(self._history, keep_from, key=_STAMP) - 1
        if i > 0:
            del self._history[:i]

    def _refilter(self, m: Measurement) -> list[UpdateResult] | None:
        """Revert to the last state at or before ``m`` and re-apply everything after it."""
        assert self.t_ns is not None
        if not self.cfg.smooth_lagged_data or m.stamp_ns < self.t_ns - self.history_ns:
            return None
        i = bisect_right(self._history, m.stamp_ns, key=_STAMP) - 1
        if i < 0:
            return None
        replay = self._history[i + 1 :]
        del self._history[i + 1 :]
        for e in replay:  # their counts are redone below
            assert e.meas is not None
            st = self._stats[e.meas.sensor]
            if e.accepted:
                st.fused -= 1
            else:
                st.rejected -= 1
        base = self._history[i]
        self.x, self.P, self.t_ns = base.x.copy(), base.P.copy(), base.stamp_ns
        results = [self._apply(m)]
        for e in replay:
            assert e.meas is not None
            self._apply(e.meas)
        self._stats[m.sensor].refiltered += 1
        return results

    def process(self, sensor: str, msg: Message) -> list[UpdateResult]:
        """Fuse one message from ``sensor`` ("odom0", "vo0" or "imu0") in arrival order."""
        if sensor not in self.specs:
            raise EkfError(f"unknown sensor {sensor!r}; expected one of {SENSOR_NAMES}")
        st = self._stats[sensor]
        st.received += 1
        if not getattr(msg, "valid", True):
            st.invalid += 1
            return [UpdateResult(msg.stamp_ns, sensor, "", False, math.nan, 0, "invalid")]
        self._mark_seen(sensor, msg.stamp_ns)
        out: list[UpdateResult] = []
        # A gyro sample at the very instant a filter started without a measurement would be
        # read as gyro bias (the start prior holds the robot still to 1e-9, the bias to 1e-4),
        # and a robot turning at the start kept that bias: it is left out like an earlier one.
        at_bare_start = (
            isinstance(msg, ImuSample)
            and len(self._history) == 1
            and self._history[0].meas is None
            and msg.stamp_ns == self.t_ns
        )
        for m in self._measurements(sensor, msg):
            if self.t_ns is not None and (m.stamp_ns < self.t_ns or at_bare_start):
                res = None if at_bare_start else self._refilter(m)
                if res is None:
                    start = self._history[0] if self._history else None
                    early = (
                        start is not None and start.meas is None and m.stamp_ns <= start.stamp_ns
                    )
                    reason = "before_start" if early else "dropped_late"
                    setattr(st, reason, getattr(st, reason) + 1)
                    out.append(
                        UpdateResult(
                            m.stamp_ns, sensor, m.kind, False, math.nan, len(m.idx), reason
                        )
                    )
                    continue
                out.extend(res)
            else:
                out.append(self._apply(m))
            self._prune_history()
        return out

    def twist_gate(self, sensor: str, msg: TwistInput) -> tuple[bool, float]:
        """(passes, NIS) of ``sensor``'s Mahalanobis gate for ``msg`` against the filter's
        prediction at its stamp, without fusing it. (True, nan) when there is nothing to
        compare with (no state yet, older than the history): :meth:`process` then decides."""
        made = self._measurements(sensor, msg)  # a twist: no per-sensor state is touched
        if not made or self.t_ns is None:
            return True, math.nan
        m = made[0]
        try:
            x, P = self.predicted(m.stamp_ns)
        except EkfError:
            return True, math.nan
        _, _, nis = innovate(x, P, m.z, _observation(m), m.R, angle_residual(m.idx == YAW))
        return passes_gate(nis, m.threshold), nis

    def process_span(self, sensor: str, pieces: Sequence[TwistInput]) -> list[UpdateResult]:
        """Fuse a twist spread over its span (the pieces :func:`interval_twists` made, oldest
        first), gated once as the one measurement it is: each of k pieces carries k times the
        covariance, so alone each would pass a gate sqrt(k) times wider and a wrong motion over
        a long span would get in piece by piece. A rejected span counts as one rejection and
        leaves the filter as it was (reason "span_rejected")."""
        if len(pieces) > 1:
            last = pieces[-1]
            mean = TwistInput(
                last.stamp_ns,
                last.vx,
                last.vy,
                last.vyaw,
                np.asarray(last.covariance) / len(pieces),
                last.valid,
            )
            ok, nis = self.twist_gate(sensor, mean) if mean.valid else (True, math.nan)
            if not ok:
                st = self._stats[sensor]
                st.received += 1
                st.rejected += 1
                return [
                    UpdateResult(mean.stamp_ns, sensor, "twist", False, nis, 0, "span_rejected")
                ]
        return [r for p in pieces for r in self.process(sensor, p)]

    def _mark_seen(self, sensor: str, stamp_ns: int) -> None:
        """Per-sensor timeouts: a sensor silent for > sensor_timeout while others talk is stale."""
        last = self._last_seen.get(sensor)
        self._last_seen[sensor] = stamp_ns if last is None else max(last, stamp_ns)
        self._stale.discard(sensor)
        for other, t in self._last_seen.items():
            if other not in self._stale and stamp_ns - t > self.timeout_ns:
                self._stale.add(other)
                self._stats[other].timeouts += 1
                log.debug("%s timed out (%.3f s silent)", other, (stamp_ns - t) / NS_PER_S)

    # 3. Outputs.

    def is_timed_out(self, stamp_ns: int) -> bool:
        """No measurement from any sensor for longer than sensor_timeout before ``stamp_ns``."""
        return self.t_ns is None or stamp_ns - self.t_ns > self.timeout_ns

    def predicted(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """(x, P) at ``stamp_ns`` without changing the filter: predicted from the newest state at
        or before it (the filtered estimate, not smoothed by later data)."""
        if self.t_ns is None:
            raise EkfError("the EKF has no measurement yet")
        if stamp_ns >= self.t_ns:
            x, P, t0 = self.x, self.P, self.t_ns
        else:
            i = bisect_right(self._history, stamp_ns, key=_STAMP) - 1
            if i < 0:
                raise EkfError(f"stamp {stamp_ns} ns is older than the kept history")
            x, P, t0 = self._history[i].x, self._history[i].P, self._history[i].stamp_ns
        dt = (stamp_ns - t0) / NS_PER_S
        return (x.copy(), P.copy()) if dt <= 0 else predict(x, P, dt, self.Q)

    def state_at(self, stamp_ns: int) -> Odometry2D:
        """``odom -> base_link`` at ``stamp_ns`` with the 3x3 (x, y, yaw) covariance."""
        x, P = self.predicted(stamp_ns)
        if self.is_timed_out(stamp_ns):
            self.timed_out_outputs += 1
        return Odometry2D(
            int(stamp_ns),
            Pose2(float(x[X]), float(x[Y]), float(x[YAW])),
            (float(x[VX]), float(x[VYAW])),
            P[:3, :3].copy(),
        )

    @property
    def stats(self) -> EkfStats:
        return EkfStats(
            {n: dict(vars(s)) for n, s in self._stats.items()},
            self.timed_out_outputs,
            tuple(sorted(self._stale)),
        )


# --- offline ----------------------------------------------------------------------------------


class FuseResult(NamedTuple):
    stamps_ns: np.ndarray  # (N,) int64 [ns]
    x: np.ndarray  # (N,) [m]
    y: np.ndarray  # (N,) [m]
    yaw: np.ndarray  # (N,) [rad] wrapped
    cov: np.ndarray  # (N, 3, 3) over x, y, yaw
    stats: EkfStats
    timed_out: np.ndarray = np.zeros(0, dtype=bool)  # (N,) predict-only outputs


def fuse(
    streams: Mapping[str, Sequence[Message]],
    cfg: EkfConfig,
    output_stamps_ns: Iterable[int] | None = None,
    gyro_z_variance: float = 1e-4,
) -> FuseResult:
    """Offline fusion of whole sensor streams (``{"odom0": [...], "vo0": [...], ...}``).

    Messages are merged by stamp (stable: ties keep the sensor order of ``streams``) and fused
    one by one: the filter is a sequence, so this loop is inherent; each step is a few 6x6
    products. Outputs are at ``output_stamps_ns`` (sorted), or after every message when None;
    outputs before the first measurement are NaN.
    """
    ekf = PlanarEkf(cfg, gyro_z_variance)
    names = list(streams)
    # 1. Time-ordered merge of all streams: (stamp, stream index, message index) per message.
    stamps = np.array([m.stamp_ns for n in names for m in streams[n]], dtype=np.int64)
    which = np.array([k for k, n in enumerate(names) for _ in streams[n]], dtype=np.int64)
    pos = np.array([i for n in names for i in range(len(streams[n]))], dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    outs = (
        stamps[order] if output_stamps_ns is None else np.asarray(list(output_stamps_ns), np.int64)
    )
    n_out = len(outs)
    res = np.full((n_out, 3), np.nan)
    cov = np.full((n_out, 3, 3), np.nan)
    timed = np.zeros(n_out, dtype=bool)

    def emit(j: int) -> None:
        if ekf.t_ns is None:
            return
        od = ekf.state_at(int(outs[j]))
        res[j] = od.pose.x, od.pose.y, od.pose.yaw
        cov[j] = od.covariance
        timed[j] = ekf.is_timed_out(int(outs[j]))

    # 2. Fuse message by message, emitting outputs as their stamps are reached.
    if output_stamps_ns is None:
        for j, k in enumerate(order):
            ekf.process(names[which[k]], streams[names[which[k]]][pos[k]])
            emit(j)
    else:
        k = 0
        for j in range(n_out):
            while k < len(order) and stamps[order[k]] <= outs[j]:
                i = order[k]
                ekf.process(names[which[i]], streams[names[which[i]]][pos[i]])
                k += 1
            emit(j)
    return FuseResult(outs, res[:, 0], res[:, 1], res[:, 2], cov, ekf.stats, timed)


__all__ = [
    "EkfError",
    "EkfStats",
    "FuseResult",
    "Measurement",
    "PlanarEkf",
    "PoseInput",
    "SensorSpec",
    "TwistInput",
    "UpdateResult",
    "angle_residual",
    "fuse",
    "innovate",
    "passes_gate",
    "pose_update",
    "predict",
    "se2_between",
    "sensor_specs",
    "transition",
    "update",
    "wheel_twist_inputs",
    "wrap_angle",
    "interval_twists",
    "spanning_motion_twists",
    "motion_twist",
]
