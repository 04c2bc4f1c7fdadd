"""Prometheus metrics: what ``GET /metrics`` shows, and how several worker processes share them.

Recorded as things happen (per process)::

    posecell_http_requests_total{method,route,status}            counter
    posecell_http_request_duration_seconds{method,route,status}  histogram
    posecell_http_requests_in_progress                           gauge (summed over live processes)
    posecell_estimate_stage_seconds{stage}                       histogram: edges, coarse, refine, total
    posecell_estimates_total{found}                              counter: "true" / "false"

Read from the template cache at each scrape (the cache is shared, so every process sees the same)::

    posecell_builds{status}    models per build status: queued, building (running), ready, failed
    posecell_cache_bytes       size of the template cache on disk

``route`` is the route's template (``/models/{model_id}``), never the raw path, so the number of
series stays fixed; requests answered before routing (no route matches, a refused API key, a
``Content-Length`` over the limit) count as ``unmatched``.

Several uvicorn workers: each is its own process with its own counters, and a scrape reaches one of
them. With ``PROMETHEUS_MULTIPROC_DIR`` set (``python -m service serve`` always sets it, to a fresh
empty directory, before the workers start) every process writes its values to files there and a
scrape sums the files of all of them. Without it (``uvicorn`` started by hand with one worker, or
the tests' in-process apps) the numbers are this process's alone.
"""

from __future__ import annotations

import os
from collections import Counter as Tally
from collections.abc import Iterator, Mapping

from prometheus_client import REGISTRY, CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client import multiprocess as prometheus_multiprocess
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.registry import Collector

from service.stores.base import Store

MULTIPROC_DIR_ENV = "PROMETHEUS_MULTIPROC_DIR"
# prometheus_client decides at import whether values go to files; this module imports it, so this
# is the same decision.
MULTIPROCESS = bool(os.environ.get(MULTIPROC_DIR_ENV))
CONTENT_TYPE = CONTENT_TYPE_LATEST
UNMATCHED_ROUTE = "unmatched"
BUILD_STATUSES = ("queued", "building", "ready", "failed")
ESTIMATE_STAGES = ("edges", "coarse", "refine", "total")

# seconds; requests range from /health (< 1 ms) to estimates without a known distance (several s)
REQUEST_BUCKETS_S = (0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
STAGE_BUCKETS_S = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)

REQUESTS = Counter("posecell_http_requests", "HTTP requests answered, by method, route template and status",
                   ["method", "route", "status"])
REQUEST_SECONDS = Histogram("posecell_http_request_duration_seconds",
                            "time from the request's arrival to the end of its response",
                            ["method", "route", "status"], buckets=REQUEST_BUCKETS_S)
IN_PROGRESS = Gauge("posecell_http_requests_in_progress", "HTTP requests being answered now",
                    multiprocess_mode="livesum")
ESTIMATE_STAGE_SECONDS = Histogram("posecell_estimate_stage_seconds",
                                   "time of each estimate stage (edges, coarse, refine, total)", ["stage"],
                                   buckets=STAGE_BUCKETS_S)
ESTIMATES = Counter("posecell_estimates", "estimates answered, by whether the object was found", ["found"])


def observe_estimate(timing_ms: Mapping[str, float], found: bool) -> None:
    """Record one estimate's stage timings (``EstimateResult.timing_ms``, milliseconds)."""
    for stage in ESTIMATE_STAGES:
        ESTIMATE_STAGE_SECONDS.labels(stage).observe(float(timing_ms[stage]) / 1000.0)
    ESTIMATES.labels("true" if found else "false").inc()


class StoreCollector(Collector):
    """Build statuses and cache size, read from the shared template cache when scraped."""

    def __init__(self, store: Store) -> None:
        self.store = store

    def collect(self) -> Iterator[GaugeMetricFamily]:
        tally = Tally(r.get("status") for r in self.store.records())
        builds = GaugeMetricFamily("posecell_builds", "models per template-build status (building = running)",
                                   labels=["status"])
        for status in BUILD_STATUSES:
            builds.add_metric([status], tally[status])
        yield builds
        yield GaugeMetricFamily("posecell_cache_bytes", "size of the template cache directory on disk, bytes",
                                value=self.store.volume_bytes())


def exposition(store: Store) -> bytes:
    """The text ``GET /metrics`` answers: every process's metrics (see the module docstring) + the cache's."""
    registry = CollectorRegistry()
    registry.register(StoreCollector(store))
    if MULTIPROCESS:
        prometheus_multiprocess.MultiProcessCollector(registry)
        return generate_latest(registry)
    return generate_latest(REGISTRY) + generate_latest(registry)


def process_stopped() -> None:
    """Drop this process's live gauges from the shared directory (a stopped worker has nothing in flight)."""
    if MULTIPROCESS:
        prometheus_multiprocess.mark_process_dead(os.getpid())
