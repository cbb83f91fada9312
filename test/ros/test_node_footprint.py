"""What the node loads at start-up: scipy.stats stays out (about 30 MB of memory)."""

from __future__ import annotations

import subprocess
import sys


def test_starting_the_node_does_not_import_scipy_stats():
    code = (
        "import sys\n"
        "import linear_slam_ros.ros.node\n"
        "import linear_slam_ros.refinement.worker\n"
        "print(sorted(m for m in sys.modules if m == 'scipy.stats' or m.startswith('scipy.stats.')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout
