"""eval/gpu_pack.py's corpus choice: the licence filter, the family round
robin and the size-bounded photo writing, on synthetic photos; and model.train's flags for a
new space's architecture (--code-size, --encoder-width, --hidden)."""
from __future__ import annotations

import importlib.util
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from model.train import build
from model.train_config import TrainConfig, parse_args

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def gpu_pack():
    spec = importlib.util.spec_from_file_location("gpu_pack_large", ROOT / "eval" / "gpu_pack.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _entry(name: str, family: str, kind: str, split: str = "train") -> dict:
    return {"name": name, "family": family, "licence_kind": kind, "split": split, "path": f"{split}/{name}.png"}


ENTRIES = [_entry("a1", "a", "GPL art"), _entry("a2", "a", "share-alike"), _entry("b1", "b", "public domain"),
           _entry("c1", "c", "attribution"), _entry("c2", "c", "GPL art"), _entry("c3", "c", "share-alike")]


def test_licence_filter_keeps_the_kinds_asked_for(gpu_pack):
    assert gpu_pack.licence_filter(ENTRIES, "all") == ENTRIES
    assert [e["name"] for e in gpu_pack.licence_filter(ENTRIES, "non-gpl")] == ["a2", "b1", "c1", "c3"]
    assert [e["name"] for e in gpu_pack.licence_filter(ENTRIES, "public domain, attribution")] == ["b1", "c1"]
    # the default corpus's index has the licence alone: its kind comes from model.corpus.LICENCES
    assert gpu_pack.licence_kind({"name": "x", "licence": "CC0-1.0"}) == "public domain"


def test_family_round_robin_takes_one_photo_per_family_first(gpu_pack):
    order = [e["name"] for e in gpu_pack.family_round_robin(list(reversed(ENTRIES)))]
    assert order == ["a1", "b1", "c1", "a2", "c2", "c3"]


def _noise_photo(path: Path, size: tuple[int, int], seed: int) -> None:
    """A high-entropy RGB photo (width, height): the worst case for a compressed pack."""
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(path)


def test_encode_photo_shrinks_crops_and_reads_back_as_jpeg(gpu_pack, tmp_path):
    _noise_photo(tmp_path / "wide.png", (1000, 500), 0)
    encoded = gpu_pack.encode_photo(tmp_path / "wide.png", 256, 384, 90)
    with Image.open(io.BytesIO(encoded)) as image:
        assert (image.format, image.size) == ("JPEG", (384, 256))
    _noise_photo(tmp_path / "small.png", (300, 150), 1)  # under the working size: kept, cropped in proportion
    with Image.open(io.BytesIO(gpu_pack.encode_photo(tmp_path / "small.png", 256, 384, 0))) as image:
        assert (image.format, image.size) == ("PNG", (225, 150))
    # training reads a packed JPEG through worker.decode at the working resolution as it is
    from model.data import load_exemplar

    path = tmp_path / "packed.jpg"
    path.write_bytes(encoded)
    assert load_exemplar(path, 256).shape == (256, 384, 3)


def test_pack_stays_within_its_photo_bound(gpu_pack, tmp_path, monkeypatch):
    corpus = tmp_path / "corpus"
    entries = [_entry(f"f{f}_{k}", f"f{f}", "GPL art" if f % 2 else "share-alike", split)
               for split, families in (("train", 6), ("val", 2)) for f in range(families) for k in range(3)]
    for k, entry in enumerate(entries):
        (corpus / entry["split"]).mkdir(parents=True, exist_ok=True)
        _noise_photo(corpus / entry["path"], (320, 256), k)
    (corpus / "index.json").write_text(json.dumps({"exemplars": entries}))
    monkeypatch.setattr(gpu_pack, "_quantised_vgg", lambda: b"vgg")  # (the real one needs the 59 MB cache)

    one = len(gpu_pack.encode_photo(corpus / entries[0]["path"], 256, 384, 90))  # ~same for every noise photo
    bound = 4.5 * one / gpu_pack.MIB
    manifest = gpu_pack.pack(str(tmp_path / "gpu"), str(corpus), "non-gpl", 90, 384, bound, val=1)
    files = sorted(p.name for p in (tmp_path / "gpu" / "data").iterdir())
    val = sorted(p.name for p in (tmp_path / "gpu" / "val").iterdir())
    written = sum(p.stat().st_size for folder in ("data", "val") for p in (tmp_path / "gpu" / folder).iterdir())
    assert written <= bound * gpu_pack.MIB
    assert val == ["f0_0.jpg"]  # at most --val, counted in the bound first
    # non-GPL families only (f0, f2, f4), one photo of each before any family's second
    assert files == ["f0_0.jpg", "f2_0.jpg", "f4_0.jpg"]
    assert manifest["splits"]["data"]["names"] == ["f0_0", "f2_0", "f4_0"]
    assert manifest["splits"]["data"]["licence_kinds"] == {"share-alike": 3}
    # the same options give the same photos (a run resumes only on the pack it started with)
    again = gpu_pack.pack(str(tmp_path / "again"), str(corpus), "non-gpl", 90, 384, bound, val=1)
    assert again["splits"] == manifest["splits"]


def test_pack_adds_the_default_corpus_outside_the_bound(gpu_pack, tmp_path, monkeypatch):
    # --add-default: the default corpus's training photos join the large ones in data/ (a
    # fine-tuned space keeps what it knew), its validation photos go to fitval/ (GPU fits of
    # what make quality measures); lossless at the working size, not counted in --photo-mib.
    large, default = tmp_path / "large", tmp_path / "default"
    entries = [_entry(f"f{f}", f"f{f}", "share-alike", split) for split, f in (("train", 0), ("train", 1), ("val", 2))]
    for k, entry in enumerate(entries):
        (large / entry["split"]).mkdir(parents=True, exist_ok=True)
        _noise_photo(large / entry["path"], (320, 256), k)
    (large / "index.json").write_text(json.dumps({"exemplars": entries}))
    for split, names in (("train", ["d_a", "d_b"]), ("val", ["d_v"])):
        (default / split).mkdir(parents=True)
        for k, name in enumerate(names):
            _noise_photo(default / split / f"{name}.png", (600, 512), 10 + k)
    monkeypatch.setattr(gpu_pack, "_quantised_vgg", lambda: b"vgg")
    monkeypatch.setitem(gpu_pack.CORPORA, "default", str(default))
    bound = 1.5 * len(gpu_pack.encode_photo(large / entries[0]["path"], 256, 384, 90)) / gpu_pack.MIB
    manifest = gpu_pack.pack(str(tmp_path / "gpu"), str(large), "non-gpl", 90, 384, bound, val=0, add_default=True)
    assert sorted(p.name for p in (tmp_path / "gpu" / "data").iterdir()) == ["d_a.png", "d_b.png", "f0.jpg"]
    assert [p.name for p in (tmp_path / "gpu" / "fitval").iterdir()] == ["d_v.png"]
    with Image.open(tmp_path / "gpu" / "fitval" / "d_v.png") as image:
        assert image.size == (300, 256)  # the working size, lossless
    assert manifest["splits"]["default train"] == {"photos": 2, "folder": "data", "names": ["d_a", "d_b"]}


def test_slim_checkpoint_keeps_buffers_exact_and_drops_adam_moments(gpu_pack, tmp_path):
    cfg = parse_args(["--out", str(tmp_path), "--code-size", "16"])
    torch.manual_seed(0)
    model, _ = build(cfg)
    optimizer = torch.optim.Adam(model.parameters())
    model.encoder.head[-1].bias.sum().backward()
    optimizer.step()
    full = {"config": model.cfg.to_dict(), "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "codes": torch.randn(3, 16)}
    torch.save(full, tmp_path / "full.pt")
    gpu_pack.slim(str(tmp_path / "full.pt"), str(tmp_path / "slim.pt"))
    slim = torch.load(tmp_path / "slim.pt", weights_only=False)
    assert slim["optimizer"]["state"] == {} and slim["optimizer"]["param_groups"]
    parameters = dict(model.named_parameters())
    for name, value in slim["model"].items():
        original = full["model"][name]
        if name in parameters:
            assert value.dtype == torch.float16
            torch.testing.assert_close(value.float(), original, rtol=1e-3, atol=1e-4)
        else:  # buffers (fixed rotations, seeds) are not relearnt: they travel exactly
            assert torch.equal(value, original)
    assert slim["codes"].dtype == torch.float16


def test_architecture_flags_parse_into_the_config_and_build_that_model(tmp_path):
    cfg = parse_args(["--out", str(tmp_path), "--code-size", "16", "--encoder-width", "16", "--hidden", "64"])
    assert (cfg.code_size, cfg.encoder_width, cfg.hidden) == (16, 16, 64)
    default = TrainConfig(out=str(tmp_path))  # not given: the shipped space's architecture
    assert (default.code_size, default.encoder_width, default.hidden) == (8, 32, 128)
    model, codes = build(cfg)
    assert codes is None  # from scratch: no --init
    assert (model.cfg.code_size, model.cfg.encoder_width, model.cfg.hidden) == (16, 16, 64)
    z = model.encode(torch.zeros(2, 3, 128, 128))
    assert z.shape == (2, 16)
