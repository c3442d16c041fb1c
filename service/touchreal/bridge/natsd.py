"""A local ``nats-server`` on 127.0.0.1 for the tests and ``touchreal bench serve --nats``.

Production runs the broker as its own service (deploy/); this only starts Debian's binary on a free
loopback port and stops it again.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

BINARY = "nats-server"


def available() -> bool:
    return shutil.which(BINARY) is not None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop_process(proc: subprocess.Popen, timeout_s: float) -> None:
    """Terminate ``proc``; kill it if it has not exited within ``timeout_s``."""
    proc.terminate()
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@contextmanager
def local_nats_server(port: int | None = None, timeout_s: float = 10.0, jetstream: bool = False,
                      config: Path | None = None, env: dict[str, str] | None = None) -> Iterator[str]:
    """Run ``nats-server -a 127.0.0.1 -p PORT`` (with ``-js`` and a temporary store directory when
    ``jetstream``; with ``-c config`` and more environment ``env`` for the variables it references,
    e.g. deploy/nats/nats-server.conf); yields its URL once it accepts connections."""
    if not available():
        raise FileNotFoundError(f"{BINARY} is not installed (Debian: apt-get install nats-server)")
    port = port or free_port()
    store = tempfile.TemporaryDirectory(prefix="touchreal-nats-") if jetstream else None
    cmd = [BINARY, "-a", "127.0.0.1", "-p", str(port)] + (["-js", "-sd", store.name] if store else []) \
        + (["-c", str(config)] if config else [])
    # its log goes to a file: a pipe nobody reads fills up and then blocks the broker mid-test
    log = tempfile.TemporaryFile(prefix="touchreal-nats-log-")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log, env={**os.environ, **(env or {})})
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    log.seek(0)
                    err = log.read().decode(errors="replace")[-2000:] if proc.poll() is not None else "timeout"
                    raise RuntimeError(f"nats-server did not start on port {port}: {err}")
                time.sleep(0.05)
        yield f"nats://127.0.0.1:{port}"
    finally:
        stop_process(proc, 5.0)
        log.close()
        if store is not None:
            store.cleanup()
