"""Result names a person can tell apart: texture, size, seed, tileable; RFC 6266 for non-ASCII."""
from __future__ import annotations

import io
import zipfile
from urllib.parse import unquote

from service.download_names import bake_name, content_disposition, region_name, sampler_name, slug, volume_name

from .conftest import upload_photo


def test_slugs_keep_words_and_drop_the_photo_extension() -> None:
    assert slug("Oak Planks (2).JPG", "abc") == "oak-planks-2"
    assert slug("oak_planks.tar", "abc") == "oak-planks-tar"          # not a photo's extension
    assert slug("Béton brut", "abc") == "béton-brut"
    assert slug("Béton brut", "abc", ascii_only=True) == "beton-brut"
    assert slug("木目", "abc12345", ascii_only=True) == "abc12345"     # nothing left in ASCII: the id
    assert slug("../../etc/passwd", "abc") == "etc-passwd"
    assert len(slug("x" * 500, "abc")) == 60


def test_names_carry_size_seed_and_tileable() -> None:
    assert region_name("Oak planks.jpg", "f00", z=6, width=1024, height=1024, seed=7, plane="xy",
                       tileable=False, ext=".png") == "oak-planks_region_z6_1024px_seed7.png"
    assert region_name("oak", "f00", z=5, width=300, height=200, seed=0, plane="xz", tileable=False,
                       ext=".tif") == "oak_region_z5_300x200px_xz_seed0.tif"
    assert region_name("oak", "f00", z=6, width=512, height=512, seed=1, plane="xy", tileable=True,
                       ext=".zip") == "oak_region_z6_512px_seed1_tileable.zip"
    assert bake_name("oak", "f00", mesh_filename="Teapot.obj", resolution=2048, seed=3,
                     ext=".glb") == "oak_teapot_bake_2048px_seed3.glb"
    assert volume_name(None, "0123456789", resolution=128, seed=2, ext=".vdb") == "01234567_volume_128px_seed2.vdb"
    assert sampler_name("oak", "f00") == "oak_sampler.onnx"


def test_content_disposition_has_an_ascii_name_and_filename_star() -> None:
    assert content_disposition("oak_region.png") == 'attachment; filename="oak_region.png"'
    header = content_disposition("béton_木.png")
    plain, star = header.split("; ")[1:]
    assert plain == 'filename="beton__.png"' and plain.isascii()
    assert unquote(star.removeprefix("filename*=UTF-8''")) == "béton_木.png"


def test_a_region_download_is_named_for_its_texture(client, photo) -> None:
    texture = upload_photo(client, photo, name="Béton brut")
    res = client.post(texture["links"]["regions"], json={"z": 6, "x0": 0, "y0": 0, "width": 64, "height": 64,
                                                         "seed": 7, "maps": ["normal"]})
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    assert job["result"]["filename"] == "béton-brut_region_z6_64px_seed7.zip"
    download = client.get(job["links"]["result"])
    assert download.headers["content-disposition"] == (
        "attachment; filename=\"beton-brut_region_z6_64px_seed7.zip\"; "
        "filename*=UTF-8''b%C3%A9ton-brut_region_z6_64px_seed7.zip")
    with zipfile.ZipFile(io.BytesIO(download.content)) as z:   # members: ASCII, after the result
        assert sorted(z.namelist()) == ["beton-brut_region_z6_64px_seed7_basecolor.png",
                                        "beton-brut_region_z6_64px_seed7_normal.png"]
