"""Put a log's stamps into another log's time base by finding the scans the two share; estimate how late a
log's scan stamps run against its odometry's.

SLAM-corrected logs are often re-stamped copies of a raw log (the Freiburg 079 corrected log runs
1211.0 to 1211.5 s behind its raw bag, by an offset that drifts). A scan's ranges identify it: scans
whose range vectors (rounded to 1 cm, readings beyond ``cap`` treated alike) occur exactly once in each
log are pairs. Pairs out of time order are dropped; between pairs the offset is interpolated linearly,
beyond the first and last pair it is held.
"""

from __future__ import annotations

import numpy as np

from slam.errors import LogFormatError
from slam.laserlog import LaserLog

#: odometry delays searched (s, either way) and the step of the search
MAX_ODOMETRY_DELAY = 0.3
ODOMETRY_DELAY_STEP = 0.01
#: the estimate compares heading changes over windows of this length (s) around each stamp
ODOMETRY_DELAY_WINDOW = 0.5

#: stamps come in bursts when more than BURST_FRACTION of the scan (or odometry) intervals are shorter than
#: BURST_RATIO times the scans' (or the odometry's) mean interval (the longest 5 % left out: pauses in the log). A
#: log replayed or converted with coarse timing does that (the Intel bag's scans come two or more within a
#: millisecond, then half a second apart); its stamps do not say when a scan or an odometry record was taken to the
#: hundredths of a second an odometry delay is about.
BURST_RATIO = 0.2
BURST_FRACTION = 0.05

#: readings at or beyond this (m) count as "no return" when comparing scans (raw and corrected logs may
#: disagree on the maximum range, e.g. 80 m in a bag and 80.99 m in the CARMEN PARAMs)
DEFAULT_CAP = 79.0


def _keys(log: LaserLog, cap: float) -> list[bytes]:
    """Per scan, its own readings (its beam count of them) in cm as bytes: equal keys, equal scans."""
    ranges = log.ranges
    finite = np.isfinite(ranges) & (ranges < cap)
    centi = np.where(finite, np.round(np.where(finite, ranges, 0.0) * 100.0), -1).astype(np.int32)
    return [row[:beams].tobytes() for row, beams in zip(centi, log.beams)]


def matching_scans(log: LaserLog, reference: LaserLog, cap: float = DEFAULT_CAP) -> tuple[np.ndarray, np.ndarray]:
    """Indices (P,), (P,) of the scans of ``log`` and ``reference`` with the same ranges (the same beam count
    and readings), each unique in both logs, in time order in both."""
    ref_index: dict[bytes, int] = {}
    ref_dupes: set[bytes] = set()
    for i, key in enumerate(_keys(reference, cap)):
        if key in ref_index:
            ref_dupes.add(key)
        ref_index[key] = i
    own_keys = _keys(log, cap)
    counts: dict[bytes, int] = {}
    for key in own_keys:
        counts[key] = counts.get(key, 0) + 1
    pairs = [
        (i, ref_index[k]) for i, k in enumerate(own_keys) if counts[k] == 1 and k in ref_index and k not in ref_dupes
    ]
    pairs.sort(key=lambda p: log.stamps[p[0]])
    kept: list[tuple[int, int]] = []
    for i, j in pairs:
        if not kept or reference.stamps[j] > reference.stamps[kept[-1][1]]:
            kept.append((i, j))
    arr = np.array(kept, dtype=np.int64).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def time_map(log: LaserLog, reference: LaserLog, cap: float = DEFAULT_CAP) -> tuple[np.ndarray, np.ndarray]:
    """(log stamps, offsets) (P,) at the shared scans: a stamp t of ``log`` is t + interp(t, stamps, offsets)
    in ``reference``'s time base. Raises :class:`LogFormatError` with fewer than two shared scans."""
    own, ref = matching_scans(log, reference, cap)
    if len(own) < 2:
        raise LogFormatError(
            f"{log.source} and {reference.source} share {len(own)} scans with identical ranges; "
            "need at least 2 to align their clocks"
        )
    stamps = log.stamps[own]
    return stamps, reference.stamps[ref] - stamps


def to_reference_time(stamps: np.ndarray, map_stamps: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``stamps`` (s, the log's clock) in the reference clock, by the offsets of :func:`time_map`."""
    return np.asarray(stamps, np.float64) + np.interp(stamps, map_stamps, offsets)


def bursty_stamps(stamps: np.ndarray, odom_stamps: np.ndarray) -> str:
    """Why the scan ``stamps`` (T,) s and the odometry's ``odom_stamps`` (K,) s cannot time an odometry delay
    (they come in bursts: :data:`BURST_FRACTION`, :data:`BURST_RATIO`, each stream against its own mean interval,
    so that odometry at 100 Hz beside scans at 10 Hz is regular), or "" when they can."""
    for what, given in (("scans", stamps), ("odometry records", odom_stamps)):
        gaps = np.diff(np.asarray(given, np.float64))
        if not len(gaps):
            continue
        typical = float(np.sort(gaps)[: max(1, int(0.95 * len(gaps)))].mean())  # (a median is a burst's)
        short = float(np.mean(gaps < BURST_RATIO * typical))
        if short > BURST_FRACTION:
            return (
                f"its {what} come in bursts ({100 * short:.0f} % of them less than "
                f"{1e3 * BURST_RATIO * typical:.0f} ms apart, their mean interval being {1e3 * typical:.0f} ms), "
                "so their stamps cannot time a delay"
            )
    return ""


def odometry_delay(
    stamps: np.ndarray,
    yaw: np.ndarray,
    odom_stamps: np.ndarray,
    odom_yaw: np.ndarray,
    max_delay: float = MAX_ODOMETRY_DELAY,
    step: float = ODOMETRY_DELAY_STEP,
    window: float = ODOMETRY_DELAY_WINDOW,
) -> tuple[float, float]:
    """The delay d (s) for which the odometry's heading changes, read at scan stamp + d, best match the
    heading changes of a scan-matched trajectory (``yaw`` (T,) rad at ``stamps`` (T,) s, e.g. a grid
    FastSLAM particle's), with ``odom_yaw`` (K,) rad at ``odom_stamps`` (K,) s.

    Scan matching fixes each scan's heading to what the scan saw; if the scan stamps run late against the
    odometry, the odometry turns early against that trajectory. Over windows of ``window`` s centred on
    every stamp (away from the ends), the mean absolute difference of the two heading changes is taken
    for every d in [-max_delay, max_delay] by ``step``; returns (best d, its mean difference in rad).
    Raises ValueError when the trajectory is too short to compare.
    """
    stamps = np.asarray(stamps, np.float64)
    yaw = np.unwrap(np.asarray(yaw, np.float64))
    odom_stamps = np.asarray(odom_stamps, np.float64)
    odom_yaw = np.unwrap(np.asarray(odom_yaw, np.float64))
    margin = max_delay + window
    centres = stamps[(stamps > stamps[0] + margin) & (stamps < stamps[-1] - margin)]
    if len(centres) < 2:
        raise ValueError(f"need a trajectory longer than {2 * margin:.1f} s to estimate the odometry delay")
    half = window / 2
    turned = np.interp(centres + half, stamps, yaw) - np.interp(centres - half, stamps, yaw)
    best = (np.inf, 0.0)
    for delay in np.arange(-max_delay, max_delay + step / 2, step):
        odom_turned = np.interp(centres + delay + half, odom_stamps, odom_yaw) - np.interp(
            centres + delay - half, odom_stamps, odom_yaw
        )
        mismatch = float(np.mean(np.abs(turned - odom_turned)))
        if mismatch < best[0]:
            best = (mismatch, float(delay))
    return round(best[1], 6), best[0]
