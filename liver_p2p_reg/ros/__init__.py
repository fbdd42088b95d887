"""ROS 2 adapters: the rclpy nodes, PointCloud2 and output message conversion, topic names and QoS profiles."""

import os

# A node's process holds three OpenMP runtimes (torch's, Open3D's and pykdtree's libgomp), each
# with its own threads. libgomp's default keeps a runtime's threads spinning after each parallel
# region, on the cores the next runtime needs: a 3-minute soak's register_node used 50-56 % CPU
# spinning and 35-41 % passive, at the same per-frame latency (two runs each), though a full registration
# takes ~11 ms longer waking the threads (docs/ros2.md weighs it). libgomp reads this once,
# when it loads, so it is set here, before any node imports torch, Open3D or pykdtree; a value
# the user set is kept. Results are the same bits either way: it only says how idle threads wait.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def openmp_wait_warning() -> str | None:
    """The line a node logs at start-up when OMP_WAIT_POLICY=ACTIVE tells every OpenMP thread to spin without pause."""
    if os.environ.get("OMP_WAIT_POLICY", "").strip().upper() != "ACTIVE":
        return None
    # ACTIVE is not libgomp's unset default (a few milliseconds of spinning): its threads never sleep, so the
    # three runtimes' threads take the cores from each other and from every other process (docs/ros2.md)
    return (
        "OMP_WAIT_POLICY=ACTIVE: the OpenMP threads of torch, Open3D and pykdtree spin without pause on the same "
        "cores, which slows registration several-fold and keeps the cores busy while idle; unset it, or set "
        "GOMP_SPINCOUNT to spin briefly (docs/ros2.md)"
    )
