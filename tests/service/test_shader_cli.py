"""``texspace shader``: an image file's texture as GLSL or WGSL, language by extension."""
from __future__ import annotations

from pathlib import Path

import pytest

from service.cli import main


def test_shader_command_writes_glsl_and_wgsl(tmp_path: Path, photo: bytes, monkeypatch, capsys):
    monkeypatch.setenv("TEXSPACE_DATA_DIR", str(tmp_path / "data"))
    image = tmp_path / "brick.png"
    image.write_bytes(photo)
    main(["shader", str(image), "-o", str(tmp_path / "brick.glsl")])
    assert "vec3 texspace_brick(vec3 p, uint seed)" in (tmp_path / "brick.glsl").read_text()
    main(["shader", str(image), "-o", str(tmp_path / "brick.wgsl")])
    assert "fn texspace_brick(p: vec3<f32>, seed: u32) -> vec3<f32>" in (tmp_path / "brick.wgsl").read_text()
    with pytest.raises(SystemExit) as exit_:
        main(["shader", str(image), "-o", str(tmp_path / "brick.hlsl")])
    assert exit_.value.code == 2 and "cannot tell the format" in capsys.readouterr().err
