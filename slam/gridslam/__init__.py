"""Grid-based FastSLAM (a Rao-Blackwellized particle filter with one occupancy grid per particle)."""
from slam.gridslam.filter import GridFastSLAM, GridSlamConfig
from slam.gridslam.run import GridSlamResult, run_gridslam

__all__ = ["GridFastSLAM", "GridSlamConfig", "GridSlamResult", "run_gridslam"]
