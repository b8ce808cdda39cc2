"""Keyframe pose-graph mapper: scan-to-local-map matching, verified loop closures, iSAM2.

Per scan (:meth:`Mapper.add_scan`), like slam_toolbox's ``addScan``:

1. reject bad input (non-finite odometry, time going backwards) with a counted reason;
2. predict the pose from the last keyframe's optimised pose and the odometry since then;
3. a scan that has not moved ``minimum_travel_distance`` / turned ``minimum_travel_heading`` is
   only remembered with its odometry offset, so the trajectory has one pose per scan;
4. a keyframe is matched against the local map of the last ``scan_buffer_size`` keyframes
   (:mod:`slam.scan_matching`) and added with a scan or odometry edge; iSAM2 updates. With
   ``revisit_distance`` > 0 (the live profile) a robot driving its route again re-anchors on
   older keyframes instead of growing the graph;
5. loop closures: older keyframes within a covariance-gated radius are matched in a window as
   wide as the relative uncertainty and verified (response, ICP inliers, chi-square residual
   under the robust kernel); nearly ambiguous or inconsistent ones are held, and a final
   robust vote (GNC) over all closures decides which stay.

Local maps are built on a second thread while the caller's thread matches (the next tracking
map during the loop-closure search); every result is awaited at a fixed point, so the map is
bit-identical to a single thread's (docs/design/speed.md).

Poses are the scan frame's in ``map`` (a log's laser, a depth scan's ``output_frame``:
:func:`slam.depth_to_scan.scan_pose`); odometry is given for the same frame. Design notes and the
measurements behind the decisions: docs/design/mapper.md and docs/benchmarks.md.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import Counter, defaultdict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from typing import Any, Literal

import numpy as np

from sensors.types import LaserScan, MapError
from slam.config import LocalizerConfig, MapperConfig
from slam.ekf import pose_update
from slam.geometry import ominus, oplus, rotate_covariance, wrap_angle
from slam.localization import Localizer, MapModel
from slam.map_bundle import GraphEdge, MapBundle
from slam.occupancy_grid import GridGeometry, OccupancyGrid, bounds_of_scans, integrate_scans
from slam.pose_graph import Edge, EdgeKind, PoseGraph
from slam.scan_matching import (
    IcpResult,
    LikelihoodField,
    ReferenceCloud,
    build_likelihood_field,
    build_reference,
    correlative_match,
    icp_refine,
    release_degenerate_axis,
    rival_score,
    scan_points,
    transform_points,
    voxel_filter,
)

log = logging.getLogger(__name__)

MIN_SCAN_POINTS = 20  # valid returns a keyframe needs to be matched at all
EMPTY_BEFORE_FIRST_KEYFRAME = "no return before the first keyframe"
LOOP_SIGMA_GATE = 3.0  # search radius/window in relative-uncertainty sigmas
LOOP_MIN_LINEAR_WINDOW = 0.5  # [m] smallest loop-closure search half-window
LOOP_MIN_ANGULAR_WINDOW = 0.2  # [rad] smallest loop-closure angular half-window
ODOM_MIN_SIGMA = (0.01, 0.005)  # [m, rad] floor of an odometry edge's sigmas
LOOP_MIN_SIGMA = (0.02, 0.01)  # [m, rad] floor of a loop closure's sigmas
UNOBSERVED_VARIANCE = 1e6  # [m^2] a direction the scan cannot constrain
ROTATED_RIVAL_WINDOW = math.pi / 4  # [rad] loop angular half-window from which turned twins count
ROTATED_RIVAL_ANGLES = np.radians([90.0, 180.0, -90.0])  # [rad] yaw offsets of a turned twin
LOOP_EXTRA_ITERATIONS = 3  # iSAM2 passes after a closure, so a large correction converges
GRID_MARGIN_M = 1.0  # [m] unknown border around the mapped area in the built grid
REVISIT_MAX_PATH_M = 2.0  # [m] re-anchor only on a keyframe this close through the graph
# The second core: local maps (likelihood field, k-d tree, normals) are built here while the
# calling thread does other work (cv2, numpy and scipy's k-d tree release the GIL). Only pure
# functions of inputs fixed before submission run here, and every result is awaited at a fixed
# point, so no result depends on which thread finishes first.
LOCAL_MAP_WORKERS = 2
_builders: dict[int, ThreadPoolExecutor] = {}  # per process id: a forked child gets its own


# 1. Odometry noise --------------------------------------------------------------------------------


def odometry_covariance(delta: np.ndarray, config: MapperConfig) -> np.ndarray:
    """Diagonal covariance of an odometry increment, growing with distance and turn."""
    dist = math.hypot(delta[0], delta[1])
    s_xy = max(config.odom_translation_noise * dist, ODOM_MIN_SIGMA[0])
    s_yaw = max(
        config.odom_rotation_noise * abs(delta[2]) + config.odom_rotation_noise_per_meter * dist,
        ODOM_MIN_SIGMA[1],
    )
    return np.diag([s_xy**2, s_xy**2, s_yaw**2])


def fuse_with_odometry(
    prior: np.ndarray, prior_cov_robot: np.ndarray, match: MatchOutcome, degeneracy_ratio: float
) -> MatchOutcome:
    """Kalman update of the odometry prediction by the scan match, with the match's weak axis
    (a featureless corridor) left to the prediction (:func:`release_degenerate_axis`).
    ``prior_cov_robot`` is in the robot frame of the prediction; the result is in the map."""
    p_cov = rotate_covariance(prior_cov_robot, prior[2])
    r_cov, degenerate = release_degenerate_axis(
        match.covariance, degeneracy_ratio, UNOBSERVED_VARIANCE
    )
    pose, cov = pose_update(prior, p_cov, match.pose, r_cov)
    return MatchOutcome(
        match.ok, match.reason, pose, cov, match.response, match.inlier_fraction, degenerate
    )


def loop_covariance(match_cov: np.ndarray, yaw: float, degeneracy_ratio: float) -> np.ndarray:
    """A loop closure's noise from the covariance of the matched pose in the map (ICP's).

    - Its weak translational axis (a corridor's length: noisy wall normals fake information
      along it) is released as for tracking (:func:`release_degenerate_axis`): in a corridor a
      closure holds the lateral offset and the heading, not where along the corridor it is.
    - It is turned into the body frame of the matched pose (heading ``yaw``): GTSAM's
      ``BetweenFactor`` measures its error there (Karto's ``LinkInfo`` turns a match covariance
      into its edge's frame too). Left in the map frame, a closure in a corridor running north
      pinned the corridor's length with its lateral sigma and freed its width (issue #12)."""
    cov, _ = release_degenerate_axis(match_cov, degeneracy_ratio, UNOBSERVED_VARIANCE)
    return rotate_covariance(cov, -yaw) + np.diag(
        [LOOP_MIN_SIGMA[0] ** 2, LOOP_MIN_SIGMA[0] ** 2, LOOP_MIN_SIGMA[1] ** 2]
    )


# 2. Records ------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Keyframe:
    id: int
    stamp_ns: int  # [ns]
    odom_pose: np.ndarray  # (3,) odometry pose of the scan frame when taken
    scan: LaserScan
    points: np.ndarray  # (N, 2) valid returns within max_laser_range, scan frame
    match_points: np.ndarray  # (M, 2) voxel-filtered points used for matching


class _Rows:
    """Rows appended one at a time into a numpy buffer that doubles when full: a scan's stamp,
    keyframe, offset and tracked pose cost 64 bytes (at most twice that before the buffer fills)
    instead of ~350 in Python lists of ints and small arrays -- the mapper keeps one entry per
    scan for as long as it runs (issue #9's soak)."""

    def __init__(self, width: int, dtype: Any = np.float64) -> None:
        self._buf = np.empty((64, width) if width else 64, dtype=dtype)
        self._n = 0

    def append(self, row: Any) -> None:
        if self._n == len(self._buf):
            self._buf = np.concatenate([self._buf, np.empty_like(self._buf)])
        self._buf[self._n] = row
        self._n += 1

    def __len__(self) -> int:
        return self._n

    @property
    def array(self) -> np.ndarray:
        """The rows so far (a view: copy it to keep it past the next append)."""
        return self._buf[: self._n]


@dataclass
class LoopStats:
    proposed: int = 0
    accepted: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    readmitted: int = 0  # held back when they came, accepted by the vote (in ``accepted``)
    outvoted: int = 0  # accepted when they came, removed by the vote (in ``rejected``)
    # wide-window matches redone at the graph's prediction, which scored nearly as well
    rematched_at_prediction: int = 0

    def as_dict(self) -> dict[str, object]:
        return {
            "proposed": self.proposed,
            "accepted": self.accepted,
            "rejected": sum(self.rejected.values()),
            "rejected_by_reason": {k: v for k, v in self.rejected.items() if v},
            "readmitted": self.readmitted,
            "outvoted": self.outvoted,
            "rematched_at_prediction": self.rematched_at_prediction,
        }


@dataclass(frozen=True)
class MatchOutcome:
    ok: bool
    reason: str  # "" when ok
    pose: np.ndarray  # (3,) matched pose (or the prior when not ok)
    covariance: np.ndarray  # (3, 3)
    response: float  # likelihood-field score at the final pose, in [0, 1]
    inlier_fraction: float
    degenerate: bool = False  # a translational axis was left to odometry (a corridor)


@dataclass(frozen=True, eq=False)
class _Held:
    """A loop closure kept out of the graph for now, with why; the vote may readmit it."""

    j: int
    k: int
    delta: np.ndarray  # (3,) pose k in the frame of j
    covariance: np.ndarray  # (3, 3)
    reason: str


@dataclass(frozen=True, eq=False)
class _LocalMap:
    """A matching map: the likelihood field (correlative search, response) and the ICP
    reference. A part built on a worker thread is awaited where it is first used."""

    _field: Future[LikelihoodField]
    _reference: Future[ReferenceCloud]

    @property
    def field(self) -> LikelihoodField:
        return self._field.result()

    @property
    def reference(self) -> ReferenceCloud:
        return self._reference.result()


@dataclass(frozen=True, eq=False)
class MapperResult:
    keyframes: list[Keyframe]
    poses: np.ndarray  # (K, 3) optimised keyframe poses in map
    edges: list[dict[str, Any]]  # graph edges (kind, from, to, delta, information)
    scan_stamps_ns: np.ndarray  # (S,) every accepted scan
    scan_poses: np.ndarray  # (S, 3) every accepted scan's pose in map
    counts: dict[str, object]
    timings_s: dict[str, float]


# 3. The mapper ---------------------------------------------------------------------------------


class Mapper:
    """Stateful shell over :mod:`slam.scan_matching` and :class:`slam.pose_graph.PoseGraph`."""

    def __init__(self, config: MapperConfig) -> None:
        self.config = config
        self.graph = PoseGraph(
            robust_kernel=config.robust_kernel, robust_kernel_width=config.robust_kernel_width
        )
        self.keyframes: list[Keyframe] = []
        self.chain_length: list[float] = []  # [m] distance travelled up to each keyframe
        self.loop_edges: list[tuple[int, int]] = []  # accepted closures (older, newer)
        # Tracking hangs off an anchor keyframe: the newest one, or (revisit_distance > 0) an
        # older one the robot came back to. Motion towards the next keyframe is measured from
        # the anchor, or from the scan at which tracking re-anchored (_ref_offset: anchor ->
        # that scan; None when the reference is the anchor itself).
        self._anchor = 0
        self._ref_stamp = 0
        self._ref_odom = np.zeros(3)
        self._ref_offset: np.ndarray | None = None
        self._kf_parent: list[int] = []  # the anchor each keyframe's edge came from (-1: none)
        self._anchor_hops: list[tuple[int, int]] = []  # (old anchor, keyframe made from it)
        self.revisits = 0  # times tracking re-anchored on an older keyframe
        self.loops = LoopStats()
        # Closures the graph found inconsistent when they came: they vote again at the end.
        self._held: list[_Held] = []
        self.skipped: Counter[str] = Counter()
        self.matches: Counter[str] = Counter()
        self.timings: dict[str, float] = defaultdict(float)
        # Per accepted scan: stamp, keyframe it hangs off, its odometry offset from that keyframe.
        self._scan_stamps = _Rows(0, np.int64)
        self._scan_kf = _Rows(0, np.int64)
        self._scan_offset = _Rows(3)
        self._scan_track = _Rows(3)  # map pose when tracked
        self._kf_track: list[np.ndarray] = []  # each keyframe's tracked pose when it was made
        self._kf_matched: list[bool] = []  # whether that pose came from a scan match
        self._last_stamp: int | None = None
        self._scans_seen = 0
        # Tracking: every scan is matched to the local map of recent keyframes (cached until a
        # keyframe is added or a loop closure moves the poses).
        self._track_pose = np.zeros(3)  # map pose of the last scan
        self._track_odom = np.zeros(3)  # its odometry pose
        self._local: _LocalMap | None = None
        self._relocalise = False  # continuing a saved map: place the first scan in it first
        self.relocalised: dict[str, object] | None = None
        self._localizer: Localizer | None = None
        # Every accept/reject decision with the numbers it was taken on, when a caller sets a
        # list here (bench/diag_mapper_flips.py diffs two runs' lists to find the first flip).
        self.decisions: list[tuple[Any, ...]] | None = None

    def _note(self, *row: Any) -> None:
        """Record one decision (kind, keyframe or scan, outcome, numbers) when tracing."""
        if self.decisions is not None:
            self.decisions.append(row)

    # 3a. Input ---------------------------------------------------------------------------------

    def add_scan(self, scan: LaserScan, odom_pose: np.ndarray) -> np.ndarray | None:
        """Feed one scan with the odometry pose of its frame; returns its current map pose, or
        None when the scan was skipped (counted in ``skipped`` by reason)."""
        self._scans_seen += 1
        odom = np.asarray(odom_pose, dtype=np.float64)
        if odom.shape != (3,) or not np.all(np.isfinite(odom)):
            self.skipped["non-finite odometry"] += 1
            return None
        if self._last_stamp is not None and scan.stamp_ns <= self._last_stamp:
            self.skipped["time not increasing"] += 1
            return None
        if len(scan.ranges) == 0:
            self.skipped["empty scan"] += 1
            return None
        self._last_stamp = scan.stamp_ns
        if self._relocalise:
            return self._relocalise_in_map(scan, odom)
        if not self.keyframes:
            # The map starts at the first scan with a return (Cartographer drops empty range
            # data, slam_toolbox too): an empty first keyframe would leave tracking with no
            # local map until the next one, and the map resting on a later keyframe.
            kf = self._make_keyframe(scan, odom)
            if len(kf.points) == 0:
                self.skipped[EMPTY_BEFORE_FIRST_KEYFRAME] += 1
                return None
            if self.skipped[EMPTY_BEFORE_FIRST_KEYFRAME]:
                log.info(
                    "mapping starts at scan %d: skipped the %d scans before it with no return",
                    self._scans_seen,
                    self.skipped[EMPTY_BEFORE_FIRST_KEYFRAME],
                )
            self.graph.add_node(odom)
            self._append_keyframe(kf, 0.0, odom, True)
            return self._record(scan.stamp_ns, odom, odom)
        # 2. Predict from the last tracked pose and the odometry since that scan.
        prior = oplus(self._track_pose, ominus(self._track_odom, odom))
        delta = ominus(self._ref_odom, odom)
        moved = math.hypot(delta[0], delta[1]) >= self.config.minimum_travel_distance
        turned = abs(delta[2]) >= self.config.minimum_travel_heading
        waited = (scan.stamp_ns - self._ref_stamp) * 1e-9 >= self.config.minimum_time_interval
        # The time gate bounds the keyframe rate of a fast sensor, whose consecutive scans nearly
        # repeat each other. A scan half a travel threshold or more from the one before it is
        # sparse (a log with one scan a metre): new ground whatever the clock says, so the gate
        # does not hold it back; nor does it let keyframes drift past twice the thresholds.
        step = ominus(self._track_odom, odom)  # since the scan before this one
        sparse = (
            math.hypot(step[0], step[1]) >= 0.5 * self.config.minimum_travel_distance
            or abs(step[2]) >= 0.5 * self.config.minimum_travel_heading
        )
        far = (
            math.hypot(delta[0], delta[1]) >= 2 * self.config.minimum_travel_distance
            or abs(delta[2]) >= 2 * self.config.minimum_travel_heading
        )
        is_keyframe = (moved or turned) and (waited or far or sparse)
        # 3. Track the scan against the local map.
        kf = self._make_keyframe(scan, odom)
        t0 = time.perf_counter()
        match = self._match_local(kf, prior)
        self.timings["sequential_matching"] += time.perf_counter() - t0
        self.matches[match.reason or "matched"] += 1
        if match.ok:
            step = ominus(self._track_odom, odom)
            match = fuse_with_odometry(
                prior,
                odometry_covariance(step, self.config),
                match,
                self.config.scan_match_degeneracy_ratio,
            )
        pose = match.pose if match.ok else prior
        if is_keyframe:
            older = self._revisit(pose) if match.ok and self.config.revisit_distance > 0 else None
            if older is not None:
                self._reanchor(older, scan.stamp_ns, odom, pose)
            else:
                self._add_keyframe(kf, delta, match, pose)
                pose = self.graph.pose(kf.id)  # optimised, and moved by any loop closure
        return self._record(scan.stamp_ns, odom, pose)

    def _record(self, stamp_ns: int, odom: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Remember the scan as an offset from its keyframe, so it follows the optimised graph."""
        kf = self.keyframes[self._anchor]
        self._track_pose, self._track_odom = pose, odom
        self._scan_stamps.append(stamp_ns)
        self._scan_kf.append(kf.id)
        self._scan_offset.append(ominus(self.graph.pose(kf.id), pose))
        self._scan_track.append(pose)
        return pose

    # 3b. Keyframes and sequential matching -----------------------------------------------------

    def _make_keyframe(self, scan: LaserScan, odom: np.ndarray) -> Keyframe:
        pts = scan_points(scan, self.config.max_laser_range)
        return Keyframe(
            id=len(self.keyframes),
            stamp_ns=scan.stamp_ns,
            odom_pose=odom,
            scan=scan,
            points=pts,
            match_points=voxel_filter(pts, self.config.scan_voxel_size),
        )

    def _append_keyframe(
        self, kf: Keyframe, step_m: float, tracked: np.ndarray, matched: bool
    ) -> None:
        parent = self._anchor if self.keyframes else -1
        self._kf_parent.append(parent)
        if parent not in (-1, kf.id - 1):
            self._anchor_hops.append((parent, kf.id))
        self._anchor, self._ref_stamp, self._ref_odom = kf.id, kf.stamp_ns, kf.odom_pose
        self._ref_offset = None
        self.keyframes.append(kf)
        self._kf_track.append(tracked)
        self._kf_matched.append(matched)
        self.chain_length.append((self.chain_length[-1] if self.chain_length else 0.0) + step_m)
        self._local = None

    def _add_keyframe(
        self, kf: Keyframe, odom_delta: np.ndarray, match: MatchOutcome, pose: np.ndarray
    ) -> None:
        """4. A new graph node: a ``scan`` edge from the previous keyframe when the match was
        good, else an ``odometry`` edge; then iSAM2, then loop closure."""
        cfg = self.config
        prev = self.keyframes[self._anchor]
        prev_pose = self.graph.pose(prev.id)
        kind: EdgeKind
        if match.ok:
            # ICP's covariance describes the fit, not the drift of matching against a local map
            # that itself drifts: add a fraction of the odometry noise so loops can close.
            edge_delta, kind = ominus(prev_pose, pose), "scan"
            # Along an axis the scans could not see, the edge is as uncertain as odometry.
            fraction = 1.0 if match.degenerate else cfg.scan_match_noise_fraction
            floor = fraction**2 * odometry_covariance(edge_delta, cfg)
            cov = match.covariance + floor
        else:
            if self._ref_offset is not None:  # re-anchored: anchor -> that scan -> odometry
                odom_delta = oplus(self._ref_offset, odom_delta)
            edge_delta, cov, kind = odom_delta, odometry_covariance(odom_delta, cfg), "odometry"
        node = self.graph.add_node(pose)
        assert node == kf.id
        self.graph.add_edge(prev.id, kf.id, edge_delta, cov, kind=kind)
        t0 = time.perf_counter()
        self.graph.update()
        self.timings["optimisation"] += time.perf_counter() - t0
        self._append_keyframe(kf, float(math.hypot(edge_delta[0], edge_delta[1])), pose, match.ok)
        if cfg.do_loop_closing:
            t0 = time.perf_counter()
            # The next scans' tracking map, built on the second core during the loop-closure
            # search from the poses as they are now; kept only if the search left every pose
            # as it was (else rebuilt from the moved ones), so it is the map a build after the
            # search would make.
            before = self.graph.poses()
            ahead = self._build_tracking_map(self._tracking_points(), first="worker")
            self._close_loops(kf)
            if self._local is None and np.array_equal(self.graph.poses(), before):
                self._local = ahead
            self.timings["loop_closure"] += time.perf_counter() - t0

    def _world_points(self, ids: list[int], poses: np.ndarray) -> np.ndarray:
        parts = [transform_points(poses[i], self.keyframes[i].points) for i in ids]
        return np.concatenate(parts) if parts else np.zeros((0, 2))

    def _build_local(
        self,
        ref_points: np.ndarray,
        linear_window: float,
        resolution: float,
        smear: float,
        first: Literal["field", "reference", "worker"],
    ) -> _LocalMap | None:
        """The matching map of world points. The part the caller needs ``first`` is built here,
        the other on a worker thread meanwhile (both there for ``"worker"``)."""
        if len(ref_points) < MIN_SCAN_POINTS:
            return None
        n_levels = int(math.ceil(math.log2(2 * linear_window / resolution + 1))) + 1
        field_job = partial(
            build_likelihood_field, ref_points, resolution, smear, linear_window, n_levels
        )
        ref_job = partial(_reference, ref_points, self.config.scan_voxel_size / 2)
        if first == "field":
            ref = _builder_pool().submit(ref_job)
            return _LocalMap(_done(field_job()), ref)
        if first == "reference":
            fld = _builder_pool().submit(field_job)
            return _LocalMap(fld, _done(ref_job()))
        ref = _builder_pool().submit(ref_job)  # the next scan's ICP needs it first
        return _LocalMap(_builder_pool().submit(field_job), ref)

    def _match_loop(
        self, kf: Keyframe, prior: np.ndarray, local: _LocalMap | None, lin: float, ang: float
    ) -> MatchOutcome:
        """:meth:`_match` with the loop closure's settings (coarse angle lattice, no prior
        penalty, the loop's Huber width and response thresholds) in a ``lin`` x ``ang`` window."""
        cfg = self.config
        return self._match(
            kf,
            prior,
            local,
            linear_window=lin,
            angular_window=ang,
            angle_step=cfg.coarse_angle_resolution,
            min_response=cfg.loop_match_minimum_response_fine,
            penalise=False,
            huber_m=cfg.loop_icp_huber_width,
            min_coarse=cfg.loop_match_minimum_response_coarse,
        )

    def _match(
        self,
        kf: Keyframe,
        prior: np.ndarray,
        local: _LocalMap | None,
        linear_window: float,
        angular_window: float,
        angle_step: float,
        min_response: float,
        penalise: bool,
        huber_m: float,
        min_coarse: float = 0.0,
        tried: tuple[np.ndarray, IcpResult] | None = None,
    ) -> MatchOutcome:
        """Correlative search in the window, then ICP from its optimum. ``tried``: an ICP of
        these scan points on this map with these settings, from the pose it holds; reused when
        the optimum is that pose (the same computation)."""
        cfg = self.config
        if len(kf.match_points) < MIN_SCAN_POINTS:
            return MatchOutcome(False, "too few scan points", prior, np.eye(3), 0.0, 0.0)
        if local is None:
            return MatchOutcome(False, "too few map points", prior, np.eye(3), 0.0, 0.0)
        penalties = (
            {
                "distance_variance_penalty": cfg.distance_variance_penalty,
                "angle_variance_penalty": cfg.angle_variance_penalty,
                "minimum_distance_penalty": cfg.minimum_distance_penalty,
                "minimum_angle_penalty": cfg.minimum_angle_penalty,
            }
            if penalise
            else {}
        )
        coarse = correlative_match(
            local.field,
            kf.match_points,
            prior,
            linear_window,
            angular_window,
            angle_step,
            min_score=min_coarse,
            **penalties,
        )
        if coarse.score < min_coarse or coarse.score == 0.0:
            return MatchOutcome(
                False, "coarse response below threshold", prior, np.eye(3), coarse.score, 0.0
            )
        if tried is not None and np.array_equal(tried[0], coarse.pose):
            icp = tried[1]
        else:
            icp = icp_refine(
                local.reference,
                kf.match_points,
                coarse.pose,
                cfg.icp_max_correspondence_distance,
                max_iterations=cfg.icp_max_iterations,
                min_sigma_m=cfg.scan_match_min_sigma,
                huber_m=huber_m,
            )
        if not np.all(np.isfinite(icp.pose)) or icp.rmse == math.inf:
            return MatchOutcome(False, "ICP failed", prior, np.eye(3), coarse.score, 0.0)
        response = _response(local.field, kf.match_points, icp.pose)
        if icp.inlier_fraction < cfg.icp_min_inlier_fraction:
            reason = "too few ICP inliers"
        elif response < min_response:
            reason = "response below threshold"
        elif np.hypot(*(icp.pose[:2] - coarse.pose[:2])) > 2 * local.field.resolution + 0.1:
            reason = "ICP left the correlative optimum"
        else:
            reason = ""
        return MatchOutcome(
            reason == "", reason, icp.pose, icp.covariance, response, icp.inlier_fraction
        )

    def _icp_first(
        self, kf: Keyframe, prior: np.ndarray
    ) -> tuple[MatchOutcome | None, IcpResult | None]:
        """Most scans follow odometry closely: ICP straight from the prior, accepted when it
        stays well inside the search window and nearly every point finds the map; otherwise
        (None) the full correlative search runs. Also returns the ICP (for that search)."""
        cfg = self.config
        local = self._local
        if local is None or len(kf.match_points) < MIN_SCAN_POINTS:
            return None, None
        icp = icp_refine(
            local.reference,
            kf.match_points,
            prior,
            cfg.icp_max_correspondence_distance,
            max_iterations=cfg.icp_max_iterations,
            min_sigma_m=cfg.scan_match_min_sigma,
            huber_m=cfg.icp_huber_width,
        )
        step = icp.pose - prior
        inside = (
            math.hypot(step[0], step[1]) <= cfg.correlation_search_space_dimension / 4
            and abs(wrap_angle(step[2])) <= cfg.coarse_search_angle_offset / 2
        )
        if not (
            icp.converged and inside and icp.inlier_fraction >= cfg.icp_first_min_inlier_fraction
        ):
            return None, icp
        response = _response(local.field, kf.match_points, icp.pose)
        if response < cfg.link_match_minimum_response_fine:
            return None, icp
        return MatchOutcome(True, "", icp.pose, icp.covariance, response, icp.inlier_fraction), icp

    def _tracking_points(self) -> np.ndarray:
        """World points of the tracking map: the keyframes around the anchor, at the graph's
        current poses (so the map is a function of those poses)."""
        cfg = self.config
        poses = self.graph.poses()
        n, anchor = len(self.keyframes), self._anchor
        if anchor == n - 1:  # the recent chain
            recent = list(range(max(0, n - cfg.scan_buffer_size), n))
        else:  # re-anchored on an older keyframe: the keyframes nearest it
            nearest = np.argsort(np.hypot(*(poses[:n, :2] - poses[anchor, :2]).T), kind="stable")[
                : cfg.scan_buffer_size
            ]
            recent = sorted(int(i) for i in nearest)
        ids = [
            i
            for i in recent
            if np.hypot(*(poses[i, :2] - poses[anchor, :2]))
            <= cfg.scan_buffer_maximum_scan_distance
        ]
        return self._world_points(ids, poses)

    def _build_tracking_map(
        self, points: np.ndarray, first: Literal["reference", "worker"] = "reference"
    ) -> _LocalMap | None:
        """The tracking map; ICP from the prediction needs its reference first."""
        cfg = self.config
        return self._build_local(
            points,
            cfg.correlation_search_space_dimension / 2,
            cfg.correlation_search_space_resolution,
            cfg.correlation_search_space_smear_deviation,
            first,
        )

    def _match_local(self, kf: Keyframe, prior: np.ndarray) -> MatchOutcome:
        cfg = self.config
        if self._local is None:
            self._local = self._build_tracking_map(self._tracking_points())
        fast, icp = self._icp_first(kf, prior)
        if fast is not None:
            self._note("track", self._scans_seen, "icp-first", fast.response, fast.inlier_fraction)
            return fast
        match = self._match(
            kf,
            prior,
            self._local,
            linear_window=cfg.correlation_search_space_dimension / 2,
            angular_window=cfg.coarse_search_angle_offset,
            angle_step=cfg.coarse_angle_resolution,
            min_response=cfg.link_match_minimum_response_fine,
            penalise=True,
            huber_m=cfg.icp_huber_width,
            tried=None if icp is None else (prior, icp),
        )
        self._note(
            "track",
            self._scans_seen,
            match.reason or "search",
            match.response,
            match.inlier_fraction,
        )
        return match

    # 3c. Continuing a saved map ----------------------------------------------------------------

    @classmethod
    def from_bundle(
        cls, config: MapperConfig, bundle: MapBundle, localizer: LocalizerConfig | None = None
    ) -> Mapper:
        """A mapper holding a saved map's keyframes and graph. The scans it is fed first go to
        the localiser's global relocalisation (:mod:`slam.localization`: a search over the whole
        map verified over several scans, ambiguity refused) until it tracks; from there the new
        keyframes extend the same graph."""
        m = cls(config)
        loc_cfg = localizer or LocalizerConfig()
        model = MapModel.from_grid(bundle.grid, loc_cfg, bundle.occupied_thresh, bundle.free_thresh)
        m._localizer = Localizer(model, loc_cfg)
        poses = np.asarray(bundle.keyframe_poses, dtype=np.float64).reshape(-1, 3)
        if len(poses) == 0:
            raise MapError("the map bundle has no keyframes to continue from")
        edges = [
            Edge(
                id=n,
                kind=e.kind,  # type: ignore[arg-type]  # a bundle's kinds are checked on load
                i=e.from_id,
                j=e.to_id,
                delta=np.asarray(e.delta, float),
                information=np.asarray(e.information),
                robust=e.kind == "loop",
            )
            for n, e in enumerate(bundle.edges)
        ]
        m.graph = PoseGraph.from_arrays(
            poses,
            edges,
            robust_kernel=config.robust_kernel,
            robust_kernel_width=config.robust_kernel_width,
        )
        for k, scan in enumerate(bundle.scans):
            kf = m._make_keyframe(scan, np.asarray(bundle.keyframe_odom_poses[k], float))
            step = 0.0 if k == 0 else float(np.hypot(*(poses[k, :2] - poses[k - 1, :2])))
            m._append_keyframe(kf, step, poses[k], True)
        m._relocalise = True
        return m

    def _relocalise_in_map(self, scan: LaserScan, odom: np.ndarray) -> np.ndarray | None:
        """Feed the localiser until it tracks; then anchor the scan to the nearest saved
        keyframe with a scan match around the localiser's pose (a loop edge)."""
        assert self._localizer is not None
        res = self._localizer.update(scan, odom)
        if res.status != "tracking":
            self.skipped["before relocalisation in the saved map"] += 1
            return None
        cfg = self.config
        kf = self._make_keyframe(scan, odom)
        poses = self.graph.poses()
        j = int(np.argmin(np.hypot(*(poses[:, :2] - res.pose[:2]).T)))
        near = np.flatnonzero(
            np.hypot(*(poses[:, :2] - poses[j, :2]).T) <= cfg.scan_buffer_maximum_scan_distance
        )
        lin = cfg.correlation_search_space_dimension / 2
        local = self._build_local(
            self._world_points([int(i) for i in near], poses),
            lin,
            cfg.correlation_search_space_resolution,
            cfg.correlation_search_space_smear_deviation,
            first="field",  # the correlative search needs it first
        )
        match = self._match(
            kf,
            res.pose,
            local,
            linear_window=lin,
            angular_window=cfg.coarse_search_angle_offset,
            angle_step=cfg.coarse_angle_resolution,
            min_response=cfg.loop_match_minimum_response_fine,
            penalise=True,
            huber_m=cfg.loop_icp_huber_width,
        )
        pose, cov = (match.pose, match.covariance) if match.ok else (res.pose, res.covariance)
        node = self.graph.add_node(pose)
        loop_cov = cov + np.diag(
            [LOOP_MIN_SIGMA[0] ** 2, LOOP_MIN_SIGMA[0] ** 2, LOOP_MIN_SIGMA[1] ** 2]
        )
        self.graph.add_edge(j, node, ominus(poses[j], pose), loop_cov, kind="loop")
        self.graph.update()
        self._append_keyframe(kf, 0.0, pose, True)
        self._relocalise = False
        self._localizer = None
        self.relocalised = {
            "keyframe": j,
            "confidence": round(float(res.confidence), 4),
            "scans_before": int(self.skipped["before relocalisation in the saved map"]),
            "pose": [round(float(v), 4) for v in pose],
        }
        return self._record(scan.stamp_ns, odom, self.graph.pose(node))

    # 3d. Loop closure ---------------------------------------------------------------------------

    def _revisit(self, pose: np.ndarray) -> int | None:
        """The older keyframe to re-anchor on instead of adding one at ``pose``: the nearest
        within ``revisit_distance`` / ``revisit_heading`` whose pose relative to the anchor the
        graph already knows (a path of at most ``REVISIT_MAX_PATH_M`` through the chain and one
        loop closure; a place the robot came back to only after a loop is first tied to it by
        a loop closure of a new keyframe). None: add a keyframe."""
        cfg = self.config
        n = len(self.keyframes)
        poses = self.graph.poses()[:n]
        dist = np.hypot(*(poses[:, :2] - pose[:2]).T)
        near = (dist <= cfg.revisit_distance) & (
            np.abs(wrap_angle(poses[:, 2] - pose[2])) <= cfg.revisit_heading
        )
        near[self._anchor] = False
        cands = np.flatnonzero(near)
        if len(cands) == 0:
            return None
        cands = cands[self._path_between(self._anchor, cands) <= REVISIT_MAX_PATH_M]
        return int(cands[np.argmin(dist[cands])]) if len(cands) else None

    def _reanchor(self, j: int, stamp_ns: int, odom: np.ndarray, pose: np.ndarray) -> None:
        self._anchor, self._ref_stamp, self._ref_odom = j, stamp_ns, odom
        self._ref_offset = ominus(self.graph.pose(j), pose)
        self._local = None
        self.revisits += 1

    def _path_between(self, a: int, cands: np.ndarray) -> np.ndarray:
        """[m] path length between keyframe ``a`` and each candidate: along the chain, or
        through one accepted loop closure or re-anchoring, whichever is shorter (a one-hop
        Dijkstra bound), in either direction. Drift, and so a search window, grows with it."""
        cl = np.asarray(self.chain_length)
        best = np.abs(cl[a] - cl[cands])
        if hops := self.loop_edges + self._anchor_hops:
            x, y = (np.array(v) for v in zip(*hops, strict=True))
            c = cl[cands][:, None]
            via = np.minimum(
                np.abs(cl[a] - cl[y])[None, :] + np.abs(cl[x][None, :] - c),
                np.abs(cl[a] - cl[x])[None, :] + np.abs(cl[y][None, :] - c),
            )
            best = np.minimum(best, via.min(axis=1))
        return best

    def _close_loops(self, kf: Keyframe) -> None:
        cfg = self.config
        k = kf.id
        older = np.arange(0, k - cfg.loop_match_minimum_chain_size)
        if len(older) == 0:
            return
        poses = self.graph.poses()
        path = self._path_between(k, older)
        sigma = cfg.loop_search_drift_rate * path  # [m]
        dist = np.hypot(*(poses[older, :2] - poses[k, :2]).T)
        radius = np.minimum(
            cfg.loop_search_maximum_distance + LOOP_SIGMA_GATE * sigma,
            cfg.loop_search_space_dimension / 2,
        )
        near = dist <= radius
        if not near.any():
            return
        j = int(older[near][np.argmin(dist[near])])
        half = cfg.loop_match_minimum_chain_size // 2
        ids = [
            i
            for i in range(
                max(0, j - half), min(k - cfg.loop_match_minimum_chain_size, j + half + 1)
            )
        ]
        sig_j = float(sigma[j])
        lin = float(
            np.clip(
                LOOP_SIGMA_GATE * sig_j, LOOP_MIN_LINEAR_WINDOW, cfg.loop_search_space_dimension / 2
            )
        )
        yaw_sigma = cfg.loop_search_heading_drift_rate * float(path[j])
        ang = float(np.clip(LOOP_SIGMA_GATE * yaw_sigma, LOOP_MIN_ANGULAR_WINDOW, math.pi))
        self.loops.proposed += 1
        local = self._build_local(
            self._world_points(ids, poses),
            lin,
            cfg.loop_search_space_resolution,
            max(cfg.loop_search_space_smear_deviation, cfg.loop_search_space_resolution),
            first="field",  # the correlative search needs it first
        )
        match = self._match_loop(kf, poses[k], local, lin, ang)
        self._note("loop", k, j, match.reason or "matched", match.response, match.inlier_fraction)
        if not match.ok:
            self.loops.rejected[match.reason] += 1
            return
        ambiguity_test = cfg.loop_match_maximum_ambiguity <= 1.0
        rival = best = 0.0
        if local is not None and lin > cfg.loop_match_ambiguity_distance and ambiguity_test:
            # A wide window can hold an aliased twin of the place (a corridor's next door):
            # a match that is not clearly better than its best rival is no evidence.
            best = _response(local.field, kf.match_points, match.pose)
            rival = rival_score(
                local.field, kf.match_points, match.pose, lin, cfg.loop_match_ambiguity_distance
            )
            if ang > ROTATED_RIVAL_WINDOW:
                # A window this wide in yaw also holds the place turned a quarter or a half (a
                # square junction): the match must beat its own turned twins too.
                turned = rival_score(
                    local.field,
                    kf.match_points,
                    match.pose,
                    lin,
                    -1.0,
                    angles_rad=ROTATED_RIVAL_ANGLES,
                )
                rival = max(rival, turned)
            self._note("rival", k, j, rival / best if best > 0 else math.inf)
            if rival > cfg.loop_match_maximum_ambiguity * best:
                self.loops.rejected["ambiguous (a rival pose scores as well)"] += 1
                log.debug("loop %d-%d ambiguous: rival %.3f vs %.3f", j, k, rival, best)
                return
        if local is not None and lin > cfg.loop_match_ambiguity_distance:
            match = self._prefer_prediction(kf, poses[k], local, match, lin / LOOP_SIGMA_GATE)
            if not match.ok:
                self.loops.rejected[match.reason] += 1
                return
        loop_cov = loop_covariance(
            match.covariance, float(match.pose[2]), cfg.scan_match_degeneracy_ratio
        )
        if rival > cfg.loop_match_hold_ambiguity * best:
            # Nearly ambiguous: no evidence to bend the graph with now, a vote at the end.
            reason = "nearly ambiguous (held for the final vote)"
            self.loops.rejected[reason] += 1
            self._held.append(_Held(j, k, ominus(poses[j], match.pose), loop_cov, reason))
            return
        # A closure the graph finds inconsistent is undone by restoring the graph, not by
        # removing the edge: remove-and-update leaves iSAM2's estimate nudged by the trial.
        before = self.graph.snapshot()
        edge = self.graph.add_edge(
            j, k, ominus(poses[j], match.pose), loop_cov, kind="loop", robust=True
        )
        self.graph.update(extra_iterations=LOOP_EXTRA_ITERATIONS)
        chi2 = self.graph.edge_chi2(edge)
        if chi2 > cfg.loop_closure_max_chi2:
            self.graph.restore(before)
            reason = "inconsistent with the graph"
            self.loops.rejected[reason] += 1
            self._held.append(_Held(j, k, ominus(poses[j], match.pose), loop_cov, reason))
            log.debug("loop %d-%d held back: chi2 %.1f", j, k, chi2)
            self._note("chi2", k, j, False, chi2)
            return
        self.loops.accepted += 1
        self._local = None  # the closure moved the recent keyframes
        self.loop_edges.append((j, k))
        self._note("chi2", k, j, True, chi2)

    def _prefer_prediction(
        self,
        kf: Keyframe,
        prior: np.ndarray,
        local: _LocalMap,
        match: MatchOutcome,
        sigma_m: float,
    ) -> MatchOutcome:
        """A wide-window closure that jumped ``d`` away from the graph's prediction must beat
        the place at the prediction (at the match's heading) by the prior's odds: its score
        times ``exp(-d^2 / 2 sigma^2)``, with the Gaussian (``sigma_m``) that sized the search
        window, unless the prediction's place scores below a loop's coarse threshold.
        Otherwise the scan fits a repeating corridor one period on about as well as where the
        graph says it is, and the graph decides (issue #12: infinite-corridor's first wrong
        closure moved a prediction 0.4 m from the truth 7.8 m to the next bay, where the place
        at the prediction scored 0.61 of it). The match is then redone in a narrow window at
        the prediction (+-half ``loop_match_ambiguity_distance``, clear of the far match); if
        that fails, the closure is rejected."""
        cfg = self.config
        jump = float(np.hypot(*(match.pose[:2] - prior[:2])))
        if jump <= cfg.loop_match_ambiguity_distance:
            return match
        near_m = cfg.loop_match_ambiguity_distance / 2  # the prediction's place: half as far
        at_prior = np.array([prior[0], prior[1], match.pose[2]])
        best = match.response  # the score at match.pose
        near = rival_score(local.field, kf.match_points, at_prior, near_m, -1.0)
        odds = math.exp(-0.5 * (jump / sigma_m) ** 2)
        self._note("prediction", kf.id, near / best if best > 0 else math.inf, odds)
        if near <= odds * best or near < cfg.loop_match_minimum_response_coarse:
            return match  # the far match wins, or nothing at the prediction could match
        again = self._match_loop(kf, at_prior, local, near_m, LOOP_MIN_ANGULAR_WINDOW)
        if again.ok:
            self.loops.rematched_at_prediction += 1
            return again
        reason = "ambiguous (the predicted place scores nearly as well)"
        return replace(again, reason=reason)

    def _vote(self) -> None:
        """At the end every loop closure votes, the accepted ones and those held back (found
        inconsistent with the graph, or nearly ambiguous): the graph with all of them goes to
        :meth:`PoseGraph.robust_edge_outliers` (graduated non-convexity); the outvoted ones
        leave the graph, the rest stay, and the graph is re-optimised.

        A wrong closure accepted early (an aliased place in a wide window) bends the graph, and
        every correct closure after it is then rejected as inconsistent: without a vote the map
        is decided by that one early call, which tiny numeric differences flip (issue #12)."""
        held, self._held = self._held, []
        held_ids = {
            self.graph.add_edge(h.j, h.k, h.delta, h.covariance, kind="loop", robust=True): h
            for h in held
        }
        out = self.graph.robust_edge_outliers(self.config.loop_closure_max_chi2)
        self._note("vote", sorted((e.i, e.j) for e in self.graph.edges if e.id in out))
        for eid in sorted(out):
            e = self.graph.remove_edge(eid)
            if eid in held_ids:
                self._held.append(held_ids[eid])
            else:  # an accepted closure the others outvote
                reason = "outvoted by the other closures"
                self.loops.accepted -= 1
                self.loops.rejected[reason] += 1
                self.loops.outvoted += 1
                self._held.append(_Held(e.i, e.j, e.delta, np.linalg.inv(e.information), reason))
        for eid in held_ids.keys() - out:
            self.loops.rejected[held_ids[eid].reason] -= 1
            self.loops.accepted += 1
            self.loops.readmitted += 1
        self.loop_edges = [(e.i, e.j) for e in self.graph.edges if e.kind == "loop" and e.robust]
        if held_ids.keys() - out or out - held_ids.keys():
            self.graph.optimize_batch()
            self._local = None
        elif held_ids:
            self.graph.update()

    # 3e. Output --------------------------------------------------------------------------------

    def _scan_poses(self, poses: np.ndarray) -> np.ndarray:
        """Every scan's map pose from the optimised keyframes. A scan between keyframes k and k+1
        was tracked in the frame both were matched in, so it is placed from each of them and the
        two are blended by time: a correction the graph made between k and k+1 is spread over
        the scans in between instead of landing as a step at k+1."""
        if not len(self._scan_stamps):
            return np.zeros((0, 3))
        kf = self._scan_kf.array
        from_prev = oplus(poses[kf], self._scan_offset.array)
        nxt = np.minimum(kf + 1, len(poses) - 1)
        stamps = self._scan_stamps.array
        kf_stamps = np.array([k.stamp_ns for k in self.keyframes], dtype=np.int64)
        # Only a next keyframe that was itself scan-matched, made from this one after the scan,
        # shares the scans' tracking frame (not one made on an earlier pass, when re-anchored).
        has_next = (
            (kf + 1 < len(poses))
            & np.asarray(self._kf_matched)[nxt]
            & (np.asarray(self._kf_parent)[nxt] == kf)
            & (kf_stamps[nxt] >= stamps)
        )
        track = self._scan_track.array
        kf_track = np.asarray(self._kf_track)
        from_next = oplus(poses[nxt], ominus(kf_track[nxt], track))
        span = np.maximum(kf_stamps[nxt] - kf_stamps[kf], 1)
        w = np.where(has_next, np.clip((stamps - kf_stamps[kf]) / span, 0.0, 1.0), 0.0)
        blended = from_prev + w[:, None] * _relative_delta(from_prev, from_next)
        blended[:, 2] = wrap_angle(blended[:, 2])
        return blended

    def finish(self, batch_optimise: bool = True) -> MapperResult:
        if self._relocalise and self._scans_seen:
            raise MapError(
                f"none of the {self._scans_seen} scans could be placed in the saved map "
                "(the localiser's global relocalisation found no verified, unambiguous pose); "
                "the map was not extended"
            )
        if batch_optimise and self.keyframes:
            t0 = time.perf_counter()
            self.graph.optimize_batch()
            if self.config.loop_closure_vote and self._held:
                self._vote()
            self.timings["optimisation"] += time.perf_counter() - t0
        poses = self.graph.poses() if self.keyframes else np.zeros((0, 3))
        scan_poses = self._scan_poses(poses)
        counts = {
            "scans": self._scans_seen,
            "scans_used": len(self._scan_stamps),
            "skipped": dict(self.skipped),
            "keyframes": len(self.keyframes),
            "sequential_matches": dict(self.matches),
            "loop_closures": self.loops.as_dict(),
        }
        if self.config.revisit_distance > 0:
            counts["revisits"] = self.revisits
        if self.relocalised is not None:
            counts["relocalised_in_saved_map"] = self.relocalised
        return MapperResult(
            keyframes=list(self.keyframes),
            poses=poses,
            edges=[edge_dict(e) for e in self.graph.edges],
            scan_stamps_ns=self._scan_stamps.array.copy(),
            scan_poses=scan_poses,
            counts=counts,
            timings_s={k: round(v, 3) for k, v in self.timings.items()},
        )


def build_grid(result: MapperResult, config: MapperConfig) -> OccupancyGrid:
    """The occupancy grid of the keyframe scans at their optimised poses."""
    scans = [k.scan for k in result.keyframes]
    bounds = bounds_of_scans(result.poses, scans, config.max_laser_range)
    geom = GridGeometry.from_bounds(*bounds, resolution=config.resolution, margin=GRID_MARGIN_M)
    return integrate_scans(geom, result.poses, scans, config)


def make_bundle(
    result: MapperResult, grid: OccupancyGrid, config: MapperConfig, source: str
) -> MapBundle:
    """The map bundle (grid, keyframes, graph, scans, config) of a mapping result."""
    kfs = result.keyframes
    return MapBundle(
        grid=grid,
        keyframe_ids=np.array([k.id for k in kfs], dtype=np.int64),
        keyframe_stamps_ns=np.array([k.stamp_ns for k in kfs], dtype=np.int64),
        keyframe_poses=np.asarray(result.poses, dtype=np.float64).reshape(-1, 3),
        keyframe_odom_poses=np.array([k.odom_pose for k in kfs], dtype=np.float64).reshape(-1, 3),
        edges=tuple(_graph_edge(e) for e in result.edges),
        scans=tuple(k.scan for k in kfs),
        config=asdict(config),
        source=source,
    )


def _graph_edge(e: dict[str, Any]) -> GraphEdge:
    dx, dy, dyaw = (float(v) for v in e["delta"])
    info = tuple(tuple(float(v) for v in row) for row in e["information"])
    return GraphEdge(
        kind=str(e["kind"]),
        from_id=int(e["from"]),
        to_id=int(e["to"]),
        delta=(dx, dy, dyaw),
        information=info,
    )


def _relative_delta(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """b - a with the yaw difference wrapped (for linear blending of nearby poses)."""
    d = b - a
    d[:, 2] = wrap_angle(d[:, 2])
    return d


def edge_dict(edge: Edge) -> dict[str, Any]:
    """A graph edge as graph.json stores it."""
    return {
        "kind": edge.kind,
        "from": edge.i,
        "to": edge.j,
        "delta": [float(v) for v in edge.delta],
        "information": np.asarray(edge.information, dtype=float).tolist(),
        "robust": edge.robust,
    }


def _builder_pool() -> ThreadPoolExecutor:
    """This process's local-map builders (the threads of a parent do not survive a fork)."""
    pool = _builders.get(os.getpid())
    if pool is None:
        pool = _builders.setdefault(
            os.getpid(),
            ThreadPoolExecutor(LOCAL_MAP_WORKERS, thread_name_prefix="mapper-local-map"),
        )
    return pool


def _done(value: Any) -> Future[Any]:
    """A future that already holds ``value`` (a local-map part built on the calling thread)."""
    done: Future[Any] = Future()
    done.set_result(value)
    return done


def _reference(points: np.ndarray, voxel_m: float) -> ReferenceCloud:
    """The ICP reference of a local map's points (thinned to half the scan voxel)."""
    return build_reference(voxel_filter(points, voxel_m))


def _response(fld: LikelihoodField, points: np.ndarray, pose: np.ndarray) -> float:
    """Mean likelihood of the scan points at ``pose`` (the fine response)."""
    return float(fld.lookup(transform_points(pose, points)).mean())


__all__ = [
    "Keyframe",
    "Mapper",
    "MapperResult",
    "build_grid",
    "make_bundle",
    "odometry_covariance",
    "oplus",
    "ominus",
]
