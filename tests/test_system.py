"""Tests of the forked-task runner."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from hogsa_loader.system import can_fork

CHILD = textwrap.dedent("""
    import os
    import torch
    from hogsa_loader.system import run_forked

    torch.set_num_threads(2)
    x = torch.randn(4_000_000)
    x.abs().sum()  # the parent runs OpenMP parallel regions before forking

    def task(i):
        torch.randn(4_000_000).abs().sum()  # would hang on two threads after the fork
        return os.getpid() == parent, torch.get_num_threads()

    parent = os.getpid()
    got = {}
    # 0 and 1 side by side on forked processes; 2 needs both, so it runs alone, in the caller
    run_forked(task, [(), (), (0, 1)], 2, on_result=got.__setitem__)
    print(sorted(got.items()))
""")


@pytest.mark.skipif(not can_fork(), reason="forked task processes run on Linux only")
def test_forked_tasks_run_after_the_parent_used_openmp():
    """A task process forked after the parent used the OpenMP pool runs with one torch
    thread and finishes (on two threads its first parallel region would never return); a
    task that runs alone runs in the caller, on its threads."""
    res = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().splitlines()[-1] == "[(0, (False, 1)), (1, (False, 1)), (2, (True, 2))]"
