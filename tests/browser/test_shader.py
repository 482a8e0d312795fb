"""The texture shaders (GET /v1/textures/{id}/shader.glsl|.wgsl) against the ONNX sampler.

A 128^2 patch of an uploaded texture is rendered in headless Chromium on its software
renderer (SwiftShader): the GLSL through WebGL2 into a float render target, the WGSL
through WebGPU as a compute shader (which also runs the browser's WGSL compiler, Tint, as
the validator). Both must match the sampler at the same float32-exact points within 1/255
mean absolute difference; the means and maxima are written to tests/artifacts/browser/.
Each shader takes ~1 minute to compile on SwiftShader.
"""
from __future__ import annotations

import json
import urllib.request
import uuid
from pathlib import Path

import numpy as np
import pytest

from tests.browser.helpers import CHROMIUM, CHROMIUM_FLAGS
from tests.browser.helpers import texture_photo_png
from worker import shader
from worker.colour_match import texture_vector
from worker.runtime import SamplerSession
from worker.triplanar import sample_triplanar, triplanar_weights

pytestmark = pytest.mark.slow
HERE = Path(__file__).resolve().parent
SAMPLER = HERE.parents[1] / "model" / "weights" / "sampler.onnx"
SIZE, SCALE, ORIGIN, SEED = 128, 1.0 / 256.0, (3.0, -2.0, 0.3), 7
LIMIT = 1.0 / 255.0


@pytest.fixture(scope="module")
def gpu_page(base_url, tmp_path_factory, playwright):
    """A page of the running service (a secure context, so WebGPU is exposed) in a Chromium
    of its own with WebGPU enabled (the shared fixture's flags leave it off)."""
    context = playwright.chromium.launch_persistent_context(
        str(tmp_path_factory.mktemp("chromium-gpu")), executable_path=str(CHROMIUM), headless=True,
        args=[*CHROMIUM_FLAGS, "--enable-unsafe-webgpu"])
    try:
        page = context.new_page()
        page.set_default_timeout(600_000)
        page.goto(base_url)
        yield page
    finally:
        context.close()


@pytest.fixture(scope="module")
def uploaded(base_url) -> dict:
    boundary = uuid.uuid4().hex
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"image\"; filename=\"brick.png\"\r\n"
            f"Content-Type: image/png\r\n\r\n").encode() + texture_photo_png() + f"\r\n--{boundary}--\r\n".encode()
    request = urllib.request.Request(base_url + "v1/textures", data=body, method="POST",
                                     headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
    with urllib.request.urlopen(request, timeout=120) as response:
        return json.load(response)


def structured_sampler(folder: Path, **structure) -> Path:
    """A sampler as a fit with ``structure`` (ModelConfig's lattice, lattice_cell, grain)
    makes one: the shipped space's weights, a mean repeat cell and phase weights drawn at
    random (a fit measures and learns them; any values take the same path through the
    shader)."""
    torch = pytest.importorskip("torch", reason="exporting a sampler needs the train extra")
    from model.export import export_sampler
    from model.networks import ModelConfig, TextureSpace

    checkpoint = torch.load(SAMPLER.parent / "space.pt", map_location="cpu", weights_only=False)
    field = TextureSpace(ModelConfig(**{**checkpoint["config"], **structure})).field
    state = {k[len("field."):]: v for k, v in checkpoint["model"].items() if k.startswith("field.")}
    missing, _ = field.load_state_dict(state, strict=False)
    assert sorted(missing) == ["decoder.from_phase.weight", "lattice_mean_cell"], missing
    torch.manual_seed(0)
    torch.nn.init.normal_(field.decoder.from_phase.weight, std=0.5)
    field.lattice_mean_cell.normal_()
    export_sampler(field.eval(), folder / "sampler.onnx")
    return folder / "sampler.onnx"


@pytest.fixture(scope="module")
def lattice_sampler(tmp_path_factory) -> Path:
    """Fitted on a running bond (world units), as a fit of a brick wall is: each brick its own
    shade (lattice_shade, as fits since 2026-12-04 have)."""
    return structured_sampler(tmp_path_factory.mktemp("lattice-sampler"), lattice=(0.125, 0.0, -0.054, 0.0417),
                              lattice_cell=(32, 13), lattice_shade=True)


@pytest.fixture(scope="module")
def boards_sampler(tmp_path_factory) -> Path:
    """Fitted on boards, as a fit of a plank floor was before 2026-12-04: grain along y (a
    strong one: cells 16x longer along it) and stripes across it, no cell shades."""
    return structured_sampler(tmp_path_factory.mktemp("boards-sampler"), lattice=(0.1, 0.0, 0.0, 0.1),
                              lattice_cell=(26, 26), grain="y", grain_stretch=16.0)


@pytest.fixture(scope="module")
def mask_noise_sampler(tmp_path_factory) -> Path:
    """The shipped space with the noise of samplers exported before 2026-11-26."""
    pytest.importorskip("torch", reason="exporting a sampler needs the train extra")
    from tests.helpers import export_mask_noise_sampler

    path = tmp_path_factory.mktemp("mask-sampler") / "sampler.onnx"
    export_mask_noise_sampler(path)
    return path


def points() -> np.ndarray:
    """The shader's points, exactly: origin + (pixel centre) * scale in float32, row-major, y up."""
    j, i = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32)
    o = np.asarray(ORIGIN, np.float32)
    xyz = [o[0] + (i + np.float32(0.5)) * np.float32(SCALE), o[1] + (j + np.float32(0.5)) * np.float32(SCALE),
           np.full(i.shape, o[2], np.float32)]
    return np.stack(xyz, -1).reshape(-1, 3).astype(np.float64)


def render(gpu_page, source: str, name: str, language: str) -> tuple[np.ndarray, dict]:
    """The shader's linear RGB [SIZE * SIZE, 3] at ``points()`` in Chromium, and the harness's result."""
    harness = (HERE / f"shader_harness{'_wgsl' if language == 'wgsl' else ''}.js").read_text()
    result = gpu_page.evaluate(harness, dict(source=source, name=name, size=SIZE, origin=list(ORIGIN),
                                             scale=SCALE, seed=SEED))
    assert not result.get("error"), (result.get("error"), result.get("messages"))
    return np.asarray(result["pixels"], np.float32).reshape(SIZE * SIZE, 4)[:, :3], result


def check_emitted(gpu_page, sampler_path: Path, vector, name: str, language: str, artifacts, label: str) -> None:
    """The shader emitted from ``sampler_path`` matches that sampler, and that sampler differs
    from the shipped one (so the check sees the difference it is about)."""
    got, _ = render(gpu_page, shader.emit_shader(sampler_path, vector, name, language), name, language)
    want = SamplerSession(sampler_path, threads=1).sample(points(), vector, SEED)
    shipped = SamplerSession(SAMPLER, threads=1).sample(points(), vector, SEED)
    diff = np.abs(got - want)
    report = {"language": language, label: True, "mean_abs_255": float(diff.mean() * 255),
              "max_abs_255": float(diff.max() * 255), "effect_255": float(np.abs(want - shipped).mean() * 255)}
    (artifacts / f"shader_{label}_{language}.json").write_text(json.dumps(report, indent=2) + "\n")
    assert np.abs(want - shipped).mean() > 4 * LIMIT, report
    assert diff.mean() <= LIMIT, report
    assert diff.max() <= 8 * LIMIT, report


@pytest.mark.parametrize("language", ["glsl", "wgsl"])
def test_shader_matches_the_sampler(gpu_page, base_url, uploaded, artifacts, language):
    with urllib.request.urlopen(f"{base_url}v1/textures/{uploaded['id']}/shader.{language}", timeout=120) as r:
        source = r.read().decode()
    got, result = render(gpu_page, source, f"texspace_{uploaded['id']}", language)
    vector = texture_vector(uploaded["code"], uploaded["colour"])
    want = SamplerSession(SAMPLER, threads=1).sample(points(), vector, SEED)
    diff = np.abs(got - want)
    report = {"language": language, "size": SIZE, "mean_abs": float(diff.mean()), "max_abs": float(diff.max()),
              "mean_abs_255": float(diff.mean() * 255), "max_abs_255": float(diff.max() * 255),
              "compile_ms": result.get("compileMs"), "draw_ms": result.get("drawMs"),
              "compiler_messages": result.get("messages", [])}
    (artifacts / f"shader_{language}.json").write_text(json.dumps(report, indent=2) + "\n")
    assert want.std() > 0.01  # a textured patch, not a flat one
    assert diff.mean() <= LIMIT, report
    assert diff.max() <= 8 * LIMIT, report


@pytest.mark.parametrize("language", ["glsl", "wgsl"])
def test_triplanar_helper_matches_the_bakes_projection(gpu_page, uploaded, artifacts, language):
    """``<name>_triplanar`` blends the same three projections with the same weights as a
    triplanar bake (worker/triplanar.py), here with a normal that blends all three."""
    vector = texture_vector(uploaded["code"], uploaded["colour"])
    name, normal = "texspace_walls", (0.62, 0.55, 0.56)
    probe = (f"vec3 probe(vec3 p, uint seed) {{ return {name}_triplanar(p, vec3{normal}, seed); }}\n"
             if language == "glsl" else
             f"fn probe(p: vec3<f32>, seed: u32) -> vec3<f32> {{ return {name}_triplanar(p, vec3<f32>{normal}, seed); }}\n")
    got, _ = render(gpu_page, shader.emit_shader(SAMPLER, vector, name, language) + probe, "probe", language)
    session = SamplerSession(SAMPLER, threads=1)
    want = sample_triplanar(session, points(), np.tile(normal, (SIZE * SIZE, 1)), vector, SEED)
    assert triplanar_weights(np.array([normal])).min() > 0.2  # all three projections take part
    diff = np.abs(got - want)
    report = {"language": language, "mean_abs_255": float(diff.mean() * 255), "max_abs_255": float(diff.max() * 255),
              "effect_255": float(np.abs(want - session.sample(points(), vector, SEED)).mean() * 255)}
    (artifacts / f"shader_triplanar_{language}.json").write_text(json.dumps(report, indent=2) + "\n")
    assert report["effect_255"] > 4, report
    assert diff.mean() <= LIMIT, report
    assert diff.max() <= 8 * LIMIT, report


@pytest.mark.parametrize("language", ["glsl", "wgsl"])
def test_lattice_shader_matches_its_sampler(gpu_page, lattice_sampler, uploaded, artifacts, language):
    """A texture fitted on a repeat lattice (bricks, tile grids): the shader computes each
    point's phase on the lattice and reads the photo's mean repeat cell there as the sampler
    does (model/networks.py lattice_phases); the phases change the texture."""
    vector = texture_vector(uploaded["code"], uploaded["colour"])
    check_emitted(gpu_page, lattice_sampler, vector, "texspace_bricks", language, artifacts, "lattice")


@pytest.mark.parametrize("language", ["glsl", "wgsl"])
def test_boards_shader_matches_its_sampler(gpu_page, boards_sampler, uploaded, artifacts, language):
    """Boards (a plank floor's fit): noise stretched along the grain and phases across it,
    both in one shader, as in the sampler."""
    vector = texture_vector(uploaded["code"], uploaded["colour"])
    check_emitted(gpu_page, boards_sampler, vector, "texspace_planks", language, artifacts, "boards")


@pytest.mark.parametrize("language", ["glsl", "wgsl"])
def test_shader_of_a_sampler_with_the_earlier_noise(gpu_page, mask_noise_sampler, uploaded, artifacts, language):
    """A texture stored before 2026-11-26 (masked 10-bit fields of a full lowbias32 hash)
    gets a shader with that noise, not today's."""
    vector = texture_vector(uploaded["code"], uploaded["colour"])
    check_emitted(gpu_page, mask_noise_sampler, vector, "texspace_earlier", language, artifacts, "mask_noise")
