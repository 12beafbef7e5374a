"""ROS 2 layer of beo_ros: node, demo, bag tools, and runtime environment helpers (env)."""
