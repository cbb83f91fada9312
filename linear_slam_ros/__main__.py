"""``python -m linear_slam_ros``: the offline command line (see :mod:`linear_slam_ros.cli.main`)."""

import sys

from linear_slam_ros.cli.main import main

sys.exit(main())
