"""Bags: rosbag2/MCAP reading and writing, making bags from cases, the rclpy player, and replay through the stream core."""
