"""Shared pieces of the benchmarks: timing, the results file, the model under test."""
from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "out"
RESULTS = OUT / "results.json"
SHIPPED_MODEL = ROOT / "model" / "weights"


def best_of(fn, repeats: int) -> float:
    """Shortest wall time of ``repeats`` calls of fn() (the least disturbed run on a shared machine)."""
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def percentile(values: list[float], q: float) -> float:
    """q-th percentile (0..100) by linear interpolation, like numpy's default."""
    ordered = sorted(values)
    if len(ordered) == 1:
        return ordered[0]
    pos = (len(ordered) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


def median(values: list[float]) -> float:
    return statistics.median(values)


def machine() -> dict:
    """What the numbers were measured on (cores, CPU model, load at the start)."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def merge_results(update: dict) -> dict:
    """Read-modify-write bench/out/results.json: keys written by others (e.g. the load
    test's ``load_32_clients``) survive; ours are replaced."""
    OUT.mkdir(parents=True, exist_ok=True)
    try:
        current = json.loads(RESULTS.read_text())
    except (OSError, ValueError):
        current = {}
    current.update(update)
    tmp = RESULTS.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(current, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, RESULTS)
    return current


def prepare_model(log) -> tuple[Path, str]:
    """The model directory to benchmark and a note on where it came from.

    With torch installed, the shipped weights (``model/weights/space.pt``) are
    re-exported with the current code into bench/out/model, so the benchmark measures
    the sampler graph this checkout produces (and torch eager runs the same weights).
    Without torch, the shipped export itself.
    """
    space = SHIPPED_MODEL / "space.pt"
    try:
        import torch  # noqa: F401
    except ImportError:
        return SHIPPED_MODEL, "shipped export (torch absent: not re-exported)"
    if not space.is_file():
        return SHIPPED_MODEL, "shipped export (no space.pt to re-export)"
    target = OUT / "model"
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "model.export", str(space), str(target)], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        log(f"re-export failed, using the shipped export:\n{proc.stderr[-2000:]}")
        return SHIPPED_MODEL, "shipped export (re-export failed)"
    return target, f"model/weights/space.pt re-exported by this checkout in {time.perf_counter() - t:.1f} s"


def print_table(rows: list[tuple[str, str, str, str]]) -> None:
    """rows: (measure, value, reference / target, verdict)."""
    head = ("measure", "value", "against", "target")
    widths = [max(len(str(r[i])) for r in rows + [head]) for i in range(4)]
    line = "  ".join(f"{{:<{w}}}" for w in widths)
    print(line.format(*head))
    print(line.format(*("-" * w for w in widths)))
    for r in rows:
        print(line.format(*r))
