"""``texspace upload``: several photos, or a folder of them, to a running server (here the
app itself, through the TestClient's transport), one after another with a line per file."""
from __future__ import annotations

from pathlib import Path

import pytest

from service import cli
from service.client import Client
from tests.helpers import brick_png


@pytest.fixture
def to_app(client, monkeypatch) -> list[str]:
    """Point ``upload`` at the app; the URLs it was given."""
    urls: list[str] = []

    def app_client(url: str, api_key: str | None, timeout: float) -> Client:
        urls.append(url)
        return Client("http://testserver", api_key=api_key, timeout=timeout, transport=client._transport)

    monkeypatch.setattr(cli, "_api_client", app_client)
    return urls


def test_upload_files_and_a_folder_one_after_another(client, to_app, tmp_path: Path, capsys) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in ("b.png", "a.PNG", "notes.txt"):
        (folder / name).write_bytes(brick_png() if name != "notes.txt" else b"not a photo")
    (folder / "sub").mkdir()
    (folder / "sub" / "c.png").write_bytes(brick_png())         # subfolders are not read
    single = tmp_path / "oak planks.png"
    single.write_bytes(brick_png())
    cli.main(["upload", str(single), str(folder), "--url", "http://example.test:9"])
    lines = capsys.readouterr().out.splitlines()
    assert to_app == ["http://example.test:9"] and len(lines) == 3
    assert [line.split(": ")[0] for line in lines] == [f"[1/3] {single}", f"[2/3] {folder / 'a.PNG'}",
                                                       f"[3/3] {folder / 'b.png'}"]
    names = sorted(t["name"] for t in client.get("/v1/textures").json()["items"])
    assert names == ["a.PNG", "b.png", "oak planks.png"]


def test_a_failed_upload_is_reported_and_the_rest_go_on(client, to_app, tmp_path: Path, capsys) -> None:
    bad, good = tmp_path / "bad.png", tmp_path / "good.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    good.write_bytes(brick_png())
    with pytest.raises(SystemExit) as exit_:
        cli.main(["upload", str(bad), str(good)])
    out, err = capsys.readouterr()
    assert exit_.value.code == 1 and "1 of 2 uploads failed" in err
    first, second = out.splitlines()
    assert first.startswith(f"[1/2] {bad}: failed: 422") and second.startswith(f"[2/2] {good}: texture ")


def test_upload_refuses_what_it_cannot_send(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        cli.main(["upload", str(tmp_path / "missing.png")])
    assert exit_.value.code == 2 and "no such file or folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        cli.main(["upload", str(tmp_path)])                   # an empty folder
    assert exit_.value.code == 2 and "no image files" in capsys.readouterr().err
    photo = tmp_path / "p.png"
    photo.write_bytes(brick_png())
    with pytest.raises(SystemExit) as exit_:                  # nothing listens there
        cli.main(["upload", str(photo), "--url", "http://127.0.0.1:9", "--timeout", "5"])
    assert exit_.value.code == 1 and "cannot reach the server" in capsys.readouterr().err
