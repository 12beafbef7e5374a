"""rosbag2 tools for beo_ros (step one of splitting the old bag.py: all of it is in player.py,
whose history it keeps; the next commit moves its sections into their own modules)."""
from beo_ros.ros.bag.player import *  # noqa: F401,F403
from beo_ros.ros.bag.player import _bag_file, _cli_node, _clock_tick, _sleep_until  # noqa: F401
