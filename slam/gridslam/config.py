"""Parameters of grid FastSLAM, and the motion step a sparse log gets, apart from the filter so that the command line
can show their defaults without loading the compiled kernels."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GridSlamConfig:
    """Parameters of grid FastSLAM (m, rad; log-odds are natural-log odds)."""

    particles: int = 30  # the least particles (KLD-sampling grows the set up to particle_cap)
    resolution: float = 0.05  # cell size, m
    tile_cells: int = 32  # tile edge in cells (copy-on-write unit; a power of two)
    max_range: float = 30.0  # m: beams are used up to here; longer or no return: free space up to here
    min_range: float = 0.05  # m: shorter readings are ignored
    match_beams: int = 180  # at most this many beams (evenly spread) for matching and likelihood
    kernel: int = 1  # cells searched around a beam's end for the nearest occupied cell
    sigma_match: float = 0.05  # m, match score width
    sigma_like: float = 0.075  # m, likelihood width
    p_rand: float = 0.05  # per-beam probability of an unexplained reading
    gain: float = 3.0  # likelihood temper (beams are correlated)
    weight_temper: float = 30.0  # the weight factor eta enters as eta^(1/weight_temper) (GMapping divides by 3N)
    lin_step: float = 0.05  # m, first hill-climbing step
    ang_step: float = 0.05  # rad
    refinements: int = 5  # step halvings
    yaw_search: float = 0.25  # rad: yaws tried around the odometry's before hill climbing
    slip_starts: bool = True  # also start the match where the robot stood and as far backwards as the odometry went
    prior_cap: float = 9.0  # squared Mahalanobis distance beyond which the matcher ignores the odometry
    stencil_xy: float = 0.02  # m, spacing of the stencil the likelihood's curvature is fitted on
    stencil_yaw: float = 0.01  # rad
    min_match: float = 0.15  # match score per beam below which the motion model is sampled instead
    proposal_floor_xy: float = 0.005  # m, std added to the proposal Gaussian
    proposal_floor_yaw: float = 0.002  # rad
    motion_alphas: tuple[float, float, float, float] = (0.05, 0.05, 0.05, 0.05)  # slam.motion odometry model
    holonomic: bool = False  # the odometry's noise along, across its travel and of its turn (OmniOdometryMotionModel)
    motion_floor_xy: float = 0.01  # m, std added to the motion model's covariance
    # m, or None: the drive motion_alphas describe. With a value, a longer drive between two integrated scans is as
    # many such drives, whose variances add (slam.gridslam.filter.motion_steps; `posegrid slam` sets it for a sparse
    # log, slam.gridslam.filter.sparse_motion_step; docs/gridslam.md, "Sparse logs"); None: each integrated drive
    # gets the model's variances as they are
    motion_step: float | None = None
    motion_floor_yaw: float = 0.005  # rad
    l_occ: float = 0.85  # log-odds added at a beam's end
    l_free: float = -0.4  # log-odds added along a beam
    l_clamp: float = 5.0  # |log-odds| cap
    linear_update: float = 0.1  # m of odometry between integrated scans
    angular_update: float = 0.05  # rad
    resample_threshold: float = 0.5  # resample when N_eff < this * particles
    # honesty and health (docs/gridslam.md, "Honesty and health"; slam.gridslam.honesty and .health)
    keep_spread: bool = True  # keep the spread resampling loses as a covariance per particle (an honest cloud)
    revisit_gap: int = 100  # integrated scans after which coming back within revisit_radius lowers it again
    revisit_radius: float = 1.0  # m
    particle_cap: int = 30  # KLD-sampling grows the set up to this many particles (<= particles: a fixed count)
    kld_epsilon: float = 0.15  # KLD-sampling's bound on the divergence of the sample from the weighted set
    kld_delta: float = 0.01  # ... exceeded with at most this probability
    kld_bin_xy: float = 0.5  # m, KLD-sampling's bins
    kld_bin_yaw: float = 0.5  # rad
    recovery: bool = True  # after a failed match: no weighting by that scan, a wider proposal for the next
    fail_match: float = 0.2  # the best particle's matched-beam fraction below which the match failed
    fail_z: float = -6.0  # ... or its z against the recent scans below which it failed
    widen: float = 1.0  # after a failure: the factor on the motion model's variances and the yaw search's square
    # loop closure (docs/gridslam.md, "Loop closure"; slam.gridslam.loops)
    loop_closure: bool = True  # search for loop closures against old submaps, keep a pose graph (docs)
    loop_every: int = 10  # integrated scans between two loop searches
    loop_submap: int = 50  # a submap holds the scans of this many nodes either side of the old node
    loop_window_xy: float = 1.0  # m: the search window's least half-width (else 3 sigma of the filter's covariance)
    loop_window_yaw: float = 0.1  # rad: ... and its least half-width in yaw
    loop_window_max: float = 4.0  # m: the search window's largest half-width
    loop_min_match: float = 0.5  # the matched-beam fraction a loop closure needs against its submap

    def validate(self) -> None:
        """Raise ValueError naming the first parameter out of range."""
        positive = (
            "resolution",
            "max_range",
            "sigma_match",
            "sigma_like",
            "gain",
            "weight_temper",
            "lin_step",
            "ang_step",
            "l_occ",
            "l_clamp",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in (
            "kld_epsilon",
            "kld_bin_xy",
            "kld_bin_yaw",
            "revisit_radius",
            "revisit_gap",
            "loop_every",
            "loop_submap",
            "loop_window_xy",
            "loop_window_yaw",
            "loop_window_max",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.motion_step is not None and not self.motion_step > 0:
            raise ValueError(f"motion_step must be > 0 or None, got {self.motion_step}")
        if not 0 <= self.loop_min_match <= 1:
            raise ValueError(f"loop_min_match must lie in [0, 1], got {self.loop_min_match}")
        if not (0 < self.kld_delta < 1 and self.widen >= 1 and 0 <= self.fail_match <= 1):
            raise ValueError(
                f"need 0 < kld_delta < 1, widen >= 1 and 0 <= fail_match <= 1, got {self.kld_delta}, {self.widen}, "
                f"{self.fail_match}"
            )
        if min(self.particles, self.particle_cap, self.match_beams, self.tile_cells) < 1 or self.kernel < 0:
            raise ValueError("particles, particle_cap, match_beams and tile_cells must be >= 1, kernel >= 0")
        if not 0 < self.p_rand < 1 or not 0 <= self.resample_threshold <= 1 or self.l_free >= 0:
            raise ValueError("need 0 < p_rand < 1, 0 <= resample_threshold <= 1 and l_free < 0")
        if not (0 <= self.min_range < self.max_range and 0 <= self.prior_cap < math.inf):
            raise ValueError(
                f"need 0 <= min_range < max_range and a finite prior_cap >= 0, got min_range "
                f"{self.min_range}, prior_cap {self.prior_cap}"
            )


#: m, the motion_step a sparse log gets: the integration step the defaults were chosen at (linear_update's default)
SPARSE_MOTION_STEP = 0.1
#: m: a log at least half of whose drives between two scans (while the robot moves) are this long or longer (its median
#: drive, that is) is sparse. The defaults were chosen on logs of up to 0.21 m a scan (MIT CSAIL; the Intel bag 0.06
#: m, Freiburg 079 0.09); the corrected Intel log's 0.67 m is one the defaults lose (docs/gridslam.md, "Sparse logs")
SPARSE_LOG_DRIVE = 0.3
#: m: consecutive scans closer than this are the robot standing (odometry jitter), not a drive between scans
STANDING_DRIVE = 0.005


def scan_drives(odometry: np.ndarray) -> np.ndarray:
    """The distances (m) the odometry (T, 3) drives between consecutive scans while it moves (over STANDING_DRIVE)."""
    drives = np.hypot(*np.diff(np.asarray(odometry, np.float64)[:, :2], axis=0).T)
    return drives[drives > STANDING_DRIVE]


def motion_step_for(drives: np.ndarray) -> float | None:
    """The config.motion_step for a log whose drives between scans (m, as :func:`scan_drives` gives them) are these:
    :data:`SPARSE_MOTION_STEP` where at least half of them are :data:`SPARSE_LOG_DRIVE` or longer, else None (the
    model's variances for each integrated drive, as the defaults were chosen); None for no drives."""
    drives = np.asarray(drives, np.float64)
    return DriveTally(len(drives), int(np.count_nonzero(drives >= SPARSE_LOG_DRIVE))).motion_step


@dataclass
class DriveTally:
    """The drives between scans seen so far, counted (a SLAM node's, which sees one scan at a time): how many, and how
    many of them :data:`SPARSE_LOG_DRIVE` or longer. Two counts, whatever the length of the run; the rule is
    :func:`motion_step_for`'s on the drives seen so far, which the whole log's converges to: on the shared logs it
    never called a dense log sparse (at most 0.22 m in the median after the first 10 drives) and the corrected Intel
    log sparse from its 22nd drive on (its first drives, leaving the start, are 0.02 to 0.11 m), where a decision
    frozen after 10 drives took it for dense."""

    drives: int = 0
    long: int = 0

    def add(self, drives: np.ndarray) -> None:
        """Count ``drives`` (m, as :func:`scan_drives` gives them)."""
        drives = np.asarray(drives, np.float64)
        self.drives += len(drives)
        self.long += int(np.count_nonzero(drives >= SPARSE_LOG_DRIVE))

    @property
    def motion_step(self) -> float | None:
        """:data:`SPARSE_MOTION_STEP` while at least half of the drives counted are long, else None."""
        return SPARSE_MOTION_STEP if self.drives and 2 * self.long >= self.drives else None


def median_scan_drive(odometry: np.ndarray) -> float:
    """The median distance (m) the odometry (T, 3) drives between two consecutive scans while it moves; 0 for a log
    that never moves."""
    drives = scan_drives(odometry)
    return float(np.median(drives)) if len(drives) else 0.0


def sparse_motion_step(odometry: np.ndarray) -> float | None:
    """The config.motion_step for a whole log with this odometry (T, 3) (:func:`motion_step_for`)."""
    return motion_step_for(scan_drives(odometry))
