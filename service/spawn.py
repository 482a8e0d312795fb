"""Start ``texspace`` processes and wait until they serve: the one helper the end-to-end
and reliability tests and the benchmarks share (and what a script driving a local
deployment needs).

    port = free_port()
    proc = spawn(["serve"], env | {"TEXSPACE_PORT": str(port)}, log_path)
    wait_ready(f"http://127.0.0.1:{port}", [proc], 120, output=lambda: log_path.read_text())
    ...
    stop([proc])

Each process runs ``python -m service.cli ARGS`` in a session of its own, so ``stop``
can kill its whole tree and nothing else. Only the standard library: the benchmarks need
no test extra for this.
"""
from __future__ import annotations

import http.client
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class NotReady(RuntimeError):
    """A process exited, or did not answer 200 in time; the message ends with its log."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def spawn(args: list[str], env: dict[str, str], log_path: str | os.PathLike) -> subprocess.Popen:
    """``python -m service.cli ARGS`` with ``env``, stdout and stderr to ``log_path``."""
    with open(log_path, "ab") as log:  # the child keeps its own handle
        return subprocess.Popen([sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env,
                                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)


def wait_ready(base_url: str, procs: Iterable[subprocess.Popen], timeout: float, *,
               output: Callable[[], str] = lambda: "", name: str = "texspace", path: str = "/readyz") -> None:
    """Poll ``base_url + path`` until it answers 200. NotReady, with the tail of
    ``output()`` (the processes' logs), as soon as one of ``procs`` has exited or after
    ``timeout`` seconds."""
    procs = list(procs)
    deadline = time.monotonic() + timeout
    while True:
        for proc in procs:
            if proc.poll() is not None:
                raise NotReady(f"{name}: a process exited with {proc.returncode}\n{output()[-3000:]}")
        try:
            with urllib.request.urlopen(base_url + path, timeout=5) as response:
                if response.status == 200:
                    return
        except (OSError, http.client.HTTPException):
            pass
        if time.monotonic() > deadline:
            raise NotReady(f"{name}: not ready within {timeout:g} s\n{output()[-3000:]}")
        time.sleep(0.25)


def stop(procs: Iterable[subprocess.Popen | None], *, sig: int = signal.SIGTERM, grace: float = 15.0) -> None:
    """Send ``sig`` to every process still running, wait up to ``grace`` seconds each,
    then kill the session of any that is left."""
    procs = [p for p in procs if p is not None]
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(sig)
    for proc in procs:
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # its own session: only the tree we started
            proc.wait(5)
