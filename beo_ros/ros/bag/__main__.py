"""``python -m beo_ros.ros.bag``: beo-replay."""
import sys

from beo_ros.ros.bag.cli import replay_main

if __name__ == '__main__':
    sys.exit(replay_main())
