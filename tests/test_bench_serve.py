"""The fan-out benchmark's light subscribers (``touchreal bench serve``, part 2) against the real service."""

import asyncio

import numpy as np
import pytest
from touchreal_client import protocol as P

from touchreal.bench.serve import _light_clients
from touchreal.server.settings import RuntimeConfig

from server_harness import running_server


@pytest.mark.slow  # four light-client processes against a real server: ~19 s (pytest -m slow; .ci/run runs it)
def test_light_subscribers_see_every_frame_in_order_with_its_size(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=4)) as (addr, svc):
        spikes, spikes_joining = asyncio.run(_light_clients(addr, 3, 1.5, {}, settle_s=0.3))
        every, every_joining = asyncio.run(_light_clients(addr, 1, 1.5, {"streams": ["spikes", "channels"]}, settle_s=0.3))
        served = svc.hub.frames_rendered
    for joining, rows in zip(spikes_joining + every_joining, spikes + every):
        assert rows.shape[0] > 20 and rows.shape[1] == 8
        # the measured rows follow the joining ones: together every frame once (settle_s of them before)
        assert joining.shape[0] >= 0.3 * 100 and joining[-1, 5] + 1 == rows[0, 5]
        assert np.all(np.diff(rows[:, 5]) == 1) and rows[-1, 6] == 0  # seq: nothing missing, nothing dropped
        assert np.all(rows[:, 3] >= rows[:, 2]) and np.all(rows[:, 2] >= rows[:, 1])  # emitted, sent, received
        assert np.all(rows[:, 7] >= P.HEADER_LEN)
    # a spikes frame is its header, its count and 12-byte events; channels frames are larger
    assert np.all(spikes[0][:, 7] == P.HEADER_LEN + P.SPIKES_HEAD.size + spikes[0][:, 4] * P.EVENT_DTYPE.itemsize)
    assert every[0][:, 7].max() > spikes[0][:, 7].max()
    assert served > 0


def test_tree_cpu_counts_the_descendants_of_a_process():
    """The whole-service bench reads the CPU of a process tree: a grandchild's busy loop is counted,
    and not in the parent's own CPU."""
    import subprocess
    import sys
    import time

    from touchreal.bench.serve_skin import process_cpu_s, tree_cpu_s

    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.6: pass\ntime.sleep(60)"
    parent = subprocess.Popen([sys.executable, "-c", f"import subprocess, sys, time\n"
                               f"subprocess.Popen([sys.executable, '-c', {burn!r}])\ntime.sleep(60)"])
    try:
        deadline = time.monotonic() + 30
        while tree_cpu_s(parent.pid) < 0.6:  # the parent alone sleeps: only its grandchild's loop gets here
            assert time.monotonic() < deadline, tree_cpu_s(parent.pid)
            time.sleep(0.1)
        assert process_cpu_s(parent.pid) < 0.3
    finally:
        subprocess.run(["pkill", "-P", str(parent.pid)])
        parent.kill()
        parent.wait()


@pytest.mark.slow  # two `touchreal serve` processes for ~8 s each
def test_whole_service_bench_runs_both_configurations_and_states_ratios():
    import re
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "touchreal", "bench", "serve", "--skin", "--skin-reference", "64",
                          "--skin-taxels", "512", "--skin-settle-s", "3", "--skin-seconds", "3"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [line.split() for line in out.stdout.splitlines() if re.match(r"\s*\d+\s+(dense|activity)\s", line)]
    assert [(r[0], r[1]) for r in rows] == [("64", "dense"), ("512", "activity")], out.stdout
    cpu = [float(r[2]) for r in rows]
    assert all(c > 0 for c in cpu) and rows[0][3] == "1.000"
    assert float(rows[1][3]) == pytest.approx(cpu[1] / cpu[0], rel=0.03)  # the ratio is the two CPU figures' (printed to 0.01)
    # per second of signal computed (the span less what was shed): never below the wall figure, and its own ratio
    computed = [float(r[4]) for r in rows]
    assert all(c >= w - 0.005 for c, w in zip(computed, cpu)) and rows[0][5] == "1.000"
    assert float(rows[1][5]) == pytest.approx(computed[1] / computed[0], rel=0.03)
    assert float(rows[0][6].rstrip("%")) == 100.0 and float(rows[1][6].rstrip("%")) < 100.0  # dense runs every taxel
    sim = [float(r[11]) for r in rows]  # the simulation's process, part of the tree's CPU
    assert all(0.0 < s_ < c for s_, c in zip(sim, cpu)), out.stdout
