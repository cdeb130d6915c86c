"""The compose deployment across real network boundaries (conftest.ComposeLab): every
service of docker-compose.yml in its own network namespace, reached only through the
compose hostnames, with PostgreSQL and Redis as real servers and two worker hosts. The
lab PC (this test) signs in as the admin the api printed at its first start, as a lab would
(``docker compose logs api | grep "created admin"``)."""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from sqlalchemy import create_engine, select
from sqlalchemy.orm import Session

from services.client import PlatformClient
from services.core.db.models import Job
from tests.deploy.conftest import DOT_ENV, WORKER_HOSTS, ComposeLab

pytestmark = pytest.mark.netns
TINY_PPO = {"n_epochs": 4, "eval_every": 256}
REPRODUCE = {"seeds": 1, "first_seed": 3, "tasks": ["sssg"], "methods": ["rl_sparse", "rl_rich"],
             "ppo": {**TINY_PPO, "total_steps": 1024}}  # fmt: skip
RUN_RECORD = ("seed", "method", "final_spl", "curve")


class LabPC:
    """Requests from the lab PC's namespace (by the addresses the compose names resolve to
    in the hosts files: this process's own /etc/hosts is the machine's): the api, and the
    database for what the api does not show (which worker host holds a job)."""

    def __init__(self, compose: ComposeLab, run: Callable[[Callable[[], Any]], Any]) -> None:
        self.compose = compose
        self.run = run
        log = compose.log("api").read_text(errors="replace")
        found = re.search(r"created admin (\S+) with password (\S+)", log)
        assert found is not None, compose.tail("api")
        hosts = compose.lab.hosts
        self.client: PlatformClient = run(lambda: PlatformClient(f"http://{hosts['api']}:8000"))
        run(lambda: self.client.login(found.group(1), found.group(2)))
        url = f"postgresql+psycopg://bgrl:{DOT_ENV['POSTGRES_PASSWORD']}@{hosts['postgres']}:5432/bgrl"
        self.engine = run(lambda: create_engine(url, pool_pre_ping=True))

    def call(self, fn: Callable[[], Any]) -> Any:
        return self.run(fn)

    def jobs(self, **where: Any) -> list[Job]:
        def query() -> list[Job]:
            with Session(self.engine) as db:
                statement = select(Job).filter_by(**where).order_by(Job.created_at)
                return list(db.scalars(statement))

        return self.run(query)

    def wait_job(
        self, job_id: str, timeout: float = 150.0, watch: Callable[[], None] | None = None
    ) -> Any:
        deadline = time.monotonic() + timeout
        while True:
            job = self.run(lambda: self.client.get_job(job_id))
            if job.finished:
                return job
            if watch is not None:
                watch()
            if time.monotonic() > deadline:
                logs = "\n".join(f"== {h}\n{self.compose.tail(h, 2000)}" for h in WORKER_HOSTS)
                pytest.fail(f"job {job_id} still {job.status} after {timeout} s\n{logs}")
            time.sleep(0.3)

    def close(self) -> None:
        self.run(self.client.close)
        self.run(self.engine.dispose)


@pytest.fixture(scope="module")
def lab_pc(compose_lab: ComposeLab) -> Iterator[LabPC]:
    compose_lab.up(("postgres", "redis", "sim", "eeg", "learner", "api", "worker"))
    with compose_lab.lab.inside("lab-pc") as run:
        pc = LabPC(compose_lab, run)
        try:
            yield pc
        finally:
            pc.close()


def run_records(pc: LabPC, parent_id: str) -> list[dict[str, Any]]:
    children = pc.jobs(parent_id=parent_id)
    assert children and all(c.status == "succeeded" for c in children), [
        (c.status, c.error) for c in children
    ]
    return sorted(
        ({k: c.result.get(k) for k in RUN_RECORD} for c in children if c.result),
        key=lambda r: (r["method"], r["seed"]),
    )


@pytest.fixture(scope="module")
def reference_records(lab_pc: LabPC) -> list[dict[str, Any]]:
    """A reproduce job fanned out over both worker hosts: its runs' records."""
    job = lab_pc.call(lambda: lab_pc.client.submit_job("reproduce", REPRODUCE))
    owners: set[str] = set()

    def watch() -> None:
        for child in lab_pc.jobs(parent_id=job.id, status="running"):
            if child.lease_owner:
                owners.add(child.lease_owner.rsplit("-", 1)[0])

    done = lab_pc.wait_job(job.id, watch=watch)
    assert done.status == "succeeded", done.error
    assert done.result["runs"] == 2 and done.result["failed"] == []
    assert owners == set(WORKER_HOSTS), owners  # one run on each worker host
    return run_records(lab_pc, job.id)


def test_a_reproduce_job_fans_out_over_both_worker_hosts(
    reference_records: list[dict[str, Any]],
) -> None:
    assert [r["method"] for r in reference_records] == ["rl_rich", "rl_sparse"]
    assert all(r["final_spl"] is not None and r["curve"] for r in reference_records)
