"""One texture as a real-time shader: GLSL ES 3.0 and WGSL source emitted from its sampler.

    emit_shader(sampler_path, vector, name, language)  ->  source text

defines ``vec3 <name>(vec3 p, uint seed)`` (GLSL) or ``fn <name>(p: vec3<f32>, seed: u32)
-> vec3<f32>`` (WGSL): the linear RGB in [0, 1] of the texture at world point ``p``, the
same function as the sampler graph (docs/SHADER.md). One truth: every number comes from
the texture's own ``sampler.onnx`` (the shared model's, or a fitted texture's):

* the decoder's weights are read from the file's initializers (protobuf wire format read
  here: the ``onnx`` package is a training extra, not a runtime dependency);
* the per-texture constants are computed by the graph itself: ONNX Runtime runs the
  sampler once with two of its intermediate tensors added as outputs, the decoder's code
  biases and the lattice coordinates of four probe points (the origin and the unit
  vectors), which give each octave's affine map ``lattice = M_k p + o_k`` exactly;
* the noise hash is model/noise.py's (its constants below; ``hash_constants_in_graph``
  lets a test check each one against the graph). Samplers exported before 2026-11-26
  read three masked 10-bit fields of a full lowbias32 hash; later ones the top bits of
  the hash times three odd constants. ``SamplerWeights.fields`` says which, found from
  the graph's constants, so a stored texture keeps its own noise.

Precision: ``p`` is float32 on a GPU where the graph takes float64. The finest octave has
about ``FINEST_CELLS_PER_UNIT`` cells per world unit, so a lattice coordinate is off by up
to ``|p| * 128 * 2**-24`` cells: 1e-5 cells at |p| = 1, 1% of a cell at |p| = 1000.
Beyond that, shift ``p`` by a local origin (docs/SHADER.md).
"""
from __future__ import annotations

import functools
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .colour_match import FLOOR  # compressed colour is (rgb + FLOOR) ** (1/4), as the table stores it
from .errors import InvalidParameter, ModelInvalid
from .files import OFFERED
from .triplanar import TRIPLANAR_DEPTHS, TRIPLANAR_MIN_WEIGHT, TRIPLANAR_SHARPNESS

LANGUAGES = OFFERED["shader"]

# model/noise.py's hash, exactly (uint32 arithmetic): lowbias32 mixer, per-axis cell
# constants (low 32 bits, bits above), seed and octave multipliers, and the channel
# multipliers of a cell's colour values (top bits of hash * multiplier, times 2**-32).
MIX_A, MIX_B = 0x7FEB352D, 0x846CA68B
COORD_LO = (0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D)
COORD_HI = (0x27D4EB2F, 0x165667B1, 0x61C88647)
SEED_MULT, OCTAVE_MULT = 0x68E31DA5, 0x2545F491
CHANNEL_MULTS = (1, 0xA54FF53B, 0x510E527F)
FIELD_SCALE = 2.0**-32
# Samplers exported before 2026-11-26: the cell hash is the full lowbias32 and its colour
# values are 10-bit fields at bits 1, 11, 21, each at the centre of its bin.
CHANNEL_LOW_BIT, CHANNEL_BITS = (1, 11, 21), 10
HALF_BIN = 0.5 / (1 << CHANNEL_BITS)
MASKS = tuple(((1 << CHANNEL_BITS) - 1) << b for b in CHANNEL_LOW_BIT)
MIN_STEP = 1e-12
FINEST_CELLS_PER_UNIT = 128

_PROBES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)


# ----------------------------------------------------------------------------- ONNX bytes


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = buf[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, i


def _fields(buf: bytes):
    """(field number, wire type, value, start, end) of each field of one protobuf message."""
    i = 0
    while i < len(buf):
        start = i
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 1:
            value, i = buf[i:i + 8], i + 8
        elif wire == 2:
            size, i = _varint(buf, i)
            value, i = buf[i:i + size], i + size
        elif wire == 5:
            value, i = buf[i:i + 4], i + 4
        else:
            raise ModelInvalid(f"unsupported protobuf wire type {wire}")
        yield number, wire, value, start, i


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _field(number: int, payload: bytes) -> bytes:
    return _encode_varint(number << 3 | 2) + _encode_varint(len(payload)) + payload


_DTYPES = {1: np.float32, 6: np.int32, 7: np.int64, 11: np.float64, 12: np.uint32}


def _tensor(buf: bytes) -> tuple[str, np.ndarray | None]:
    """TensorProto -> (name, array); None for a type read nowhere here."""
    dims, dtype, name, raw, floats = [], None, "", None, []
    for number, wire, value, _, _ in _fields(buf):
        if number == 1:
            if wire == 2:  # packed
                j = 0
                while j < len(value):
                    d, j = _varint(value, j)
                    dims.append(d)
            else:
                dims.append(value)
        elif number == 2:
            dtype = _DTYPES.get(value)
        elif number == 4:
            floats.append(np.frombuffer(value, "<f4"))  # packed, or one fixed32 per field
        elif number == 8:
            name = value.decode()
        elif number == 9:
            raw = value
    if dtype is None:
        return name, None
    data = (np.frombuffer(raw, np.dtype(dtype).newbyteorder("<")) if raw is not None
            else np.concatenate(floats or [np.zeros(0, np.float32)]))
    return name, data.astype(dtype).reshape(dims)


@dataclass(frozen=True)
class _Graph:
    model: bytes
    initializers: dict[str, np.ndarray]
    nodes: list[tuple[str, list[str], list[str], list[np.ndarray]]]  # op, inputs, outputs, tensor attributes


def _read_graph(data: bytes) -> _Graph:
    graph = next((v for n, w, v, _, _ in _fields(data) if n == 7 and w == 2), None)
    if graph is None:
        raise ModelInvalid("sampler.onnx holds no graph")
    initializers, nodes = {}, []
    for number, _, value, _, _ in _fields(graph):
        if number == 5:
            name, array = _tensor(value)
            if array is not None:
                initializers[name] = array
        elif number == 1:
            inputs, outputs, op, tensors = [], [], "", []
            for n, _, v, _, _ in _fields(value):
                if n == 1:
                    inputs.append(v.decode())
                elif n == 2:
                    outputs.append(v.decode())
                elif n == 4:
                    op = v.decode()
                elif n == 5:
                    tensors += [_tensor(t)[1] for an, _, t, _, _ in _fields(v) if an == 5]
            nodes.append((op, inputs, outputs, [t for t in tensors if t is not None]))
    return _Graph(data, initializers, nodes)


def _with_outputs(data: bytes, outputs: dict[str, int]) -> bytes:
    """The model with more graph outputs (name -> ONNX element type), as bytes."""
    def value_info(name: str, elem: int) -> bytes:  # ValueInfoProto{name, type{tensor_type{elem_type}}}
        return _field(1, name.encode()) + _field(2, _field(1, _encode_varint(1 << 3) + _encode_varint(elem)))

    extra = b"".join(_field(12, value_info(name, elem)) for name, elem in outputs.items())
    out = bytearray()
    for number, wire, value, start, end in _fields(data):
        out += _field(7, value + extra) if number == 7 and wire == 2 else data[start:end]
    return bytes(out)


# ----------------------------------------------------------------------------- constants


@dataclass(frozen=True)
class SamplerWeights:
    """What every texture of one sampler file shares: the decoder and how to probe it."""

    path: str
    first: np.ndarray  # float32 [H, K*3 + 4*harmonics] first layer: noise, then phase features -> hidden
    hidden: tuple[np.ndarray, ...]  # float32 [H, H] each
    out: np.ndarray  # float32 [3, H]
    code_size: int
    probe_model: bytes  # the sampler with the biases and the lattices as extra outputs
    biases_name: str
    lattice_names: tuple[str, ...]  # the noise lattice q [.., K, 3] and, fitted on a repeat lattice, u [.., 2]
    n_noise: int  # K*3 noise features
    harmonics: int  # per repeat-lattice axis (model/networks.py lattice_phases); 0: no repeat lattice
    fields: str = "multiply"  # how a cell hash gives its colour values: "multiply" or "mask" (before 2026-11-26)
    mean_cell: np.ndarray | None = None  # float32 [n_a, n_b, 3]: the photo's mean repeat cell, read at the phase
    shade: bool = False  # each repeat cell's own hashed shade, 3 inputs after the phases (model/noise.py cell_shade)


@dataclass(frozen=True)
class TextureConstants:
    """One texture's constants: float64 matrices [K,3,3] and offsets [K,3] (lattice =
    M p + o), float32 biases [L*H + 3], float32 colour table [colour_size] (may be empty),
    and for a sampler fitted on a repeat lattice its map u = R p + r, float64 [2, 4] (R | r)."""

    matrices: np.ndarray
    offsets: np.ndarray
    biases: np.ndarray
    colour: np.ndarray
    repeat: np.ndarray | None = None


@functools.lru_cache(maxsize=8)
def _weights(path: str, _mtime: float) -> SamplerWeights:
    data = Path(path).read_bytes()
    g = _read_graph(data)
    init = g.initializers

    def weight(suffix: str) -> np.ndarray:
        found = [v for k, v in init.items() if k.endswith(suffix)]
        if len(found) != 1:
            raise ModelInvalid(f"{Path(path).name}: expected one initializer *{suffix}, found {len(found)}")
        return found[0]

    hidden = tuple(init[k] for k in sorted((k for k in init if re.search(r"decoder\.layers\.\d+\.weight$", k)),
                                           key=lambda k: int(k.split(".")[-2])))
    biases = [o[0] for op, i, o, _ in g.nodes
              if op == "Gemm" and len(i) > 1 and i[1].endswith("decoder.from_code.weight")]
    # The cell lattice q = lattice - 0.5: the input of the Floor whose output is subtracted
    # from that same input (frac = q - floor(q), model/noise.py). A sampler fitted on a
    # repeat lattice has a second such input, the point's lattice coordinates u
    # (model/networks.py lattice_phases); the probe tells them apart by shape.
    floors = {o[0]: i[0] for op, i, o, _ in g.nodes if op == "Floor"}
    lattices = [i[0] for op, i, o, _ in g.nodes if op == "Sub" and len(i) == 2 and floors.get(i[1]) == i[0]]
    phase = [v for k, v in init.items() if k.endswith("decoder.from_phase.weight")]
    noise = weight("decoder.from_noise.weight")
    if len(biases) != 1 or len(lattices) != 1 + len(phase) or not hidden or len(phase) > 1:
        raise ModelInvalid(f"{Path(path).name}: not a TextureField sampler this shader emitter knows "
                           f"(code-bias Gemm: {len(biases)}, lattices: {len(lattices)}, phase weights: {len(phase)}, "
                           f"hidden layers: {len(hidden)})")
    cells = [v for k, v in init.items() if k.endswith("lattice_mean_cell")]
    mean_cell = cells[0] if len(cells) == 1 and phase and cells[0].ndim == 3 and cells[0].shape[2] == 3 else None
    first = np.concatenate([noise, *phase], axis=1)
    # After the 4 * harmonics phase inputs: 3 cell shades (lattice_shade), then 3 for the mean
    # cell; whatever is left of 4 after the mean cell's tells the shades apart.
    before_cell = int(phase[0].shape[1]) - (3 if mean_cell is not None else 0) if phase else 0
    if before_cell % 4 not in (0, 3):
        raise ModelInvalid(f"{Path(path).name}: {phase[0].shape[1]} phase inputs are not the sines, cosines, "
                           "cell shades and mean cell this shader emitter knows")
    shade = before_cell % 4 == 3
    pad = -first.shape[1] % 4  # zero columns that make whole vec4s
    first = np.concatenate([first, np.zeros((first.shape[0], pad), first.dtype)], axis=1)
    if first.shape[1] % 4 or noise.shape[1] % 4 or len(cells) != (mean_cell is not None):
        raise ModelInvalid(f"{Path(path).name}: decoder inputs ({noise.shape[1]} noise, {first.shape[1]} in all, "
                           f"{len(cells)} mean cells) are not whole vec4s this shader emitter knows")
    # The code's width: the weight of the translator's first Gemm, which reads z (samplers
    # exported since 2026-11-27 read it through a Cast to float64, and their folded weight
    # has no name of its own).
    casts = {o[0]: i[0] for op, i, o, _ in g.nodes if op == "Cast"}
    firsts = [init[i[1]] for op, i, o, _ in g.nodes
              if op == "Gemm" and len(i) > 1 and casts.get(i[0], i[0]) == "z" and i[1] in init]
    if len(firsts) != 1:
        raise ModelInvalid(f"{Path(path).name}: expected one Gemm reading the code z, found {len(firsts)}")
    z = firsts[0]
    held = _held_uint32(g)
    if CHANNEL_MULTS[1] in held and CHANNEL_MULTS[2] in held:
        fields = "multiply"
    elif all(m in held for m in MASKS):
        fields = "mask"
    else:
        raise ModelInvalid(f"{Path(path).name}: its noise reads colour values neither by the channel multipliers "
                           "nor by the 10-bit masks this shader emitter knows")
    return SamplerWeights(
        path=path, first=first, hidden=hidden, out=weight("decoder.out.weight"),
        code_size=int(z.shape[1]),
        probe_model=_with_outputs(data, {biases[0]: 1, **{name: 11 for name in lattices}}),
        biases_name=biases[0], lattice_names=tuple(lattices), n_noise=int(noise.shape[1]),
        harmonics=before_cell // 4, fields=fields, mean_cell=mean_cell, shade=shade)


def sampler_weights(path: str | os.PathLike) -> SamplerWeights:
    """The decoder weights of one ``sampler.onnx`` (read once per file version)."""
    path = str(Path(path).resolve())
    return _weights(path, os.stat(path).st_mtime)


@functools.lru_cache(maxsize=64)
def _constants(path: str, _mtime: float, vector: bytes) -> TextureConstants:
    import onnxruntime as ort

    w = _weights(path, _mtime)
    session = ort.InferenceSession(w.probe_model, providers=["CPUExecutionProvider"])
    inputs = {i.name: i for i in session.get_inputs()}
    vec = np.frombuffer(vector, np.float32)
    z = vec[:w.code_size][None]
    seed = np.zeros((1,) if len(inputs["seed"].shape) == 1 else (), np.int64)  # Contract 1: [] or [1]
    feed = {"points": _PROBES, "z": z, "seed": seed}
    colour = np.zeros(0, np.float32)
    if "colour" in inputs:
        size = int(inputs["colour"].shape[1])
        colour = vec[w.code_size:] if len(vec) > w.code_size else _identity_colour(size)
        if len(colour) != size:
            raise InvalidParameter(f"colour table has {len(colour)} numbers, the sampler takes {size}")
        feed["colour"] = colour[None].astype(np.float32)
    biases, *lattices = session.run([w.biases_name, *w.lattice_names], feed)
    repeat = q = None
    for found in lattices:
        if found.shape[-1] == 2:  # u = R p + r on the repeat lattice: [.., probe, 2]
            u = found.reshape(len(_PROBES), 2)
            repeat = np.concatenate([(u[1:] - u[0]).T, u[0][:, None]], axis=1)  # [2, 4]: R | r
        else:
            q = found
    if q is None or q.shape[0] != 3 or (w.harmonics and repeat is None):
        raise ModelInvalid(f"shaders are emitted for 3D samplers only (lattices {[x.shape for x in lattices]})")
    q = q.reshape(3, len(_PROBES), -1) + 0.5  # [D, probe, K]: the lattice points themselves
    offsets = q[:, 0, :].T  # [K, 3]
    matrices = np.stack([q[:, j + 1, :] - q[:, 0, :] for j in range(3)], axis=-1).transpose(1, 0, 2)  # [K, D, 3]
    return TextureConstants(matrices, offsets, biases.reshape(-1).astype(np.float32), colour.astype(np.float32),
                            repeat)


def texture_constants(path: str | os.PathLike, vector: np.ndarray) -> TextureConstants:
    """The constants of the texture with ``vector`` (z then colour table, as samplers take it)."""
    path = str(Path(path).resolve())
    vec = np.ascontiguousarray(vector, np.float32).reshape(-1)
    return _constants(path, os.stat(path).st_mtime, vec.tobytes())


def _identity_colour(size: int) -> np.ndarray:
    from .colour_match import identity_colour

    return np.asarray(identity_colour(size), np.float32)


def _held_uint32(g: _Graph) -> set[int]:
    """Every uint32 number the graph holds as an initializer or a constant."""
    arrays = list(g.initializers.values()) + [t for *_, ts in g.nodes for t in ts]
    return {int(v) for a in arrays if a.dtype == np.uint32 for v in a.reshape(-1)}


def hash_constants_in_graph(path: str | os.PathLike) -> dict[str, bool]:
    """For each hash constant here: whether the sampler graph holds it (as a uint32
    initializer or constant). A test's check that this module and model/noise.py agree."""
    held = _held_uint32(_read_graph(Path(path).read_bytes()))
    wanted = {"MIX_A": MIX_A, "MIX_B": MIX_B, "SEED_MULT": SEED_MULT, "OCTAVE_MULT": OCTAVE_MULT,
              **{f"COORD_LO{i}": c for i, c in enumerate(COORD_LO)},
              **{f"COORD_HI{i}": c for i, c in enumerate(COORD_HI)},
              **{f"CHANNEL_MULT{i}": c for i, c in enumerate(CHANNEL_MULTS) if c != 1}}
    return {k: v in held for k, v in wanted.items()}


# ----------------------------------------------------------------------------- emitters


def _num(x: float) -> str:
    """The shortest decimal that reads back as the same float32 (a float literal in GLSL and WGSL)."""
    v = np.float32(x)
    a = np.format_float_positional(v, unique=True, trim="0")
    b = np.format_float_scientific(v, unique=True, trim="-", exp_digits=1)
    return min(a, b, key=len)


def _blocks(w: np.ndarray) -> list[np.ndarray]:
    """float [R, C] -> the 4x4 blocks (row block i, column block j) at i * (C/4) + j, each as
    16 numbers in column-major order (a GLSL mat4 / WGSL mat4x4 constructor): mat * x[j]
    is the block's share of the output rows 4i..4i+3."""
    rows, cols = w.shape
    pad = np.zeros((-(-rows // 4) * 4, -(-cols // 4) * 4), np.float32)
    pad[:rows, :cols] = w
    return [pad[4 * i:4 * i + 4, 4 * j:4 * j + 4].T.reshape(-1)
            for i in range(pad.shape[0] // 4) for j in range(pad.shape[1] // 4)]


def _vec4s(v: np.ndarray) -> list[np.ndarray]:
    pad = np.zeros(-(-len(v) // 4) * 4, np.float32)
    pad[:len(v)] = v
    return list(pad.reshape(-1, 4))


@dataclass(frozen=True)
class _Syntax:
    mat4: str
    mat3: str
    vec4: str
    vec3: str
    f32: str

    def array(self, kind: str, items: list[str], name: str) -> str:
        body = ",\n  ".join(items)
        if self.f32 == "float":
            return f"const {kind} {name}[{len(items)}] = {kind}[{len(items)}](\n  {body});\n"
        return f"const {name} = array<{kind}, {len(items)}>(\n  {body});\n"

    def ctor(self, kind: str, numbers) -> str:
        return f"{kind}({', '.join(_num(x) for x in numbers)})"


GLSL = _Syntax("mat4", "mat3", "vec4", "vec3", "float")
WGSL = _Syntax("mat4x4<f32>", "mat3x3<f32>", "vec4<f32>", "vec3<f32>", "f32")


def _tables(w: SamplerWeights, c: TextureConstants, s: _Syntax, n: str) -> str:
    """The constant arrays of one texture, every name prefixed with ``n``."""
    def arr(kind, rows, name):
        return s.array(kind, [s.ctor(kind, r) for r in rows], name)

    lattice = [np.asarray(m, np.float64).T.reshape(-1) for m in c.matrices]  # column-major 3x3
    parts = [
        "// this texture: octave lattices (q = M p + o - 0.5)\n",
        arr(s.mat3, lattice, f"{n}_M"),
        arr(s.vec3, list(c.offsets - 0.5), f"{n}_O"),
    ]
    if w.mean_cell is not None:
        parts += ["// the photo's mean repeat cell, [i_a * n_b + i_b] (model/networks.py mean_cell_colour)\n",
                  arr(s.vec3, list(w.mean_cell.reshape(-1, 3)), f"{n}_CELL")]
    if len(c.colour):
        knots = _knots(c)
        t = c.colour
        parts += [
            f"// colour table (model/colour.py): A, start, step, {knots} knots x 3 channels, B\n",
            arr(s.mat3, [t[:9].reshape(3, 3).T.reshape(-1), t[-9:].reshape(3, 3).T.reshape(-1)], f"{n}_AB"),
            arr(s.vec3, [t[9:12], np.maximum(t[12:15], MIN_STEP)], f"{n}_GRID"),
            s.array(s.f32, [_num(x) for x in t[15:15 + 3 * knots]], f"{n}_CURVE"),
        ]
    return "".join(parts)


def _decoder(n: str, w: SamplerWeights, c: TextureConstants, s: _Syntax) -> str:
    """The MLP, unrolled: each 4x4 weight block is an immediate mat4 (no arrays, so no
    per-invocation copy of 200 KiB of constants, and no array size limit), each layer's
    code bias an immediate vec4. Input: the feature array ``x``, read as vec4s x0..;
    output ``o``."""
    let = "vec4" if s.f32 == "float" else "let"
    zero = f"{s.vec4}(0.0)"
    inputs = [f"x{j}" for j in range(w.first.shape[1] // 4)]
    lines = [f"  {let} x{j} = {s.vec4}(x[{4 * j}], x[{4 * j + 1}], x[{4 * j + 2}], x[{4 * j + 3}]);\n"
             for j in range(len(inputs))]
    layers = [w.first, *w.hidden, w.out]
    offset = 0
    for depth, weight in enumerate(layers):
        blocks = _blocks(weight)
        width = len(inputs)
        rows = -(-weight.shape[0] // 4)
        bias = _vec4s(c.biases[offset:offset + weight.shape[0]])
        offset += weight.shape[0]
        last = depth == len(layers) - 1
        names = ["o"] if last else [f"h{depth}_{i}" for i in range(rows)]
        for i in range(rows):
            terms = " + ".join(f"{s.ctor(s.mat4, blocks[i * width + j])} * {inputs[j]}" for j in range(width))
            value = f"{s.ctor(s.vec4, bias[i])} + {terms}"
            lines.append(f"  {let} {names[i]} = {value if last else f'max({value}, {zero})'};\n")
        inputs = names
    return "".join(lines)


def _cell_hash(w: SamplerWeights, s: _Syntax, n: str) -> tuple[str, str]:
    """The cell hash and colour-value functions of this sampler's noise (model/noise.py
    cell_mix, channel_fields), and the expression that turns blended values into [0, 1]."""
    glsl = s.f32 == "float"
    cell = f"uint {n}_cell(uint x) {{" if glsl else f"fn {n}_cell(x: u32) -> u32 {{"
    fields = f"vec3 {n}_fields(uint h) {{" if glsl else f"fn {n}_fields(h: u32) -> vec3<f32> {{"
    if w.fields == "mask":
        masked = ", ".join(f"{s.f32}(h & {m:#x}u)" for m in MASKS)
        scale = f" * {s.ctor(s.vec3, [2.0 ** -(b + CHANNEL_BITS) for b in CHANNEL_LOW_BIT])} + {_num(HALF_BIN)}"
        return (f"{cell}  // lowbias32\n  return {n}_mix(x);\n}}\n\n"
                f"{fields}  // three 10-bit fields at bits 1, 11, 21, unscaled\n"
                f"  return {s.vec3}({masked});\n}}\n"), scale
    uvec3 = "uvec3" if glsl else "vec3<u32>"
    mults = ", ".join(f"{m:#010x}u" for m in CHANNEL_MULTS)
    return (f"{cell}  // lowbias32 without its last xorshift\n  return {n}_rounds(x);\n}}\n\n"
            f"{fields}  // top bits of h times three odd constants, unscaled\n"
            f"  return {s.vec3}({uvec3}(h) * {uvec3}({mults}));\n}}\n"), f" * {_num(FIELD_SCALE)}"


def _knots(c: TextureConstants) -> int:
    """Knots per channel curve of the texture's colour table (0 without one)."""
    return (len(c.colour) - 24) // 3 if len(c.colour) else 0


def _phases(w: SamplerWeights, c: TextureConstants, s: _Syntax, n: str) -> str:
    """The repeat-lattice phase features after the noise ones (model/networks.py
    lattice_phases): ph = R p + r, then sin and cos of 2 pi k frac(ph), k = 1..harmonics, as
    x[noise + i * H + k - 1] (sin) and x[noise + 2H + i * H + k - 1] (cos) for axis i."""
    if not w.harmonics:
        return ""
    h, first = w.harmonics, w.n_noise
    rows = [s.ctor(s.vec3, c.repeat[i, :3]) for i in range(2)]
    at = first + 4 * h + (3 if w.shade else 0)  # the mean cell's first input
    used = at + (3 if w.mean_cell is not None else 0)
    zeros = "".join(f" x[{i}] = 0.0;" for i in range(used, w.first.shape[1]))  # (the last vec4's rest)
    pad = f" {zeros}\n" if zeros else ""
    if s.f32 == "float":
        return f"""  // phase on the photo's repeat lattice
  vec2 ph = vec2(dot({rows[0]}, p), dot({rows[1]}, p)) + vec2({_num(c.repeat[0, 3])}, {_num(c.repeat[1, 3])});
  vec2 pc = floor(ph);
  ph -= pc;
  for (int i = 0; i < 2; ++i) for (int k = 1; k <= {h}; ++k) {{
    float angle = {_num(2 * np.pi)} * ph[i] * float(k);
    x[{first} + i * {h} + k - 1] = sin(angle);
    x[{first + 2 * h} + i * {h} + k - 1] = cos(angle);
  }}
{_shade(w, c, s, n, first + 4 * h)}{_mean_cell(w, s, n, at)}{pad}"""
    return f"""  // phase on the photo's repeat lattice
  var ph = vec2<f32>(dot({rows[0]}, p), dot({rows[1]}, p)) + vec2<f32>({_num(c.repeat[0, 3])}, {_num(c.repeat[1, 3])});
  let pc = floor(ph);
  ph -= pc;
  for (var i = 0; i < 2; i++) {{
    for (var k = 1; k <= {h}; k++) {{
      let angle = {_num(2 * np.pi)} * ph[i] * f32(k);
      x[{first} + i * {h} + k - 1] = sin(angle);
      x[{first + 2 * h} + i * {h} + k - 1] = cos(angle);
    }}
  }}
{_shade(w, c, s, n, first + 4 * h)}{_mean_cell(w, s, n, at)}{pad}"""


def _shade(w: SamplerWeights, c: TextureConstants, s: _Syntax, n: str, at: int) -> str:
    """The repeat cell's own shade (model/noise.py cell_shade), into x[at..at+2]: the hash of
    cell (pc, 0) with the seed of one octave past the noise's, as the noise hashes a cell."""
    if not w.shade:
        return ""
    scale = _cell_hash(w, s, n)[1]
    k = len(c.matrices) + 1
    head = (f"  uint ss = {n}_mix(base ^ (uint({k}) * {OCTAVE_MULT:#010x}u));\n"
            f"  uvec2 ti = {n}_terms(pc.x, {COORD_LO[0]:#010x}u, {COORD_HI[0]:#010x}u);\n"
            f"  uvec2 tj = {n}_terms(pc.y, {COORD_LO[1]:#010x}u, {COORD_HI[1]:#010x}u);\n"
            f"  vec3 sh = ({n}_fields({n}_cell(ss + ti.x + tj.x)){scale} - 0.5) * 2.0;\n"
            if s.f32 == "float" else
            f"  let ss = {n}_mix(base ^ (u32({k}) * {OCTAVE_MULT:#010x}u));\n"
            f"  let ti = {n}_terms(pc.x, {COORD_LO[0]:#010x}u, {COORD_HI[0]:#010x}u);\n"
            f"  let tj = {n}_terms(pc.y, {COORD_LO[1]:#010x}u, {COORD_HI[1]:#010x}u);\n"
            f"  let sh = ({n}_fields({n}_cell(ss + ti.x + tj.x)){scale} - 0.5) * 2.0;\n")
    return (f"  // this repeat cell's own shade\n{head}"
            f"  x[{at}] = sh.x; x[{at + 1}] = sh.y; x[{at + 2}] = sh.z;\n")


def _mean_cell(w: SamplerWeights, s: _Syntax, n: str, at: int) -> str:
    """The mean repeat cell's colour at phase ``ph``, bilinear and wrapping (model/networks.py
    mean_cell_colour), into x[at..at+2]."""
    if w.mean_cell is None:
        return ""
    na, nb = w.mean_cell.shape[:2]
    if s.f32 == "float":
        return f"""  // the photo's mean repeat cell at this phase
  vec2 cx = ph * vec2({na}.0, {nb}.0) - 0.5;
  vec2 lo = floor(cx), ct = cx - lo;
  int a0 = (int(lo.x) + {na}) % {na}, b0 = (int(lo.y) + {nb}) % {nb};
  int a1 = (a0 + 1) % {na}, b1 = (b0 + 1) % {nb};
  vec3 top = {n}_CELL[a0 * {nb} + b0] + ct.x * ({n}_CELL[a1 * {nb} + b0] - {n}_CELL[a0 * {nb} + b0]);
  vec3 bottom = {n}_CELL[a0 * {nb} + b1] + ct.x * ({n}_CELL[a1 * {nb} + b1] - {n}_CELL[a0 * {nb} + b1]);
  vec3 mc = top + ct.y * (bottom - top);
  x[{at}] = mc.x; x[{at + 1}] = mc.y; x[{at + 2}] = mc.z;
"""
    return f"""  // the photo's mean repeat cell at this phase
  let cx = ph * vec2<f32>({na}.0, {nb}.0) - 0.5;
  let lo = floor(cx);
  let ct = cx - lo;
  let a0 = (i32(lo.x) + {na}) % {na};
  let b0 = (i32(lo.y) + {nb}) % {nb};
  let a1 = (a0 + 1) % {na};
  let b1 = (b0 + 1) % {nb};
  let top = {n}_CELL[a0 * {nb} + b0] + ct.x * ({n}_CELL[a1 * {nb} + b0] - {n}_CELL[a0 * {nb} + b0]);
  let bottom = {n}_CELL[a0 * {nb} + b1] + ct.x * ({n}_CELL[a1 * {nb} + b1] - {n}_CELL[a0 * {nb} + b1]);
  let mc = top + ct.y * (bottom - top);
  x[{at}] = mc.x; x[{at + 1}] = mc.y; x[{at + 2}] = mc.z;
"""


def _glsl_body(n: str, w: SamplerWeights, c: TextureConstants) -> str:
    k, nb = len(c.matrices), w.first.shape[1] // 4
    (cell, scale), decoder, knots = _cell_hash(w, GLSL, n), _decoder(n, w, c, GLSL), _knots(c)
    colour = f"""
  // colour table: fourth-root compression, A, per-channel curves, B, back to linear
  vec3 u = {n}_AB[0] * sqrt(sqrt(clamp(raw, 0.0, 1.0) + {_num(FLOOR)}));
  vec3 t = clamp((u - {n}_GRID[0]) / {n}_GRID[1], 0.0, {_num(knots - 1)});
  vec3 knot = min(floor(t), {_num(knots - 2)});
  vec3 d;
  for (int ch = 0; ch < 3; ++ch) {{
    int at = ch * {knots} + int(knot[ch]);
    d[ch] = {n}_CURVE[at] + (t[ch] - knot[ch]) * ({n}_CURVE[at + 1] - {n}_CURVE[at]);
  }}
  vec3 e = {n}_AB[1] * d;
  e = e * e;
  return clamp(e * e - {_num(FLOOR)}, 0.0, 1.0);""" if knots else "\n  return raw;"
    return f"""
uint {n}_rounds(uint h) {{  // lowbias32's two xorshift-multiply rounds
  h ^= h >> 16u; h *= {MIX_A:#010x}u;
  h ^= h >> 15u;
  return h * {MIX_B:#010x}u;
}}

uint {n}_mix(uint x) {{  // lowbias32
  uint h = {n}_rounds(x);
  return h ^ (h >> 16u);
}}

// an axis' share of a cell hash, for cell c and cell c + 1 (model/noise.py: _axis_terms)
uvec2 {n}_terms(float c, uint lo_mult, uint hi_mult) {{
  int ci = int(c);
  uint lo = uint(ci), hi = ci < 0 ? 0xffffffffu : 0u;
  uint t = lo * lo_mult + hi * hi_mult;
  return uvec2(t, t + (lo == 0xffffffffu ? lo_mult + hi_mult : lo_mult));
}}

{cell}
vec3 {n}(vec3 p, uint seed) {{
  uint base = {n}_mix({n}_mix(seed));
  float x[{4 * nb}];
  for (int k = 0; k < {k}; ++k) {{
    uint s = {n}_mix(base ^ (uint(k + 1) * {OCTAVE_MULT:#010x}u));
    vec3 q = {n}_M[k] * p + {n}_O[k];
    vec3 b = floor(q), f = q - b, wt = f * f * (3.0 - 2.0 * f);
    uvec2 tx = {n}_terms(b.x, {COORD_LO[0]:#010x}u, {COORD_HI[0]:#010x}u);
    uvec2 ty = {n}_terms(b.y, {COORD_LO[1]:#010x}u, {COORD_HI[1]:#010x}u);
    uvec2 tz = {n}_terms(b.z, {COORD_LO[2]:#010x}u, {COORD_HI[2]:#010x}u);
    vec3 v[4];  // blended along x first, then y, then z, as the graph does
    for (int j = 0; j < 2; ++j) for (int l = 0; l < 2; ++l) {{
      uint h = s + ty[j] + tz[l];
      vec3 a = {n}_fields({n}_cell(h + tx[0]));
      v[j * 2 + l] = a + wt.x * ({n}_fields({n}_cell(h + tx[1])) - a);
    }}
    vec3 v0 = v[0] + wt.y * (v[2] - v[0]), v1 = v[1] + wt.y * (v[3] - v[1]);
    vec3 level = (v0 + wt.z * (v1 - v0)){scale};
    vec3 feature = (level - 0.5) * 2.0;
    x[3 * k] = feature.x; x[3 * k + 1] = feature.y; x[3 * k + 2] = feature.z;
  }}
{_phases(w, c, GLSL, n)}{decoder}  vec3 raw = 1.0 / (1.0 + exp(-2.0 * o.xyz));  // sigmoid(2 logits)
{colour}
}}
"""


def _wgsl_body(n: str, w: SamplerWeights, c: TextureConstants) -> str:
    k, nb = len(c.matrices), w.first.shape[1] // 4
    (cell, scale), decoder, knots = _cell_hash(w, WGSL, n), _decoder(n, w, c, WGSL), _knots(c)
    colour = f"""
  // colour table: fourth-root compression, A, per-channel curves, B, back to linear
  let u = {n}_AB[0] * sqrt(sqrt(clamp(raw, vec3<f32>(0.0), vec3<f32>(1.0)) + {_num(FLOOR)}));
  let t = clamp((u - {n}_GRID[0]) / {n}_GRID[1], vec3<f32>(0.0), vec3<f32>({_num(knots - 1)}));
  let knot = min(floor(t), vec3<f32>({_num(knots - 2)}));
  var d: vec3<f32>;
  for (var ch = 0; ch < 3; ch++) {{
    let at = ch * {knots} + i32(knot[ch]);
    d[ch] = {n}_CURVE[at] + (t[ch] - knot[ch]) * ({n}_CURVE[at + 1] - {n}_CURVE[at]);
  }}
  var e = {n}_AB[1] * d;
  e = e * e;
  return clamp(e * e - {_num(FLOOR)}, vec3<f32>(0.0), vec3<f32>(1.0));""" if knots else "\n  return raw;"
    return f"""
fn {n}_rounds(x: u32) -> u32 {{  // lowbias32's two xorshift-multiply rounds
  var h = x;
  h ^= h >> 16u; h *= {MIX_A:#010x}u;
  h ^= h >> 15u;
  return h * {MIX_B:#010x}u;
}}

fn {n}_mix(x: u32) -> u32 {{  // lowbias32
  let h = {n}_rounds(x);
  return h ^ (h >> 16u);
}}

// an axis' share of a cell hash, for cell c and cell c + 1 (model/noise.py: _axis_terms)
fn {n}_terms(c: f32, lo_mult: u32, hi_mult: u32) -> vec2<u32> {{
  let ci = i32(c);
  let lo = bitcast<u32>(ci);
  let hi = select(0u, 0xffffffffu, ci < 0);
  let t = lo * lo_mult + hi * hi_mult;
  return vec2<u32>(t, t + select(lo_mult, lo_mult + hi_mult, lo == 0xffffffffu));
}}

{cell}
fn {n}(p: vec3<f32>, seed: u32) -> vec3<f32> {{
  let base = {n}_mix({n}_mix(seed));
  var x: array<f32, {4 * nb}>;
  for (var k = 0; k < {k}; k++) {{
    let s = {n}_mix(base ^ (u32(k + 1) * {OCTAVE_MULT:#010x}u));
    let q = {n}_M[k] * p + {n}_O[k];
    let b = floor(q);
    let f = q - b;
    let wt = f * f * (3.0 - 2.0 * f);
    let tx = {n}_terms(b.x, {COORD_LO[0]:#010x}u, {COORD_HI[0]:#010x}u);
    let ty = {n}_terms(b.y, {COORD_LO[1]:#010x}u, {COORD_HI[1]:#010x}u);
    let tz = {n}_terms(b.z, {COORD_LO[2]:#010x}u, {COORD_HI[2]:#010x}u);
    var v: array<vec3<f32>, 4>;  // blended along x first, then y, then z, as the graph does
    for (var j = 0; j < 2; j++) {{
      for (var l = 0; l < 2; l++) {{
        let h = s + ty[j] + tz[l];
        let a = {n}_fields({n}_cell(h + tx[0]));
        v[j * 2 + l] = a + wt.x * ({n}_fields({n}_cell(h + tx[1])) - a);
      }}
    }}
    let v0 = v[0] + wt.y * (v[2] - v[0]);
    let v1 = v[1] + wt.y * (v[3] - v[1]);
    let level = (v0 + wt.z * (v1 - v0)){scale};
    let feature = (level - 0.5) * 2.0;
    x[3 * k] = feature.x; x[3 * k + 1] = feature.y; x[3 * k + 2] = feature.z;
  }}
{_phases(w, c, WGSL, n)}{decoder}  let raw = 1.0 / (1.0 + exp(-2.0 * o.xyz));  // sigmoid(2 logits)
{colour}
}}
"""


def shader_name(texture_id: str) -> str:
    """``texspace_<id>``: a valid GLSL and WGSL identifier (no double underscore)."""
    clean = re.sub(r"_+", "_", re.sub(r"[^0-9A-Za-z_]", "_", texture_id)).strip("_")
    return f"texspace_{clean}" if clean else "texspace"


def emit_shader(sampler_path: str | os.PathLike, vector: np.ndarray, name: str, language: str = "glsl",
                header: str = "") -> str:
    """Source text of the texture with ``vector`` (z then colour table) in ``language``.

    sampler_path : the texture's sampler.onnx; vector : (C,) float32; name : the function's
    name (``shader_name``); header : comment lines put first (model version, texture id).
    GLSL is GLSL ES 3.00 without the ``#version`` line (paste it into a fragment shader);
    every top-level name starts with ``name``, so several textures share one shader.
    """
    if language not in LANGUAGES:
        raise InvalidParameter(f"language must be one of {LANGUAGES}, got {language!r}")
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name) or "__" in name:
        raise InvalidParameter(f"{name!r} is not a GLSL/WGSL identifier")
    w = sampler_weights(sampler_path)
    c = texture_constants(sampler_path, vector)
    syntax, body = (GLSL, _glsl_body) if language == "glsl" else (WGSL, _wgsl_body)
    signature = (f"vec3 {name}(vec3 p, uint seed)" if language == "glsl"
                 else f"fn {name}(p: vec3<f32>, seed: u32) -> vec3<f32>")
    lines = [*(f"// {line}" for line in header.splitlines()),
             f"// {signature}: linear RGB in [0, 1] at world point p (world units), instance `seed`.",
             "// Generated by texspace worker/shader.py from the texture's sampler.onnx; docs/SHADER.md.",
             f"// float32 lattice: off by up to {FINEST_CELLS_PER_UNIT} * |p| * 2^-24 cells; keep |p| below ~1e3 "
             "(local origin).", ""]
    return "\n".join(lines) + _tables(w, c, syntax, name) + body(name, w, c) + _triplanar(name, language)


def _triplanar(n: str, language: str) -> str:
    """``<n>_triplanar(p, normal, seed)``: the texture's xy plane projected along x, y and z,
    blended by the normal, as a triplanar bake does (worker/triplanar.py, its constants)."""
    d0, d1, d2 = (_num(d) for d in TRIPLANAR_DEPTHS)
    sharp, cut = _num(TRIPLANAR_SHARPNESS), _num(TRIPLANAR_MIN_WEIGHT)
    doc = (f"\n// {n}_triplanar: the texture's xy plane read along the axis the surface faces (x-facing at\n"
           "// (z, y), y-facing at (x, z), z-facing at (x, y)), blended by the normal n (any length): the\n"
           "// default for textures fitted on a repeat lattice, whose pattern lies in xy only (docs/SHADER.md).\n")
    if language == "glsl":
        return doc + f"""vec3 {n}_triplanar(vec3 p, vec3 n, uint seed) {{
  vec3 w = pow(max(abs(n), vec3(1e-20)), vec3({sharp}));
  w /= max(w.x + w.y + w.z, 1e-30);
  w *= step(vec3({cut}), w);
  float s = w.x + w.y + w.z;
  if (s == 0.0) {{ w = vec3(0.0, 0.0, 1.0); s = 1.0; }}
  w /= s;
  vec3 rgb = vec3(0.0);
  if (w.x > 0.0) rgb += w.x * {n}(vec3(p.z, p.y, {d0}), seed);
  if (w.y > 0.0) rgb += w.y * {n}(vec3(p.x, p.z, {d1}), seed);
  if (w.z > 0.0) rgb += w.z * {n}(vec3(p.x, p.y, {d2}), seed);
  return rgb;
}}
"""
    return doc + f"""fn {n}_triplanar(p: vec3<f32>, n: vec3<f32>, seed: u32) -> vec3<f32> {{
  var w = pow(max(abs(n), vec3<f32>(1e-20)), vec3<f32>({sharp}));
  w = w / max(w.x + w.y + w.z, 1e-30);
  w = w * step(vec3<f32>({cut}), w);
  var s = w.x + w.y + w.z;
  if (s == 0.0) {{ w = vec3<f32>(0.0, 0.0, 1.0); s = 1.0; }}
  w = w / s;
  var rgb = vec3<f32>(0.0);
  if (w.x > 0.0) {{ rgb += w.x * {n}(vec3<f32>(p.z, p.y, {d0}), seed); }}
  if (w.y > 0.0) {{ rgb += w.y * {n}(vec3<f32>(p.x, p.z, {d1}), seed); }}
  if (w.z > 0.0) {{ rgb += w.z * {n}(vec3<f32>(p.x, p.y, {d2}), seed); }}
  return rgb;
}}
"""
