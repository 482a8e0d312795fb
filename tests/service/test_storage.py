"""One behaviour test mixin run against every storage backend (local folder, S3 via moto)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from service.storage import LocalStorage, S3Storage, StorageKeyError


class StorageContract:
    """Behaviour every Storage must have; subclasses provide the ``storage`` fixture."""

    def test_put_get_roundtrip(self, storage, tmp_path: Path) -> None:
        data = bytes(range(256)) * 5000  # > 1 chunk boundary is not required, but several KB
        assert storage.put_bytes("jobs/a/result/x.bin", data) == len(data)
        assert storage.get_bytes("jobs/a/result/x.bin") == data
        assert storage.size("jobs/a/result/x.bin") == len(data)
        dest = storage.get_file("jobs/a/result/x.bin", tmp_path / "out" / "x.bin")
        assert dest.read_bytes() == data
        assert b"".join(storage.iter_chunks("jobs/a/result/x.bin", 1000)) == data

    def test_overwrite_replaces_whole_object(self, storage) -> None:
        storage.put_bytes("k/v", b"first version, long")
        storage.put_bytes("k/v", b"second")
        assert storage.get_bytes("k/v") == b"second"

    def test_missing_key(self, storage, tmp_path: Path) -> None:
        assert not storage.exists("nope/x")
        with pytest.raises(StorageKeyError):
            storage.size("nope/x")
        with pytest.raises(StorageKeyError):
            storage.iter_chunks("nope/x")
        with pytest.raises(StorageKeyError):
            storage.get_file("nope/x", tmp_path / "x")

    def test_delete_prefix(self, storage) -> None:
        storage.put_bytes("textures/t1/a.png", b"a")
        storage.put_bytes("textures/t1/b/c.png", b"c")
        storage.put_bytes("textures/t2/a.png", b"keep")
        assert storage.delete_prefix("textures/t1") == 2
        assert not storage.exists("textures/t1/a.png")
        assert storage.get_bytes("textures/t2/a.png") == b"keep"

    def test_delete_one_object(self, storage) -> None:
        storage.put_bytes("textures/t1/sampler.onnx", b"s")
        storage.put_bytes("textures/t1/sampler.onnx.kept", b"k")
        assert storage.delete("textures/t1/sampler.onnx") is True
        assert storage.delete("textures/t1/sampler.onnx") is False  # already gone
        assert not storage.exists("textures/t1/sampler.onnx")
        assert storage.get_bytes("textures/t1/sampler.onnx.kept") == b"k"

    @pytest.mark.parametrize("key", ["../x", "/abs", "a//b", "a/./b", ""])
    def test_rejects_unsafe_keys(self, storage, key: str) -> None:
        with pytest.raises(ValueError):
            storage.put_bytes(key, b"x")

    def test_ping(self, storage) -> None:
        storage.ping()


class TestLocalStorage(StorageContract):
    @pytest.fixture
    def storage(self, tmp_path: Path) -> LocalStorage:
        return LocalStorage(tmp_path / "store")

    def test_ping_fails_when_its_folder_is_gone(self, storage) -> None:
        storage.ping()
        shutil.rmtree(storage.root)
        with pytest.raises(OSError, match="not writable"):
            storage.ping()

    def test_local_path_points_at_file(self, storage) -> None:
        storage.put_bytes("a/b.txt", b"hi")
        assert storage.local_path("a/b.txt").read_bytes() == b"hi"
        assert not list(storage.root.rglob(".tmp-*"))

    def test_a_failed_write_leaves_no_folder_it_made(self, storage, monkeypatch) -> None:
        # an upload that failed for space left an empty textures/<id>/ behind
        import errno
        import os

        storage.put_bytes("textures/kept/a.png", b"a")

        def full(src, dst, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), dst)

        monkeypatch.setattr(shutil, "copyfile", full)
        for key in ("textures/new/refined/j-1/sampler.onnx", "textures/kept/refined/sampler.onnx", "jobs/j/x"):
            with pytest.raises(OSError):
                storage.put_bytes(key, b"never stored")
        folders = sorted(str(p.relative_to(storage.root)) for p in storage.root.rglob("*") if p.is_dir())
        assert folders == ["textures", "textures/kept"]
        assert [p.name for p in storage.root.rglob("*") if p.is_file()] == ["a.png"]

    def test_a_delete_removes_the_folders_it_leaves_empty(self, storage) -> None:
        storage.put_bytes("textures/t/refined/j-1/interim/sampler.onnx", b"s")
        storage.put_bytes("textures/u/refined/j-1/interim/sampler.onnx", b"s")
        storage.put_bytes("textures/u/exemplar.png", b"e")
        assert storage.delete_prefix("textures/t/refined/j-1/interim") == 1
        assert storage.delete_prefix("textures/u/refined/j-1/interim") == 1
        folders = sorted(str(p.relative_to(storage.root)) for p in storage.root.rglob("*") if p.is_dir())
        assert folders == ["textures", "textures/u"]  # up to the top level, and only while empty
        storage.put_bytes("textures/t/refined/j-2/sampler.onnx", b"s")  # a folder pruned is made again
        assert storage.get_bytes("textures/t/refined/j-2/sampler.onnx") == b"s"


class TestS3Storage(StorageContract):
    @pytest.fixture
    def storage(self, moto_s3_url: str, request) -> S3Storage:
        bucket = "t-" + request.node.name.lower().replace("_", "-").replace("[", "-").strip("]-")[:40]
        bucket = "".join(c if c.isalnum() or c == "-" else "-" for c in bucket)
        return S3Storage(bucket=bucket, prefix="pre", endpoint_url=moto_s3_url,
                         access_key="test", secret_key="test")
