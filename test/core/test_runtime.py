"""Process tuning: glibc's allocator thresholds."""

from __future__ import annotations

import sys

import pytest

from linear_slam_ros.core import runtime


class _FakeLibc:
    def __init__(self, answer: int = 1) -> None:
        self.calls: list[tuple[int, int]] = []
        self.answer = answer

    def mallopt(self, param: int, value: int) -> int:
        self.calls.append((param, value))
        return self.answer


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_tune_allocator_fixes_the_mmap_and_the_trim_thresholds(monkeypatch):
    libc = _FakeLibc()
    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: libc)
    assert runtime.tune_allocator(runtime.MMAP_THRESHOLD_REUSE)
    assert sorted(libc.calls) == [(-3, 1 << 30), (-1, 1 << 30)]  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
    returning = _FakeLibc()
    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: returning)
    assert runtime.tune_allocator(runtime.MMAP_THRESHOLD_RETURN)  # freed memory handed back: trim at glibc's default
    assert sorted(returning.calls) == [(-3, 4 << 20), (-1, 128 << 10)]
    refused = _FakeLibc(answer=0)
    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: refused)
    assert not runtime.tune_allocator(runtime.MMAP_THRESHOLD_RETURN)
    assert len(refused.calls) == 2


def test_tune_allocator_without_a_c_library_is_a_no_op(monkeypatch):
    def missing(name):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(runtime.ctypes, "CDLL", missing)
    monkeypatch.setattr(runtime.sys, "platform", "linux")
    assert runtime.tune_allocator(runtime.MMAP_THRESHOLD_REUSE) is False
    monkeypatch.setattr(runtime.sys, "platform", "darwin")
    assert runtime.tune_allocator(runtime.MMAP_THRESHOLD_REUSE) is False
