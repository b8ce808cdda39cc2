"""Config sections owned by the slam layer: EKF, visual odometry, depth->scan, mapper, localiser.

Names and defaults follow the ROS packages a user already knows (robot_localization, RTAB-Map,
depthimage_to_laserscan / pointcloud_to_laserscan, slam_toolbox, AMCL, Cartographer). Where a
default differs from the upstream one because of the Kinect or the planar robot, the field's doc
says so. Declared with :func:`sensors.config.param`; see ``config/<section>.yaml`` for the
shipped defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from sensors.config import param

# robot_localization state order, used by every 15-element vector below.
STATE_NAMES = (
    "x",
    "y",
    "z",
    "roll",
    "pitch",
    "yaw",
    "vx",
    "vy",
    "vz",
    "vroll",
    "vpitch",
    "vyaw",
    "ax",
    "ay",
    "az",
)
STATE_SIZE = len(STATE_NAMES)

# robot_localization defaults a rejection threshold to numeric_limits<double>::max() (never
# reject). We use a large finite value instead so the YAML stays readable and JSON-safe.
NO_REJECTION = 1.0e9  # [Mahalanobis distance]

_CONFIG_VECTOR_DOC = "15 flags in robot_localization order (x y z roll pitch yaw vx vy vz ..)"


def _mask(*names: str) -> tuple[bool, ...]:
    """A robot_localization ``*_config`` vector with ``names`` set."""
    return tuple(n in names for n in STATE_NAMES)


@dataclass(frozen=True)
class EkfConfig:
    """Planar EKF with robot_localization semantics (ekf_localization_node parameter names)."""

    frequency: float = param(
        30.0,
        unit="Hz",
        gt=0.0,
        doc="filter rate: a wheel reading or VO motion spanning longer than 1/frequency is "
        "fused spread over its span at this rate (slam.ekf.interval_twists)",
    )
    sensor_timeout: float = param(
        0.1, unit="s", gt=0.0, doc="predict without correction after this long without data"
    )
    two_d_mode: bool = param(True, doc="ignore z, roll, pitch and their rates")
    publish_tf: bool = param(True, doc="publish odom -> base_link")
    odom_frame: str = param("odom", doc="REP-105 odometry frame")
    base_link_frame: str = param("base_link", doc="robot body frame")
    world_frame: str = param("odom", doc="frame the estimate is expressed in")
    smooth_lagged_data: bool = param(False, doc="re-filter from history when late data arrives")
    history_length: float = param(
        0.0, unit="s", ge=0.0, doc="state history kept for smooth_lagged_data"
    )
    # 0. Wheel odometry (nav_msgs/Odometry-like twist from the encoders).
    odom0_config: tuple[bool, ...] = param(
        _mask("vx", "vy", "vyaw"),
        length=STATE_SIZE,
        doc=_CONFIG_VECTOR_DOC + "; vy=0 enforces the non-holonomic constraint",
    )
    odom0_differential: bool = param(False, doc="differentiate absolute pose into velocity")
    odom0_relative: bool = param(False, doc="treat the first measurement as zero")
    odom0_pose_rejection_threshold: float = param(
        NO_REJECTION,
        unit="sigma",
        gt=0.0,
        doc="Mahalanobis gate on pose (1e9 = never, as upstream max)",
    )
    odom0_twist_rejection_threshold: float = param(
        NO_REJECTION,
        unit="sigma",
        gt=0.0,
        doc="Mahalanobis gate on twist (1e9 = never, as upstream max)",
    )
    # 1. Visual odometry: each frame pair's motion as a body twist (a failed pair is skipped, so
    #    a VO dropout never becomes a zero-motion measurement).
    vo0_config: tuple[bool, ...] = param(
        _mask("vx", "vy", "vyaw"), length=STATE_SIZE, doc=_CONFIG_VECTOR_DOC
    )
    vo0_differential: bool = param(False, doc="differentiate an absolute VO pose instead")
    vo0_relative: bool = param(False, doc="treat the first measurement as zero")
    vo0_pose_rejection_threshold: float = param(
        NO_REJECTION,
        unit="sigma",
        gt=0.0,
        doc="Mahalanobis gate on pose (1e9 = never, as upstream max)",
    )
    vo0_twist_rejection_threshold: float = param(
        5.0,
        unit="sigma",
        gt=0.0,
        doc="Mahalanobis gate on VO twist: a bad frame pair is rejected, not fused",
    )
    # 2. IMU (gyro z only on this robot).
    imu0_config: tuple[bool, ...] = param(_mask("vyaw"), length=STATE_SIZE, doc=_CONFIG_VECTOR_DOC)
    imu0_angular_velocity_variance: float = param(
        1e-4, unit="(rad/s)^2", gt=0.0, doc="gyro z noise (ImuSample carries no covariance)"
    )
    imu0_gyro_bias_initial_variance: float = param(
        1e-4, unit="(rad/s)^2", ge=0.0, doc="prior on the gyro z bias state (0.01 rad/s sigma)"
    )
    imu0_gyro_bias_process_noise: float = param(
        1e-8, unit="(rad/s)^2/s", ge=0.0, doc="random walk of the gyro z bias"
    )
    odom0_default_variance: float = param(
        1e-3,
        unit="(m/s)^2, (rad/s)^2 or m^2, rad^2",
        gt=0.0,
        doc="odometry messages (nav_msgs/Odometry) whose covariance is all zero, as many "
        "drivers leave it: this variance on each fused variable instead",
    )
    odom0_vy_variance: float = param(
        1e-4, unit="(m/s)^2", gt=0.0, doc="variance of the non-holonomic vy = 0 measurement"
    )
    # A robot standing still shows its gyro's bias (docs/design/gyro_bias.md).
    odom0_still_window: float = param(
        1.0,
        unit="s",
        ge=0.0,
        doc="encoder counts unchanged this long: the robot stood still in the window's middle, "
        "whose mean gyro z is fused as the gyro bias (0 = off)",
    )
    imu0_differential: bool = param(False, doc="differentiate absolute orientation")
    imu0_relative: bool = param(False, doc="treat the first orientation as zero")
    imu0_pose_rejection_threshold: float = param(
        NO_REJECTION, unit="sigma", gt=0.0, doc="Mahalanobis gate on orientation (1e9 = never)"
    )
    imu0_twist_rejection_threshold: float = param(
        NO_REJECTION, unit="sigma", gt=0.0, doc="Mahalanobis gate on angular velocity (1e9 = never)"
    )
    imu0_linear_acceleration_rejection_threshold: float = param(
        NO_REJECTION, unit="sigma", gt=0.0, doc="Mahalanobis gate on acceleration (1e9 = never)"
    )
    # Diagonals of Q and P0; robot_localization's default matrices (off-diagonals are zero).
    # robot_localization's defaults except vx, vy, vyaw: its 0.025 / 0.02 let the velocity change
    # far slower than Eddie accelerates (0.5 m/s^2, turns in place at 1.5 rad/s^2); with noisy
    # 36-position encoder twists the filter then lags every start and turn. Wheels only through
    # the EKF on the simulated house route: ATE 2.45 m with upstream's values, 1.30 m with these
    # (`rgbdnav odometry scenes/house.yaml --no-vo --set ekf.imu0_config=[false,...]`).
    process_noise_covariance: tuple[float, ...] = param(
        (0.05, 0.05, 0.06, 0.03, 0.03, 0.06, 0.5, 0.5, 0.04, 0.01, 0.01, 2.0, 0.01, 0.01, 0.015),
        ge=0.0,
        length=STATE_SIZE,
        doc="diagonal of Q per second, robot_localization order",
    )
    initial_estimate_covariance: tuple[float, ...] = param(
        (1e-9,) * STATE_SIZE,
        ge=0.0,
        length=STATE_SIZE,
        doc="diagonal of P0, robot_localization order",
    )

    def validate(self) -> str | None:
        if not any(self.odom0_config + self.vo0_config + self.imu0_config):
            return "odom0_config, vo0_config and imu0_config are all false: nothing is fused"
        if self.smooth_lagged_data and self.history_length <= 0.0:
            return "smooth_lagged_data needs history_length > 0"
        return None


@dataclass(frozen=True)
class VoTuning:
    """The ORB + PnP pipeline's inner constants (``vo.advanced``); measurements behind each
    default: docs/design/vo_tuning.md."""

    grid_rows: int = param(6, unit="cells", ge=1, doc="feature bucketing grid rows")
    grid_cols: int = param(8, unit="cells", ge=1, doc="feature bucketing grid columns")
    detect_factor: float = param(
        1.2, ge=1.0, doc="detect this many times max_features, then bucket"
    )
    clahe_clip: float = param(0.0, ge=0.0, doc="CLAHE contrast limit before detection (0 = off)")
    clahe_tiles: int = param(8, ge=1, doc="CLAHE tiles per image side")
    depth_as_mask: bool = param(
        True, doc="detect only on in-range depth (RTAB-Map Vis/DepthAsMask)"
    )
    depth_margin_px: int = param(
        4, unit="px", ge=0, doc="depth mask grown into holes so keypoints at depth edges stay"
    )
    unmasked_share: float = param(
        0.9,
        gt=0.0,
        le=1.0,
        doc="detect unmasked if the depth mask covers this share of the image and keypoints",
    )
    fast_threshold: int = param(5, unit="8-bit levels", ge=1, doc="ORB's FAST threshold")
    orb_levels: int = param(6, ge=1, doc="ORB pyramid levels (OpenCV default 8)")
    orb_scale: float = param(1.2, gt=1.0, doc="ORB pyramid scale factor")
    orb_split_level: int = param(
        2, ge=0, doc="ORB levels [0, n) and [n, L) detected in two threads (0 = one call)"
    )
    cross_check: bool = param(False, doc="keep mutual best matches only")
    knn: int = param(2, ge=1, doc="candidates kept per feature for the guided search")
    level_window: int = param(
        0, unit="levels", ge=-1, doc="match only across this many pyramid levels (-1 = all)"
    )
    guided_radius_px: float = param(
        20.0, unit="px", gt=0.0, doc="guided search window around the PnP projection"
    )
    guided_max_hamming: int = param(
        64, unit="bits", ge=0, doc="descriptor distance accepted in the guided search"
    )
    second_radius_px: float = param(
        6.0, unit="px", ge=0.0, doc="2nd guided search around the refined pose (0 = none)"
    )
    second_max_hamming: int = param(
        64, unit="bits", ge=0, doc="descriptor distance accepted in the 2nd search"
    )
    min_pnp_inliers: int = param(6, ge=3, doc="RANSAC inliers a hypothesis needs to be verified")
    pnp_method: Literal["rigid", "magsac", "ransac", "ap3p", "prosac"] = param(
        "rigid", doc="rigid: seeded 3-point rigid RANSAC; others: cv2.solvePnPRansac flavours"
    )
    ransac_seed: int = param(0, ge=0, doc="seed of the rigid hypotheses' sampler (repeatable runs)")
    rigid_samples: int = param(3000, ge=1, doc="3-point samples drawn for the rigid hypotheses")
    rigid_tol_m: float = param(
        0.03, unit="m", ge=0.0, doc="pairwise-distance consistency of a sample, plus ..."
    )
    rigid_tol_z2: float = param(
        0.01, unit="1/m", ge=0.0, doc="... this times z^2 per point (depth noise grows as z^2)"
    )
    rigid_min_span_m: float = param(
        0.1, unit="m", ge=0.0, doc="shortest side of a sample triangle (conditioning)"
    )
    rigid_refits: int = param(4, ge=0, doc="best hypotheses refitted on their inliers (LO-RANSAC)")
    rigid_max_hypotheses: int = param(64, ge=1, doc="consistent samples solved and scored at most")
    verify_hypotheses: int = param(
        3, ge=1, doc="distinct hypotheses verified by guided search + refinement"
    )
    distinct_m: float = param(
        0.05, unit="m", ge=0.0, doc="hypotheses closer than this in translation are one"
    )
    close_call: float = param(
        0.9, gt=0.0, le=1.0, doc="candidates within this share of the best go to the 2nd search"
    )
    verify_ratio: float = param(
        0.7, gt=0.0, le=1.0, doc="verify only hypotheses with this share of the best's inliers"
    )
    ransac_confidence: float = param(0.999, gt=0.0, lt=1.0, doc="OpenCV PnP methods only")
    refine: Literal["none", "lm", "rgbd"] = param("rgbd", doc="pose refinement after PnP")
    refine_iterations: int = param(4, ge=0, doc="Gauss-Newton steps of the refinement")
    second_iterations: int = param(2, ge=0, doc="Gauss-Newton steps after the 2nd guided search")
    converged: float = param(1e-4, unit="rad | m", gt=0.0, doc="Gauss-Newton stops below this step")
    pixel_sigma: float = param(
        1.0, unit="px", gt=0.0, doc="keypoint localisation noise at pyramid level 0"
    )
    disparity_sigma: float = param(
        0.5, unit="px", gt=0.0, doc="virtual right-column noise (depth incl. registration)"
    )
    huber_px: float = param(2.0, unit="sigma", gt=0.0, doc="Huber threshold of the refinement")
    min_inlier_ratio: float = param(
        0.1, ge=0.0, le=1.0, doc="inliers / matches below this: too_few_inliers"
    )
    keyframe_inliers: int = param(
        40, ge=0, doc="new keyframe below this many inliers, besides the ratio test"
    )
    prior_radius_px: float = param(
        0.0, unit="px", ge=0.0, doc="look for a match first near the predicted point (0 = off)"
    )
    prior_seed: bool = param(
        True, doc="while the prior holds, the last pose seeds the refinement instead of RANSAC"
    )
    prior_max_error_px: float = param(
        7.5, unit="px", ge=0.0, doc="the prior holds after a frame it predicted within this"
    )
    prior_min_inlier_ratio: float = param(
        0.5, ge=0.0, le=1.0, doc="refined inliers / window matches below this: match globally"
    )
    min_sigma_m: float = param(0.002, unit="m", ge=0.0, doc="covariance floor per translation axis")
    min_sigma_rad: float = param(
        0.002, unit="rad", ge=0.0, doc="covariance floor per rotation axis"
    )


@dataclass(frozen=True)
class VoConfig:
    """RGB-D visual odometry (names after RTAB-Map's Vis/* and Odom/* parameters)."""

    method: Literal["orb_pnp", "depth_icp"] = param(
        "orb_pnp",
        doc="orb_pnp: ORB + PnP RANSAC + RGB-D refinement (Open3D RGB-D odometry measured worse: "
        "bench_vo); depth_icp: KISS-ICP on the depth cloud, geometry only (bench_depth_icp)",
    )
    fallback: Literal["none", "depth_icp"] = param(
        "depth_icp",
        doc="when orb_pnp fails on a frame, take depth_icp's motion for it (counted in "
        "VisualOdometry.stats; docs/design/kiss_icp_and_filterpy.md)",
    )
    force_3dof: bool = param(
        True, doc="keep x, y, yaw only (Reg/Force3DoF; RTAB-Map default false)"
    )
    max_features: int = param(1000, ge=1, doc="features per frame (Vis/MaxFeatures)")
    cor_nndr: float = param(
        0.8, gt=0.0, le=1.0, doc="nearest-neighbour distance ratio (Vis/CorNNDR)"
    )
    min_inliers: int = param(20, ge=3, doc="accept a motion only above this (Vis/MinInliers)")
    pnp_reproj_error: float = param(
        3.0, unit="px", gt=0.0, doc="RANSAC inlier threshold (Vis/PnPReprojError; 2 px: 89 %)"
    )
    ransac_iterations: int = param(
        150, ge=1, doc="max RANSAC iterations (Vis/Iterations; 300 measured no better)"
    )
    min_depth: float = param(
        0.5, unit="m", ge=0.0, doc="ignore features nearer than this (Vis/MinDepth)"
    )
    max_depth: float = param(
        4.0, unit="m", gt=0.0, doc="ignore features beyond this; Kinect noise ~z^2 (Vis/MaxDepth)"
    )
    keyframe_thr: float = param(
        0.3, ge=0.0, le=1.0, doc="new keyframe when inlier ratio drops below (Odom/KeyFrameThr)"
    )
    keyframe_translation: float = param(
        0.25, unit="m", gt=0.0, doc="new keyframe after this much travel"
    )
    keyframe_rotation: float = param(
        0.26, unit="rad", gt=0.0, doc="new keyframe after this much turning"
    )
    max_translation: float = param(
        0.2, unit="m", gt=0.0, doc="reject a frame-to-frame jump larger than this"
    )
    max_rotation: float = param(
        0.78, unit="rad", gt=0.0, doc="reject a frame-to-frame turn larger than this"
    )
    every_n_frames: int = param(
        1,
        ge=1,
        doc="with wheel encoders in the EKF, VO on every n-th frame only (the pair spans the "
        "frames between; docs/design/speed.md)",
    )
    stride_below_bias_sigma: float = param(
        0.0,
        unit="rad/s",
        ge=0.0,
        doc="with every_n_frames > 1 and a gyro in the EKF: VO on every frame until the EKF's "
        "gyro-bias sigma first falls below this, then on every n-th (0: from the first frame; "
        "docs/design/gyro_bias.md)",
    )

    cor_type: Literal["features", "optical_flow"] = param(
        "features",
        doc="Vis/CorType: 'features' matches ORB descriptors on every frame; 'optical_flow' "
        "tracks the keyframe's points with pyramidal Lucas-Kanade between keyframes (ORB only "
        "on keyframes and when tracking fails)",
    )
    cor_flow_win_size: int = param(
        16, unit="px", ge=3, doc="Lucas-Kanade window side (Vis/CorFlowWinSize)"
    )
    cor_flow_iterations: int = param(
        30, ge=1, doc="Lucas-Kanade iterations per level (Vis/CorFlowIterations)"
    )
    cor_flow_eps: float = param(
        0.01, unit="px", gt=0.0, doc="Lucas-Kanade convergence step (Vis/CorFlowEps)"
    )
    cor_flow_max_level: int = param(
        3, ge=0, doc="Lucas-Kanade pyramid levels above the image (Vis/CorFlowMaxLevel)"
    )

    icp_voxel_size: float = param(
        0.05, unit="m", gt=0.0, doc="depth_icp: KISS-ICP voxel size (map 0.5x, ICP 1.5x)"
    )
    icp_initial_threshold: float = param(
        0.1, unit="m", gt=0.0, doc="depth_icp: KISS-ICP sigma before motion is seen (3 sigma gate)"
    )
    icp_min_motion: float = param(
        0.01, unit="m", ge=0.0, doc="depth_icp: KISS-ICP min_motion_th of its adaptive threshold"
    )
    icp_pixel_stride: int = param(
        4, unit="px", ge=1, doc="depth_icp: every n-th pixel per row and column becomes a point"
    )
    icp_min_points: int = param(
        100, ge=7, doc="depth_icp: fewer points after down-sampling -> too_few_points"
    )
    icp_check_stride: int = param(
        8, unit="px", ge=1, doc="depth_icp: pixel grid of the overlap / constraint check"
    )
    icp_check_distance: float = param(
        0.05, unit="m", gt=0.0, doc="depth_icp: a check point within this of the previous frame's"
    )
    icp_refine_iterations: int = param(
        3, ge=0, doc="depth_icp: point-to-plane Gauss-Newton steps after KISS-ICP (0 = none)"
    )
    icp_max_deviation: float = param(
        0.03,
        unit="m",
        ge=0.0,
        doc="depth_icp: a motion this far off the last one is implausible_motion (0 = off)",
    )
    icp_min_overlap: float = param(
        0.5, ge=0.0, le=1.0, doc="depth_icp: share of check points matched, else too_few_inliers"
    )
    icp_min_constraint: float = param(
        0.01,
        ge=0.0,
        doc="depth_icp: smallest point-to-plane information eigenvalue per point "
        "(within 60 deg of it), else degenerate (a blank wall and the floor: none)",
    )

    advanced: VoTuning = field(
        default_factory=VoTuning,
        metadata={"doc": "the ORB + PnP pipeline's inner constants (vo.advanced.*)"},
    )

    def validate(self) -> str | None:
        if self.min_depth >= self.max_depth:
            return f"min_depth ({self.min_depth}) must be below max_depth ({self.max_depth})"
        return None


@dataclass(frozen=True)
class DepthToScanConfig:
    """Depth image -> planar LaserScan (depthimage_to_laserscan + pointcloud_to_laserscan names).

    Unlike depthimage_to_laserscan the scan is tilt-compensated through the camera extrinsics
    and expressed in ``output_frame`` on the floor plane; points outside the height band
    [min_height, max_height] above the floor are dropped, and each beam keeps its nearest return.
    """

    scan_height: int = param(
        0, unit="px", ge=0, doc="rows about the centre row used; 0 = all rows (upstream: 1)"
    )
    range_min: float = param(0.45, unit="m", ge=0.0, doc="shorter returns are dropped")
    range_max: float = param(
        4.0, unit="m", gt=0.0, doc="longer returns are dropped (upstream 10.0; Kinect v1)"
    )
    output_frame: str = param(
        "base_link", doc="scan frame (upstream camera_depth_frame; ours is tilt-compensated)"
    )
    min_height: float = param(
        0.05, unit="m", doc="drop points below this height above the floor (floor removal)"
    )
    max_height: float = param(
        1.0, unit="m", doc="drop points above this height above the floor (ceiling removal)"
    )
    angle_increment: float = param(
        0.017453292519943295, unit="rad", gt=0.0, doc="beam spacing (pi/180, as upstream)"
    )
    scan_time: float = param(
        0.033,
        unit="s",
        ge=0.0,
        doc="time between scans: informational, as upstream's LaserScan.scan_time (accepted so "
        "depthimage_to_laserscan configs load; scans carry their own stamps)",
    )
    return_averaging_window: float = param(
        0.0,
        unit="1/m",
        ge=0.0,
        doc="average returns within this * r^2 of the nearest (0 = nearest only, as upstream)",
    )

    def validate(self) -> str | None:
        if self.range_min >= self.range_max:
            return f"range_min ({self.range_min}) must be below range_max ({self.range_max})"
        if self.min_height >= self.max_height:
            return f"min_height ({self.min_height}) must be below max_height ({self.max_height})"
        return None


@dataclass(frozen=True)
class MapperConfig:
    """Keyframe pose-graph mapper with slam_toolbox parameter names, plus the occupancy model.

    Only parameters the mapper acts on are here: slam_toolbox's ``map_update_interval``,
    ``link_scan_maximum_distance``, ``loop_match_maximum_variance_coarse``,
    ``fine_search_angle_offset`` and ``use_response_expansion`` were accepted and ignored until
    2026-11-22, and are now refused as unknown keys (widening the search on a weak response,
    tried on MIT CSAIL, accepted wrong matches: 6-9 deg rotation error)."""

    resolution: float = param(
        0.05, unit="m/cell", ge=0.005, le=1.0, doc="occupancy grid resolution"
    )
    max_laser_range: float = param(20.0, unit="m", gt=0.0, doc="longest ray used to build the grid")
    minimum_time_interval: float = param(
        0.5, unit="s", ge=0.0, doc="min time between processed scans"
    )
    # Keyframes.
    minimum_travel_distance: float = param(
        0.5, unit="m", ge=0.0, doc="new keyframe after this much travel"
    )
    minimum_travel_heading: float = param(
        0.5, unit="rad", ge=0.0, doc="new keyframe after this much rotation"
    )
    scan_buffer_size: int = param(10, ge=1, doc="recent scans in the local matching map")
    scan_buffer_maximum_scan_distance: float = param(
        10.0, unit="m", gt=0.0, doc="drop buffered scans farther than this"
    )
    revisit_distance: float = param(
        0.0,
        unit="m",
        ge=0.0,
        doc="a keyframe due this close to an older one (0 = off) that the graph already ties "
        "to the current one re-anchors tracking on it instead of adding a node: the graph "
        "stops growing where the robot only drives again (the live profile turns it on)",
    )
    revisit_heading: float = param(
        0.35, unit="rad", gt=0.0, doc="...and whose heading is within this of the robot's"
    )
    link_match_minimum_response_fine: float = param(
        0.1, ge=0.0, le=1.0, doc="min response to link a scan to its neighbours"
    )
    # Loop closure.
    do_loop_closing: bool = param(True, doc="search for and add loop-closure factors")
    loop_search_maximum_distance: float = param(
        3.0, unit="m", gt=0.0, doc="only consider candidates within this distance"
    )
    loop_match_minimum_chain_size: int = param(
        10, ge=1, doc="min consecutive scans in a loop candidate chain"
    )
    loop_match_minimum_response_coarse: float = param(
        0.35, ge=0.0, le=1.0, doc="min coarse-match response to accept a loop"
    )
    loop_match_minimum_response_fine: float = param(
        0.45, ge=0.0, le=1.0, doc="min fine-match response to accept a loop"
    )
    loop_match_maximum_ambiguity: float = param(
        0.9,
        gt=0.0,
        doc="reject a loop match when a pose > loop_match_ambiguity_distance away scores this "
        "fraction of it (aliased corridors); > 1 disables",
    )
    loop_match_hold_ambiguity: float = param(
        0.8,
        gt=0.0,
        doc="a loop match whose best rival scores more than this fraction of it (but not "
        "loop_match_maximum_ambiguity) does not enter the graph at once: it waits for the "
        "final vote of all closures",
    )
    loop_match_ambiguity_distance: float = param(
        1.0, unit="m", gt=0.0, doc="a rival pose must be this far from the match to count"
    )
    # Correlative scan matching.
    correlation_search_space_dimension: float = param(
        0.5, unit="m", gt=0.0, doc="side of the sequential matching search window"
    )
    correlation_search_space_resolution: float = param(
        0.1,
        unit="m",
        gt=0.0,
        doc="step of the sequential matching search (upstream 0.01; ICP refines below it)",
    )
    correlation_search_space_smear_deviation: float = param(
        0.1, unit="m", gt=0.0, doc="blur of the sequential matching grid"
    )
    loop_search_space_dimension: float = param(
        20.0, unit="m", gt=0.0, doc="largest side of the loop-closure search window (upstream 8)"
    )
    loop_search_drift_rate: float = param(
        0.03, unit="m/m", ge=0.0, doc="position drift sigma per metre of path: widens the search"
    )
    loop_search_heading_drift_rate: float = param(
        0.01, unit="rad/m", ge=0.0, doc="heading drift sigma per metre of path"
    )
    loop_search_space_resolution: float = param(
        0.1, unit="m", gt=0.0, doc="step of the loop-closure search (upstream 0.05; ICP refines)"
    )
    loop_search_space_smear_deviation: float = param(
        0.03, unit="m", gt=0.0, doc="blur of the loop-closure matching grid"
    )
    distance_variance_penalty: float = param(
        0.5, unit="m^2", gt=0.0, doc="penalise matches far from the odometry guess"
    )
    angle_variance_penalty: float = param(
        1.0, unit="rad^2", gt=0.0, doc="penalise matches rotated from the odometry guess"
    )
    coarse_search_angle_offset: float = param(
        0.349, unit="rad", gt=0.0, doc="angular range of the coarse search"
    )
    coarse_angle_resolution: float = param(
        0.0349, unit="rad", gt=0.0, doc="angular step of the coarse search"
    )
    minimum_angle_penalty: float = param(0.9, ge=0.0, le=1.0, doc="floor of the angle penalty")
    minimum_distance_penalty: float = param(
        0.5, ge=0.0, le=1.0, doc="floor of the distance penalty"
    )
    # Refinement and noise models (ours: slam_toolbox has no equivalents).
    scan_voxel_size: float = param(
        0.05, unit="m", ge=0.0, doc="scan points kept per square cell for matching (0 = all)"
    )
    icp_max_correspondence_distance: float = param(
        0.3, unit="m", gt=0.0, doc="point-to-line ICP: farthest neighbour accepted as a match"
    )
    icp_max_iterations: int = param(20, ge=1, doc="point-to-line ICP Gauss-Newton iterations")
    icp_huber_width: float = param(
        0.02,
        unit="m",
        gt=0.0,
        doc="point-to-line residual beyond which ICP down-weights (Huber) when tracking: ~2 "
        "sigma of a laser's range noise",
    )
    loop_icp_huber_width: float = param(
        0.05,
        unit="m",
        gt=0.0,
        doc="the same for loop closure and relocalisation, which start from a coarser pose "
        "against older, less consistent keyframes",
    )
    icp_min_inlier_fraction: float = param(
        0.5, ge=0.0, le=1.0, doc="scan points that must find a neighbour for a match to count"
    )
    icp_first_min_inlier_fraction: float = param(
        0.9,
        ge=0.0,
        le=1.0,
        doc="track by ICP from odometry alone when this many points match (1 = always search)",
    )
    scan_match_degeneracy_ratio: float = param(
        20.0,
        gt=1.0,
        doc="ICP position variance ratio above which the weak axis is left to odometry",
    )
    scan_match_min_sigma: float = param(
        0.01, unit="m", gt=0.0, doc="floor of the ICP residual sigma behind a match covariance"
    )
    scan_match_noise_fraction: float = param(
        0.2, ge=0.0, doc="scan edges add this fraction of the odometry sigmas to ICP's covariance"
    )
    odom_translation_noise: float = param(
        0.1, unit="m/m", ge=0.0, doc="odometry translation sigma per metre travelled"
    )
    odom_rotation_noise: float = param(
        0.1, unit="rad/rad", ge=0.0, doc="odometry heading sigma per radian turned"
    )
    odom_rotation_noise_per_meter: float = param(
        0.05, unit="rad/m", ge=0.0, doc="odometry heading sigma per metre travelled"
    )
    loop_closure_vote: bool = param(
        True,
        doc="at the end, every closure (also those held back as inconsistent) votes again under "
        "a Cauchy kernel: closures the others outvote are dropped",
    )
    loop_closure_max_chi2: float = param(
        16.27,
        gt=0.0,
        doc="drop a closure whose residual exceeds this after optimising (3 dof 99.9%)",
    )
    # Pose graph.
    robust_kernel: Literal["huber", "cauchy", "none"] = param(
        "huber", doc="loss on loop-closure factors (slam_toolbox ceres_loss_function: None)"
    )
    robust_kernel_width: float = param(
        1.0, gt=0.0, doc="kernel threshold in whitened (sigma) units"
    )
    # Occupancy grid, log-odds (OctoMap names) and map_server thresholds.
    prob_hit: float = param(0.7, gt=0.5, lt=1.0, doc="P(occupied) for a cell a ray ends in")
    prob_miss: float = param(0.4, gt=0.0, lt=0.5, doc="P(occupied) for a cell a ray crosses")
    clamping_thres_min: float = param(
        0.12, gt=0.0, lt=1.0, doc="lower clamp of a cell's occupancy probability"
    )
    clamping_thres_max: float = param(
        0.97, gt=0.0, lt=1.0, doc="upper clamp of a cell's occupancy probability"
    )
    occupied_thresh: float = param(
        0.65, gt=0.0, lt=1.0, doc="map.yaml occupied_thresh: at or above is occupied"
    )
    free_thresh: float = param(0.25, gt=0.0, lt=1.0, doc="map.yaml free_thresh: below is free")

    def validate(self) -> str | None:
        if self.clamping_thres_min >= self.clamping_thres_max:
            return (
                f"clamping_thres_min ({self.clamping_thres_min}) must be below "
                f"clamping_thres_max ({self.clamping_thres_max})"
            )
        if self.free_thresh >= self.occupied_thresh:
            return (
                f"free_thresh ({self.free_thresh}) must be below "
                f"occupied_thresh ({self.occupied_thresh})"
            )
        if self.correlation_search_space_resolution > self.correlation_search_space_dimension:
            return "correlation_search_space_resolution exceeds its search space dimension"
        if self.loop_search_space_resolution > self.loop_search_space_dimension:
            return "loop_search_space_resolution exceeds its search space dimension"
        return None


@dataclass(frozen=True)
class LocalizerConfig:
    """Scan-to-map tracking and global relocalisation (Cartographer / AMCL names where they fit).

    Confidence everywhere is the mean likelihood ``exp(-d^2 / 2 sigma_hit^2)`` of the scan's
    points at a pose, ``d`` the distance to the nearest occupied map cell (AMCL's likelihood
    field without the random component)."""

    # Tracking.
    linear_search_window: float = param(
        0.3, unit="m", gt=0.0, doc="half-width of the tracking search around the prediction"
    )
    angular_search_window: float = param(
        0.349, unit="rad", gt=0.0, doc="half-width of the tracking search in yaw (20 deg)"
    )
    angular_search_step: float = param(
        0.0175, unit="rad", gt=0.0, doc="yaw step of the tracking search (ICP refines below it)"
    )
    min_score: float = param(
        0.5, ge=0.0, le=1.0, doc="accept a tracking match at or above this confidence"
    )
    update_min_d: float = param(
        0.0, unit="m", ge=0.0, doc="match after this much travel (AMCL 0.25; 0 = every scan)"
    )
    update_min_a: float = param(
        0.0, unit="rad", ge=0.0, doc="match after this much turning (AMCL 0.2; 0 = every scan)"
    )
    match_gate: float = param(
        0.0,
        unit="sigma",
        ge=0.0,
        doc="a match farther than this Mahalanobis distance from the odometry prediction is a "
        "jump hypothesis, not fused (0 = fuse every match)",
    )
    jump_confirm_scans: int = param(
        3,
        ge=0,
        doc="consecutive gated matches that must agree (and the earlier scans support) before "
        "the estimate jumps to them (0 = never: a gated match waits until the prediction's "
        "growing covariance admits it)",
    )
    match_sigma_floor: float = param(
        0.005, unit="m", ge=0.0, doc="added in quadrature to a match's position sigmas"
    )
    match_sigma_floor_yaw: float = param(
        0.002, unit="rad", ge=0.0, doc="added in quadrature to a match's yaw sigma"
    )
    # Lost detection.
    lost_score: float = param(
        0.3, ge=0.0, le=1.0, doc="confidence below this counts towards being lost"
    )
    lost_time: float = param(2.0, unit="s", ge=0.0, doc="declare lost after this long below")
    lost_min_scans: int = param(
        3, ge=1, doc="...and after at least this many scans below (sparse logs: 2-3 s per scan)"
    )
    dead_reckoning_max_sigma: float = param(
        0.0,
        unit="m",
        ge=0.0,
        doc="when tracking fails for lost_time, keep dead-reckoning on odometry (status "
        "tracking, covariance growing) until the position sigma reaches this, then declare lost "
        "(0 = lost at once)",
    )
    kidnap_check_ratio: float = param(
        0.7,
        ge=0.0,
        le=1.0,
        doc="confidence below this times its recent median searches the map for a better pose "
        "(a clearly better one declares lost at once; 0 = never)",
    )
    kidnap_check_scans: int = param(
        5, ge=1, doc="tracked scans whose median confidence the kidnap check compares against"
    )
    # Global relocalisation.
    global_search_resolution: float = param(
        0.1, unit="m", gt=0.0, doc="cell size of the global search (coarser than the map is ok)"
    )
    global_search_angular_resolution: float = param(
        0.0349, unit="rad", gt=0.0, doc="yaw step of the exhaustive global search (full turn)"
    )
    global_search_sigma: float = param(
        0.2, unit="m", gt=0.0, doc="smear of the global search field (tolerates the coarse lattice)"
    )
    global_search_min_score: float = param(
        0.35, ge=0.0, le=1.0, doc="global candidates below this coarse score are pruned"
    )
    global_search_max_hypotheses: int = param(
        5, ge=1, doc="distinct global candidates kept for verification"
    )
    gps_prior_sigmas: float = param(
        3.0, gt=0.0, doc="with a GPS fix, the global search covers this many sigma_h around it"
    )
    global_search_candidate_ratio: float = param(
        0.75, gt=0.0, le=1.0, doc="keep global candidates scoring at least this times the best"
    )
    global_localization_min_score: float = param(
        0.6, ge=0.0, le=1.0, doc="accept a global candidate at or above this confidence"
    )
    relocalization_verification_scans: int = param(
        3, ge=1, doc="consecutive scans (incl. the searched one) a hypothesis must match"
    )
    relocalization_update_min_d: float = param(
        0.1,
        unit="m",
        ge=0.0,
        doc="a verification scan counts once odometry moved this far (or turned "
        "relocalization_update_min_a) since the last counted one, as AMCL's update_min_d",
    )
    relocalization_update_min_a: float = param(
        0.1,
        unit="rad",
        ge=0.0,
        doc="the turn that makes a verification scan count (AMCL update_min_a); both 0: every scan",
    )
    relocalization_agreement_distance: float = param(
        0.25, unit="m", gt=0.0, doc="verification match within this distance of the prediction"
    )
    relocalization_agreement_angle: float = param(
        0.2, unit="rad", gt=0.0, doc="verification match within this yaw of the prediction"
    )
    relocalization_ambiguity_ratio: float = param(
        0.9,
        gt=0.0,
        le=1.0,
        doc="two verified hypotheses within this score ratio are ambiguous: keep relocalising",
    )
    relocalization_history_m: float = param(
        1.0,
        unit="m",
        ge=0.0,
        doc="while relocalising, hypotheses are also scored on the scans of this much recent "
        "odometry travel stacked by odometry (a wider view than one scan; 0 = off)",
    )
    # Likelihood field and scan handling.
    sigma_hit: float = param(
        0.1, unit="m", gt=0.0, doc="std dev of the hit model behind confidence (AMCL 0.2)"
    )
    laser_max_range: float = param(
        30.0, unit="m", gt=0.0, doc="returns beyond this are not matched (AMCL laser_max_range)"
    )
    max_beams: int = param(60, ge=10, doc="scan points used by the global search (AMCL 60)")
    scan_voxel_size: float = param(
        0.05, unit="m", ge=0.0, doc="scan points kept per square cell for tracking (0 = all)"
    )
    icp_max_correspondence_distance: float = param(
        0.3, unit="m", gt=0.0, doc="point-to-line ICP: farthest neighbour accepted as a match"
    )
    icp_max_iterations: int = param(20, ge=1, doc="point-to-line ICP Gauss-Newton iterations")
    scan_match_degeneracy_ratio: float = param(
        20.0,
        gt=1.0,
        doc="ICP position variance ratio above which the weak axis is left to odometry",
    )
    scan_match_min_sigma: float = param(
        0.01, unit="m", gt=0.0, doc="floor of the ICP residual sigma behind a match covariance"
    )
    refine_max_iterations: int = param(
        10,
        ge=0,
        doc="Levenberg-Marquardt polish of each match on the bicubic-interpolated, smoothed map "
        "(Cartographer's ceres_scan_matcher max_num_iterations): sub-cell poses where ICP snaps "
        "to cell centres (0 = off)",
    )
    refine_smoothing_sigma: float = param(
        0.0375,
        unit="m",
        gt=0.0,
        doc="Gaussian blur of the map's wall cells the polish runs on (0.75 cells at 5 cm)",
    )
    # Odometry motion noise (AMCL diff-drive model: variances from rotation and translation).
    alpha1: float = param(0.2, ge=0.0, doc="rotation noise from rotation")
    alpha2: float = param(0.2, ge=0.0, doc="rotation noise from translation")
    alpha3: float = param(0.2, ge=0.0, doc="translation noise from translation")
    alpha4: float = param(0.2, ge=0.0, doc="translation noise from rotation")

    def validate(self) -> str | None:
        if self.lost_score > self.min_score:
            return f"lost_score ({self.lost_score}) must not exceed min_score ({self.min_score})"
        if self.angular_search_step > self.angular_search_window:
            return "angular_search_step exceeds angular_search_window"
        return None


@dataclass(frozen=True)
class AlignConfig:
    """Map alignment with no initial guess (`rgbdnav fleet align`).

    FFT correlative search over every yaw, ICP refinement, two-way verification (see
    :mod:`slam.map_align`)."""

    coarse_resolution: float = param(0.25, unit="m/cell", gt=0.0, doc="grid of the global search")
    smear_sigma: float = param(
        0.5, unit="m", gt=0.0, doc="likelihood field width of the global search"
    )
    yaw_step_deg: float = param(1.0, unit="deg", gt=0.0, le=90.0, doc="rotation sweep step")
    candidates: int = param(6, ge=1, doc="distinct peaks refined and verified")
    distinct_m: float = param(
        2.0, unit="m", gt=0.0, doc="peaks closer than this (and distinct_deg) are one"
    )
    distinct_deg: float = param(
        10.0, unit="deg", gt=0.0, doc="peaks closer than this (and distinct_m) are one"
    )
    icp_correspondence_m: float = param(1.0, unit="m", gt=0.0, doc="ICP neighbour radius")
    icp_voxel_m: float = param(0.1, unit="m", gt=0.0, doc="B's wall cells thinned for ICP")
    agree_distance_m: float = param(
        0.2, unit="m", gt=0.0, doc="a wall cell within this of the other map's walls agrees"
    )
    min_agreement: float = param(
        0.5,
        gt=0.0,
        le=1.0,
        doc="fraction of wall cells over the other's known area that must agree",
    )
    min_overlap_m: float = param(15.0, unit="m", ge=0.0, doc="wall length matched both ways")
    max_rival_ratio: float = param(
        0.7, gt=0.0, le=1.0, doc="a distinct pose scoring this fraction of the best: ambiguous"
    )
    free_penalty: float = param(
        1.0, ge=0.0, doc="global search: cost of a wall point on the other's open floor"
    )
