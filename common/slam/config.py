"""The localiser's settings, apart from its algorithms: light to import (numpy only), so that the
localiser service can parse its flags and start publishing while the numba, SciPy and GTSAM code it
runs is still loading (services/localiser.py).  The modules that use them re-export them."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class LocaliserConfig:
    keep_fraction: float = 0.7          # fittest fraction of the population used
    max_depth_m: float | None = None    # farther flies do not enter δ; None: 0.3·f·B (0.5 px = 15 % of depth)
    min_height_m: float = 0.05          # δ drops flies on the floor (a plane under a planar search is flat)
    max_height_m: float = 3.0
    voxel_m: float = 0.04               # keyframe points are thinned to one per voxel
    keyframe_distance_m: float = 1.5    # a keyframe where none is this near ...
    keyframe_angle_rad: float = np.deg2rad(15.0)   # ... and looking within this of the same way
    max_keyframes: int = 40             # window of keyframes the local map is chosen from (oldest dropped)
    local_keyframes: int = 3            # keyframes merged into the local map (those seeing most of the view)
    window: tuple = (0.25, 0.25, np.deg2rad(8.0))   # δ search half-widths around the prediction, at least
    max_window: tuple = (0.6, 0.6, np.deg2rad(25.0))   # ... widened to 3 σ of the prior, at most
    max_map_points: int = 6000          # local map subsampled to this many points
    min_flies: int = 150                # fewer usable flies: odometry carries the pose
    min_generations: int = 100          # the map starts only from a population evolved this long
    first_fix_gap_s: float = 0.3        # motion unknown: a population later than this after the map's origin
                                        # restarts the map from itself (the limit doubles at each restart) ...
    max_frame_interval_s: float = 1.0   # ... unless it is of the next camera frame, at most this much later
    eps: float = 0.05                   # δ's ε (m)
    prior_sigma_xy: tuple = (0.01, 0.05)    # odometry prior σ = base + rate × metres since the last fix
    prior_sigma_yaw: tuple = (0.01, 0.08)   # ... for the heading (rad, rad/m)
    prior_sigma_yaw_per_rad: float = 0.05   # ... plus this per radian turned since the last fix
    registration_sigma: tuple = (0.3, 0.03, np.deg2rad(0.6))   # δ's noise: along, across the view (m), heading
    tracked_disparity_px: float = 1.0   # a fly's disparity is trusted to this (the evolver's inlier bound): the σ of
                                        # visual odometry and photometric loop factors (common.slam.backend)
    gate_chi2: float = 16.0             # a δ registration this far (Mahalanobis²) from the prediction is refused
    use_stereo_model: bool = True       # δ with depth-uncertainty and footprint weights (StereoModel)
    min_view_coverage: float = 0.5      # a view the map covers less than this gets a keyframe even unregistered
    max_turn_rate_radps: float = np.deg2rad(20.0)   # turning faster (wheels): no δ, no keyframes (tracking goes on)
    max_slip_rad: float = np.deg2rad(15.0)   # a faster turn up to this large may be a wheel slipping (see _slip_hypothesis)
    tracking_gap_s: float = 0.25        # within this of a fix δ searches from one seed at the prediction
    tracking_max_turn_rate_radps: float = np.deg2rad(5.0)   # ... and not while turning faster than this
    tracking_recheck_pinned: int = 10   # axes pinned on the window's edge are tried free again this often
    fallback_half_fov_rad: float = np.deg2rad(35.0)   # view cone when there is no calibration
    odometry: str = "wheels"            # 'wheels': T_odom_base predicts; 'visual': constant velocity of own estimates
    photometric: bool = True            # track on the flies' image neighbourhoods when images come along
    photometric_flies: int = 2000       # fittest flies the tracking reference keeps
    photometric_levels: int = 4         # image pyramid levels (the start may be ~2^levels px off)
    photometric_smooth_px: float = 0.5  # Gaussian σ on the full-resolution images before tracking (px)
    photometric_min_inliers: float = 0.5   # share of neighbourhoods within the robust threshold to accept
    photometric_reference_spacing: float = 0.1   # renew the reference after moving this × its median depth ...
    photometric_reference_angle_rad: float = np.deg2rad(5.0)   # ... or turning this much
    pose_graph: bool = True             # keyframes as nodes of common.slam.backend's pose graph
    loop_closure: bool = True           # register a new keyframe against old ones near it (a loop factor)
    loop_photometric: bool = True       # measure a loop on the two keyframes' fly neighbourhoods (half-
                                        # resolution images kept with each keyframe; needs photometric)
    loop_radius_m: float | None = None  # an old keyframe this near (map frame) is a loop candidate (None:
                                        # keyframe_distance_m: the views nearly coincide, see backend) ...
    loop_max_angle_rad: float = np.deg2rad(30.0)   # ... when it looks within this of the same way
    loop_min_separation: int = 10       # ... and is at least this many keyframes older
    loop_window: tuple = (1.0, 1.5, np.deg2rad(15.0))   # its δ search half-widths: along, across the view, heading
    local_map_from_archive: bool = False   # choose the local map from every archived keyframe, not the window


@dataclass
class LocaliserServiceConfig:
    """The live localiser's settings outside :class:`LocaliserConfig`."""
    tum: str | None = field(default=None, metadata={
        "help": "append each pose to this TUM file (kept across restarts), rewritten optimised every tum_period_s"})
    tum_period_s: float = field(default=5.0, metadata={"help": "seconds between atomic rewrites of --tum"})
    seed: int = field(default=0, metadata={"help": "random seed of the localiser"})
    map: str | None = field(default=None, metadata={
        "help": "start from this saved map (map.mcap of an earlier run)"})
    map_period_s: float = field(default=2.0, metadata={
        "help": "seconds between rewrites of map.mcap next to --tum once it changed (and on exit)"})


@dataclass
class ArchiveConfig:
    """The back-end's hard size bound.  500 keyframes hold ~20 MB of flies (~1,200 points each, points,
    map-frame copy and fitness: ~28 bytes a point) and, at keyframe_distance_m = 1.5 m, 750 m of distinct
    path; a robot that comes back to a place adds keyframes there again (the local map is chosen from
    the sliding window), so a long run reaches the bound however small its world is."""
    max_archive_keyframes: int = field(default=500, metadata={
        "help": "keyframes the map keeps at most (past it the most redundant old ones are dropped)"})
    drop_fraction: float = field(default=0.1, metadata={
        "help": "share of the bound dropped at once when it is reached (the graph is rebuilt once for them)"})

    def __post_init__(self):
        if int(self.max_archive_keyframes) < 1:
            raise ValueError(f"max_archive_keyframes must be at least 1, got {self.max_archive_keyframes}")
        if not 0.0 <= float(self.drop_fraction) < 1.0:
            raise ValueError(f"drop_fraction must be in [0, 1), got {self.drop_fraction}")
