"""ROS 2 adapters: the rclpy nodes, PointCloud2 and output message conversion, topic names and QoS profiles."""

import os

# A node's process holds three OpenMP runtimes (torch's, Open3D's and pykdtree's libgomp), each
# with its own threads. libgomp's default keeps a runtime's threads spinning after each parallel
# region, on the cores the next runtime needs: a 3-minute soak's register_node used 50-56 % CPU
# spinning and 35-41 % passive, at the same latency (two runs each). libgomp reads this once,
# when it loads, so it is set here, before any node imports torch, Open3D or pykdtree; a value
# the user set is kept. Results are the same bits either way: it only says how idle threads wait.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
