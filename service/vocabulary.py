"""The job vocabulary: the states a job passes through and the kinds of work a job does
(docs/ARCHITECTURE.md, Contract 3). Every module of the service, and the Python client,
names a state or a kind through these two enums; nothing else spells them.

They are ``StrEnum``s: a member compares and hashes equal to its string, so database rows,
JSON bodies, query parameters and queue messages carry the plain strings. Standard library
only, so :mod:`service.client` can share them without pulling in the service.
"""
from __future__ import annotations

import enum


class JobState(enum.StrEnum):
    """Where a job is: queued -> running -> one of the three ends (a lease that expires,
    or a fit paused after its interim, puts a running job back to queued)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"


#: the states a job never leaves
TERMINAL_STATES = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELED})


class JobKind(enum.StrEnum):
    """What a job makes. Fits run on a queue of their own (service/queue.py); a worker may
    run only some kinds (``Settings.worker_kinds``)."""

    VOLUME = "volume"
    BAKE = "bake"
    REGION = "region"
    FIT = "fit"
