"""Reading uploads with size limits, and what the service stores for a new texture."""
from __future__ import annotations

import hashlib
import re

from fastapi import UploadFile

from worker.errors import LimitExceeded

CHUNK = 1 << 20


def read_limited(upload: UploadFile, limit: int, what: str) -> bytes:
    """The whole upload, refusing (LimitExceeded) as soon as it passes ``limit`` bytes."""
    parts, total = [], 0
    upload.file.seek(0)
    while chunk := upload.file.read(CHUNK):
        total += len(chunk)
        if total > limit:
            raise LimitExceeded(f"{what} is larger than the limit of {limit} bytes")
        parts.append(chunk)
    return b"".join(parts)


def safe_filename(name: str | None, default: str) -> str:
    """A file name safe to use as the last part of a storage key."""
    base = (name or "").replace("\\", "/").rsplit("/", 1)[-1]
    base = re.sub(r"[^A-Za-z0-9._-]", "_", base).lstrip(".")[:100]
    return base or default


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
