"""Export a checkpoint to the portable model directory (docs/ARCHITECTURE.md).

    python -m model.export CHECKPOINT [OUTDIR]      # OUTDIR defaults to model/weights/

writes ``encoder.onnx``, ``sampler.onnx`` (docs/ARCHITECTURE.md, Contract 1), ``style.onnx`` (the
VGG16 statistics an upload chooses its code by) and ``manifest.json``.
The sampler graph holds the hash noise itself, so any ONNX runtime reproduces a texture
from (z, seed) without our code.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import tempfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch
from torch import nn

from model.colour import KNOTS, apply_colour, colour_size, identity_colour
from model.losses import default_layer_weights, gram_matrix
from model.networks import TextureField, TextureSpace, load_checkpoint
from model.vgg import VGG16Features
from worker.contract import STYLE_FEATURES, TILEABLE_SAMPLER

OPSET = 18  # BitwiseAnd / BitwiseXor need 18; onnxruntime 1.31 reads it
MAX_IR_VERSION = 13  # onnxruntime 1.31 refuses newer IR
DEFAULT_OUTDIR = Path(__file__).resolve().parent / "weights"
ENCODER_INPUT_SIZE = 128
ENCODER_INPUT_RANGE = [-1.0, 1.0]
_SHIFT_DOMAIN = "texspace"  # placeholder op domain, gone from the written file


def _register_bitwise_symbolics() -> None:
    """Teach the TorchScript exporter the ONNX 18 bitwise ops it does not map itself.

    (Right shifts are model/noise.py's own autograd Function, whose ``symbolic`` writes
    the placeholder ShiftRight node that ``_hash_in_uint32`` replaces.)"""
    from torch.onnx import register_custom_op_symbolic

    def xor(g, a, b):
        return g.op("BitwiseXor", a, b)

    def and_(g, a, b):
        return g.op("BitwiseAnd", a, b)

    register_custom_op_symbolic("aten::bitwise_xor", xor, OPSET)
    register_custom_op_symbolic("aten::bitwise_and", and_, OPSET)


# Ops whose result depends on reading an int32 as signed: none may touch the hash.
_SIGNED_OPS = {"Less", "Greater", "LessOrEqual", "GreaterOrEqual", "Div", "Mod", "Min", "Max", "Abs", "Neg", "Sign"}


def _hash_in_uint32(graph) -> None:
    """Run the noise hash in uint32: every int32 tensor becomes uint32, and each
    placeholder ShiftRight(x, bits) becomes one ONNX BitShift.

    The noise (model/noise.py) holds 32-bit patterns in int32 because torch has no
    usable uint32; every op it applies to them (Add, Mul, BitwiseXor, Equal, Where,
    casts from int64) gives the same bits read as uint32, its casts to float read the
    bits unsigned (``_UnsignedToFloat`` in torch, a plain Cast here), and its right
    shifts are logical, which is what the uint32 BitShift does. ONNX BitShift takes
    unsigned types only; as uint32 the shifts need no casts around them, and the graph
    none of the 5 casts per mix32 it needed.
    """
    from onnx import TensorProto, helper, numpy_helper, shape_inference

    g = graph.graph
    typed = shape_inference.infer_shapes(graph).graph
    int32 = {v.name for v in list(typed.value_info) + list(typed.input) + list(typed.output)
             if v.type.tensor_type.elem_type == TensorProto.INT32}
    int32 |= {t.name for t in g.initializer if t.data_type == TensorProto.INT32}
    for node in g.node:
        if node.op_type in _SIGNED_OPS and int32.intersection(node.input):
            raise ValueError(f"{node.op_type} {node.name} reads an int32 hash value as signed")

    def unsigned(tensor):
        return numpy_helper.from_array(numpy_helper.to_array(tensor).view(np.uint32), tensor.name)

    for i, init in enumerate(g.initializer):
        if init.data_type == TensorProto.INT32:
            g.initializer[i].CopyFrom(unsigned(init))
    for info in list(g.value_info) + list(g.input) + list(g.output):
        if info.type.tensor_type.elem_type == TensorProto.INT32:
            info.type.tensor_type.elem_type = TensorProto.UINT32
    nodes = []
    for node in g.node:
        for attr in node.attribute:
            if node.op_type == "Cast" and attr.name == "to" and attr.i == TensorProto.INT32:
                attr.i = TensorProto.UINT32
            if node.op_type == "Constant" and attr.name == "value" and attr.t.data_type == TensorProto.INT32:
                attr.t.CopyFrom(unsigned(attr.t))
        if node.domain != _SHIFT_DOMAIN:
            nodes.append(node)
            continue
        bits = next(a.i for a in node.attribute if a.name == "bits")
        amount = numpy_helper.from_array(np.array(bits, dtype=np.uint32), f"{node.output[0]}_bits")
        g.initializer.append(amount)
        nodes.append(helper.make_node("BitShift", [node.input[0], amount.name], [node.output[0]], direction="RIGHT"))
    del g.node[:]
    g.node.extend(nodes)
    kept = [o for o in graph.opset_import if o.domain != _SHIFT_DOMAIN]
    del graph.opset_import[:]
    graph.opset_import.extend(kept)


class SamplerGraph(nn.Module):
    """Contract 1 around a TextureField.

    points float64 [P,3], z float32 [P,8] or [1,8], seed int64 [] or [1],
    colour float32 [P,K] or [1,K] (model/colour.py)  ->  rgb float32 [P,3]
    A shared code is one row evaluated for all P points; per-point codes are P rows of
    one point each. ``reshape(rows, -1, 3)`` covers both with one graph. The colour
    table's rows are independent of z's: the raw colours are regrouped by the table's
    rows before it is applied (``_coloured``), so all four combinations give [P,3], and
    the same pixels, since the colour stage is exact per point.
    """

    def __init__(self, field: TextureField):
        super().__init__()
        self.field = field

    def forward(self, points, z, seed, colour):
        raw = self.field(points.reshape(z.shape[0], -1, 3), z, seed.reshape([]))
        return _coloured(raw, colour)


class TileableSamplerGraph(SamplerGraph):
    """Contract 1 plus ``period`` float64 [] (world units): the same texture made periodic
    in x and y with that period (``TextureField.periodic_lattice``), for tileable images."""

    def forward(self, points, z, seed, colour, period):
        raw = self.field(points.reshape(z.shape[0], -1, 3), z, seed.reshape([]), period=period.reshape([]))
        return _coloured(raw, colour)


def _coloured(raw: torch.Tensor, colour: torch.Tensor) -> torch.Tensor:
    """Raw colours [R, P/R, 3] (R rows of z) coloured by tables [T, K] (T = 1 or P) -> [P, 3].

    Regrouped as [T, P/T, 3] first: with the tables' own row count the stage broadcasts
    one table over all points or pairs table i with point i, whatever z's rows were
    (applied in z's grouping, a shared z with per-point tables broadcast to P x P rows).
    """
    return apply_colour(raw.reshape(colour.shape[0], -1, 3), colour).reshape(-1, 3)


# Dynamic axes of both samplers: z and colour rows are named apart (1 or P each, chosen
# independently); one shared name let ONNX Runtime assume them equal and reuse one's buffer
# for the other.
_SAMPLER_AXES = {"points": {0: "P"}, "z": {0: "code_rows"}, "colour": {0: "colour_rows"}, "rgb": {0: "P"}}


def _export(module: nn.Module, args: tuple, path: Path, input_names, output_names, dynamic_axes):
    import onnx

    _register_bitwise_symbolics()
    module.eval()
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "graph.onnx"
        with torch.no_grad():
            torch.onnx.export(
                module,
                args,
                str(raw),
                input_names=input_names,
                output_names=output_names,
                dynamic_axes=dynamic_axes,
                opset_version=OPSET,
                dynamo=False,
                do_constant_folding=True,
            )
        graph = onnx.load(str(raw))
    _hash_in_uint32(graph)
    if graph.ir_version > MAX_IR_VERSION:
        graph.ir_version = MAX_IR_VERSION
    graph.producer_name = "texspace"
    graph.doc_string = ""
    onnx.checker.check_model(graph)
    tmp_path = path.with_suffix(".onnx.tmp")
    onnx.save(graph, str(tmp_path))
    os.replace(tmp_path, path)


def export_sampler(field: TextureField, path: Path) -> None:
    points = torch.rand(64, 3, dtype=torch.float64)
    z = torch.zeros(1, field.cfg.code_size)
    seed = torch.tensor(0, dtype=torch.int64)
    colour = identity_colour(KNOTS)[None]
    _export(
        SamplerGraph(field),
        (points, z, seed, colour),
        path,
        ["points", "z", "seed", "colour"],
        ["rgb"],
        _SAMPLER_AXES,
    )


def export_tileable_sampler(field: TextureField, path: Path) -> None:
    points = torch.rand(64, 3, dtype=torch.float64)
    z = torch.zeros(1, field.cfg.code_size)
    seed = torch.tensor(0, dtype=torch.int64)
    colour = identity_colour(KNOTS)[None]
    period = torch.tensor(4.0, dtype=torch.float64)
    _export(
        TileableSamplerGraph(field),
        (points, z, seed, colour, period),
        path,
        ["points", "z", "seed", "colour", "period"],
        ["rgb"],
        _SAMPLER_AXES,
    )


#: the VGG16 layers of the style vector (``StyleGraph``): the Gram loss's first four. relu5_1
#: would add 7.1 M weights to the 2.9 M these need, for a small part of the choice (docs/DECISIONS.md)
STYLE_LAYERS = ("relu1_1", "relu2_1", "relu3_1", "relu4_1")


class StyleGraph(nn.Module):
    """sRGB images (N, 3, H, W) in 0..1 -> style vectors (N, D): each layer's Gram
    (``model.losses.gram_matrix``), flattened and scaled by sqrt(weight / C^2) with the Gram
    loss's own layer weights, so the squared distance between two rows is ``gram_loss``
    between the images (over ``STYLE_LAYERS``). An upload picks its code by it
    (``worker.encode``) with no torch in the worker."""

    def __init__(self, layers: tuple[str, ...] = STYLE_LAYERS):
        super().__init__()
        self.vgg = VGG16Features(layers)
        weights = default_layer_weights(layers)
        self.scales = {name: float(np.sqrt(weights[name])) for name in layers}

    def forward(self, images):
        features = self.vgg(images)
        return torch.cat([gram_matrix(value).flatten(1) * (self.scales[name] / value.shape[1])
                          for name, value in features.items()], dim=1)


def export_style(path: Path) -> None:
    """``StyleGraph`` as ONNX, its conv kernels stored in float16 (half the bytes; the graph casts
    them back once, when a runtime loads it, and computes in float32)."""
    import onnx
    from onnx import numpy_helper

    _export(StyleGraph(), (torch.rand(1, 3, 64, 64),), path, ["image"], ["style"],
            {"image": {0: "N", 2: "H", 3: "W"}, "style": {0: "N"}})
    graph = onnx.load(str(path))
    casts = []
    for init in graph.graph.initializer:
        values = numpy_helper.to_array(init)
        if values.dtype != np.float32 or values.ndim != 4:  # the conv kernels; biases stay float32
            continue
        name = init.name
        init.CopyFrom(numpy_helper.from_array(values.astype(np.float16), name + "_f16"))
        casts.append(onnx.helper.make_node("Cast", [name + "_f16"], [name], to=onnx.TensorProto.FLOAT))
    nodes = casts + list(graph.graph.node)
    del graph.graph.node[:]
    graph.graph.node.extend(nodes)
    onnx.checker.check_model(graph)
    onnx.save(graph, str(path))


def export_encoder(model: TextureSpace, path: Path) -> None:
    image = torch.zeros(2, 3, ENCODER_INPUT_SIZE, ENCODER_INPUT_SIZE)
    _export(model.encoder, (image,), path, ["image"], ["z"], {"image": {0: "N"}, "z": {0: "N"}})


def model_version(*files: Path) -> str:
    digest = hashlib.sha256()
    for f in files:
        digest.update(Path(f).read_bytes())
    return digest.hexdigest()[:16]


def write_manifest(outdir: Path, cfg_dict: dict, training: dict, extra: dict | None = None) -> dict:
    manifest = {
        "version": model_version(outdir / "encoder.onnx", outdir / "sampler.onnx"),
        "variant": cfg_dict["variant"],
        "code_size": cfg_dict["code_size"],
        "dims": cfg_dict["dims"],
        "pixels_per_unit": float(cfg_dict["pixels_per_unit"]),
        "encoder_input_size": ENCODER_INPUT_SIZE,
        "encoder_input_range": ENCODER_INPUT_RANGE,
        "exemplar_short_side": cfg_dict["exemplar_short_side"],
        "output_colour": "linear",
        # the sampler's colour input: a per-texture table of this many numbers (model/colour.py)
        "colour_size": colour_size(KNOTS),
        "config": cfg_dict,
        "training": training,
        "created_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    manifest.update(extra or {})
    tmp = outdir / "manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, outdir / "manifest.json")
    return manifest


def save_weights(model: TextureSpace, path: Path, training: dict) -> None:
    """A slim checkpoint (config + weights, no optimiser): what ``model.fit`` starts from."""
    tmp = path.with_suffix(".tmp")
    torch.save({"config": model.cfg.to_dict(), "model": model.state_dict(), "step": training.get("steps", 0),
                "mode": "space", **{k: v for k, v in training.items() if k in ("wall_seconds", "data")}}, tmp)
    os.replace(tmp, path)


def export_model(model: TextureSpace, outdir: Path, training: dict | None = None) -> dict:
    """Write encoder.onnx, sampler.onnx, style.onnx, space.pt and manifest.json into outdir;
    return the manifest."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    training = training or {}
    export_encoder(model, outdir / "encoder.onnx")
    export_sampler(model.field, outdir / "sampler.onnx")
    export_tileable_sampler(model.field, outdir / TILEABLE_SAMPLER)
    export_style(outdir / STYLE_FEATURES)
    save_weights(model, outdir / "space.pt", training)
    return write_manifest(outdir, model.cfg.to_dict(), training,
                          {"tileable_sampler": TILEABLE_SAMPLER, "style_features": STYLE_FEATURES})


REPO_ROOT = Path(__file__).resolve().parent.parent
#: training arguments that name files or folders (a manifest records them as the repository sees them)
PATH_ARGS = ("data", "init", "exemplar", "out")


def portable_path(value: str | None, root: Path = REPO_ROOT) -> str | None:
    """``value`` relative to the repository ``root`` when it lies inside it, else its last
    part: a shipped manifest names no folder of the machine that trained it."""
    if not value or not Path(value).is_absolute():
        return value
    try:
        return Path(value).relative_to(root).as_posix()
    except ValueError:
        return Path(value).name


def training_summary(ckpt: dict) -> dict:
    keys = ("mode", "steps", "wall_seconds", "data", "loss", "final_loss", "args")
    summary = {k: ckpt[k] for k in keys if k in ckpt}
    summary.setdefault("steps", ckpt.get("step", 0))
    if isinstance(summary.get("args"), dict):
        summary["args"] = {k: portable_path(v) if k in PATH_ARGS else v for k, v in summary["args"].items()}
    return summary


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="checkpoint .pt written by model.train, or 'random' for an untrained model")
    parser.add_argument("outdir", nargs="?", default=str(DEFAULT_OUTDIR))
    parser.add_argument("--variant", default="ours", help="with 'random': which variant to initialise")
    parser.add_argument("--seed", type=int, default=0, help="with 'random': torch seed of the initialisation")
    args = parser.parse_args(argv)
    if args.checkpoint == "random":
        from model.networks import ModelConfig

        torch.manual_seed(args.seed)
        model = TextureSpace(ModelConfig(variant=args.variant))
        training = {"mode": "untrained", "steps": 0, "note": f"random initialisation, torch seed {args.seed}"}
    else:
        model, ckpt = load_checkpoint(args.checkpoint)
        training = training_summary(ckpt)
    manifest = export_model(model, Path(args.outdir), training)
    print(json.dumps({k: manifest[k] for k in ("version", "variant", "pixels_per_unit")}))


if __name__ == "__main__":
    main()
