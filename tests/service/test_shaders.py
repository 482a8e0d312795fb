"""Shader sources (``service/shaders.py``): generated once per texture version, one at a
time, a bounded few waiting (16 concurrent 731 kB shaders once slowed the texture list
from 0.013 s to 2.34 s)."""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from service import shaders
from worker.errors import Busy


@pytest.fixture
def generations(monkeypatch) -> dict:
    """Fresh SOURCES; counts calls of the real ``emit_shader`` and how many ran at once."""
    monkeypatch.setattr(shaders, "SOURCES", shaders.ShaderSources())
    seen = {"calls": 0, "now": 0, "most": 0}
    lock = threading.Lock()
    emit = shaders.emit_shader

    def counting(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        with lock:
            seen["calls"] += 1
            seen["now"] += 1
            seen["most"] = max(seen["most"], seen["now"])
        try:
            time.sleep(0.05)             # widen the window in which two could overlap
            return emit(*args, **kwargs)
        finally:
            with lock:
                seen["now"] -= 1

    monkeypatch.setattr(shaders, "emit_shader", counting)
    return seen


def test_a_repeat_is_served_from_memory(client, texture, generations) -> None:
    url = f"/v1/textures/{texture['id']}/shader.glsl"
    first, again = client.get(url), client.get(url)
    assert first.status_code == again.status_code == 200
    assert again.content == first.content and again.headers["etag"] == first.headers["etag"]
    assert generations["calls"] == 1
    assert client.get(url, headers={"If-None-Match": first.headers["etag"]}).status_code == 304
    assert client.get(f"/v1/textures/{texture['id']}/shader.wgsl").status_code == 200
    assert generations["calls"] == 2


def test_concurrent_requests_generate_one_at_a_time_once_each(client, texture, generations) -> None:
    urls = [f"/v1/textures/{texture['id']}/shader.{language}" for language in ("glsl", "wgsl")] * 4
    with ThreadPoolExecutor(len(urls)) as pool:
        answers = list(pool.map(client.get, urls))
    assert [a.status_code for a in answers] == [200] * len(urls)
    assert generations["calls"] == 2 and generations["most"] == 1, generations
    assert len({a.content for a in answers[0::2]}) == 1 and len({a.content for a in answers[1::2]}) == 1


def test_beyond_the_queue_is_503_busy_with_retry_after(client, texture, generations) -> None:
    sources = shaders.SOURCES
    sources.depth = 0
    sources._making.add("another texture's shader")      # the one generation slot is taken
    try:
        res = client.get(f"/v1/textures/{texture['id']}/shader.glsl")
    finally:
        sources._making.clear()
    assert res.status_code == 503, res.text
    assert res.headers["content-type"] == "application/problem+json"
    assert res.json()["type"] == "urn:texspace:problem:busy" and int(res.headers["retry-after"]) >= 1
    assert client.get(f"/v1/textures/{texture['id']}/shader.glsl").status_code == 200
    assert generations["calls"] == 1


def test_waiting_callers_are_bounded_and_served_in_turn() -> None:
    sources = shaders.ShaderSources(workers=1, depth=1, wait_seconds=5)
    started, release = threading.Event(), threading.Event()

    def slow() -> bytes:
        started.set()
        release.wait(5)
        return b"a"

    with ThreadPoolExecutor(2) as pool:
        making = pool.submit(sources.get, "a", slow)
        started.wait(5)
        waiting = pool.submit(sources.get, "b", lambda: b"b")       # waits for the slot
        time.sleep(0.05)
        with pytest.raises(Busy) as busy:                           # one waits already: refused
            sources.get("c", lambda: b"c")
        assert busy.value.retry_after >= 1 and "1 shader requests are waiting" in busy.value.detail
        release.set()
        assert making.result(5) == b"a" and waiting.result(5) == b"b"
    assert sources.get("a", lambda: b"not again") == b"a"            # from memory


def test_textures_with_one_code_keep_their_own_names(client, photo, generations) -> None:
    """Two uploads of one photo share code and ETag, not text: each names its own function."""
    from tests.service.helpers import upload_photo

    first, second = upload_photo(client, photo), upload_photo(client, photo)
    texts = [client.get(f"/v1/textures/{t['id']}/shader.glsl").text for t in (first, second)]
    assert f"texspace_{first['id']}(" in texts[0] and f"texspace_{second['id']}(" in texts[1]
