"""What a robot's heading means, and so where the self-calibration puts the angle by which its drive and its
camera disagree (:func:`slam.selfcal.split_drive_and_camera`; docs/slam.md, "Drive angle").

A module of its own, with no imports, so that the command line can offer the choices without loading the fit."""

#: what a robot's ground truth calls its heading -> the share of the drive/camera disagreement given to the drive:
#: the drive's direction (ROS's base_link: the bias is the camera's), the sensor's axis (the robot crabs by the
#: bias), or unknown (half each, and the drive angle's sd the half)
HEADING_FRAMES = {"unknown": 0.5, "drive": 0.0, "sensor": 1.0}
