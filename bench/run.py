"""texspace benchmarks (``make bench``): how close the product gets to this machine.

    .venv/bin/python bench/run.py [--only NAME ...] [--quick]

Measures, in one run: the machine's float32 GEMM roofline for the decoder, the ONNX
sampler through worker/runtime (best chunk size and threads), the same weights in
PyTorch eager, cold and cached 256^2 tiles over HTTP on an embedded ``texspace serve``,
a map viewport of 16 cold tiles (idle, beside 4 volume jobs, zoomed out; bench/viewport.py),
the encode of a 1024^2 upload, a 256^3 volume (child process, peak RSS), a 2048^2
bake of a ~100k-face mesh without UVs, the shipped encoder on one 128^2 crop on one
thread and an upload's whole encode in process beside its encoder alone (``--only encode``
runs just these), and one score of a fit's probe
(bench/fit_probe.py). Every target is a ratio against a reference measured in the same
run, so the verdicts hold on a noisy shared machine. Prints a table and merges the
numbers into bench/out/results.json (other keys are kept).
"""
from __future__ import annotations

import argparse
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench import common, fit_probe, jobs, kernels, serving, viewport

SECTIONS = ("kernels", "http", "viewport", "volume", "bake", "encode", "fit")


def log(msg: str) -> None:
    print(msg, flush=True)


def measure(only: set[str], quick: bool) -> dict:
    results: dict = {"machine": common.machine(), "errors": {}}
    model_dir = config = None
    if only - {"encode", "fit"}:  # these time the shipped model's files: no re-export for them alone
        model_dir, note = common.prepare_model(log)
        results["model"] = {"dir": str(model_dir.relative_to(common.ROOT)), "source": note}
        config = kernels.model_config(model_dir)
    threads = max(1, min(2, results["machine"]["cores"] or 1))

    def section(name, fn):
        if name not in only:
            return
        log(f"[{name}]")
        t = time.perf_counter()
        try:
            fn()
        except Exception as exc:  # noqa: BLE001 - one broken section must not hide the others' numbers
            traceback.print_exc()
            results["errors"][name] = f"{type(exc).__name__}: {exc}"
        results.setdefault("section_seconds", {})[name] = round(time.perf_counter() - t, 1)

    def run_kernels():
        flops = kernels.decoder_flops_per_point(config)
        gemm = kernels.gemm_gflops(threads)
        log(f"  GEMM float32: {', '.join(f'{k} {v:.1f}' for k, v in gemm.items())} GFLOP/s; "
            f"decoder {flops} FLOP/point")
        sweep = kernels.sampler_sweep(model_dir, thread_options=(1, threads) if threads > 1 else (1,),
                                      chunks=(2048, 4096, 16384) if quick else kernels.CHUNKS, log=log)
        # GEMM again after the sampler: the roofline is the better of the two, so a
        # quiet moment of the shared machine never flatters the sampler's ratio.
        again = kernels.gemm_gflops(threads)
        log(f"  GEMM float32 again: {', '.join(f'{k} {v:.1f}' for k, v in again.items())} GFLOP/s")
        gemm = {k: max(v, again[k]) for k, v in gemm.items()}
        peak = max(gemm.values())
        results.update({
            "gemm_gflops": gemm, "decoder_flops_per_point": flops,
            "roofline_points_per_s": peak * 1e9 / flops,
            "sampler_points_per_s": sweep["best"]["points_per_s"],
            "sampler_best_setting": {k: sweep["best"][k] for k in ("threads", "chunk")},
            "sampler_max_points_per_s": sweep["best"]["max_points_per_s"],
            "sampler_default_points_per_s": sweep["default"]["points_per_s"],
            "sampler_grid": sweep["grid"],
        })
        passes = kernels.sampler_passes(model_dir / "sampler.onnx", sweep["best"]["chunk"])
        ns = kernels.elementwise_ns()
        floor = kernels.noise_floor(passes, ns, sweep["best"]["threads"])
        log(f"  noise and colour stage per point: {passes['bitwise_ops'] + passes['other_ops']:.0f} element-ops "
            f"({passes['bitwise_ops']:.0f} bitwise), {passes['bytes'] / 1e3:.1f} kB moved; one thread per element: "
            f"Add {ns['add']:.3f} ns, Xor {ns['xor']:.3f} ns -> floor {floor / 1e6:.2f} M points/s")
        results.update({"noise_passes_per_point": passes, "elementwise_ns": ns, "noise_floor_points_per_s": floor})
        eager = kernels.torch_eager(model_dir, threads, log=log)
        if eager is None:
            results["torch_eager_points_per_s"] = None
            results["torch_eager_note"] = "skipped: torch (the train extra) is not installed"
        else:
            results["torch_eager_points_per_s"] = eager["points_per_s"]
            results["torch_eager_setting"] = {k: eager[k] for k in ("batch", "threads")}
        colour = kernels.colour_stage_cost(model_dir, sweep["best"]["threads"], sweep["best"]["chunk"], log=log)
        if colour is not None:
            results["sampler_with_colour_points_per_s"] = colour["with_colour"]
            results["sampler_without_colour_points_per_s"] = colour["without_colour"]
        results["tile_256_render_in_process_s"] = serving.tile_in_process(model_dir)
        log(f"  tile 256^2 rendered in process (no HTTP, no PNG): {results['tile_256_render_in_process_s']:.3f} s")

    def run_http():
        results.update(serving.bench_http(model_dir, uploads=3 if quick else 7, cold_tiles=8 if quick else 24,
                                          log=log))

    def run_viewport():
        results["viewport"] = viewport.bench_viewport(model_dir, log=log)

    def run_volume():
        res = 128 if quick else 256
        v = jobs.bench_volume(model_dir, res, log=log)
        results[f"volume_{res}_s"], results[f"volume_{res}_peak_rss_mb"] = v["seconds"], v["peak_rss_mb"]

    def run_bake():
        results.update(jobs.bench_bake(model_dir, 1024 if quick else 2048, log=log))

    def run_encode():
        # The acceptance figure is for the shipped encoder.onnx through worker/runtime, one
        # intra-op thread. Reference: its multiply-adds at the 1-thread GEMM rate, measured
        # before and after (the better of the two, as for the sampler's roofline). Only
        # ONNX Runtime's MatMul is used: numpy's BLAS takes every core unless
        # OMP_NUM_THREADS says otherwise, so its figure is not a 1-thread one.
        flops = kernels.encoder_flops(common.SHIPPED_MODEL / "encoder.onnx")
        before = kernels.gemm_gflops(1)
        enc = kernels.encode_crop(common.SHIPPED_MODEL, log=log)
        after = kernels.gemm_gflops(1)
        gflops = max(before["onnxruntime_decoder_shape"], after["onnxruntime_decoder_shape"])
        log(f"  encoder {flops['total'] / 1e6:.1f} MFLOP per crop (Conv {flops['Conv'] / 1e6:.1f}, Gemm "
            f"{flops['Gemm'] / 1e6:.2f}, MatMul {flops['MatMul'] / 1e6:.2f}); GEMM float32 1 thread: "
            f"onnxruntime {before['onnxruntime_decoder_shape']:.1f} / {after['onnxruntime_decoder_shape']:.1f} "
            f"GFLOP/s (numpy, all BLAS threads: {before['numpy_1024']:.1f} / {after['numpy_1024']:.1f})")
        if enc["size"] != 128:
            raise ValueError(f"the target is for 128^2 crops; this encoder takes {enc['size']}^2")
        ms, reference_ms = enc["median_s"] * 1000, flops["total"] / (gflops * 1e9) * 1000
        results.update({
            "encode_128_ms": ms, "encode_128_all_ms": [round(t * 1000, 2) for t in enc["all_s"]],
            "encode_128_reference_ms": reference_ms, "encode_128_vs_gemm": ms / reference_ms,
            "encoder_flops": flops, "encode_gemm_gflops_1_thread": gflops,
            "encode_model": str(common.SHIPPED_MODEL.relative_to(common.ROOT)),
        })
        upload = kernels.encode_upload(common.SHIPPED_MODEL, log=log)
        results.update({"encode_upload_1024_s": upload["upload"], "encode_upload_mean_code_s": upload["mean_code"],
                        "encode_upload_quantile_table_s": upload["quantile_table"],
                        "encode_upload_crops_72_s": upload["crops_72"],
                        "encode_upload_crops_9_s": upload["crops_9"]})

    def run_fit():
        results.update(fit_probe.bench_probe(common.SHIPPED_MODEL / "space.pt", log=log))
        photo = common.ROOT / "data" / "textures" / "val" / "vpython_granite.png"  # (make data)
        results.update(fit_probe.bench_steps(common.SHIPPED_MODEL / "space.pt", photo, log=log))

    section("kernels", run_kernels)
    section("http", run_http)
    section("viewport", run_viewport)
    section("volume", run_volume)
    section("bake", run_bake)
    section("encode", run_encode)
    section("fit", run_fit)
    return results


def verdicts(r: dict) -> tuple[dict, list[tuple[str, str, str, str]]]:
    """Ratios against their targets, and the printed table's rows."""
    rows, ratios = [], {}
    sampler = r.get("sampler_points_per_s")

    def ratio(key, value, target, ok, measure, shown, against):
        ratios[key] = {"value": value, "target": target, "met": bool(ok)}
        rows.append((measure, shown, against, f"{target} {'MET' if ok else 'NOT MET'}"))

    if sampler and r.get("roofline_points_per_s"):
        x = sampler / r["roofline_points_per_s"]
        ratio("sampler_vs_roofline", x, ">= 0.5", x >= 0.5, "sampler points/s",
              f"{sampler / 1e6:.3f} M", f"{x:.2f} x roofline {r['roofline_points_per_s'] / 1e6:.2f} M")
    if sampler and r.get("roofline_points_per_s") and r.get("noise_floor_points_per_s"):
        # The decoder's GEMMs and the noise run one after the other on each chunk: the two
        # floors add up in time per point.
        floor, passes = r["noise_floor_points_per_s"], r["noise_passes_per_point"]
        limit = 1.0 / (1.0 / r["roofline_points_per_s"] + 1.0 / floor)
        rows.append(("noise floor (elementwise ops at an Add's cost)", f"{floor / 1e6:.3f} M",
                     f"{passes['bitwise_ops'] + passes['other_ops']:.0f} ops, {passes['bytes'] / 1e3:.1f} kB per point",
                     "-"))
        rows.append(("sampler vs GEMM roofline + noise floor", f"{sampler / 1e6:.3f} M",
                     f"{sampler / limit:.2f} x limit {limit / 1e6:.2f} M", "-"))
    if sampler and r.get("torch_eager_points_per_s"):
        x = sampler / r["torch_eager_points_per_s"]
        ratio("sampler_vs_torch_eager", x, ">= 3", x >= 3.0, "sampler vs torch eager",  # the ONNX graph must pay for itself
              f"{sampler / 1e6:.3f} M", f"{x:.2f} x torch {r['torch_eager_points_per_s'] / 1e6:.3f} M")
    if r.get("sampler_with_colour_points_per_s") and r.get("sampler_without_colour_points_per_s"):
        x = r["sampler_with_colour_points_per_s"] / r["sampler_without_colour_points_per_s"]
        ratio("colour_stage_cost", x, ">= 0.9", x >= 0.9, "sampler with colour stage",
              f"{r['sampler_with_colour_points_per_s'] / 1e6:.3f} M",
              f"{x:.2f} x without it {r['sampler_without_colour_points_per_s'] / 1e6:.3f} M")
    if sampler and "tile_256_cold_p50_s" in r:
        ref = 65536 / sampler
        x = r["tile_256_cold_p50_s"] / ref
        ratio("tile_cold_p50_vs_sampler", x, "<= 1.5", x <= 1.5, "tile 256^2 cold p50 (HTTP)",
              f"{r['tile_256_cold_p50_s']:.3f} s", f"{x:.2f} x sampler 65,536 pts {ref:.3f} s")
        rows.append(("tile 256^2 cold p95 (HTTP)", f"{r['tile_256_cold_p95_s']:.3f} s",
                     f"{r['tile_256_cold_p95_s'] / ref:.2f} x sampler", "-"))
    if "tile_cached_p50_s" in r:
        ms = r["tile_cached_p50_s"] * 1000
        ratio("tile_cached_p50_ms", ms, "< 5 ms", ms < 5, "tile cached p50 (HTTP)", f"{ms:.2f} ms", "absolute", )
    if "encode_p50_s" in r:
        rows.append(("encode 1024^2 upload p50 (HTTP)", f"{r['encode_p50_s']:.3f} s", "-", "-"))
    if "encode_even_p50_s" in r:
        rows.append(("encode 1024^2 upload, lighting=even, p50 (HTTP)", f"{r['encode_even_p50_s']:.3f} s",
                     f"{r['encode_even_p50_s'] / r['encode_p50_s']:.2f} x as-is", "-"))
    if "encode_upload_1024_s" in r:
        rows.append(("encode a 1024^2 upload, code chosen by style + colour table (in process, median)",
                     f"{r['encode_upload_1024_s'] * 1000:.0f} ms",
                     f"the crops' mean code instead {r['encode_upload_mean_code_s'] * 1000:.0f} ms; quantile curves "
                     f"always {r.get('encode_upload_quantile_table_s', float('nan')) * 1000:.0f} ms; encoder on its 72 "
                     f"crops {r['encode_upload_crops_72_s'] * 1000:.0f} ms; on the 9 as they lie "
                     f"{r['encode_upload_crops_9_s'] * 1000:.0f} ms", "-"))
    if "encode_128_ms" in r:
        ms, ref = r["encode_128_ms"], r["encode_128_reference_ms"]
        ratio("encode_128_ms", ms, "< 100 ms", ms < 100, "encode one 128^2 crop (1 thread, median)", f"{ms:.1f} ms",
              f"{ms / ref:.2f} x GEMM-bound {ref:.1f} ms ({r['encoder_flops']['total'] / 1e6:.0f} MFLOP at "
              f"{r['encode_gemm_gflops_1_thread']:.1f} GFLOP/s)")
    if "fit_probe_s" in r:
        x = r["fit_probe_s"] / r["fit_probe_batched_s"]
        ratio("fit_probe_vs_batched", x, "<= 1.0", x <= 1.0, "fit probe, 4 planes of 256 px (1 thread)",
              f"{r['fit_probe_s']:.2f} s", f"{x:.2f} x the same in one batch {r['fit_probe_batched_s']:.2f} s")
    if "fit_step_bf16_s" in r:
        x = r["fit_step_bf16_s"] / r["fit_step_fp32_s"]
        target = "<= 0.7" if r["fit_native_bf16"] else "(no native bf16: auto keeps fp32)"
        ratio("fit_step_bf16_vs_fp32", x, target, x <= 0.7 or not r["fit_native_bf16"],
              "fit step, 2 x 128 px, bf16 autocast (1 thread)", f"{r['fit_step_bf16_s']:.3f} s",
              f"{x:.2f} x float32 {r['fit_step_fp32_s']:.3f} s ({1 / r['fit_step_bf16_s']:.2f} vs "
              f"{1 / r['fit_step_fp32_s']:.2f} steps/s)")
    vp = r.get("viewport") or {}
    if "native_idle" in vp:
        last = vp["native_idle"]["last_s"]
        ratio("viewport_idle_last_s", last, "<= 1.0 s", last <= 1.0, "viewport 16 cold 256^2 tiles, idle: last",
              f"{last:.3f} s", f"p50 {vp['native_idle']['p50_s']:.3f} s, p95 {vp['native_idle']['p95_s']:.3f} s; "
              f"{last / vp['sampler_16_tiles_before_s']:.2f} x 16 tiles in process "
              f"{vp['sampler_16_tiles_before_s']:.3f} s")
    if "native_4_volumes" in vp:
        last = vp["native_4_volumes"]["last_s"]
        ratio("viewport_4_volumes_last_s", last, "<= 1.5 s", last <= 1.5,
              "viewport, 4 volume jobs 128^3 running: last", f"{last:.3f} s",
              f"{last / vp['native_idle']['last_s']:.2f} x idle; p50 {vp['native_4_volumes']['p50_s']:.3f} s")
    if "out2_progressive_cold" in vp:   # the default server: the target
        x = vp["out2_progressive_cold"]["last_s"] / vp["native_idle"]["last_s"]
        ratio("viewport_out2_progressive_vs_native", x, "<= 1.5", x <= 1.5,
              "viewport two zoom levels out, cold, progressive previews: last",
              f"{vp['out2_progressive_cold']['last_s']:.3f} s", f"{x:.2f} x native {vp['native_idle']['last_s']:.3f} s")
    if "out2_supersample_cold" in vp and "supersample_native_idle" in vp:   # opt-in exact mode: reported
        native = vp["supersample_native_idle"]["last_s"]
        rows.append(("viewport two zoom levels out, cold, supersample server: last",
                     f"{vp['out2_supersample_cold']['last_s']:.3f} s",
                     f"{vp['out2_supersample_cold']['last_s'] / native:.2f} x its native {native:.3f} s", "-"))
    if "out2_progressive_cold" in vp:
        exact_last = vp["out2_progressive_cold"]["exact_last_s"]
        rows.append(("viewport two zoom levels out, progressive: last exact tile", f"{exact_last:.3f} s",
                     f"{exact_last / vp['native_idle']['last_s']:.2f} x native", "-"))
    if "out1_from_children" in vp:
        rows.append(("viewport one level out over viewed tiles (from children): last",
                     f"{vp['out1_from_children']['last_s']:.3f} s", "no sampling", "-"))
    for res in (256, 128):
        key = f"volume_{res}_s"
        if sampler and key in r:
            ref = res ** 3 / sampler
            x = r[key] / ref
            ratio(f"volume_{res}_vs_sampler", x, "<= 1.3", x <= 1.3, f"volume {res}^3",
                  f"{r[key]:.2f} s", f"{x:.2f} x sampler {res ** 3:,} pts {ref:.2f} s")
            rss = r[f"volume_{res}_peak_rss_mb"]
            ratio(f"volume_{res}_peak_rss_mb", rss, "< 1024 MB", rss < 1024, f"volume {res}^3 peak RSS",
                  f"{rss:.0f} MB", "absolute")
    if "bake_2048_excl_xatlas_s" in r:
        # reference: the sampler on as many points as the bake has texels, timed in the bake section
        ref = r.get("bake_2048_sampler_s") or r["bake_2048_texels"] / sampler
        x = r["bake_2048_excl_xatlas_s"] / ref
        ratio("bake_vs_sampler", x, "<= 1.3", x <= 1.3, "bake excl. xatlas",
              f"{r['bake_2048_excl_xatlas_s']:.2f} s",
              f"{x:.2f} x sampler {r['bake_2048_texels']:,} texels {ref:.2f} s")
        rows.append(("bake total / xatlas", f"{r['bake_2048_s']:.2f} s", f"xatlas {r['bake_2048_xatlas_s']:.2f} s",
                     "-"))
        if "bake_2048_cpu_vs_sampler" in r:
            rows.append(("bake excl. xatlas, CPU seconds", f"{r['bake_2048_cpu_s']:.2f} s",
                         f"{r['bake_2048_cpu_vs_sampler']:.2f} x sampler {r['bake_2048_sampler_cpu_s']:.2f} s", "-"))
        if "bake_2048_repeat_atlas_s" in r:
            q = r["bake_2048_atlas_quality"]
            rows.append(("atlas utilisation / L2 stretch", f"{r['bake_2048_texel_utilisation']:.3f}",
                         f"stretch {q['stretch_l2']:.3f}", "-"))
            t = r["bake_2048_repeat_atlas_s"]
            ratio("bake_repeat_atlas_s", t, "< 1 s", t < 1.0, "repeated bake: atlas (cached)",
                  f"{t:.3f} s", f"bake {r['bake_2048_repeat_s']:.2f} s")
        if "bake_2048_triplanar_vs_solid" in r:
            rows.append(("triplanar bake excl. xatlas", f"{r['bake_2048_triplanar_excl_xatlas_s']:.2f} s",
                         f"{r['bake_2048_triplanar_vs_solid']:.2f} x the solid bake", "-"))
    return ratios, rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="+", choices=SECTIONS, help="run only these sections")
    parser.add_argument("--quick", action="store_true",
                        help="smaller sizes (volume 128^3, bake 1024^2), written to results-quick.json")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    results = measure(set(args.only or SECTIONS), args.quick)
    results["ratios"], rows = verdicts(results)
    results["bench_seconds"] = round(time.perf_counter() - started, 1)
    print()
    common.print_table(rows)
    print(f"\nmachine: {results['machine']['cpu']}, {results['machine']['cores']} cores, load at start "
          f"{results['machine']['load_average_at_start']}; {results['machine']['date_utc']}; "
          f"{results['bench_seconds']} s")
    if args.quick:
        common.RESULTS = common.OUT / "results-quick.json"
    common.merge_results(results)
    print(f"results: {common.RESULTS.relative_to(common.ROOT)}")
    return 1 if results["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
