"""Point-throughput benchmarks: the machine's GEMM roofline, the ONNX sampler through
worker/runtime, and the same weights in PyTorch eager mode; the encoder on one crop
against its own FLOP count."""
from __future__ import annotations

import json
import os
import time
from functools import partial
from pathlib import Path

import numpy as np

from bench.common import best_of, median

POINTS = 1 << 18                       # 3D points per throughput measurement
CHUNKS = (1024, 2048, 4096, 8192, 16384, 65536)


def bench_points(n: int = POINTS, seed: int = 0) -> np.ndarray:
    """(n, 3) float64 random 3D points in a 4-unit cube (1024 exemplar pixels a side)."""
    return np.random.default_rng(seed).random((n, 3)) * 4.0


def bench_code(code_size: int = 8) -> np.ndarray:
    return np.random.default_rng(1).standard_normal(code_size).astype(np.float32)


def decoder_flops_per_point(config: dict) -> int:
    """Multiply-adds x 2 of the decoder MLP per point (the code's share is per code, not per point)."""
    k, hidden, layers = config["n_octaves"], config["hidden"], config["n_hidden_layers"]
    inputs = k * 3 * (2 if config.get("nearest_input", True) else 1)
    if config.get("variant") == "oursP":
        inputs += config["dims"]
    return 2 * (inputs * hidden + (layers - 1) * hidden * hidden + hidden * 3)


def _one_op_session(op: str, inputs: list[tuple[str, list]], output_shape: list, proto: int, threads: int):
    """An ONNX Runtime session of one ``op`` node on ``inputs`` (name, shape), all of element
    type ``proto``, on ``threads`` intra-op threads that sleep when idle."""
    import onnxruntime as ort
    from onnx import helper

    graph = helper.make_graph([helper.make_node(op, [name for name, _ in inputs], ["out"])], op,
                              [helper.make_tensor_value_info(name, proto, shape) for name, shape in inputs],
                              [helper.make_tensor_value_info("out", proto, output_shape)])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def gemm_gflops(threads: int) -> dict:
    """float32 GEMM throughput measured now: numpy (BLAS, square 1024) and onnxruntime
    (MatMul of the decoder's own shape, 65536 x 128 @ 128 x 128); GFLOP/s each."""
    from onnx import TensorProto

    rng = np.random.default_rng(0)
    a = rng.standard_normal((1024, 1024), dtype=np.float32)
    b = rng.standard_normal((1024, 1024), dtype=np.float32)
    a @ b
    numpy_s = best_of(lambda: a @ b, 7)
    sess = _one_op_session("MatMul", [("x", [None, 128]), ("w", [128, 128])], [None, 128], TensorProto.FLOAT,
                           threads)
    x = rng.standard_normal((65536, 128), dtype=np.float32)
    w = rng.standard_normal((128, 128), dtype=np.float32)
    sess.run(None, {"x": x, "w": w})
    ort_s = best_of(lambda: sess.run(None, {"x": x, "w": w}), 7)
    return {"numpy_1024": 2 * 1024 ** 3 / numpy_s / 1e9, "onnxruntime_decoder_shape": 2 * 65536 * 128 * 128 / ort_s / 1e9}


# Nodes that only relabel a tensor's shape (ONNX Runtime reuses the buffer) or make
# constants: no pass over the points' data.
_NO_PASS = {"Reshape", "Unsqueeze", "Squeeze", "Shape", "Constant", "Range"}
_BITWISE = {"BitwiseXor", "BitwiseAnd", "BitwiseOr", "BitShift"}
_GEMM = {"Gemm", "MatMul"}


def noise_floor(passes: dict, ns: dict, threads: int) -> float:
    """Points/s the sampler's non-decoder work allows on ``threads`` threads if every
    element-op ran at the measured cost of an Add (bitwise ones at a Xor's): a floor for
    the noise's time, since most of its ops (casts, gathers, splits) cost more."""
    seconds = (passes["bitwise_ops"] * ns["xor"] + passes["other_ops"] * ns["add"]) * 1e-9
    return threads / seconds


def sampler_passes(path: Path, chunk: int = 2048) -> dict:
    """What the sampler graph does per point besides its decoder (the noise, its lattice
    transforms and the colour stage), from one run of ``chunk`` points with every
    intermediate tensor made an output (shapes inferred from the graph alone miss the
    data-dependent ones): element-ops (output elements of every node that passes over
    data, per point; bitwise ones apart, they cost ~3x an Add in ONNX Runtime) and bytes
    moved (inputs read + outputs written, per point). The decoder's nodes are left out:
    its GEMMs are the roofline's, and ONNX Runtime fuses its ReLUs into them."""
    import onnx
    import onnxruntime as ort

    model = onnx.load(str(path))
    listed = {o.name for o in model.graph.output}
    model.graph.output.extend(onnx.ValueInfoProto(name=name) for node in model.graph.node
                              for name in node.output if name and name not in listed)
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    dtypes = {"tensor(double)": np.float64, "tensor(float)": np.float32, "tensor(int64)": np.int64}
    feed = {i.name: np.zeros([d if isinstance(d, int) else (chunk if i.name == "points" else 1) for d in i.shape],
                             dtypes[i.type]) for i in session.get_inputs()}
    feed["points"] = bench_points(chunk)
    names = [o.name for o in session.get_outputs()]
    tensors = dict(zip(names, session.run(names, feed)))
    tensors.update(feed)
    tensors.update({init.name: onnx.numpy_helper.to_array(init) for init in model.graph.initializer})
    ops = {"bitwise": 0, "other": 0}
    nbytes = 0
    for node in model.graph.node:
        if node.op_type in _NO_PASS or node.op_type in _GEMM or "/decoder/" in node.name:
            continue
        kind = "bitwise" if node.op_type in _BITWISE else "other"
        ops[kind] += sum(tensors[name].size for name in node.output if name)
        nbytes += sum(tensors[name].nbytes for name in (*node.input, *node.output) if name in tensors)
    return {"bitwise_ops": ops["bitwise"] / chunk, "other_ops": ops["other"] / chunk, "bytes": nbytes / chunk}


def elementwise_ns(elements: int = 1 << 17) -> dict:
    """ONNX Runtime's cost per element on one thread, measured now: an Add of two float32
    tensors and a BitwiseXor of two uint32 tensors of ``elements`` elements (the size of
    the sampler's per-chunk temporaries)."""
    from onnx import TensorProto

    costs = {}
    for name, op, dtype, proto in (("add", "Add", np.float32, TensorProto.FLOAT),
                                   ("xor", "BitwiseXor", np.uint32, TensorProto.UINT32)):
        sess = _one_op_session(op, [("a", [elements]), ("b", [elements])], [elements], proto, 1)
        feed = {n: np.arange(elements).astype(dtype) for n in "ab"}
        sess.run(None, feed)
        costs[name] = best_of(lambda: sess.run(None, feed), 50) / elements * 1e9
    return costs


def encoder_flops(path: Path, size: int = 128) -> dict:
    """Multiply-adds x 2 of one [1, 3, size, size] image through an encoder ONNX graph,
    counted from the graph with shapes inferred for batch 1: Conv (2 x output elements x
    Cin/group x kh x kw), Gemm and MatMul (2 x M x N x K). Normalisation, activations and
    reductions are a few passes over the activations and are not counted."""
    import onnx
    from onnx import shape_inference

    model = onnx.load(str(path))
    for dim, value in zip(model.graph.input[0].type.tensor_type.shape.dim, (1, 3, size, size)):
        dim.ClearField("dim_param")
        dim.dim_value = value
    model = shape_inference.infer_shapes(model, strict_mode=True)
    shapes = {init.name: tuple(init.dims) for init in model.graph.initializer}
    for info in (*model.graph.input, *model.graph.value_info, *model.graph.output):
        dims = info.type.tensor_type.shape.dim
        if all(d.HasField("dim_value") for d in dims):
            shapes[info.name] = tuple(d.dim_value for d in dims)

    def shape(name: str, node) -> tuple[int, ...]:
        if name not in shapes:
            raise ValueError(f"{node.op_type} {node.name!r}: no static shape for {name!r}")
        return shapes[name]

    counts = {"Conv": 0, "Gemm": 0, "MatMul": 0}
    for node in model.graph.node:
        if node.op_type == "Conv":
            weight = shape(node.input[1], node)  # [Cout, Cin / group, kh, kw]
            counts["Conv"] += 2 * int(np.prod(shape(node.output[0], node))) * int(np.prod(weight[1:]))
        elif node.op_type == "Gemm":
            trans = {a.name: a.i for a in node.attribute if a.name in ("transA", "transB")}
            b = shape(node.input[1], node)
            n, k = b if trans.get("transB") else b[::-1]
            # the input's shape is not always inferred (the colour-blind encoder's Concat of
            # features and zeroed statistics); its rows are then the batch of one crop
            a = shapes.get(node.input[0], (k, 1) if trans.get("transA") else (1, k))
            m = a[1] if trans.get("transA") else a[0]
            counts["Gemm"] += 2 * m * n * k
        elif node.op_type == "MatMul":
            k = shape(node.input[0], node)[-1]
            counts["MatMul"] += 2 * int(np.prod(shape(node.output[0], node))) * k
    return {"total": sum(counts.values()), **counts}


def encode_crop(model_dir: Path, repeats: int = 41, warmup: int = 5, log=print) -> dict:
    """worker/runtime's ``ModelRuntime.encode`` (the upload path's encoder session) on one
    [1, 3, S, S] crop, 1 intra-op thread: wall time of each of ``repeats`` calls after
    ``warmup`` calls. Returns the median and all times in seconds, and S."""
    from worker.runtime import ModelRuntime

    runtime = ModelRuntime(model_dir, threads=1)
    size = runtime.input_size
    crop = np.random.default_rng(2).uniform(-1, 1, (1, 3, size, size)).astype(np.float32)
    for _ in range(warmup):
        runtime.encode(crop)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        runtime.encode(crop)
        times.append(time.perf_counter() - t)
    log(f"  encode {size}^2 crop, 1 thread: median {median(times) * 1000:.1f} ms, min {min(times) * 1000:.1f} ms "
        f"over {repeats} (after {warmup} warm-up)")
    return {"median_s": median(times), "all_s": times, "size": size}


def encode_upload(model_dir: Path, side: int = 1024, repeats: int = 9, log=print) -> dict:
    """What an upload's encode costs (``worker.encode.encode_texture``: the working photo, its
    crops in eight orientations, the encoder, the choice of code by style, the colour table)
    for a ``side``^2 photo, against the same without the choice (the crops' mean code and its
    colour table), the same choice of code with quantile curves always (no choice of curves),
    and the encoder alone on the same 72 crops and on the 9 as they lie (the upload's crops
    before their orientations), each in the same run, default threads. Returns medians in
    seconds."""
    from unittest.mock import patch

    from worker import encode
    from worker.colour_match import calibrate_texture
    from worker.encode import encode_image, encode_texture
    from worker.photo import encoder_crops, working_photo
    from worker.runtime import ModelRuntime

    runtime = ModelRuntime(model_dir)
    rng = np.random.default_rng(3)  # smooth blobs over fine grain: a photo-like spread of scales
    coarse = rng.random((side // 32, side // 32, 3)).repeat(32, 0).repeat(32, 1)
    photo = np.clip(0.6 * coarse + 0.4 * rng.random((side, side, 3)), 0, 1).astype(np.float32)
    crops = encoder_crops(photo, short_side=runtime.short_side, size=runtime.input_size)
    as_they_lie = encoder_crops(photo, short_side=runtime.short_side, size=runtime.input_size, dihedral=False)

    def mean_code():
        working = working_photo(photo, runtime.short_side)
        return calibrate_texture(runtime.sampler, encode_image(runtime, working), working)

    def quantile_table():  # nearer_curves(runtime, working, code, target, quantile, distance): the quantile one
        with patch.object(encode, "nearer_curves", lambda *args: args[4]):
            return encode_texture(runtime, photo)

    times: dict[str, list[float]] = {"upload": [], "mean_code": [], "quantile_table": [], "crops_72": [],
                                     "crops_9": []}
    calls = {"upload": lambda: encode_texture(runtime, photo), "mean_code": mean_code,
             "quantile_table": quantile_table,
             "crops_72": lambda: runtime.encode(crops), "crops_9": lambda: runtime.encode(as_they_lie)}
    for call in calls.values():
        call()  # warm-up
    for _ in range(repeats):  # in turns, so a slow spell falls on all of them
        for name, call in calls.items():
            t = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - t)
    result = {name: median(values) for name, values in times.items()}
    log(f"  encode a {side}^2 upload (code chosen by style + colour table): median {result['upload'] * 1000:.0f} ms; "
        f"the crops' mean code instead {result['mean_code'] * 1000:.0f} ms; quantile curves always "
        f"{result['quantile_table'] * 1000:.0f} ms; encoder on its {len(crops)} crops "
        f"{result['crops_72'] * 1000:.0f} ms, on the {len(as_they_lie)} as they lie {result['crops_9'] * 1000:.0f} ms")
    return result


def sampler_sweep(model_dir: Path, thread_options=(1, 2), chunks=CHUNKS, log=print) -> dict:
    """sampler.onnx through worker/runtime.SamplerSession over chunk sizes and threads.

    Returns {"best": {...}, "default": {...}, "grid": [...]}: points/s of each setting.
    """
    from worker.runtime import DEFAULT_CHUNK, SamplerSession

    points, code = bench_points(), bench_code()
    grid = []
    for threads in thread_options:
        session = SamplerSession(model_dir / "sampler.onnx", threads=threads)
        session.sample(points[:4096], code, 0)
        for chunk in chunks:
            session.chunk = chunk
            seconds = best_of(partial(session.sample, points, code, 7), 2)
            grid.append({"threads": threads, "chunk": chunk, "points_per_s": len(points) / seconds})
            log(f"  sampler threads={threads} chunk={chunk:6d}: {len(points) / seconds / 1e6:.3f} M points/s")
    best = dict(max(grid, key=lambda g: g["points_per_s"]))
    # The maximum over a noisy grid is an outlier; the reference for the product's
    # timings is the best setting's median over more runs.
    session = SamplerSession(model_dir / "sampler.onnx", threads=best["threads"], chunk=best["chunk"])
    runs = [len(points) / best_of(lambda: session.sample(points, code, 7), 1) for _ in range(7)]
    best["max_points_per_s"], best["points_per_s"] = best["points_per_s"], float(np.median(runs))
    log(f"  sampler best setting threads={best['threads']} chunk={best['chunk']}: median of 7 "
        f"{best['points_per_s'] / 1e6:.3f} M points/s (max in sweep {best['max_points_per_s'] / 1e6:.3f})")
    default_threads = os.cpu_count() or 1
    default = next((g for g in grid if g["threads"] == min(default_threads, max(thread_options))
                    and g["chunk"] == DEFAULT_CHUNK), best)
    return {"best": best, "default": default, "grid": grid}


def torch_eager(model_dir: Path, threads: int, log=print) -> dict | None:
    """TextureSpace.sample (model/networks.py) on CPU, no_grad, same points and code.

    The research code's way: one forward per batch of points. Best over a few batch sizes.
    None when torch (the ``train`` extra) is absent.
    """
    try:
        import torch
    except ImportError:
        return None
    from model.networks import load_checkpoint

    torch.set_num_threads(threads)
    model, _ = load_checkpoint(model_dir / "space.pt")
    points = torch.from_numpy(bench_points())
    code = torch.from_numpy(bench_code(model.cfg.code_size))[None]
    results = {}
    with torch.no_grad():
        for batch in (16384, 65536):
            run = partial(_torch_batches, model, points, code, batch)
            run()
            seconds = best_of(run, 2)
            results[batch] = len(points) / seconds
            log(f"  torch eager batch={batch:6d}: {results[batch] / 1e6:.3f} M points/s")
    batch = max(results, key=results.get)
    return {"points_per_s": results[batch], "batch": batch, "threads": threads}


def _torch_batches(model, points, code, batch: int) -> None:
    for start in range(0, len(points), batch):
        model.sample(points[None, start:start + batch], code, 7)


def model_config(model_dir: Path) -> dict:
    manifest = json.loads((model_dir / "manifest.json").read_text())
    return manifest.get("config") or {"n_octaves": 8, "hidden": 128, "n_hidden_layers": 4,
                                      "nearest_input": True, "variant": manifest["variant"], "dims": 3}


def colour_stage_cost(model_dir: Path, threads: int, chunk: int, rounds: int = 5, log=print) -> dict | None:
    """The sampler with its colour stage against the same weights exported without it.

    The budget: the colour table may cost the sampler at most 10% (every tile pays it). Both graphs run
    through worker/runtime at the same setting, alternated ``rounds`` times so a change in
    the shared machine's load hits both; returns their medians. None without torch.
    """
    try:
        import torch
    except ImportError:
        return None
    import tempfile

    from model.export import _export
    from model.networks import load_checkpoint
    from worker.runtime import SamplerSession

    class RawSampler(torch.nn.Module):  # Contract 1 before the colour stage (points, z, seed -> rgb)
        def __init__(self, field):
            super().__init__()
            self.field = field

        def forward(self, points, z, seed):
            return self.field(points.reshape(z.shape[0], -1, 3), z, seed.reshape([])).reshape(-1, 3)

    model, _ = load_checkpoint(model_dir / "space.pt")
    points, code = bench_points(), bench_code()
    with tempfile.TemporaryDirectory() as tmp:
        raw_path = Path(tmp) / "sampler.onnx"
        _export(RawSampler(model.field), (torch.rand(64, 3, dtype=torch.float64), torch.zeros(1, 8),
                                          torch.tensor(0)), raw_path, ["points", "z", "seed"], ["rgb"],
                {"points": {0: "P"}, "z": {0: "R"}, "rgb": {0: "P"}})
        sessions = {"with_colour": SamplerSession(model_dir / "sampler.onnx", threads=threads, chunk=chunk),
                    "without_colour": SamplerSession(raw_path, threads=threads, chunk=chunk)}
        times: dict[str, list[float]] = {name: [] for name in sessions}
        for session in sessions.values():
            session.sample(points[:4096], code, 0)
        for _ in range(rounds):
            for name, session in sessions.items():
                times[name].append(best_of(partial(session.sample, points, code, 7), 1))
    rates = {name: len(points) / float(np.median(t)) for name, t in times.items()}
    log(f"  colour stage: with {rates['with_colour'] / 1e6:.3f} / without {rates['without_colour'] / 1e6:.3f} "
        f"M points/s (median of {rounds}, alternated)")
    return rates
