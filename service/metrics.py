"""Prometheus metrics: requests, latencies, jobs by state, queue depth, tile cache.

Each app gets its own CollectorRegistry (tests build many apps in one process). Job
counts and queue depth are read at scrape time from the job table and the broker.
"""
from __future__ import annotations

import logging

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily
from sqlalchemy import func, select

from .tables import Job
from .vocabulary import JobState

log = logging.getLogger(__name__)
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30)


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("texspace_http_requests_total", "HTTP requests",
                                ["method", "route", "status"], registry=self.registry)
        self.latency = Histogram("texspace_http_request_duration_seconds", "HTTP request latency",
                                 ["method", "route"], buckets=LATENCY_BUCKETS, registry=self.registry)
        self.tile_cache_hits = Counter("texspace_tile_cache_hits_total", "tiles served from the LRU",
                                       registry=self.registry)
        self.tile_cache_misses = Counter("texspace_tile_cache_misses_total", "tiles rendered",
                                         registry=self.registry)
        self.tile_not_modified = Counter("texspace_tile_not_modified_total", "304 answers to If-None-Match",
                                         registry=self.registry)
        self.tile_previews = Counter("texspace_tile_previews_total", "zoomed-out previews rendered "
                                     "(progressive zoom-out; the exact tile follows)", registry=self.registry)
        self.tile_render = Histogram("texspace_tile_render_seconds", "time to render and encode a tile",
                                     buckets=LATENCY_BUCKETS, registry=self.registry)

    def watch(self, services) -> None:  # noqa: ANN001
        """Add scrape-time gauges for job states and queue depth."""
        self.registry.register(_JobCollector(services))


class _JobCollector:
    def __init__(self, services) -> None:  # noqa: ANN001
        self.services = services

    def collect(self):  # noqa: ANN201
        jobs = GaugeMetricFamily("texspace_jobs", "jobs in the job table by state", labels=["state"])
        depth = GaugeMetricFamily("texspace_queue_depth", "messages waiting in the queue broker")
        try:
            with self.services.sessions() as session:
                counts = dict(session.execute(select(Job.state, func.count()).group_by(Job.state)).all())
            for state in JobState:
                jobs.add_metric([state], counts.get(state, 0))
            yield jobs
        except Exception:  # a scrape must not fail because the database hiccups
            log.exception("job metrics unavailable")
        try:
            depth.add_metric([], self.services.pending_count())
            yield depth
        except Exception:
            log.exception("queue depth unavailable")
