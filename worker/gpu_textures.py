"""Mipmapped GPU texture files: DDS (BC1/BC3 or BC7 blocks) and KTX2 (Basis Universal
UASTC), sRGB, full mip chain.

DDS blocks come from the ``quicktex`` encoder (rgbcx's BC1/BC3 at level 5) or, with
``compression="bc7"``, from ``etcpak``'s BC7 encoder (bc7enc), in a container written here;
KTX2 files come whole from Basis Universal's encoder (``alktx2``). Every texel is
sRGB-encoded R, G, B and a straight alpha (255: the textures are opaque); a BC7 DDS of
data (``srgb=False``: normal, roughness maps) stores the values themselves.

Mip chain (``mip_chain``): level 0 is the image; level k+1 has ``max(1, w // 2) x
max(1, h // 2)`` pixels, down to 1 x 1 (``floor(log2(max(w, h))) + 1`` levels, the count
Direct3D, Vulkan and the KTX tools expect). Each level is an exact box (area) average of
the previous one **in linear light**, and only then sRGB-encoded to 8 bits, so mips keep
the image's brightness (averaging sRGB codes would darken them). For even sides this is
the plain 2 x 2 average; odd sides are averaged with fractional pixel weights.

* ``dds``: the legacy DirectX 9 layout that every DDS reader knows: "DDS " + DDS_HEADER
  (flags with DDSD_LINEARSIZE and DDSD_MIPMAPCOUNT, caps TEXTURE | COMPLEX | MIPMAP), a
  FourCC pixel format ``DXT1`` (BC1, 8 bytes per 4 x 4 block) when every alpha is 255,
  else ``DXT5`` (BC3, 16 bytes), then the levels largest first, blocks in rows top to
  bottom. A level whose side is not a multiple of 4 is padded by repeating its last
  row / column (the reader crops). No DX10 header: OpenImageIO 2.4, ImageMagick 6 and
  Blender 3.4 (Debian 12) read none of its sRGB RGBA8 or BC7 formats, and the legacy
  header has no colour-space field, so readers take the codes as the sRGB colour they are.
* ``dds`` with ``compression="bc7"``: the same levels as BC7 blocks (16 bytes per 4 x 4
  block, 8 bits a texel, the format artists pick for colour today) behind the DX10
  extension header, the only one that can name BC7: FourCC ``DX10``, then
  DDS_HEADER_DXT10 with ``DXGI_FORMAT_BC7_UNORM_SRGB`` (99) for colour or
  ``DXGI_FORMAT_BC7_UNORM`` (98) for data, TEXTURE2D, array size 1, alpha mode opaque
  (or straight with alpha). Blender 4, DirectXTex and game engines read it; the DX10
  header is what Debian 12's Blender 3.4, ImageMagick 6 and OpenImageIO 2.4 cannot read.
  An opaque texture is encoded with BC7 mode 1 only (``BC7_OPAQUE_MODES``): bc7enc's other
  opaque mode, 6, stores alpha with the colour's low bit and gave alpha 254 on even-coded
  blocks; mode 1 alone keeps every alpha 255 at a mean error 0.1 code higher (measured on
  256 x 256 crops of three photos, linear weights: 1.09-1.30 codes against 0.99-1.20 with
  mode 6, BC1 2.59-2.85).
* ``ktx2``: KTX 2.0 as glTF's ``KHR_texture_basisu`` wants it: Basis Universal UASTC LDR
  4 x 4 blocks (``VK_FORMAT_UNDEFINED``, DFD colour model UASTC, sRGB transfer, BT.709
  primaries), Zstandard supercompression (scheme 2), our own mip chain passed level by
  level (basisu's own mip filter would average sRGB codes). UASTC transcodes on the GPU
  side to BC7 / ASTC / ETC2 at near its own quality; ETC1S (smaller, blockier) is not
  offered. Encoding costs 3-6 s per 1024 x 1024 on one core (effort 2; measured on a
  brick photo: mean error 1.86 codes in 5.8 s, effort 4: 1.84 in 15.4 s). Binomial's
  ``basisu`` 1.16.4 validates these files (a region's and a GLB bake's) and transcodes
  them (tests/worker/test_open_in_tools.py); Khronos's libktx (``ktx validate``) is not
  installable here: Debian has no package and PyPI's pyktx needs libktx built.
"""
from __future__ import annotations

import struct

import alktx2
import numpy as np
from quicktex import RawTexture
from quicktex.s3tc.bc1 import BC1Encoder
from quicktex.s3tc.bc3 import BC3Encoder

from worker.colour import linear_to_srgb8
from worker.errors import InvalidParameter
from worker.files import OFFERED

GPU_FORMATS = OFFERED["gpu_texture"]
KTX2_IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
UASTC_EFFORT = 2            # basisu 0-10: speed against the best reachable quality
ZSTD_LEVEL = 6              # KTX2 Zstandard supercompression of the UASTC blocks
BC_BLOCK = 4                                    # texels per side of one BC1 / BC3 block
# quicktex's quality level (0-18): 5 is its default; measured on a 2048 x 2048 image,
# 0.44 s (level 10: 4.7 s for barely less error). etcpak's faster BC1 left errors of
# 41 codes on an 8 x 4 level of a two-colour ramp where this one leaves 14.
BC_LEVEL = 5
#: a DDS's block compression: BC1 (BC3 with alpha) in the legacy header, or BC7 (DX10 header)
DDS_COMPRESSIONS = ("bc1", "bc7")
DXGI_FORMAT_BC7_UNORM, DXGI_FORMAT_BC7_UNORM_SRGB = 98, 99
D3D10_RESOURCE_DIMENSION_TEXTURE2D = 3
DDS_ALPHA_MODE_STRAIGHT, DDS_ALPHA_MODE_OPAQUE = 1, 3
# bc7enc's opaque modes are 1 and 6; mode 6 shares its endpoints' low bit with alpha and
# left alpha 254 on blocks whose colours are even codes (module doc), so opaque texels
# get mode 1 only. Texels with alpha may use every mode.
BC7_OPAQUE_MODES = 1 << 1
BC7_ALL_MODES = 0xFF


def mip_sizes(width: int, height: int) -> list[tuple[int, int]]:
    """[(w, h)] of every level, level 0 first, down to 1 x 1."""
    sizes = [(int(width), int(height))]
    while sizes[-1] != (1, 1):
        w, h = sizes[-1]
        sizes.append((max(1, w // 2), max(1, h // 2)))
    return sizes


def _halve(a: np.ndarray, axis: int) -> np.ndarray:
    """Area average of ``a`` to ``max(1, n // 2)`` samples along ``axis`` (n = a.shape[axis])."""
    n = a.shape[axis]
    m = max(1, n // 2)
    if n == m:
        return a
    if n == 2 * m:
        a = np.moveaxis(a, axis, 0)
        return np.moveaxis(0.5 * (a[0::2] + a[1::2]), 0, axis)
    # odd n: output i covers [i * r, (i + 1) * r) source pixels, r = n / m
    a = np.moveaxis(a, axis, 0).astype(np.float64)
    prefix = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])
    edges = np.arange(m + 1) * (n / m)
    whole = np.minimum(np.floor(edges).astype(np.int64), n - 1)
    frac = (edges - whole).reshape((-1,) + (1,) * (a.ndim - 1))
    area = prefix[whole] + frac * a[whole]          # integral of the signal up to each edge
    out = (area[1:] - area[:-1]) / (n / m)
    return np.moveaxis(out.astype(np.float32), 0, axis)


def mip_chain(rgb: np.ndarray) -> list[np.ndarray]:
    """Linear levels of a linear image. rgb : (H, W, C) float, -> [(h_k, w_k, C) float32]."""
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or min(rgb.shape[:2]) < 1:
        raise InvalidParameter(f"expected an (H, W, C) image, got shape {rgb.shape}")
    levels = [rgb]
    for w, h in mip_sizes(rgb.shape[1], rgb.shape[0])[1:]:
        levels.append(_halve(_halve(levels[-1], 0), 1))
        assert levels[-1].shape[:2] == (h, w)
    return levels


def _rgba8_array(level: np.ndarray, srgb: bool = True) -> np.ndarray:
    """(h, w, 3 or 4) linear float -> (h, w, 4) uint8, colour sRGB-encoded (``srgb``) or
    the values themselves (data: normals, roughness), alpha straight."""
    out = np.empty(level.shape[:2] + (4,), dtype=np.uint8)
    if srgb:
        out[..., :3] = linear_to_srgb8(level[..., :3])
    else:
        out[..., :3] = np.clip(np.rint(level[..., :3] * 255.0), 0, 255)
    if level.shape[2] == 4:
        out[..., 3] = np.clip(np.rint(level[..., 3] * 255.0), 0, 255)
    else:
        out[..., 3] = 255
    return out


def _bc_blocks(rgba: np.ndarray, opaque: bool) -> bytes:
    """BC1 (opaque) or BC3 blocks of one (h, w, 4) uint8 level, padded to whole blocks."""
    h, w = rgba.shape[:2]
    pad = ((0, -h % BC_BLOCK), (0, -w % BC_BLOCK), (0, 0))
    padded = np.ascontiguousarray(np.pad(rgba, pad, mode="edge"))
    ph, pw = padded.shape[:2]
    encoder = BC1Encoder(BC_LEVEL) if opaque else BC3Encoder(BC_LEVEL)
    return encoder.encode(RawTexture.frombytes(padded.tobytes(), pw, ph)).tobytes()


def _bc7_blocks(rgba: np.ndarray, opaque: bool) -> bytes:
    """BC7 blocks of one (h, w, 4) uint8 level, padded to whole blocks by repeating its
    last row / column; rows of blocks top to bottom, as DDS stores them."""
    import etcpak   # here, not at import: 50 ms (its CPU probe) the API's start-up need not pay

    h, w = rgba.shape[:2]
    pad = ((0, -h % BC_BLOCK), (0, -w % BC_BLOCK), (0, 0))
    padded = np.ascontiguousarray(np.pad(rgba, pad, mode="edge"))
    params = etcpak.BC7CompressBlockParams()
    # error in R, G, B alike: the weights bc7enc calls perceptual (YCbCr) left a larger mean
    # error per channel on every test image (astronaut crop: 1.13 codes against 0.99)
    params.init_linear_weights()
    params.m_mode_mask = BC7_OPAQUE_MODES if opaque else BC7_ALL_MODES
    return etcpak.compress_bc7(padded.tobytes(), padded.shape[1], padded.shape[0], params)


def check_dds_compression(compression: str) -> None:
    """InvalidParameter unless ``compression`` is one of DDS_COMPRESSIONS."""
    if compression not in DDS_COMPRESSIONS:
        raise InvalidParameter(f"DDS compression must be one of {DDS_COMPRESSIONS}, got {compression!r}")


def dds_bytes(rgb: np.ndarray, compression: str = "bc1", srgb: bool = True) -> bytes:
    """A 2D DDS with the full mip chain of a linear (H, W, 3 or 4) image (see module doc):
    BC1, or BC3 with alpha, in the legacy header (``compression="bc1"``), or BC7 in the
    DX10 header (``"bc7"``). ``srgb``: the texels are colour, sRGB-encoded (a BC7 file then
    says ``BC7_UNORM_SRGB``); False for data maps, stored as they are (``BC7_UNORM``; the
    legacy header cannot say which)."""
    check_dds_compression(compression)
    levels = [_rgba8_array(level, srgb) for level in mip_chain(rgb)]
    opaque = all(bool((level[..., 3] == 255).all()) for level in levels)
    if compression == "bc7":
        blocks = [_bc7_blocks(level, opaque) for level in levels]
        four_cc = b"DX10"
    else:
        blocks = [_bc_blocks(level, opaque) for level in levels]
        four_cc = b"DXT1" if opaque else b"DXT5"
    h, w = levels[0].shape[:2]
    flags = 0x1 | 0x2 | 0x4 | 0x1000 | 0x20000 | 0x80000   # CAPS HEIGHT WIDTH PIXELFORMAT MIPMAPCOUNT LINEARSIZE
    pixel_format = struct.pack("<2I4s5I", 32, 0x4, four_cc, 0, 0, 0, 0, 0)   # DDPF_FOURCC
    caps = 0x1000 | 0x8 | 0x400000                     # TEXTURE COMPLEX MIPMAP
    header = struct.pack("<7I11I", 124, flags, h, w, len(blocks[0]), 0, len(levels), *([0] * 11))
    header += pixel_format + struct.pack("<5I", caps, 0, 0, 0, 0)
    if compression == "bc7":   # DDS_HEADER_DXT10: format, dimension, misc flags, array size, alpha mode
        dxgi_format = DXGI_FORMAT_BC7_UNORM_SRGB if srgb else DXGI_FORMAT_BC7_UNORM
        alpha_mode = DDS_ALPHA_MODE_OPAQUE if opaque else DDS_ALPHA_MODE_STRAIGHT
        header += struct.pack("<5I", dxgi_format, D3D10_RESOURCE_DIMENSION_TEXTURE2D, 0, 1, alpha_mode)
    return b"DDS " + header + b"".join(blocks)


def ktx2_bytes(rgb: np.ndarray) -> bytes:
    """A KTX 2.0 UASTC + Zstandard texture with the full mip chain of a linear (H, W, 3 or 4)
    image (see module doc), encoded on one thread."""
    levels = [_rgba8_array(level) for level in mip_chain(rgb)]
    opaque = all(bool((level[..., 3] == 255).all()) for level in levels)
    return alktx2.encode_raw_mips_to_ktx2(
        [(level.tobytes(), level.shape[1], level.shape[0]) for level in levels], has_alpha=not opaque,
        codec="uastc", effort=UASTC_EFFORT, srgb=True, threads=1, zstd_supercompression_level=ZSTD_LEVEL)


def check_gpu_options(fmt: str | None, dds_compression: str = "bc1") -> None:
    """InvalidParameter unless ``fmt`` (None: no GPU texture) is a GPU format and
    ``dds_compression`` is one of DDS_COMPRESSIONS, BC7 asked for only with a DDS."""
    if fmt is not None and fmt not in GPU_FORMATS:
        raise InvalidParameter(f"GPU texture format must be one of {GPU_FORMATS}, got {fmt!r}")
    check_dds_compression(dds_compression)
    if dds_compression != "bc1" and fmt != "dds":
        raise InvalidParameter(f"dds_compression {dds_compression!r} applies to a DDS texture only")


def gpu_texture_bytes(rgb: np.ndarray, fmt: str, dds_compression: str = "bc1") -> bytes:
    """``dds_bytes`` (with ``dds_compression``) or ``ktx2_bytes`` by name."""
    check_gpu_options(fmt, dds_compression)
    return dds_bytes(rgb, dds_compression) if fmt == "dds" else ktx2_bytes(rgb)
