"""The whole service on a large skin (``touchreal bench serve --skin``): the CPU time of the
``touchreal serve`` process tree (the simulated skin's process included), activity-driven against
``--dense``, side by side in one run.

Each configuration starts ``touchreal serve`` in its own process on the large-skin scene
(``--sim-scene large``, ``--sim-touched``), waits for health, connects one client in this process
subscribed to every spike (its clock model from ``time`` exchanges and ``clock`` messages), and
``--skin-settle-s`` after subscribing (past the stream start, where every taxel runs until the
detector has judged it) reads for ``--skin-seconds`` the CPU time of the process and all its
descendants from /proc, the spikes' latency as the client holds them (receipt minus the
acquisition of the causing sample) and the service's counters (sheds, overload drops, real-time
factor, taxels awake). Ratios are against ``--dense`` at ``--skin-reference`` taxels (4096) in the
same run. A configuration the machine cannot serve sheds; its CPU per second is then capped by the
cores, and its row says how much signal it shed. So each row also gives the CPU per second of signal
*computed*: the serve process's CPU over the measured span less the signal shed, plus its children's
(the simulation, which runs whether or not a chunk is shed; its own column) per second of wall time:
what the configuration would cost where the cores cap the wall figure (it still charges the event
loop's CPU while a chunk is shed to the computed signal, so it overstates a shedding row slightly).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..bridge.natsd import free_port, stop_process
from ..settings import CLASSES
from .skin import cpu_name


def _stat(pid: int) -> list[str]:
    """The fields of /proc/``pid``/stat after the command name (OSError: the process is gone)."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def process_cpu_s(pid: int) -> float:
    """User + system CPU time (s) of process ``pid`` alone (all its threads), from /proc."""
    fields = _stat(pid)
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def tree_cpu_s(pid: int) -> float:
    """User + system CPU time (s) of process ``pid`` and every live descendant, from /proc."""
    parent: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parent[int(entry.name)] = int(_stat(int(entry.name))[1])
            except OSError:
                continue
    tree, frontier = {pid}, [pid]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parent.items() if pp == p and c not in tree]
        tree.update(kids)
        frontier.extend(kids)
    total = 0.0
    for p in tree:
        try:
            total += process_cpu_s(p)
        except OSError:
            continue
    return total


def _metric(text: str, name: str) -> float:
    """The value of an unlabelled sample ``name`` in a Prometheus exposition (0 when absent)."""
    m = re.search(rf"^{name} (\S+)$", text, re.M)
    return float(m.group(1)) if m else 0.0


async def _measure(base: str, pid: int, settle_s: float, seconds: float) -> dict:
    """One client subscribed to everything; the figures over ``seconds`` from ``settle_s`` after subscribing."""
    import httpx
    from touchreal_client import protocol as P
    from touchreal_client.stream import AsyncStream

    lat: dict[str, list[np.ndarray]] = {c: [] for c in CLASSES}
    awake: list[float] = []
    measuring = False

    async def read(st: AsyncStream) -> None:  # every frame is taken; those held while measuring count
        async for frame in st.frames():
            if measuring and isinstance(frame, P.SpikesFrame) and frame.t_us.size:
                v = st.spike_latency_us(frame)
                for i, c in enumerate(CLASSES):
                    lat[c].append(v[frame.cls == i])

    async with httpx.AsyncClient(base_url=base, timeout=10) as http, AsyncStream(f"{base.replace('http', 'ws')}/v1/stream") as st:
        await st.sync_clock()
        reader = asyncio.create_task(read(st))
        await asyncio.sleep(settle_s)
        measuring = True
        t0, cpu0, own0, before = time.monotonic(), tree_cpu_s(pid), process_cpu_s(pid), (await http.get("/metrics")).text
        while time.monotonic() < t0 + seconds:  # whether or not frames arrive (a service shedding every chunk sends none)
            awake.append(_metric((await http.get("/metrics")).text, "touchreal_taxels_awake"))
            await asyncio.sleep(min(1.0, max(0.0, t0 + seconds - time.monotonic())))
        wall, cpu, own = time.monotonic() - t0, tree_cpu_s(pid) - cpu0, process_cpu_s(pid) - own0
        after = (await http.get("/metrics")).text
        reader.cancel()
    delta = {k: _metric(after, k) - _metric(before, k) for k in
             ("touchreal_sheds_total", "touchreal_shed_seconds_total", "touchreal_updates_dropped_overload_total")}
    computed = wall - delta["touchreal_shed_seconds_total"]
    children = max(0.0, cpu - own) / wall  # the simulation's process: it runs whether or not a chunk is shed
    return {"cpu_per_s": cpu / wall, "children_per_s": children,
            "cpu_per_computed_s": children + own / computed if computed > 0 else float("inf"),
            "awake": float(np.mean(awake)) if awake else float("nan"),
            "rtf": _metric(after, "touchreal_real_time_factor"),
            "latency_ms": {c: np.concatenate(v) / 1000.0 if v else np.zeros(0) for c, v in lat.items()}, **delta}


def _serve(n: int, dense: bool, touched: float, settle_s: float, seconds: float, state: Path) -> dict:
    """Start ``touchreal serve`` for one configuration, measure it, stop it."""
    import httpx

    port = free_port()
    cmd = [sys.executable, "-m", "touchreal", "serve", "--taxels", str(n), "--port", str(port), "--state-dir",
           str(state / f"{n}-{'dense' if dense else 'activity'}"), "--sim-scene", "large", "--sim-touched", str(touched)]
    log = state / f"serve-{port}.log"  # a file, not a pipe: nobody reads it while the service runs
    with open(log, "wb") as err:
        proc = subprocess.Popen(cmd + (["--dense"] if dense else []), stdout=subprocess.DEVNULL, stderr=err)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"touchreal serve exited ({proc.returncode}): {log.read_text()[-500:]}")
            try:
                if httpx.get(base + "/v1/health", timeout=1).status_code < 500:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("touchreal serve did not answer /v1/health within 120 s")
            time.sleep(0.2)
        return asyncio.run(_measure(base, proc.pid, settle_s, seconds))
    finally:
        stop_process(proc, 20.0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--skin", action="store_true", help="only the whole service on a large skin: the serve process "
                   "tree's CPU, activity-driven against --dense 4096 (bench/serve_skin.py)")
    p.add_argument("--skin-taxels", default="4096,16384", help="activity-driven taxel counts for --skin")
    p.add_argument("--skin-touched", type=float, default=0.05, help="the large scene's touched fraction for --skin")
    p.add_argument("--skin-reference", type=int, default=4096, help="taxels of the --dense reference for --skin")
    p.add_argument("--skin-settle-s", type=float, default=10.0, help="--skin: the measurement starts this long after "
                   "subscribing (past the stream start, where every taxel runs until the detector has judged it)")
    p.add_argument("--skin-seconds", type=float, default=60.0, help="measured seconds per --skin configuration")


def run(args: argparse.Namespace) -> int:
    configs = [(args.skin_reference, True)] + [(int(x), False) for x in args.skin_taxels.split(",") if x]
    print(f"== the whole service on a large skin ({cpu_name()}; `touchreal serve --sim-scene large --sim-touched "
          f"{args.skin_touched:g}`, one client subscribed to every spike, {args.skin_seconds:g} s after {args.skin_settle_s:g} s; "
          f"CPU of the serve process tree per second, ratios against --dense {args.skin_reference})")
    print(f"{'taxels':>6} {'compute':>8} {'CPU s/s':>8} {'x dense':>8} {'per computed s':>14} {'x dense':>8} "
          f"{'awake':>7} {'rtf':>5} {'sheds':>6} "
          f"{'shed s':>7} {'overload':>8} {'sim s/s':>7}  latency p50 / p95 ms: " + " ".join(f"{c:>13}" for c in CLASSES))
    ref = None
    with tempfile.TemporaryDirectory(prefix="touchreal-bench-") as tmp:
        for n, dense in configs:
            r = _serve(n, dense, args.skin_touched, args.skin_settle_s, args.skin_seconds, Path(tmp))
            ref = ref or (r["cpu_per_s"], r["cpu_per_computed_s"])
            lat = " ".join(f"{f'{np.median(v):.1f}/{np.percentile(v, 95):.1f}' if v.size else '-':>13}"
                           for v in (r["latency_ms"][c] for c in CLASSES))
            print(f"{n:6d} {'dense' if dense else 'activity':>8} {r['cpu_per_s']:8.2f} {r['cpu_per_s'] / ref[0]:8.3f} "
                  f"{r['cpu_per_computed_s']:14.2f} {r['cpu_per_computed_s'] / ref[1]:8.3f} {100 * r['awake'] / n:6.1f}% {r['rtf']:5.2f} {r['touchreal_sheds_total']:6.0f} "
                  f"{r['touchreal_shed_seconds_total']:7.2f} {r['touchreal_updates_dropped_overload_total']:8.0f} "
                  f"{r['children_per_s']:7.2f}  {'':>21}{lat}", flush=True)
    return 0
