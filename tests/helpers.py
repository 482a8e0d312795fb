"""Plain helpers shared by several test folders (fixtures live in the conftests)."""
from __future__ import annotations

import subprocess
from collections.abc import Callable, Iterable

import pytest

from service import spawn


def wait_ready(base_url: str, procs: Iterable[subprocess.Popen], timeout: float, *,
               output: Callable[[], str] = lambda: "", name: str = "texspace", path: str = "/readyz") -> None:
    """``service.spawn.wait_ready``, failing the test (with the processes' logs) instead of raising."""
    try:
        spawn.wait_ready(base_url, procs, timeout, output=output, name=name, path=path)
    except spawn.NotReady as exc:
        pytest.fail(str(exc))