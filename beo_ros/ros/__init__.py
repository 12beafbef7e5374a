"""ROS 2 layer of beo_ros: node, demo, bag tools, and runtime environment helpers (env)."""

# the last stamp a builtin_interfaces/Time holds (int32 seconds: 2038-01-19T03:14:07.999999999)
MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999
