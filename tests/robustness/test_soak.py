"""The soak benchmark's measurements (``tests/robustness/soak.py``): process memory, children, flatness."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
soak = importlib.import_module("soak")

pytestmark = [
    pytest.mark.robustness,
    pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads Linux /proc"),
]


def test_rss_and_children_of_a_process():
    child = subprocess.Popen([sys.executable, "-c", "import time; x = bytearray(64 << 20); time.sleep(30)"])
    try:
        deadline = time.monotonic() + 25  # until the child has touched its 64 MiB (slow hosts: seconds)
        while time.monotonic() < deadline:
            rss = soak.rss_bytes(child.pid)
            if rss and rss > 60 << 20:
                break
            time.sleep(0.05)
        assert child.pid in soak.child_pids(os.getpid())
        assert soak.rss_bytes(child.pid) > 60 << 20
        assert soak.rss_bytes(os.getpid()) > 10 << 20
    finally:
        child.kill()
        child.wait()
    assert soak.rss_bytes(child.pid) is None and child.pid not in soak.child_pids(os.getpid())


def test_flatness_after_warm_up():
    mib = 2**20
    flat = [{"samples": s, "main": 400 * mib, "workers": (900 + (s % 7)) * mib} for s in range(0, 1001, 10)]
    f = soak.flatness(flat, 1000)
    assert f["flat"] and f["spread"] < 0.01 and abs(f["slope_mib_per_1000"]) < 1
    # a leak of 1 MiB per 10 samples after warm-up: 80 MiB over the fit, 6 % of 1.3 GiB
    leak = [dict(r, workers=r["workers"] + r["samples"] // 10 * mib) for r in flat]
    f = soak.flatness(leak, 1000)
    assert not f["flat"] and f["slope_mib_per_1000"] == pytest.approx(100, rel=0.05)
    # warm-up growth does not count
    warm = [dict(r, main=r["main"] + (300 * mib if r["samples"] < 150 else 0)) for r in flat]
    assert soak.flatness(warm, 1000)["flat"]
