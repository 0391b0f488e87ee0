"""One writer per output: a second writer is refused naming the holder, with real processes;
a killed holder's lock is taken over."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from hogsa_loader.io.locks import FolderBusyError, writer_lock

HOLD = (
    "import sys, time\n"
    "from hogsa_loader.io.locks import writer_lock\n"
    "with writer_lock(sys.argv[1], sys.argv[2], 'rank 0 of an export'):\n"
    "    print('held', flush=True)\n"
    "    time.sleep(120)\n"
)


def _holder(folder, name):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder), name], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_and_a_dead_holders_lock_is_taken_over(tmp_path):
    proc = _holder(tmp_path, ".rank-0.lock")
    try:
        with pytest.raises(FolderBusyError, match=rf"rank 0 of an export is being written by process {proc.pid}"):
            with writer_lock(tmp_path, ".rank-0.lock", "rank 0 of an export"):
                pass
        with writer_lock(tmp_path, ".rank-1.lock"):  # another rank's lock is free
            pass
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    with writer_lock(tmp_path, ".rank-0.lock"):  # the kernel released the killed holder's lock
        assert (tmp_path / ".rank-0.lock").read_text().strip() == str(os.getpid())


def test_an_export_of_a_rank_being_written_is_refused(tmp_path):
    from hogsa_loader.sample.export import write_shards

    out = tmp_path / "export"
    out.mkdir()
    proc = _holder(out, ".rank-0.lock")
    try:
        t0 = time.perf_counter()
        with pytest.raises(FolderBusyError, match=str(proc.pid)):
            write_shards(lambda s: iter(()), out, 4, 2, progress=False)
        assert time.perf_counter() - t0 < 30  # refused at once, not after waiting
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
