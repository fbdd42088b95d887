"""The live ROS 2 graph harness: the nodes as processes on an isolated domain, bags played through them (make demo)."""
