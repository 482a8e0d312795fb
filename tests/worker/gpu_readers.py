"""Readers for the GPU texture files the tests check: DDS through OpenImageIO (every mip
level, BC blocks decoded), a BC7 DDS's DX10 header by the DDS specification and its blocks
through ``texture2ddecoder`` (a decoder independent of the encoder); KTX2's layout by the
KTX 2.0 specification and its pixels through Basis Universal's transcoder (``alktx2``).
Khronos's libktx installs from no registry here (PyPI's pyktx has no Linux wheel and needs
it built; Debian has no package): tests/worker/test_open_in_tools.py validates and
transcodes the files with Binomial's ``basisu`` 1.16.4 and reads them with ``ktx-parse``
instead."""
from __future__ import annotations

import io
import struct

import alktx2
import numpy as np
import OpenImageIO as oiio
import texture2ddecoder
from PIL import Image

KTX2_ID = b"\xabKTX 20\xbb\r\n\x1a\n"


def read_dds_levels(path) -> list[np.ndarray]:
    """[(h, w, 4) uint8] of every mip level, as OpenImageIO decodes them."""
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    levels = []
    while inp.seek_subimage(0, len(levels)):
        levels.append(inp.read_image(0, len(levels), 0, 4, "uint8"))
    inp.close()
    return levels


def read_bc7_dds(data: bytes) -> tuple[dict, list[np.ndarray]]:
    """(header fields, [(h, w, 4) uint8 RGBA per level, level 0 first]) of a BC7 DDS with
    the DX10 header, checking its layout: the legacy header's size, flags and FourCC, the
    DX10 header, and that the levels' blocks (16 bytes per 4 x 4, each level padded to whole
    blocks) fill the file to its end."""
    assert data[:4] == b"DDS "
    size, flags, height, width, linear_size, _depth, mips = struct.unpack_from("<7I", data, 4)
    pf_size, pf_flags, four_cc = struct.unpack_from("<2I4s", data, 76)
    caps, = struct.unpack_from("<I", data, 108)
    assert (size, pf_size, pf_flags, four_cc) == (124, 32, 0x4, b"DX10")      # DDPF_FOURCC
    assert flags & 0x20000 and caps & 0x400000                                  # MIPMAPCOUNT, MIPMAP
    dxgi_format, dimension, misc, array_size, alpha_mode = struct.unpack_from("<5I", data, 128)
    header = dict(width=width, height=height, mips=mips, linear_size=linear_size, dxgi_format=dxgi_format,
                  dimension=dimension, misc=misc, array_size=array_size, alpha_mode=alpha_mode)
    levels, at = [], 148
    for k in range(mips):
        w, h = max(1, width >> k), max(1, height >> k)
        pw, ph = -(-w // 4) * 4, -(-h // 4) * 4
        blocks = data[at:at + 16 * (pw // 4) * (ph // 4)]
        assert len(blocks) == 16 * (pw // 4) * (ph // 4), f"level {k} is cut short"
        if k == 0:
            assert linear_size == len(blocks)
        bgra = np.frombuffer(texture2ddecoder.decode_bc7(blocks, pw, ph), np.uint8).reshape(ph, pw, 4)
        levels.append(bgra[:h, :w, [2, 1, 0, 3]])           # the decoder gives BGRA, padded to blocks
        at += len(blocks)
    assert at == len(data)
    return header, levels


def assert_block_compressed_close(got: np.ndarray, want: np.ndarray, mean: float, worst: int) -> None:
    """BC1 / BC3 keep each 4 x 4 block's colours on a line between two 5:6:5 end points:
    ``got`` (h, w, 3) uint8 is near, not equal to, ``want``: mean and largest absolute code
    error bounded, and, over levels of 4 blocks or more, no brightness drift (each channel's
    mean within 3 codes; one 5-bit end point alone can be 4 codes off)."""
    diff = np.abs(got.astype(np.int16) - want.astype(np.int16))
    assert diff.mean() < mean and diff.max() <= worst, (diff.mean(), diff.max())
    if got.shape[0] * got.shape[1] >= 64:
        drift = np.abs(got.mean(axis=(0, 1)) - want.mean(axis=(0, 1)))
        assert drift.max() < 3, (got.shape, drift)


def read_ktx2(data: bytes) -> tuple[dict, list[np.ndarray]]:
    """(header fields, [(h, w, 4) uint8 per level, level 0 first]), checking the layout."""
    assert data[:12] == KTX2_ID
    fields = struct.unpack_from("<9I", data, 12)
    header = dict(zip(("vk_format", "type_size", "width", "height", "depth", "layers", "faces",
                       "levels", "supercompression"), fields))
    dfd_off, dfd_len, kvd_off, kvd_len, sgd_off, sgd_len = struct.unpack_from("<4I2Q", data, 48)
    n = header["levels"]
    index = [struct.unpack_from("<3Q", data, 80 + 24 * k) for k in range(n)]
    assert dfd_off == 80 + 24 * n and kvd_off == dfd_off + dfd_len
    # DFD: total size, then one basic block (24 bytes + 16 per sample)
    total, = struct.unpack_from("<I", data, dfd_off)
    assert total == dfd_len
    vendor_type, version, block_size = struct.unpack_from("<IHH", data, dfd_off + 4)
    model, primaries, transfer, flags = data[dfd_off + 12:dfd_off + 16]
    header.update(dfd=dict(vendor_type=vendor_type, version=version, model=model, primaries=primaries,
                           transfer=transfer, flags=flags, block=tuple(d + 1 for d in data[dfd_off + 16:dfd_off + 18]),
                           samples=(block_size - 24) // 16))
    # key/value data: length-prefixed "key\0value", each padded to 4 bytes, keys sorted
    kv, at = {}, kvd_off
    while at < kvd_off + kvd_len:
        length, = struct.unpack_from("<I", data, at)
        key, value = data[at + 4:at + 4 + length].split(b"\0", 1)
        kv[key.decode()] = value
        at += 4 + length + (-length % 4)
    assert list(kv) == sorted(kv)
    header["kv"] = kv
    # levels: stored smallest first after the key/value and supercompression data, to the
    # end of the file; each inflates to whole 16-byte UASTC blocks
    end = max(kvd_off + kvd_len, sgd_off + sgd_len)
    for k in reversed(range(n)):
        offset, length, uncompressed = index[k]
        assert offset >= end and length > 0
        w, h = max(1, header["width"] >> k), max(1, header["height"] >> k)
        assert uncompressed == 16 * -(-w // 4) * -(-h // 4)          # 16-byte UASTC blocks
        end = offset + length
    assert end == len(data)
    levels = []
    for k in range(n):
        w, h = max(1, header["width"] >> k), max(1, header["height"] >> k)
        png, _ = alktx2.decode_ktx2_to_bytes(data, format="png", level=k)
        decoded = np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))
        levels.append(decoded[:h, :w])                                # the transcoder pads to blocks
    return header, levels
