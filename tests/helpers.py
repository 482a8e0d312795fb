"""Plain helpers shared by several test folders (fixtures live in the conftests)."""
from __future__ import annotations

import subprocess
import time
from collections.abc import Callable, Iterable

import httpx
import pytest


def wait_ready(base_url: str, procs: Iterable[subprocess.Popen], timeout: float, *,
               output: Callable[[], str] = lambda: "", name: str = "texspace", path: str = "/readyz") -> None:
    """Poll ``base_url + path`` until it answers 200; fail the test, with ``output()`` (the
    processes' logs), as soon as one of ``procs`` has exited or after ``timeout`` seconds."""
    procs = list(procs)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for proc in procs:
            if proc.poll() is not None:
                pytest.fail(f"{name}: a process exited with {proc.returncode}\n{output()}")
        try:
            if httpx.get(base_url + path, timeout=5).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.25)
    pytest.fail(f"{name}: not ready within {timeout}s\n{output()}")
