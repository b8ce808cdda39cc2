"""A 3-DoF (x, y, yaw) pose graph for the keyframe mapper: GTSAM Pose2 factors solved by iSAM2.

This is the only module of rgbdnav that imports gtsam. Everything it hands out is numpy: poses are
``(x [m], y [m], yaw [rad])`` rows, covariances and information matrices are 3x3 in the order
(x, y, yaw), which is also the order of GTSAM's Pose2 tangent space, so they map one to one onto
``noiseModel.Gaussian``.

An edge ``i -> j`` measures ``delta = T_i^-1 T_j``: pose j in the frame of pose i. Its residual at
an estimate is GTSAM's BetweenFactor error ``e = Log(delta^-1 T_i^-1 T_j)`` and its chi-square
(squared Mahalanobis distance) is ``e^T Omega e`` with ``Omega`` the information matrix; GTSAM's
graph error is ``0.5 * sum chi2`` (robust edges contribute ``rho(sqrt(chi2))`` instead).

Life cycle (as in GTSAM's ``VisualISAM2Example``): ``add_node``/``add_edge``/``remove_edge`` only
queue changes; ``update()`` hands them to iSAM2 in one step; ``optimize_batch()`` runs
Levenberg-Marquardt on the whole graph and re-seeds iSAM2 with the result.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import gtsam
import numpy as np
from numpy.typing import ArrayLike

from sensors.types import MapError

log = logging.getLogger(__name__)

EdgeKind = Literal["odometry", "scan", "loop"]
RobustKernel = Literal["huber", "cauchy", "none"]

# 1. Named noise models. The first node is pinned to where it was put (the map origin) by a prior
#    much tighter than any measurement, which removes the gauge freedom without bending the graph.
PRIOR_SIGMAS = np.array([1e-4, 1e-4, 1e-4])  # [m, m, rad]
PRIOR_COVARIANCE = np.diag(PRIOR_SIGMAS**2)  # [m^2, m^2, rad^2]

# Linear solver for batch LM; iSAM2 takes `factorization` ("qr" by default for the same reason).
LM_LINEAR_SOLVER = "MULTIFRONTAL_QR"
# Symmetry tolerance for user covariances / information matrices (relative to their largest entry).
SYMMETRY_RTOL = 1e-9
# Below this rotation angle the SE(2) logarithm uses its Taylor series.
SMALL_ANGLE = 1e-8  # [rad]
# Chi-square 99% quantile, 3 degrees of freedom: a consistent edge stays below it 99% of the time.
CHI2_3DOF_99 = 11.345


class PoseGraphError(MapError):
    """The pose graph was given something it cannot use (unknown node, bad covariance, bad file)."""


@dataclass(frozen=True)
class Edge:
    """A relative-pose measurement between two nodes."""

    id: int  # stable id returned by PoseGraph.add_edge
    kind: EdgeKind  # "odometry" | "scan" | "loop"
    i: int  # node the measurement is expressed in
    j: int  # node that is measured
    delta: np.ndarray  # (3,) float64: pose j in frame i, (x [m], y [m], yaw [rad])
    information: np.ndarray  # (3, 3) float64: inverse covariance, order (x, y, yaw)
    robust: bool = False  # under the graph's robust kernel (loop closures) or plain Gaussian


@dataclass(frozen=True)
class BatchStats:
    """What one Levenberg-Marquardt run did (``PoseGraph.optimize_batch``)."""

    initial_error: float  # GTSAM graph error (0.5 * robust chi2, priors included) before
    final_error: float  # ... and after
    iterations: int
    seconds: float  # [s] wall time of the optimiser alone


# -------------------------------------------------------------------------------------------------
# Pure kernels (numpy only): the residual GTSAM's BetweenFactor<Pose2> computes, vectorised.
# -------------------------------------------------------------------------------------------------


def se2_log(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """SE(2) logarithm of poses (x, y, yaw) -> (N, 3) tangent vectors (v_x, v_y, theta).

    With theta = wrap(yaw) and t = (x, y): v = V(theta)^-1 t,
    V^-1 = [[a, theta/2], [-theta/2, a]],  a = (theta/2) / tan(theta/2)  (-> 1 - theta^2/12).
    This is GTSAM's ``Pose2::Logmap`` (its default chart), so residuals match BetweenFactorPose2.
    """
    theta = np.arctan2(np.sin(yaw), np.cos(yaw))
    half = 0.5 * theta
    small = np.abs(theta) < SMALL_ANGLE
    safe_tan = np.where(small, 1.0, np.tan(half))
    a = np.where(small, 1.0 - theta**2 / 12.0, half / safe_tan)
    return np.stack([a * x + half * y, -half * x + a * y, theta], axis=-1)


def between_residuals(poses_i: np.ndarray, poses_j: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """Residuals ``Log(delta^-1 T_i^-1 T_j)`` of (N, 3) edges -> (N, 3), order (x, y, yaw)."""
    xi, yi, ti = poses_i.T
    xj, yj, tj = poses_j.T
    dx, dy, dt = deltas.T
    # T_ij = T_i^-1 T_j
    c, s = np.cos(ti), np.sin(ti)
    rx, ry = c * (xj - xi) + s * (yj - yi), -s * (xj - xi) + c * (yj - yi)
    # delta^-1 T_ij
    cd, sd = np.cos(dt), np.sin(dt)
    ex, ey = cd * (rx - dx) + sd * (ry - dy), -sd * (rx - dx) + cd * (ry - dy)
    return se2_log(ex, ey, (tj - ti) - dt)


def mahalanobis_sq(residuals: np.ndarray, information: np.ndarray) -> np.ndarray:
    """``e^T Omega e`` for (N, 3) residuals and (N, 3, 3) information matrices -> (N,)."""
    return np.einsum("ni,nij,nj->n", residuals, information, residuals)


# -------------------------------------------------------------------------------------------------
# Validation helpers: every public entry point rejects bad numbers with a message saying which.
# -------------------------------------------------------------------------------------------------


def _as_pose(value: ArrayLike, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise PoseGraphError(f"{what} must have shape (3,) as (x, y, yaw), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PoseGraphError(f"{what} must be finite, got {arr.tolist()}")
    return arr


def _as_spd(value: ArrayLike, what: str) -> np.ndarray:
    """A symmetric positive definite 3x3 matrix, symmetrised, or PoseGraphError naming ``what``."""
    m = np.asarray(value, dtype=np.float64)
    if m.shape != (3, 3):
        raise PoseGraphError(f"{what} must be 3x3 (x, y, yaw), got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise PoseGraphError(f"{what} must be finite, got {m.tolist()}")
    scale = float(np.max(np.abs(m)))
    if float(np.max(np.abs(m - m.T))) > SYMMETRY_RTOL * scale:
        raise PoseGraphError(f"{what} must be symmetric, got {m.tolist()}")
    m = 0.5 * (m + m.T)
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(m)
        raise PoseGraphError(
            f"{what} must be positive definite, eigenvalues {eig.tolist()}"
        ) from None
    return m


def _gtsam_message(err: Exception) -> str:
    """GTSAM's first paragraph (e.g. "Indeterminate linear system ... near variable 160")."""
    return " ".join(str(err).strip().split("\n\n")[0].split())


def _make_robust(kernel: RobustKernel, width: float) -> gtsam.noiseModel.mEstimator.Base | None:
    if kernel == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(width)
    if kernel == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(width)
    return None


def _copied(value: Any) -> Any:
    """A shallow copy of a list or dict (the graph's containers); anything else as it is (GTSAM
    objects the graph replaces rather than mutates, numbers)."""
    return copy.copy(value) if isinstance(value, list | dict) else value


@dataclass
class _Prior:
    node: int
    factor: gtsam.PriorFactorPose2


class PoseGraph:
    """Incremental Pose2 graph: nodes are keyframe poses, edges relative-pose measurements.

    Node ``k`` is GTSAM key ``k``. Changes are queued and applied by ``update()``; ``poses()``
    returns the iSAM2 estimate for nodes already in the solver and the initial guess for the rest.
    A queued node enters the solver once a prior or a chain of queued edges ties it to the solved
    part; until then it (and its edges) wait, so a half-built graph never reaches the solver
    under-constrained.
    """

    def __init__(
        self,
        robust_kernel: RobustKernel = "huber",
        robust_kernel_width: float = 1.0,
        relinearize_threshold: float = 0.01,
        relinearize_skip: int = 1,
        factorization: Literal["cholesky", "qr"] = "qr",
        wildfire_threshold: float = 0.0,
    ) -> None:
        if robust_kernel not in get_args(RobustKernel):
            raise PoseGraphError(
                f"robust_kernel must be one of {get_args(RobustKernel)}, got {robust_kernel!r}"
            )
        if not (math.isfinite(robust_kernel_width) and robust_kernel_width > 0):
            raise PoseGraphError(f"robust_kernel_width must be > 0, got {robust_kernel_width}")
        if not (math.isfinite(relinearize_threshold) and relinearize_threshold >= 0):
            raise PoseGraphError(f"relinearize_threshold must be >= 0, got {relinearize_threshold}")
        if not (math.isfinite(wildfire_threshold) and wildfire_threshold >= 0):
            raise PoseGraphError(f"wildfire_threshold must be >= 0, got {wildfire_threshold}")
        if relinearize_skip < 1:
            raise PoseGraphError(f"relinearize_skip must be >= 1, got {relinearize_skip}")
        if factorization not in ("cholesky", "qr"):
            raise PoseGraphError(f"factorization must be 'cholesky' or 'qr', got {factorization!r}")
        self.robust_kernel: RobustKernel = robust_kernel
        self.robust_kernel_width = float(robust_kernel_width)
        self._robust = _make_robust(robust_kernel, self.robust_kernel_width)

        # 2. iSAM2 parameters: relinearise a variable when its update exceeds the threshold,
        #    checking every `relinearize_skip` updates.
        self._params = gtsam.ISAM2Params()
        self._params.setRelinearizeThreshold(float(relinearize_threshold))
        self._params.relinearizeSkip = int(relinearize_skip)
        self._params.setFactorization(factorization.upper())
        # Wildfire 0: every Gauss-Newton step reaches every variable it changes. GTSAM's default
        # (0.001) stops back-substitution where a change is smaller, a cut that rounding moves:
        # the estimate then differed by 1e-7..1e-2 m between two CPUs' BLAS kernels within 60
        # keyframes of aces, enough to move the points of a local map across voxel boundaries
        # and flip later matches (issue #12, docs/design/mapper_stability.md).
        gauss_newton = gtsam.ISAM2GaussNewtonParams()
        gauss_newton.setWildfireThreshold(float(wildfire_threshold))
        self._params.setOptimizationParams(gauss_newton)
        self._isam = gtsam.ISAM2(self._params)

        self._initial: list[np.ndarray] = []  # initial guess per node
        self._in_solver: list[bool] = []  # node is a variable of iSAM2
        self._priors: list[_Prior] = []
        self._pending_priors: list[_Prior] = []
        self._edges: dict[int, Edge] = {}  # active edges by id, insertion-ordered
        self._factors: dict[int, gtsam.BetweenFactorPose2] = {}  # edge id -> factor
        self._factor_index: dict[int, int] = {}  # edge id -> iSAM2 factor slot (edges in solver)
        self._pending_edges: list[int] = []  # edge ids not yet in the solver
        self._pending_removals: list[int] = []  # iSAM2 factor slots to drop at the next update
        self._next_edge_id = 0
        self._estimate_cache: gtsam.Values | None = gtsam.Values()  # None: ask iSAM2
        self._poses_cache: np.ndarray | None = None  # poses() until a node or update changes it

    @property
    def _estimate(self) -> gtsam.Values:
        """iSAM2's current estimate, computed on first use after an update (it costs O(N))."""
        if self._estimate_cache is None:
            self._estimate_cache = self._isam.calculateEstimate()
        return self._estimate_cache

    # ---------------------------------------------------------------------------------------------
    # Building the graph
    # ---------------------------------------------------------------------------------------------

    @property
    def num_nodes(self) -> int:
        return len(self._initial)

    @property
    def edges(self) -> list[Edge]:
        """Active edges (queued or in the solver; removed ones are gone), in insertion order."""
        return list(self._edges.values())

    def add_node(self, pose_xyyaw: ArrayLike, prior_covariance: ArrayLike | None = None) -> int:
        """Queue a node with initial guess ``(x, y, yaw)``; return its index.

        The first node always gets a prior at its pose (``PRIOR_COVARIANCE`` unless given); later
        nodes get one only when ``prior_covariance`` is given (e.g. a GNSS fix or a map anchor).
        """
        pose = _as_pose(pose_xyyaw, "node pose")
        node = self.num_nodes
        cov = None
        if prior_covariance is not None:
            cov = _as_spd(prior_covariance, f"prior covariance of node {node}")
        elif node == 0:
            cov = PRIOR_COVARIANCE
        self._initial.append(pose)
        self._in_solver.append(False)
        self._poses_cache = None
        if cov is not None:
            noise = gtsam.noiseModel.Gaussian.Covariance(cov)
            prior = gtsam.PriorFactorPose2(node, gtsam.Pose2(*pose), noise)
            self._pending_priors.append(_Prior(node, prior))
        return node

    def add_edge(
        self,
        i: int,
        j: int,
        delta: ArrayLike,
        covariance: ArrayLike | None = None,
        kind: EdgeKind = "odometry",
        robust: bool = False,
        *,
        information: ArrayLike | None = None,
        edge_id: int | None = None,
    ) -> int:
        """Queue a measurement of node j in node i's frame; return the edge id.

        Give exactly one of ``covariance`` or ``information`` (3x3, order x, y, yaw, symmetric
        positive definite). ``robust`` puts the edge under the graph's robust kernel (use it for
        loop closures). ``edge_id`` restores a saved id (``from_arrays``); it must be unused.
        """
        for name, node in (("i", i), ("j", j)):
            if isinstance(node, bool) or not isinstance(node, int | np.integer):
                raise PoseGraphError(f"edge node {name} must be an int, got {node!r}")
            if not 0 <= node < self.num_nodes:
                raise PoseGraphError(
                    f"edge {i}->{j}: unknown node {node} (graph has {self.num_nodes} nodes)"
                )
        if i == j:
            raise PoseGraphError(f"edge {i}->{j} connects a node to itself")
        if kind not in get_args(EdgeKind):
            raise PoseGraphError(f"edge kind must be one of {get_args(EdgeKind)}, got {kind!r}")
        d = _as_pose(delta, f"edge {i}->{j} delta")
        if (covariance is None) == (information is None):
            raise PoseGraphError(f"edge {i}->{j}: give exactly one of covariance or information")
        if covariance is not None:
            cov = _as_spd(covariance, f"edge {i}->{j} covariance")
            info = _as_spd(np.linalg.inv(cov), f"edge {i}->{j} information (inverse covariance)")
            gaussian = gtsam.noiseModel.Gaussian.Covariance(cov)
        else:
            assert information is not None  # checked above; for mypy
            info = _as_spd(information, f"edge {i}->{j} information")
            gaussian = gtsam.noiseModel.Gaussian.Information(info)
        if edge_id is None:
            edge_id = self._next_edge_id
        elif edge_id in self._edges or edge_id < 0:
            raise PoseGraphError(f"edge id {edge_id} is negative or already used")
        self._next_edge_id = max(self._next_edge_id, edge_id + 1)

        noise: gtsam.noiseModel.Base = gaussian
        if robust and self._robust is not None:
            noise = gtsam.noiseModel.Robust.Create(self._robust, gaussian)
        d.setflags(write=False)
        info.setflags(write=False)
        edge = Edge(edge_id, kind, int(i), int(j), d, info, bool(robust))
        self._edges[edge_id] = edge
        self._factors[edge_id] = gtsam.BetweenFactorPose2(int(i), int(j), gtsam.Pose2(*d), noise)
        self._pending_edges.append(edge_id)
        return edge_id

    def remove_edge(self, edge_id: int) -> Edge:
        """Drop an edge (e.g. a loop closure found inconsistent); applied at the next ``update()``.

        Refuses to remove an edge whose loss would leave solved nodes without any path to a prior.
        """
        edge = self._edges.get(edge_id)
        if edge is None:
            raise PoseGraphError(f"no active edge with id {edge_id}")
        if edge_id in self._factor_index:
            stranded = self._unanchored_after_removing(edge_id)
            if stranded:
                raise PoseGraphError(
                    f"removing edge {edge_id} ({edge.i}->{edge.j}) would leave nodes "
                    f"{stranded[:10]} unconstrained"
                )
            self._pending_removals.append(self._factor_index.pop(edge_id))
        else:
            self._pending_edges.remove(edge_id)
        del self._edges[edge_id]
        del self._factors[edge_id]
        return edge

    def _unanchored_after_removing(self, edge_id: int) -> list[int]:
        """Solver nodes that would have no path to a prior without ``edge_id``."""
        adjacency: dict[int, list[int]] = {}
        for eid in self._factor_index:
            if eid != edge_id:
                e = self._edges[eid]
                adjacency.setdefault(e.i, []).append(e.j)
                adjacency.setdefault(e.j, []).append(e.i)
        reached = {p.node for p in self._priors}
        stack = list(reached)
        while stack:
            for other in adjacency.get(stack.pop(), ()):
                if other not in reached:
                    reached.add(other)
                    stack.append(other)
        return [k for k, solved in enumerate(self._in_solver) if solved and k not in reached]

    def _ready(self) -> tuple[list[int], list[_Prior], list[int]]:
        """Queued nodes, priors and edges that can enter the solver now (anchored ones)."""
        solved = self._in_solver
        anchored = {p.node for p in self._pending_priors}
        # Grow the anchored set through queued edges until nothing changes (few passes in practice:
        # queued edges arrive in node order).
        waiting = list(self._pending_edges)
        ready_edges: list[int] = []
        progress = True
        while progress and waiting:
            progress, still = False, []
            for eid in waiting:
                e = self._edges[eid]
                if solved[e.i] or solved[e.j] or e.i in anchored or e.j in anchored:
                    anchored.update((e.i, e.j))
                    ready_edges.append(eid)
                    progress = True
                else:
                    still.append(eid)
            waiting = still
        new_nodes = sorted(k for k in anchored if not solved[k])
        return new_nodes, list(self._pending_priors), ready_edges

    # ---------------------------------------------------------------------------------------------
    # Solving
    # ---------------------------------------------------------------------------------------------

    def update(self, extra_iterations: int = 0) -> None:
        """Hand queued nodes, edges and removals to iSAM2 (one Gauss-Newton step on the affected
        part), plus ``extra_iterations`` further steps (useful right after a loop closure)."""
        if extra_iterations < 0:
            raise PoseGraphError(f"extra_iterations must be >= 0, got {extra_iterations}")
        new_nodes, priors, edge_ids = self._ready()
        deferred = len(self._pending_edges) - len(edge_ids)
        if deferred:
            log.debug("%d queued edges wait for their nodes to be anchored", deferred)

        # 3a. Collect the new factors; remember which edge each one is.
        graph = gtsam.NonlinearFactorGraph()
        for p in priors:
            graph.add(p.factor)
        for eid in edge_ids:
            graph.add(self._factors[eid])
        # 3b. Initial guesses for variables iSAM2 has not seen yet.
        values = gtsam.Values()
        for k in new_nodes:
            values.insert(k, gtsam.Pose2(*self._initial[k]))
        # 3c. One iSAM2 step: add new factors, drop removed ones.
        if graph.size() or self._pending_removals:
            result = self._run_isam(graph, values, self._pending_removals)
            slots = list(result.getNewFactorsIndices())
            for eid, slot in zip(edge_ids, slots[len(priors) :], strict=True):
                self._factor_index[eid] = slot
            for k in new_nodes:
                self._in_solver[k] = True
            self._priors.extend(priors)
            self._pending_priors = []
            ready = set(edge_ids)
            self._pending_edges = [e for e in self._pending_edges if e not in ready]
            self._pending_removals = []
        # 3d. Further iterations re-solve without new information. They force relinearisation:
        #     otherwise a robust edge whose weight was tiny when it was linearised (a correct loop
        #     closure after long drift, under Cauchy) keeps its stale weight and iSAM2 stalls.
        for _ in range(extra_iterations if self._isam.size() else 0):
            self._run_isam(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], force_relinearize=True)
        self._estimate_cache = None
        self._poses_cache = None

    def _run_isam(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        removals: list[int],
        force_relinearize: bool = False,
    ) -> gtsam.ISAM2Result:
        try:
            return self._isam.update(graph, values, removals, force_relinearize=force_relinearize)
        except RuntimeError as err:
            raise PoseGraphError(f"iSAM2 update failed: {_gtsam_message(err)}") from err

    def optimize_batch(self, max_iterations: int = 100) -> BatchStats:
        """Levenberg-Marquardt on the whole graph (solved plus ready queued parts), then re-seed
        iSAM2 with the result so later incremental updates continue from it."""
        if max_iterations < 1:
            raise PoseGraphError(f"max_iterations must be >= 1, got {max_iterations}")
        new_nodes, priors, edge_ids = self._ready()
        solved_edges = [eid for eid in self._edges if eid in self._factor_index]
        all_priors = self._priors + priors
        all_edges = solved_edges + edge_ids
        # 4a. The full graph and the current estimate (initial guesses for queued nodes).
        graph = gtsam.NonlinearFactorGraph()
        for p in all_priors:
            graph.add(p.factor)
        for eid in all_edges:
            graph.add(self._factors[eid])
        initial = gtsam.Values(self._estimate)
        for k in new_nodes:
            initial.insert(k, gtsam.Pose2(*self._initial[k]))
        if graph.size() == 0:
            return BatchStats(0.0, 0.0, 0, 0.0)
        # 4b. Levenberg-Marquardt from there. Ceres' lambda schedule (start 1e-4, factor 2, no
        #     practical upper bound) but plain (not diagonal) damping, and QR: benchmark graphs mix
        #     information entries from 1e0 to 1e12, where Cholesky reports an indeterminate system
        #     and GTSAM's default schedule stalls (Intel from odometry: 3686 after 1000 iterations
        #     against 107.9 in 410 with these settings).
        params = gtsam.LevenbergMarquardtParams.CeresDefaults()
        params.setDiagonalDamping(False)
        params.setMaxIterations(int(max_iterations))
        params.setLinearSolverType(LM_LINEAR_SOLVER)
        t0 = time.perf_counter()
        initial_error = graph.error(initial)
        try:
            optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
            result = optimizer.optimize()
        except RuntimeError as err:
            raise PoseGraphError(f"batch optimisation failed: {_gtsam_message(err)}") from err
        seconds = time.perf_counter() - t0
        stats = BatchStats(initial_error, graph.error(result), optimizer.iterations(), seconds)
        # 4c. Re-seed iSAM2: a fresh solver holding the same factors, linearised at the optimum.
        self._isam = gtsam.ISAM2(self._params)
        update = self._run_isam(graph, result, [])
        slots = list(update.getNewFactorsIndices())
        self._factor_index = dict(zip(all_edges, slots[len(all_priors) :], strict=True))
        self._priors = all_priors
        self._pending_priors = []
        ready = set(edge_ids)
        self._pending_edges = [e for e in self._pending_edges if e not in ready]
        self._pending_removals = []  # removed factors are not in the rebuilt graph
        for k in new_nodes:
            self._in_solver[k] = True
        self._estimate_cache = None
        self._poses_cache = None
        log.info(
            "batch LM: error %.6g -> %.6g in %d iterations (%.3f s)",
            stats.initial_error,
            stats.final_error,
            stats.iterations,
            stats.seconds,
        )
        return stats

    def robust_edge_outliers(self, max_chi2: float, max_iterations: int = 100) -> set[int]:
        """Robust edges (loop closures) that the rest of the graph outvotes: graduated
        non-convexity (GTSAM's ``GncOptimizer``, truncated least squares; Yang et al., RA-L 2020)
        over the whole graph, every non-robust edge and prior a known inlier, every robust edge
        a Gaussian whose weight GNC decides; an edge ends an outlier when its chi-square at the
        robust optimum is above ``max_chi2``. The solver's state is left as it was.

        Unlike a Huber optimum, where one wrong closure bends the graph until the closures
        after it look wrong, GNC starts convex and tightens the kernel step by step, so a
        majority of mutually consistent closures decides which ones fit."""
        new_nodes, priors, edge_ids = self._ready()
        graph = gtsam.NonlinearFactorGraph()
        for p in self._priors + priors:
            graph.add(p.factor)
        ids = [eid for eid in self._edges if eid in self._factor_index or eid in edge_ids]
        voters: list[tuple[int, int]] = []  # (edge id, factor slot)
        for eid in ids:
            e = self._edges[eid]
            if e.robust:
                voters.append((eid, graph.size()))
                gaussian = gtsam.noiseModel.Gaussian.Information(e.information)
                graph.add(gtsam.BetweenFactorPose2(e.i, e.j, gtsam.Pose2(*e.delta), gaussian))
            else:
                graph.add(self._factors[eid])
        if not voters:
            return set()
        initial = gtsam.Values(self._estimate)
        for k in new_nodes:
            initial.insert(k, gtsam.Pose2(*self._initial[k]))
        voting = {slot for _, slot in voters}
        lm = gtsam.LevenbergMarquardtParams.CeresDefaults()
        lm.setDiagonalDamping(False)
        lm.setMaxIterations(int(max_iterations))
        lm.setLinearSolverType(LM_LINEAR_SOLVER)
        params = gtsam.GncLMParams(lm)
        params.setLossType(gtsam.GncLossType.TLS)
        params.setKnownInliers([k for k in range(graph.size()) if k not in voting])
        try:
            gnc = gtsam.GncLMOptimizer(graph, initial, params)
            gnc.setInlierCostThresholds(0.5 * float(max_chi2))  # factor error = chi2 / 2
            gnc.optimize()
            weights = np.asarray(gnc.getWeights(), dtype=np.float64)
        except RuntimeError as err:
            raise PoseGraphError(f"loop-closure vote failed: {_gtsam_message(err)}") from err
        return {eid for eid, slot in voters if weights[slot] < 0.5}

    # ---------------------------------------------------------------------------------------------
    # Reading the estimate
    # ---------------------------------------------------------------------------------------------

    def poses(self) -> np.ndarray:
        """(N, 3) float64 (x [m], y [m], yaw [rad]): solver estimate, initial guess if queued.

        A fresh copy each call; the array it is copied from is kept until the next ``add_node``,
        ``update`` or ``optimize_batch`` (the mapper asks several times per keyframe)."""
        if self._poses_cache is None:
            est = self._estimate
            if est.size() == self.num_nodes:
                # Every node solved (the mapper's case after each update): the keys are exactly
                # 0 .. N-1 (only node indices are ever inserted), in key order, so the estimate
                # is the whole array; no initial guesses to gather and scatter over (the same
                # values, ~0.3 ms less per update on MIT CSAIL's 660 nodes).
                out = np.ascontiguousarray(gtsam.utilities.extractPose2(est), dtype=np.float64)
            else:
                out = np.array(self._initial, dtype=np.float64).reshape(-1, 3)
                if est.size():
                    keys = np.asarray(est.keys(), dtype=np.int64)  # in key order
                    out[keys] = gtsam.utilities.extractPose2(est)
            self._poses_cache = out
        return self._poses_cache.copy()

    def pose(self, i: int) -> np.ndarray:
        """(3,) pose of node i (see ``poses``)."""
        self._check_node(i)
        if self._estimate.exists(i):
            p = self._estimate.atPose2(i)
            return np.array([p.x(), p.y(), p.theta()])
        return self._initial[i].copy()

    def marginal_covariance(self, i: int) -> np.ndarray:
        """3x3 marginal covariance of node i (x, y, yaw) at the current linearisation point."""
        self._check_node(i)
        if not self._in_solver[i]:
            raise PoseGraphError(f"node {i} is not solved yet: call update() first")
        return np.asarray(self._isam.marginalCovariance(i), dtype=np.float64)

    def _check_node(self, i: int) -> None:
        if not 0 <= i < self.num_nodes:
            raise PoseGraphError(f"unknown node {i} (graph has {self.num_nodes} nodes)")

    def edge_errors(self, edge_ids: Iterable[int] | None = None) -> dict[int, float]:
        """Chi-square (``e^T Omega e``, no robust weighting) of active edges at the estimate.

        A consistent edge stays below ``CHI2_3DOF_99`` (11.34) 99% of the time; a wrong loop
        closure sits far above it.
        """
        ids = list(self._edges) if edge_ids is None else list(edge_ids)
        if not ids:
            return {}
        for eid in ids:
            if eid not in self._edges:
                raise PoseGraphError(f"no active edge with id {eid}")
        edges = [self._edges[eid] for eid in ids]
        poses = self.poses()
        ij = np.array([(e.i, e.j) for e in edges], dtype=np.int64)
        deltas = np.array([e.delta for e in edges])
        info = np.array([e.information for e in edges])
        chi2 = mahalanobis_sq(between_residuals(poses[ij[:, 0]], poses[ij[:, 1]], deltas), info)
        return dict(zip(ids, chi2.tolist(), strict=True))

    def edge_chi2(self, edge_id: int) -> float:
        """Chi-square of one active edge at the estimate (see ``edge_errors``)."""
        return self.edge_errors([edge_id])[edge_id]

    def total_chi2(self) -> float:
        """Sum of ``edge_errors`` (g2o's "chi2": no priors, no robust kernel)."""
        return float(sum(self.edge_errors().values()))

    def total_error(self) -> float:
        """GTSAM graph error at the estimate: ``0.5 * chi2`` per Gaussian factor (priors included),
        the robust loss for robust edges. This is what ``update``/``optimize_batch`` minimise."""
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values(self._estimate)
        for p in self._priors + self._pending_priors:
            graph.add(p.factor)
            if not values.exists(p.node):
                values.insert(p.node, gtsam.Pose2(*self._initial[p.node]))
        for eid in self._edges:
            e = self._edges[eid]
            for k in (e.i, e.j):
                if not values.exists(k):
                    values.insert(k, gtsam.Pose2(*self._initial[k]))
            graph.add(self._factors[eid])
        return float(graph.error(values))

    # ---------------------------------------------------------------------------------------------
    # Trials: try a change, judge it, undo it without a trace
    # ---------------------------------------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """The whole graph state now, for :meth:`restore`. Removing an edge after an ``update``
        does not give the estimate back: iSAM2 keeps the linearisation point and the relinearised
        cliques the trial moved. A trial (add a loop closure, update, judge its chi-square) that
        is rejected and restored leaves the graph bit-identical to never having tried (issue
        #12: a rejected closure must not move the map). iSAM2 is copied (GTSAM's copy
        constructor, a deep copy of the Bayes tree); the rest are shallow copies of containers
        whose elements are never mutated."""
        state = {k: _copied(v) for k, v in vars(self).items() if k != "_isam"}
        state["_isam"] = gtsam.ISAM2(self._isam)
        return state

    def restore(self, state: dict[str, Any]) -> None:
        """Put the graph back as :meth:`snapshot` found it (the snapshot stays reusable)."""
        for k, v in state.items():
            setattr(self, k, gtsam.ISAM2(v) if k == "_isam" else _copied(v))

    # ---------------------------------------------------------------------------------------------
    # Saving and restoring (graph.json keyframes + edges)
    # ---------------------------------------------------------------------------------------------

    def to_arrays(self) -> tuple[np.ndarray, list[Edge]]:
        """(N, 3) current poses and the active edges, enough to rebuild with ``from_arrays``."""
        return self.poses(), self.edges

    @classmethod
    def from_arrays(
        cls, poses: ArrayLike, edges: Sequence[Edge], update: bool = True, **kwargs: Any
    ) -> PoseGraph:
        """Rebuild a graph from saved poses (initial guesses; node 0 pinned where it is) and edges
        (ids kept). ``kwargs`` go to the constructor; ``update`` runs one iSAM2 step at the end."""
        arr = np.asarray(poses, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise PoseGraphError(f"poses must have shape (N, 3), got {arr.shape}")
        graph = cls(**kwargs)
        for k, row in enumerate(arr):
            try:
                graph.add_node(row)
            except PoseGraphError as err:
                raise PoseGraphError(f"pose {k}: {err}") from None
        for e in edges:
            graph.add_edge(
                e.i,
                e.j,
                e.delta,
                kind=e.kind,
                robust=e.robust,
                information=e.information,
                edge_id=e.id,
            )
        if update:
            graph.update()
        return graph


# -------------------------------------------------------------------------------------------------
# g2o files (VERTEX_SE2 / EDGE_SE2), the format of the classic 2D pose-graph benchmarks.
# -------------------------------------------------------------------------------------------------


def read_g2o(path: str | Path) -> tuple[np.ndarray, list[Edge]]:
    """Read a 2D g2o file -> ((N, 3) poses, edges), node indices in order of vertex appearance.

    ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33`` (the
    upper triangle of the information matrix, order x, y, theta). Edges between consecutive
    vertices become "odometry", the rest "loop". Other tags are counted and skipped.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise PoseGraphError(f"cannot read g2o file {path}: {err}") from err
    index: dict[int, int] = {}
    poses: list[list[float]] = []
    raw_edges: list[tuple[int, int, int, list[float]]] = []  # line, id i, id j, numbers
    skipped: dict[str, int] = {}

    def numbers(tokens: list[str], count: int, lineno: int, tag: str) -> list[float]:
        if len(tokens) != count:
            raise PoseGraphError(f"{path}:{lineno}: {tag} needs {count} numbers, got {len(tokens)}")
        try:
            values = [float(t) for t in tokens]
        except ValueError as err:
            raise PoseGraphError(f"{path}:{lineno}: {tag}: {err}") from None
        if not all(math.isfinite(v) for v in values):
            raise PoseGraphError(f"{path}:{lineno}: {tag} has non-finite numbers")
        return values

    def vertex_id(token: str, lineno: int, tag: str) -> int:
        try:
            return int(token)
        except ValueError:
            raise PoseGraphError(f"{path}:{lineno}: {tag} id {token!r} is not an int") from None

    for lineno, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        if tag == "VERTEX_SE2":
            if len(tokens) < 2:
                raise PoseGraphError(f"{path}:{lineno}: VERTEX_SE2 without an id")
            vid = vertex_id(tokens[1], lineno, tag)
            if vid in index:
                raise PoseGraphError(f"{path}:{lineno}: vertex {vid} defined twice")
            index[vid] = len(poses)
            poses.append(numbers(tokens[2:], 3, lineno, tag))
        elif tag == "EDGE_SE2":
            if len(tokens) < 3:
                raise PoseGraphError(f"{path}:{lineno}: EDGE_SE2 without two vertex ids")
            vi, vj = vertex_id(tokens[1], lineno, tag), vertex_id(tokens[2], lineno, tag)
            raw_edges.append((lineno, vi, vj, numbers(tokens[3:], 9, lineno, tag)))
        else:
            skipped[tag] = skipped.get(tag, 0) + 1

    edges: list[Edge] = []
    for eid, (lineno, vi, vj, v) in enumerate(raw_edges):
        for vid in (vi, vj):
            if vid not in index:
                raise PoseGraphError(f"{path}:{lineno}: EDGE_SE2 refers to unknown vertex {vid}")
        if vi == vj:
            raise PoseGraphError(f"{path}:{lineno}: EDGE_SE2 connects vertex {vi} to itself")
        i11, i12, i13, i22, i23, i33 = v[3:]
        info = np.array([[i11, i12, i13], [i12, i22, i23], [i13, i23, i33]])
        try:
            info = _as_spd(info, "information")
        except PoseGraphError as err:
            raise PoseGraphError(f"{path}:{lineno}: EDGE_SE2 {vi} {vj}: {err}") from None
        i, j = index[vi], index[vj]
        kind: EdgeKind = "odometry" if j == i + 1 else "loop"
        delta = np.array(v[:3])
        delta.setflags(write=False)
        info.setflags(write=False)
        edges.append(Edge(eid, kind, i, j, delta, info, False))
    if skipped:
        log.info("%s: skipped %s", path.name, ", ".join(f"{n} {t}" for t, n in skipped.items()))
    if not poses:
        raise PoseGraphError(f"{path}: no VERTEX_SE2 lines")
    return np.array(poses, dtype=np.float64), edges


def optimize_g2o(
    path: str | Path,
    method: Literal["batch", "isam2"] = "batch",
    max_iterations: int = 100,
    final_isam_iterations: int = 0,
    nodes_per_update: int = 1,
    **kwargs: Any,
) -> dict[str, Any]:
    """Optimise a g2o file from its initial guess; return a summary dict.

    ``batch``: Levenberg-Marquardt on the whole graph. ``isam2``: nodes fed in file order, each with
    the edges to earlier nodes, one ``update()`` per ``nodes_per_update`` nodes, then
    ``final_isam_iterations`` extra steps. Node 0 is pinned by the tight default prior (g2o's
    "fix the first vertex"). Keys: nodes, edges, initial/final ``chi2`` (sum e^T Omega e, g2o's
    number) and ``error`` (GTSAM's, 0.5 chi2 plus the prior), iterations (LM iterations or iSAM2
    updates), seconds, graph.
    """
    if nodes_per_update < 1:
        raise PoseGraphError(f"nodes_per_update must be >= 1, got {nodes_per_update}")
    poses, edges = read_g2o(path)
    kwargs.setdefault("robust_kernel", "none")
    if method == "batch":
        graph = PoseGraph.from_arrays(poses, edges, update=False, **kwargs)
        initial_chi2, initial_error = graph.total_chi2(), graph.total_error()
        t0 = time.perf_counter()
        stats = graph.optimize_batch(max_iterations)
        seconds = time.perf_counter() - t0
        iterations = stats.iterations
    elif method == "isam2":
        graph = PoseGraph(**kwargs)
        # Each edge enters with its later node.
        by_node: dict[int, list[Edge]] = {}
        for e in edges:
            by_node.setdefault(max(e.i, e.j), []).append(e)
        t0 = time.perf_counter()
        for k, row in enumerate(poses):
            graph.add_node(row)
            for e in by_node.get(k, ()):
                graph.add_edge(e.i, e.j, e.delta, kind=e.kind, information=e.information)
            if (k + 1) % nodes_per_update == 0 or k + 1 == len(poses):
                graph.update()
        if final_isam_iterations:
            graph.update(extra_iterations=final_isam_iterations)
        seconds = time.perf_counter() - t0
        iterations = math.ceil(len(poses) / nodes_per_update) + final_isam_iterations
        initial = PoseGraph.from_arrays(poses, edges, update=False, **kwargs)
        initial_chi2, initial_error = initial.total_chi2(), initial.total_error()
    else:
        raise PoseGraphError(f"method must be 'batch' or 'isam2', got {method!r}")
    return {
        "file": Path(path).name,
        "method": method,
        "nodes": graph.num_nodes,
        "edges": len(graph.edges),
        "initial_chi2": initial_chi2,
        "final_chi2": graph.total_chi2(),
        "initial_error": initial_error,
        "final_error": graph.total_error(),
        "iterations": iterations,
        "seconds": seconds,
        "graph": graph,
    }
