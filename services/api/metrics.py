"""The api's own Prometheus series, read from the database when scraped: jobs by status, the
queue's depth (jobs queued, not yet claimed) and the live loop's decision latency (epoch end
to decision, over the latest live decisions)."""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterator

from fastapi import FastAPI, Request
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import func, select

from services.api.deps import authenticate
from services.api.errors import ForbiddenError
from services.core.db.live import LiveDecision
from services.core.db.models import JOB_STATUSES, Job
from services.core.metrics import token_guard

LIVE_LATENCY_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 0.85, 1.5)
"""Decision latency buckets (s); 0.85 s is the loop's budget for a decision."""
LIVE_DECISIONS_SEEN = 1000
"""How many of the latest live decisions the latency histogram covers."""


class PlatformCollector(Collector):
    """Jobs by status, queue depth and live decision latency, from ``app``'s database."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app

    def collect(self) -> Iterator[Metric]:
        with self.app.state.sessions() as db:
            counts = dict(db.execute(select(Job.status, func.count()).group_by(Job.status)).all())
            latencies = db.scalars(
                select(LiveDecision.decided_ts - LiveDecision.epoch_end_ts)
                .where(LiveDecision.epoch_end_ts.is_not(None))
                .order_by(LiveDecision.id.desc())
                .limit(LIVE_DECISIONS_SEEN)
            ).all()
        jobs = GaugeMetricFamily("bgrl_jobs", "Jobs by status.", labels=["status"])
        for status in JOB_STATUSES:
            jobs.add_metric([status], counts.get(status, 0))
        yield jobs
        yield GaugeMetricFamily(
            "bgrl_job_queue_depth",
            "Jobs queued and not yet claimed by a worker.",
            value=counts.get("queued", 0),
        )
        observed = sorted(float(v) for v in latencies)
        buckets = [
            (str(bound), float(bisect.bisect_right(observed, bound)))
            for bound in LIVE_LATENCY_BUCKETS_S
        ]
        yield HistogramMetricFamily(
            "bgrl_live_decision_latency_seconds",
            f"Epoch end to the EEG decision, over the latest {LIVE_DECISIONS_SEEN} live decisions.",
            buckets=[*buckets, ("+Inf", float(len(observed)))],
            sum_value=sum(observed),
        )


def admin_or_internal(service_token: str | None) -> Callable[[Request], None]:
    """A metrics guard: the internal token, or an admin's bearer token."""
    internal = token_guard(service_token)

    def guard(request: Request) -> None:
        header = request.headers.get("authorization", "")
        if not header.lower().startswith("bearer "):
            internal(request)
            return
        with request.app.state.sessions() as db:
            user = authenticate(db, header[7:].strip(), request.app.state.jwt_key)
        if user.role != "admin":
            raise ForbiddenError(f"metrics need the admin role (you are {user.role})", field="role")

    return guard
