"""The load benchmark itself (``bench/load.py``, run in full by ``make bench``) works: a
short run with few clients against a real server has no errors, loses no job, and
merges its numbers into the results file without dropping other keys."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]


def test_load_benchmark_short_run(tmp_path: Path) -> None:
    out = tmp_path / "results.json"
    out.write_text(json.dumps({"someone_else": {"kept": True}}))
    # a queue of 1 makes back-pressure likely: 503 + Retry-After is counted apart, never as an error
    proc = subprocess.run([sys.executable, "bench/load.py", "--clients", "4", "--seconds", "4", "--out", str(out),
                           "--max-queued-jobs", "1"], cwd=ROOT, capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    results = json.loads(out.read_text())
    assert results["someone_else"] == {"kept": True}
    load = results["load_4_clients"]
    assert load["errors"] == 0 and load["requests"] > 0 and load["requests_per_second"] > 0
    assert load["p95_ms"] >= load["p50_ms"] > 0
    assert set(load["by_kind"]) >= {"tile_cached", "tile_cold"}
    assert load["jobs_final_states"].get("succeeded", 0) == load["jobs_accepted"]


def test_the_mix_moves_the_upload_share_to_cached_tiles() -> None:
    from bench.load import MIX, mix
    for share in (0.0, 0.05):
        weights = dict(zip(*mix(share)))
        assert weights["upload"] == share and sum(weights.values()) == pytest.approx(1.0)
        assert {k: v for k, v in weights.items() if k not in ("upload", "tile_cached")} == {
            k: v for k, v in MIX if k not in ("upload", "tile_cached")}
