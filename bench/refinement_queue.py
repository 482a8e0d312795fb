"""Uploads refined at once (``make bench-refine``; not part of ``make test``): N photos posted
together to a fresh ``texspace serve`` (the embedded default: one worker, one fit lane), then
each texture followed until its refinement ends.

    .venv/bin/python bench/refinement_queue.py [--photos DIR] [--count 4] [--seconds S]

Prints, per upload, the seconds from its upload to its first refined tiles (``sampler``
becomes ``interim``, or ``fitted`` when no interim came) and to its final fitted sampler, the
estimates the texture gave right after its upload, and the medians; merges them into
bench/out/results.json under ``refinement_queue``. The reference, measured in the same run:
one upload alone, before the others (its interim and its final).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script (``python bench/refinement_queue.py``)

from bench.common import merge_results  # noqa: E402
from bench.load import serve  # noqa: E402

POLL_SECONDS = 0.5


def upload(base: str, photo: Path) -> dict:
    """POST one photo; the texture as answered, with the time it was accepted."""
    with httpx.Client(base_url=base, timeout=120) as http:
        res = http.post("/v1/textures", files={"image": (photo.name, photo.read_bytes())}, data={"name": photo.stem})
        res.raise_for_status()
        return {**res.json(), "uploaded_at": time.monotonic()}


def follow(base: str, textures: list[dict], timeout: float) -> list[dict]:
    """Poll every texture until its refinement ends; per texture the seconds to its interim
    (or first fitted tiles) and to its final sampler."""
    rows = [{"name": t["name"], "id": t["id"], "uploaded_at": t["uploaded_at"], "first_s": None, "final_s": None,
             "estimate": (t.get("refinement") or {})} for t in textures]
    deadline = time.monotonic() + timeout
    with httpx.Client(base_url=base, timeout=30) as http:
        while time.monotonic() < deadline and any(r["final_s"] is None for r in rows):
            for row in rows:
                if row["final_s"] is not None:
                    continue
                texture = http.get(f"/v1/textures/{row['id']}").json()
                now = time.monotonic() - row["uploaded_at"]
                if texture["sampler"] != "encoder" and row["first_s"] is None:
                    row["first_s"] = now
                if texture["sampler"] == "fitted" or texture["refinement"]["state"] in ("failed", "canceled"):
                    row["final_s"], row["state"] = now, texture["refinement"]["state"]
            time.sleep(POLL_SECONDS)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", type=Path, default=ROOT / "data" / "textures" / "val", help="folder of photos")
    parser.add_argument("--count", type=int, default=4, help="uploads posted at once")
    parser.add_argument("--seconds", type=float, help="TEXSPACE_FIT_SECONDS (default: the service's)")
    parser.add_argument("--timeout", type=float, default=1200.0)
    args = parser.parse_args(argv)
    photos = sorted(args.photos.glob("*.png"))[: args.count + 1]
    if len(photos) < args.count + 1:
        raise SystemExit(f"need {args.count + 1} photos in {args.photos} (make data)")
    env = {"TEXSPACE_AUTO_FIT": "true", "TEXSPACE_LOG_LEVEL": "WARNING"}
    if args.seconds:
        env["TEXSPACE_FIT_SECONDS"] = str(args.seconds)
    with serve(env) as base:
        alone = follow(base, [upload(base, photos[0])], args.timeout)[0]  # the reference: one upload, idle
        with ThreadPoolExecutor(args.count) as pool:
            textures = list(pool.map(lambda p: upload(base, p), photos[1:]))
        rows = follow(base, textures, args.timeout)
    for row in [alone, *rows]:
        est = row["estimate"]
        print(f"{row['name']:32s} first refined tiles {row['first_s'] or float('nan'):6.1f} s (estimated "
              f"{est.get('interim_eta_seconds') or float('nan'):6.1f}), final {row['final_s'] or float('nan'):6.1f} s "
              f"(estimated {est.get('final_eta_seconds') or float('nan'):6.1f}), queue position {est.get('queue_position')}")
    firsts = sorted(r["first_s"] for r in rows if r["first_s"] is not None)
    finals = sorted(r["final_s"] for r in rows if r["final_s"] is not None)
    summary = {"count": args.count, "fit_seconds": args.seconds, "alone_first_s": alone["first_s"],
               "alone_final_s": alone["final_s"], "worst_first_s": max(firsts, default=None),
               "worst_final_s": max(finals, default=None),
               "rows": [{k: v for k, v in r.items() if k != "uploaded_at"} for r in rows]}
    print(f"{args.count} at once: last first refined tiles {summary['worst_first_s']:.1f} s (target <= 90 s), last "
          f"final {summary['worst_final_s']:.1f} s (target <= 360 s); one alone: {alone['first_s']:.1f} s / "
          f"{alone['final_s']:.1f} s")
    merge_results({"refinement_queue": summary})
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
