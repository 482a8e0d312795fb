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


def test_noise_floor_rows_and_the_shipped_samplers_op_count():
    """The noise's own floor is reported beside the GEMM roofline; its bitwise op count is
    the hash's: 8 octaves x 8 corners x 2 xorshift rounds x (shift + xor) per point."""
    from bench.common import SHIPPED_MODEL
    from bench.kernels import noise_floor, sampler_passes

    passes = sampler_passes(SHIPPED_MODEL / "sampler.onnx", chunk=256)
    assert round(passes["bitwise_ops"]) == 8 * 8 * 2 * 2      # (+ the seeds' few, once per chunk)
    assert 1000 < passes["other_ops"] < 4000 and passes["bytes"] > 1000
    floor = noise_floor(passes, {"add": 0.14, "xor": 0.5}, threads=2)
    assert abs(floor - 2 / ((passes["bitwise_ops"] * 0.5 + passes["other_ops"] * 0.14) * 1e-9)) < 1
    _, rows = verdicts({"sampler_points_per_s": 2e6, "roofline_points_per_s": 3.5e6,
                        "noise_floor_points_per_s": floor, "noise_passes_per_point": passes})
    assert [row[0] for row in rows][1:] == ["noise floor (elementwise ops at an Add's cost)",
                                            "sampler vs GEMM roofline + noise floor"]


def test_fit_budget_means_each_run_over_its_seeds_against_the_reference():
    from bench.fit_budget import seed_means

    rows = [{"photo": "gravel", "run": "70 s bf16, every core", "reference": False, "style": s} for s in (2.0, 1.6, 2.1)]
    rows += [{"photo": "gravel", "run": "reference: 240 s fp32, 1 thread (before)", "reference": True, "style": s}
             for s in (1.9, 2.0)]
    rows += [{"photo": "granite", "run": "70 s bf16, every core", "reference": False, "style": 0.3}]
    means = {(m["photo"], m["run"]): m for m in seed_means(rows)}
    fast = means["gravel", "70 s bf16, every core"]
    assert fast["seeds"] == 3 and abs(fast["style"] - 1.9) < 1e-9
    assert abs(fast["vs_reference"] - 1.9 / 1.95) < 1e-9
    assert means["gravel", "reference: 240 s fp32, 1 thread (before)"]["vs_reference"] == 1.0
    assert means["granite", "70 s bf16, every core"]["vs_reference"] is None  # no reference for that photo


def test_the_upload_encode_is_timed_beside_its_encoder_alone():
    """``--only encode``'s upload row: encode_texture in process, against the same with the
    crops' mean code (no choice), with quantile curves always (no choice of curves) and the
    encoder on the same 72 crops and on the 9 as they lie, timed in turns in the same run."""
    from bench.common import SHIPPED_MODEL
    from bench.kernels import encode_upload

    lines = []
    times = encode_upload(SHIPPED_MODEL, side=256, repeats=1, log=lines.append)
    assert set(times) == {"upload", "mean_code", "quantile_table", "crops_72", "crops_9"}
    assert all(t > 0 for t in times.values())
    assert "mean code instead" in lines[0] and "its 72 crops" in lines[0] and "the 9 as they lie" in lines[0]
    assert "quantile curves always" in lines[0]
    _, rows = verdicts({"encode_upload_1024_s": times["upload"], "encode_upload_mean_code_s": times["mean_code"],
                        "encode_upload_quantile_table_s": times["quantile_table"],
                        "encode_upload_crops_72_s": times["crops_72"], "encode_upload_crops_9_s": times["crops_9"]})
    assert rows[0][0].startswith("encode a 1024^2 upload") and rows[0][3] == "-"
