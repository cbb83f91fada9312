"""Timing figures: the peak RSS is the process's own, not what it inherited from its parent."""

from __future__ import annotations

import subprocess
import sys

from linear_slam_ros.core.timing import peak_rss_mb, reset_peak_rss


def test_peak_rss_is_the_processs_own_high_water_mark_not_its_parents(tmp_path):
    status = tmp_path / "status"
    status.write_text("Name:\tpython\nVmPeak:\t  900000 kB\nVmHWM:\t   51200 kB\nVmRSS:\t   40960 kB\n")
    assert peak_rss_mb(status) == 50.0
    # A child of a process holding 300 MB: ru_maxrss says >= 300 MB, its own high-water mark far less.
    code = (
        "import subprocess, sys, numpy as np\n"
        "held = np.ones(300 * 2**20 // 8)\n"
        "child = 'from linear_slam_ros.core.timing import peak_rss_mb; print(peak_rss_mb())'\n"
        "print(subprocess.run([sys.executable, '-c', child], capture_output=True, text=True, check=True).stdout)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert float(out.stdout.strip()) < 200.0, out.stdout


def test_without_a_status_file_it_falls_back_to_ru_maxrss(tmp_path):
    assert peak_rss_mb(tmp_path / "missing") > 0.0


def test_reset_peak_rss_makes_the_peak_that_of_what_runs_next(tmp_path):
    """In a fresh interpreter (a test worker's allocator may keep freed memory, and its peak is its own)."""
    child = (
        "import numpy as np\n"
        "from linear_slam_ros.core.timing import peak_rss_mb, reset_peak_rss\n"
        "big = np.ones(32 * 2**20)  # 256 MiB of float64, touched\n"
        "before = peak_rss_mb()\n"
        "del big\n"
        "assert reset_peak_rss()\n"
        "print(before, peak_rss_mb())\n"
    )
    out = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, check=True, timeout=120)
    before, after = (float(v) for v in out.stdout.split())
    assert before - after > 200, (before, after)  # the freed quarter gigabyte no longer counts
    assert not reset_peak_rss(tmp_path / "no" / "clear_refs")  # elsewhere: says it could not
