"""Grid-based FastSLAM (a Rao-Blackwellized particle filter with one occupancy grid per particle).

The filter and its runner load compiled kernels, so they are imported on first use; the configuration
alone is light.
"""

from slam.gridslam.config import GridSlamConfig

__all__ = ["GridFastSLAM", "GridSlamConfig", "GridSlamResult", "run_gridslam"]


def __getattr__(name: str):
    if name == "GridFastSLAM":
        from slam.gridslam.filter import GridFastSLAM

        return GridFastSLAM
    if name in ("GridSlamResult", "run_gridslam"):
        from slam.gridslam import run

        return getattr(run, name)
    raise AttributeError(f"module 'slam.gridslam' has no attribute {name!r}")
