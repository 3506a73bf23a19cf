"""Config of frame-to-map tracking, a leaf module: no algorithms."""

from __future__ import annotations

from dataclasses import dataclass, field

from planeslam.core.errors import ConfigError


@dataclass(frozen=True)
class PointConfig:
    """Keypoints with depth (ORB): detection, matching against keyframes, noise."""

    enabled: bool = True
    """Use keypoints (needs colour images) as a primitive of tracking and relocalisation."""
    max_keypoints: int = 1000
    """ORB keypoints per image at most."""
    pyramid_levels: int = 8
    """ORB pyramid levels (scale factor 1.2 between them)."""
    fast_threshold: int = 20
    """FAST corner threshold of ORB (intensity levels)."""
    max_depth_m: float = 4.0
    """Keypoints farther than this are left out [m]."""
    max_depth_step: float = 0.03
    """A keypoint whose 5x5 depth window spans more than this fraction of its depth lies
    on a depth edge and is left out."""
    sigma_px: float = 1.0
    """Keypoint position noise across the viewing ray [pixels]."""
    sigma_floor_m: float = 0.01
    """Isotropic noise added to every point [m] (colour-to-depth registration, blur)."""
    keyframe_sigma_m: float = 0.02
    """Pose noise of a keyframe, shared by all its points [m]: the points matched with one
    keyframe together constrain a pose about as much as this (the map's planes, which
    carry no such common error, then dominate the directions they fix)."""
    match_ratio: float = 0.8
    """Lowe's ratio test on the two nearest descriptors."""
    window: int = 4
    """Most recent keyframes whose images are kept, so their keypoints can be computed
    when a later frame first needs them (none are computed while planes suffice)."""
    recent_keyframes: int = 3
    """Recent keyframes a frame's keypoints are matched against."""
    ransac_iterations: int = 200
    """3-point samples of the point RANSAC."""
    inlier_sigmas: float = 3.0
    """A point match agrees with a pose within this many sigmas (both ends' depth noise
    and the floor) ..."""
    inlier_margin_m: float = 0.01
    """... plus this margin [m]."""
    min_inliers: int = 12
    """Point matches a pose needs before points alone may constrain it."""
    vote_max_distance: int = 50
    """Descriptor distance [bits] within which two keypoints may be one point: a nearest
    neighbour votes for its keyframe (relocalisation), a guided match is made."""
    guided_radius_px: float = 10.0
    """Matching by projection: a keyframe point projected with a candidate pose (one a
    texture period from the points' best, `tracking.periodic`) matches a keypoint within
    this radius [pixels] (0: none)."""
    vote_descriptors: int = 300
    """Relocalisation: descriptors per keyframe that take part in the vote."""
    vote_keyframes: int = 3
    """Relocalisation: best-voted keyframes matched in full."""

    def __post_init__(self) -> None:
        for name in (
            "max_keypoints",
            "pyramid_levels",
            "window",
            "recent_keyframes",
            "ransac_iterations",
            "vote_descriptors",
            "vote_keyframes",
        ):
            if getattr(self, name) < 1:
                raise ConfigError(f"tracking.points.{name} must be >= 1, got {getattr(self, name)}")
        if self.min_inliers < 3:
            raise ConfigError(f"tracking.points.min_inliers must be >= 3, got {self.min_inliers}")
        for name in (
            "max_depth_m",
            "max_depth_step",
            "sigma_px",
            "sigma_floor_m",
            "keyframe_sigma_m",
            "inlier_sigmas",
        ):
            if not getattr(self, name) > 0:
                raise ConfigError(f"tracking.points.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.match_ratio <= 1:
            raise ConfigError(
                f"tracking.points.match_ratio must be in (0, 1], got {self.match_ratio}"
            )
        if self.inlier_margin_m < 0 or self.fast_threshold < 1 or self.vote_max_distance < 1:
            raise ConfigError(
                "tracking.points: inlier_margin_m must be >= 0, fast_threshold and "
                f"vote_max_distance >= 1 (got {self.inlier_margin_m}, {self.fast_threshold}, "
                f"{self.vote_max_distance})"
            )
        if not self.guided_radius_px >= 0:
            raise ConfigError(
                f"tracking.points.guided_radius_px must be >= 0, got {self.guided_radius_px}"
            )


@dataclass(frozen=True)
class TrackingConfig:
    """Gates and fallbacks of frame-to-map tracking."""

    max_angle_deg: float = 10.0
    """Association gate on the angle between an observed and a map normal [deg]."""
    max_offset_m: float = 0.10
    """Association gate on the offset difference of two planes [m]."""
    max_corner_distance_m: float = 0.25
    """Association gate on the distance between an observed and a map corner [m]."""
    sigma_angle_deg: float = 1.0
    """Normal noise of an observed plane in the closed-form solve [deg]."""
    sigma_offset_m: float = 0.01
    """Offset noise of an observed plane in the closed-form solve [m]."""
    sigma_point_m: float = 0.02
    """Corner point noise in the closed-form solve [m]."""
    max_residual_angle_deg: float = 3.0
    """A plane pose is trusted when every matched normal agrees within this after solving."""
    max_residual_offset_m: float = 0.05
    """... and every matched offset within this [m]. Correspondences beyond either gate are
    dropped and the pose solved again (see `max_outlier_rounds`)."""
    size_gate_ratio: float = 2.0
    """An observed plane may match a map plane of area A when its own visible area is at
    most size_gate_ratio * A + size_gate_margin_m2 (a floor never matches a box top)."""
    size_gate_margin_m2: float = 0.1
    """See `size_gate_ratio` [m^2]."""
    weigh_unpaired_min_area_m2: float | None = 3.0
    """Association contests over map planes of at least this area [m^2] (>= 0; a wall, a
    floor; 0: every map plane; null: none) are decided by weight: leaving an observed
    plane unpaired costs its inlier share times the largest cost the gates allow
    (`association.associate_planes`), so a structure goes to the observation that loses
    more when left out (a wall keeps its landmark rather than giving it to a picture on
    it). Contests over smaller map planes (furniture, clutter, where the inlier share says
    little about which observation is the map plane) stay count-first: the most pairs,
    then the lower weighted cost."""
    max_outlier_rounds: int = 3
    """Rounds of dropping correspondences beyond the residual gates and solving again."""
    fast_max_gap_s: float = 0.1
    """Within this time of the last tracked frame a trusted plane pose is taken up to
    `fast_max_jump_*` from the prediction [s] (the camera moved a few cm at most, and a
    pose somewhat off the prediction reflects the map's own corrections, the backend
    moving planes); frames farther apart are held to `fast_max_correction_*`."""
    fast_max_jump_m: float = 0.05
    """Within `fast_max_gap_s`, a plane pose farther than this [m] (> 0) both from the
    prediction and from the last frame's pose (the constant-velocity prediction overshoots
    when the camera stops or turns back) ... needs the agreement of `points.min_inliers`
    keypoint matches: at video rate such a jump is a plane matched to a parallel face or
    to another copy of a revisited wall, not motion. The same as `fast_max_correction_m`
    by default (a close frame gets no looser check than a far one)."""
    fast_max_jump_deg: float = 3.0
    """... or turned farther than this [deg] (> 0)."""
    weak_translation_share: float = 0.01
    """A plane pose whose weakest translation direction holds less than this share of the
    planes' translation information (`RegistrationResult.translation_observability`; in
    [0, 1/3), a share of three directions) is taken only where the frame's keypoints agree
    with it (`points.min_inliers`), however near the prediction; otherwise the robust
    estimate over every start decides (frames without keypoints: no check). It catches a
    pose pushed off along an axis that the planes fix only weakly; 0 turns the check off."""
    fast_max_correction_m: float = 0.05
    """Beyond `fast_max_gap_s`, the plane pose from the prediction alone (the fast path) is
    taken when it moved the prediction by at most this [m] ... Beyond it (frames far
    apart, a jump) the prediction is no longer evidence and three planes always fit
    exactly: the pose needs the keypoints' agreement, or goes to the robust estimate over
    every start."""
    fast_max_correction_deg: float = 3.0
    """... and turned it by at most this [deg]; farther, when `points.min_inliers`
    keypoint matches with the last keyframe agree with it."""
    refine_floor_deg: float = 0.17
    """Normal noise added to every plane when a frame's pose is re-estimated against the
    final map from planes weighted by their fit and patch covariances (`final_poses`):
    the map plane's and the pose's own error [deg] (> 0) ..."""
    refine_floor_m: float = 0.003
    """... and offset noise [m] (> 0)."""
    final_poses: bool = True
    """When the run finishes, re-estimate each frame between keyframes against the final map
    from the planes and corners it was tracked with (`tracking.final_poses`), rather than
    carrying its tracked pose rigidly by its anchor keyframe's correction. Tracking, map and
    graph are unchanged; only trajectory.txt's final poses move."""
    relocalise: bool = True
    """Search the whole map (corner, plane-triple, edge and keypoint hypotheses) when
    nothing near the prediction fits."""
    max_triple_planes: int = 10
    """Largest observed planes that form plane-triple hypotheses when relocalising."""
    max_triple_map_planes: int = 24
    """Largest map planes that form plane-triple hypotheses when relocalising."""
    relocalise_max_hypotheses: int = 2000
    """Plane-triple hypotheses at most (and an eighth as many edge pairings, which give up
    to 8 poses each) in a whole-map search: a box-shaped world matches every orthogonal
    triple with every other."""
    relocalise_candidates: int = 8
    """Best-supported relocalisation candidates refined in full."""
    relocalise_min_planes: int = 4
    """A relocalised pose needs this many inlier planes (one more than a plane triple
    always fits) ..."""
    relocalise_min_plane_fraction: float = 0.6
    """... and at least this fraction of the frame's planes (a floor and a few walls of a
    box-shaped world fit in many places; most of what the frame sees must fit) ..."""
    relocalise_min_points: int = 30
    """... or this many inlier point matches."""
    relocalise_ambiguity: float = 0.8
    """A relocalisation is refused when a candidate elsewhere scores at least this
    fraction of the best (a symmetric room seen from its middle)."""
    sigma_line_m: float = 0.03
    """Noise of an edge end along its edge in the robust estimate [m]."""
    line_gate_m: float = 0.03
    """An observed edge end pairs with the nearer end of its map edge only within this
    along the edge [m] under the start pose: a map edge keeps its longest extent, so an
    end seen shorter (occluded) must not pull the pose."""
    huber_k: float = 2.0
    """Huber threshold of the robust estimate, in sigmas of each term."""
    max_sigma_deg: float = 2.0
    """A pose is trusted when every rotation direction has at most this sigma [deg] ..."""
    max_sigma_m: float = 0.03
    """... and every translation direction at most this sigma [m]; the same thresholds
    decide which directions a primitive constrains."""
    points: PointConfig = field(default_factory=PointConfig)
    """Keypoints with depth."""
    segments: bool = True
    """After a loss, track on in a new segment (from the lost frame) and join it to the
    map when a later frame relocalises (`segments`); false: stay lost until then."""
    segment_keyframe_m: float = 0.05
    """A segment frame this far [m] from the segment's last keyframe becomes its keyframe ..."""
    segment_keyframe_deg: float = 5.0
    """... or one turned this much [deg]."""
    icp: bool = True
    """Use frame-to-frame ICP where planes leave directions free, and as a fallback."""
    icp_stride: int = 4
    """Take every icp_stride-th pixel in each direction for ICP clouds."""
    icp_voxel_m: float = 0.03
    """Voxel size of the ICP clouds [m]."""
    icp_max_distance_m: float = 0.10
    """ICP correspondence gate [m]."""
    icp_min_fitness: float = 0.5
    """ICP result trusted when at least this fraction of points has a correspondence."""
    icp_max_rmse_m: float = 0.03
    """... and their RMSE is below this [m]."""
    rgbd_odometry: bool = True
    """Fall back to Open3D RGB-D odometry when planes and ICP fail (needs colour)."""
    max_depth_m: float = 4.0
    """Points farther than this are left out of ICP and RGB-D odometry [m]."""

    def __post_init__(self) -> None:
        positive = (
            "max_angle_deg",
            "max_offset_m",
            "max_corner_distance_m",
            "sigma_angle_deg",
            "sigma_offset_m",
            "sigma_point_m",
            "max_residual_angle_deg",
            "max_residual_offset_m",
            "size_gate_ratio",
            "sigma_line_m",
            "line_gate_m",
            "huber_k",
            "fast_max_gap_s",
            "fast_max_correction_m",
            "segment_keyframe_m",
            "segment_keyframe_deg",
            "fast_max_correction_deg",
            "fast_max_jump_m",
            "fast_max_jump_deg",
            "refine_floor_deg",
            "refine_floor_m",
            "max_sigma_deg",
            "max_sigma_m",
            "icp_voxel_m",
            "icp_max_distance_m",
            "icp_max_rmse_m",
            "max_depth_m",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"tracking.{name} must be > 0, got {getattr(self, name)}")
        for name in ("max_triple_planes", "max_triple_map_planes"):
            if getattr(self, name) < 3:
                raise ConfigError(f"tracking.{name} must be >= 3, got {getattr(self, name)}")
        for name in (
            "relocalise_candidates",
            "relocalise_min_planes",
            "relocalise_min_points",
            "relocalise_max_hypotheses",
        ):
            if getattr(self, name) < 1:
                raise ConfigError(f"tracking.{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.relocalise_min_plane_fraction <= 1:
            raise ConfigError(
                "tracking.relocalise_min_plane_fraction must be in [0, 1], got "
                f"{self.relocalise_min_plane_fraction}"
            )
        if not 0 < self.relocalise_ambiguity <= 1:
            raise ConfigError(
                f"tracking.relocalise_ambiguity must be in (0, 1], got {self.relocalise_ambiguity}"
            )
        if self.icp_stride < 1:
            raise ConfigError(f"tracking.icp_stride must be >= 1, got {self.icp_stride}")
        if not 0 <= self.icp_min_fitness <= 1:
            raise ConfigError(
                f"tracking.icp_min_fitness must be in [0, 1], got {self.icp_min_fitness}"
            )
        area = self.weigh_unpaired_min_area_m2
        if area is not None and (isinstance(area, bool) or not float(area) >= 0):
            raise ConfigError(
                "tracking.weigh_unpaired_min_area_m2 must be a number >= 0 [m^2] or null, "
                f"got {area!r}"
            )
        if not 0 <= self.weak_translation_share < 1 / 3:
            raise ConfigError(
                "tracking.weak_translation_share must be in [0, 1/3) (a share of three "
                f"directions' information), got {self.weak_translation_share}"
            )
