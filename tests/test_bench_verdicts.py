"""``make bench``'s verdict table (``bench/run.py: verdicts``): every section's targets are
judged from one results dict, whichever sections ran together."""
from __future__ import annotations

from bench.run import verdicts

VIEWPORT = {"sampler_16_tiles_before_s": 0.58,
            "native_idle": {"last_s": 0.65, "p50_s": 0.37, "p95_s": 0.64},
            "native_4_volumes": {"last_s": 0.86, "p50_s": 0.52},
            "out2_progressive_cold": {"last_s": 0.68, "exact_last_s": 10.4},
            "supersample_native_idle": {"last_s": 0.58},
            "out2_supersample_cold": {"last_s": 8.5},
            "out1_from_children": {"last_s": 0.13}}
BAKE = {"bake_2048_s": 9.9, "bake_2048_xatlas_s": 8.4, "bake_2048_excl_xatlas_s": 1.54,
        "bake_2048_texels": 2_495_004, "bake_2048_sampler_s": 1.25, "bake_2048_cpu_s": 2.85,
        "bake_2048_cpu_vs_sampler": 1.16, "bake_2048_sampler_cpu_s": 2.45,
        "bake_2048_texel_utilisation": 0.595, "bake_2048_atlas_quality": {"stretch_l2": 1.014},
        "bake_2048_repeat_atlas_s": 0.004, "bake_2048_repeat_s": 1.56}


def test_every_section_gets_its_verdicts_together():
    results = {"sampler_points_per_s": 1.87e6, "roofline_points_per_s": 3.56e6,
               "torch_eager_points_per_s": 0.44e6, "volume_256_s": 8.4, "volume_256_peak_rss_mb": 140,
               "viewport": VIEWPORT, **BAKE}
    ratios, rows = verdicts(results)
    assert {"sampler_vs_roofline", "sampler_vs_torch_eager", "viewport_idle_last_s", "viewport_4_volumes_last_s",
            "viewport_out2_progressive_vs_native", "volume_256_vs_sampler", "bake_vs_sampler",
            "bake_repeat_atlas_s"} <= set(ratios)
    assert all(r["met"] for r in ratios.values())
    assert abs(ratios["bake_vs_sampler"]["value"] - 1.54 / 1.25) < 1e-9
    # the opt-in supersample server is reported, not judged: its exact tiles cost 16x by design
    assert "viewport_out2_supersample_vs_native" not in ratios
    assert any("supersample" in row[0] and row[3] == "-" for row in rows)


def test_a_missed_target_is_reported_as_missed():
    ratios, rows = verdicts({**BAKE, "bake_2048_excl_xatlas_s": 1.70})
    assert ratios["bake_vs_sampler"]["met"] is False
    assert any(row[0] == "bake excl. xatlas" and row[3].endswith("NOT MET") for row in rows)
