"""Where uploads and job results live: a local folder or an S3-compatible bucket.

One small interface (:class:`Storage`); :func:`make_storage` picks the implementation
from the settings. Keys are ``/``-separated relative paths (``textures/<id>/exemplar.png``,
``jobs/<id>/result/volume.npy``). Writes are atomic: readers see the old object or the
whole new one, never half a file, so a re-run job overwrites its key with equal content.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from .settings import Settings

CHUNK_BYTES = 1 << 20


class StorageKeyError(KeyError):
    """The key does not exist."""


def _check_key(key: str) -> str:
    parts = key.split("/")
    if not key or key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"invalid storage key: {key!r}")
    return key


class Storage:
    """Interface of every storage backend."""

    def put_file(self, key: str, path: Path) -> int:
        """Store the file at ``path`` under ``key`` atomically; return its size in bytes."""
        raise NotImplementedError

    def put_bytes(self, key: str, data: bytes) -> int:
        """Store ``data`` under ``key`` atomically; return its size."""
        fd, tmp = tempfile.mkstemp()
        try:  # removed whatever fails, a write to a full temporary folder too
            with os.fdopen(fd, "wb") as file:
                file.write(data)
            return self.put_file(key, Path(tmp))
        finally:
            os.unlink(tmp)

    def get_file(self, key: str, dest: Path) -> Path:
        """Copy the object to the local path ``dest`` (atomically); raise StorageKeyError."""
        raise NotImplementedError

    def get_bytes(self, key: str) -> bytes:
        """The whole object; raise StorageKeyError."""
        return b"".join(self.iter_chunks(key))

    def iter_chunks(self, key: str, chunk_bytes: int = CHUNK_BYTES) -> Iterator[bytes]:
        """Stream the object in chunks; raise StorageKeyError before the first chunk."""
        raise NotImplementedError

    def size(self, key: str) -> int:
        """Size in bytes; raise StorageKeyError."""
        raise NotImplementedError

    def exists(self, key: str) -> bool:
        try:
            self.size(key)
            return True
        except StorageKeyError:
            return False

    def delete(self, key: str) -> bool:
        """Delete one object; False if there was none."""
        raise NotImplementedError

    def delete_prefix(self, prefix: str) -> int:
        """Delete every object whose key starts with ``prefix/``; return how many."""
        raise NotImplementedError

    def local_path(self, key: str) -> Path | None:
        """A local file holding the object, if this backend has one (lets HTTP send files)."""
        return None

    def ping(self) -> None:
        """Raise if the backend is unreachable."""


def _gone_already(function, path, exc_info) -> None:  # noqa: ANN001 (shutil.rmtree's onerror)
    """rmtree's error hook: a file or folder another delete removed first is fine; the rest raises."""
    if not issubclass(exc_info[0], FileNotFoundError):
        raise exc_info[1]


class LocalStorage(Storage):
    """Files under a root folder; writes go to a temporary file then ``os.replace``.
    Folders exist only while they hold files: a write that fails removes the folders it
    made, and a delete the folders it leaves empty (a texture's folder does not outlive it)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str) -> Path:
        return self.root / _check_key(key)

    def put_file(self, key: str, path: Path) -> int:
        dest = self._path(key)
        made = self._missing_folders(dest.parent)
        tmp = None
        try:
            tmp = self._temporary_in(dest.parent)
            shutil.copyfile(path, tmp)
            os.replace(tmp, dest)
        except BaseException:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
            self._remove_empty(made)  # a write that failed (for space, say) leaves no empty folder
            raise
        return dest.stat().st_size

    def _missing_folders(self, folder: Path) -> list[Path]:
        """The folders from ``folder`` up that do not exist yet, deepest first."""
        missing = []
        while folder != self.root and not folder.exists():
            missing.append(folder)
            folder = folder.parent
        return missing

    @staticmethod
    def _temporary_in(folder: Path) -> str:
        """A new empty file in ``folder``, made first (again if a delete pruned it meanwhile)."""
        tries = 3
        while True:
            tries -= 1
            folder.mkdir(parents=True, exist_ok=True)
            try:
                fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-")
            except FileNotFoundError:
                if not tries:
                    raise
                continue
            os.close(fd)
            return tmp

    @staticmethod
    def _remove_empty(folders: list[Path]) -> None:
        """Remove ``folders`` (deepest first) while they are empty."""
        for folder in folders:
            try:
                folder.rmdir()
            except FileNotFoundError:  # another delete was first
                continue
            except OSError:  # not empty: another write's files
                return

    def get_file(self, key: str, dest: Path) -> Path:
        src = self._path(key)
        if not src.is_file():
            raise StorageKeyError(key)
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=".tmp-")
        os.close(fd)
        shutil.copyfile(src, tmp)
        os.replace(tmp, dest)
        return dest

    def iter_chunks(self, key: str, chunk_bytes: int = CHUNK_BYTES) -> Iterator[bytes]:
        path = self._path(key)
        try:
            handle: BinaryIO = open(path, "rb")
        except (FileNotFoundError, IsADirectoryError):
            raise StorageKeyError(key) from None
        return self._chunks(handle, chunk_bytes)

    @staticmethod
    def _chunks(handle: BinaryIO, chunk_bytes: int) -> Iterator[bytes]:
        with handle:
            while chunk := handle.read(chunk_bytes):
                yield chunk

    def size(self, key: str) -> int:
        path = self._path(key)
        if not path.is_file():
            raise StorageKeyError(key)
        return path.stat().st_size

    def delete(self, key: str) -> bool:
        path = self._path(key)
        if not path.is_file():
            return False
        path.unlink(missing_ok=True)
        return True

    def delete_prefix(self, prefix: str) -> int:
        folder = self._path(prefix)
        if not folder.exists():
            return 0
        try:
            count = sum(1 for p in folder.rglob("*") if p.is_file())
        except FileNotFoundError:  # a concurrent delete of the same prefix got there first
            count = 0
        shutil.rmtree(folder, onerror=_gone_already)
        # the folders above it that it leaves empty (textures/<id>/refined/ ...), up to the top level
        inner = len(folder.relative_to(self.root).parents) - 2
        self._remove_empty(list(folder.parents)[:max(inner, 0)])
        return count

    def local_path(self, key: str) -> Path | None:
        path = self._path(key)
        return path if path.is_file() else None

    def ping(self) -> None:
        if not os.access(self.root, os.W_OK):
            raise OSError(f"storage folder not writable: {self.root}")


class S3Storage(Storage):
    """Objects in an S3-compatible bucket (AWS, MinIO, moto). Uploads are whole objects."""

    def __init__(self, *, bucket: str, prefix: str = "", endpoint_url: str | None = None,
                 access_key: str | None = None, secret_key: str | None = None,
                 region: str = "us-east-1", create_bucket: bool = True) -> None:
        try:
            import boto3
            from botocore.config import Config
        except ImportError as exc:  # pragma: no cover - boto3 is a runtime dependency
            raise RuntimeError("S3 storage needs boto3: pip install boto3") from exc
        self.bucket = bucket
        self.prefix = prefix.strip("/")
        self.client = boto3.client(
            "s3", endpoint_url=endpoint_url, aws_access_key_id=access_key,
            aws_secret_access_key=secret_key, region_name=region,
            config=Config(retries={"max_attempts": 5, "mode": "standard"}, s3={"addressing_style": "path"}),
        )
        if create_bucket:
            self._ensure_bucket(region)

    def _ensure_bucket(self, region: str) -> None:
        from botocore.exceptions import ClientError

        try:
            self.client.head_bucket(Bucket=self.bucket)
        except ClientError:
            kwargs = {} if region == "us-east-1" else {
                "CreateBucketConfiguration": {"LocationConstraint": region}}
            try:
                self.client.create_bucket(Bucket=self.bucket, **kwargs)
            except ClientError as exc:  # another process won the race
                if exc.response.get("Error", {}).get("Code") not in (
                        "BucketAlreadyOwnedByYou", "BucketAlreadyExists"):
                    raise

    def _key(self, key: str) -> str:
        _check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _missing(self, exc: Exception) -> bool:
        code = getattr(exc, "response", {}).get("Error", {}).get("Code")
        return code in ("404", "NoSuchKey", "NotFound")

    def put_file(self, key: str, path: Path) -> int:
        self.client.upload_file(str(path), self.bucket, self._key(key))
        return Path(path).stat().st_size

    def get_file(self, key: str, dest: Path) -> Path:
        from botocore.exceptions import ClientError

        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=".tmp-")
        os.close(fd)
        try:
            self.client.download_file(self.bucket, self._key(key), tmp)
        except ClientError as exc:
            os.unlink(tmp)
            if self._missing(exc):
                raise StorageKeyError(key) from None
            raise
        os.replace(tmp, dest)
        return dest

    def iter_chunks(self, key: str, chunk_bytes: int = CHUNK_BYTES) -> Iterator[bytes]:
        from botocore.exceptions import ClientError

        try:
            body = self.client.get_object(Bucket=self.bucket, Key=self._key(key))["Body"]
        except ClientError as exc:
            if self._missing(exc):
                raise StorageKeyError(key) from None
            raise
        return self._chunks(body, chunk_bytes)

    @staticmethod
    def _chunks(body, chunk_bytes: int) -> Iterator[bytes]:  # noqa: ANN001
        try:
            yield from body.iter_chunks(chunk_bytes)
        finally:
            body.close()

    def size(self, key: str) -> int:
        from botocore.exceptions import ClientError

        try:
            return int(self.client.head_object(Bucket=self.bucket, Key=self._key(key))["ContentLength"])
        except ClientError as exc:
            if self._missing(exc):
                raise StorageKeyError(key) from None
            raise

    def delete(self, key: str) -> bool:
        if not self.exists(key):
            return False
        self.client.delete_object(Bucket=self.bucket, Key=self._key(key))
        return True

    def delete_prefix(self, prefix: str) -> int:
        full = self._key(prefix) + "/"
        count = 0
        paginator = self.client.get_paginator("list_objects_v2")
        for page in paginator.paginate(Bucket=self.bucket, Prefix=full):
            objects = [{"Key": obj["Key"]} for obj in page.get("Contents", [])]
            if objects:
                self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": objects})
                count += len(objects)
        return count

    def ping(self) -> None:
        self.client.head_bucket(Bucket=self.bucket)


def make_storage(settings: Settings) -> Storage:
    """The storage backend the settings ask for."""
    if settings.storage_backend == "s3":
        return S3Storage(bucket=settings.s3_bucket, prefix=settings.s3_prefix,
                         endpoint_url=settings.s3_endpoint_url, access_key=settings.s3_access_key,
                         secret_key=settings.s3_secret_key, region=settings.s3_region)
    return LocalStorage(settings.resolved_storage_dir)
