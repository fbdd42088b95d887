"""ROS 2 side of liver_p2p_reg: ROS-free node core, PointCloud2 conversion, bag I/O and replay; rclpy adapters."""
