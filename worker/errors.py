"""Domain exceptions raised by worker/ (and model/).

They carry a human-readable ``detail``; ``service/errors.py`` owns the one table that
maps each class to an HTTP status and problem+json body. Nothing here knows HTTP.
"""
from __future__ import annotations


class TexspaceError(Exception):
    """Base of every domain error. ``detail`` says what was wrong, for the user."""

    def __init__(self, detail: str):
        super().__init__(detail)
        self.detail = detail


class InvalidImage(TexspaceError):
    """An uploaded image is empty, truncated, of an unsupported format or unusable size."""


class InvalidMesh(TexspaceError):
    """An uploaded mesh cannot be parsed or fails validation (NaN, bad indices, no faces)."""


class InvalidParameter(TexspaceError):
    """A numeric or enum argument is outside what the function supports."""


class LimitExceeded(TexspaceError):
    """A request would exceed a configured size limit (pixels, faces, voxels...)."""


class AtlasFailed(TexspaceError):
    """UV atlas generation (xatlas, in a child process) crashed, timed out or ran out of memory."""


class Canceled(TexspaceError):
    """A job's ``should_cancel()`` returned True; work stopped between two steps."""


class Paused(Exception):
    """A job stopped (or not started) on purpose: it goes back to the queue without using an
    attempt. An upload's fit after its interim, its state saved, while other uploads wait for
    theirs (``stage="interim"``, sent again at once); a job that waits for its texture's
    refinement (``resend=False``: the refinement's end sends it). Not an error: no problem."""

    def __init__(self, detail: str, *, stage: str | None = None, resend: bool = True):
        super().__init__(detail)
        self.stage, self.resend = stage, resend


class ModelNotFound(TexspaceError):
    """No loaded model has the requested version, or a model directory is incomplete."""


class ModelInvalid(TexspaceError):
    """A model directory exists but its manifest or ONNX files break the contract."""


class FeatureUnavailable(TexspaceError):
    """An optional dependency (e.g. torch for fitting) is not installed."""


class InsufficientStorage(TexspaceError):
    """A write failed for lack of space: the disk (ENOSPC, a quota) or the database is full.
    Nothing was stored; a retry fails the same way until space is freed."""


class Busy(TexspaceError):
    """A shared resource (the API's decode budget) had no room in time; try again after
    ``retry_after`` seconds."""

    def __init__(self, detail: str, *, retry_after: int = 1):
        super().__init__(detail)
        self.retry_after = retry_after
