"""ROS 2 adapters: the rclpy nodes, PointCloud2 and output message conversion, topic names and QoS profiles."""
