"""ROS-free logic of a stream of clouds: intake and scheduling, tracking, survey, fiducials, outputs and diagnostics."""
