"""Result files written atomically: under a temporary name in the target folder, renamed
into place only when complete, so readers never see half a file and a re-run simply
overwrites."""
from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_output(path: str | os.PathLike, suffix: str = "") -> Iterator[str]:
    """Yield a temporary path (str) in ``path``'s folder (created if missing), ending in
    ``suffix`` (writers that pick the format by extension need it). When the block
    succeeds the file is made world-readable (0644: the API process reads results a
    worker wrote) and renamed to ``path``; when it raises, the temporary file is removed
    and the exception propagates."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o644)  # mkstemp makes 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
