"""The compose deployment across real network boundaries (conftest.ComposeLab): every
service of docker-compose.yml in its own network namespace, reached only through the
compose hostnames, with PostgreSQL and Redis as real servers and two worker hosts. The
lab PC (this test) signs in as the admin created at the first start, with the password in
the file the api's log names, as a lab would (``docker compose exec api cat
/data/first-admin-password``)."""

from __future__ import annotations

import contextlib
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
from sqlalchemy import create_engine, select, text
from sqlalchemy.orm import Session

from services.client import PlatformClient
from services.core.db.live import LiveDecision, LiveRun
from services.core.db.models import Classifier, FeedbackLabel, Job, Recording
from tests.deploy.conftest import DOT_ENV, WORKER_HOSTS, ComposeLab

pytestmark = pytest.mark.netns
RowT = TypeVar("RowT")
TINY_PPO = {"n_epochs": 4, "eval_every": 256}
REPRODUCE = {"seeds": 1, "first_seed": 3, "tasks": ["sssg"], "methods": ["rl_sparse", "rl_rich"],
             "ppo": {**TINY_PPO, "total_steps": 1024}, "checkpoint_every": 2,
             "batch_runs": 1}  # fmt: skip
"""One run a child job (batch_runs 1), so that the two runs fan out over the two worker
hosts and a child's run checkpoints where a cut-off host's successor resumes it; a batch of
runs in one child resumes after a SIGKILL in tests/worker/test_reproduce_batches.py."""
RUN_RECORD = ("seed", "method", "final_spl", "curve")


class LabPC:
    """Requests from the lab PC's namespace (by the addresses the compose names resolve to
    in the hosts files: this process's own /etc/hosts is the machine's): the api, and the
    database for what the api does not show (which worker host holds a job)."""

    def __init__(self, compose: ComposeLab, run: Callable[[Callable[[], Any]], Any]) -> None:
        self.compose = compose
        self.run = run
        log = compose.log("api").read_text(errors="replace")
        found = re.search(r"created admin (\S+); its password is in ([^\s\"]+)", log)
        assert found is not None, compose.tail("api")
        email, password = found.group(1), Path(found.group(2)).read_text().strip()
        hosts = compose.lab.hosts
        self.client: PlatformClient = run(lambda: PlatformClient(f"http://{hosts['api']}:8000"))
        run(lambda: self.client.login(email, password))
        url = f"postgresql+psycopg://bgrl:{DOT_ENV['POSTGRES_PASSWORD']}@{hosts['postgres']}:5432/bgrl"
        self.engine = run(lambda: create_engine(url, pool_pre_ping=True))

    def call(self, fn: Callable[[], Any]) -> Any:
        return self.run(fn)

    def rows(self, model: type[RowT], **where: Any) -> list[RowT]:
        def query() -> list[RowT]:
            with Session(self.engine) as db:
                return list(db.scalars(select(model).filter_by(**where)))

        return self.run(query)

    def jobs(self, **where: Any) -> list[Job]:
        return sorted(self.rows(Job, **where), key=lambda job: job.created_at)

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
                pytest.fail(f"job {job_id} still {job.status} after {timeout} s\n"
                            f"{self.diagnosis(job_id)}\n{logs}")  # fmt: skip
            time.sleep(0.3)

    def diagnosis(self, job_id: str) -> str:
        """The job's children and the database's sessions that wait on a lock or hold one
        open: what a job stuck "running" is waiting for."""
        children = [(c.id[:8], c.status, c.lease_owner, c.lease_expires_at, c.attempts)
                    for c in self.jobs(parent_id=job_id)]  # fmt: skip

        def sessions() -> list[Any]:
            with self.engine.connect() as conn:
                return list(conn.execute(text(
                    "SELECT pid, client_addr, state, wait_event_type, now() - xact_start, "
                    "left(query, 80) FROM pg_stat_activity WHERE datname = 'bgrl' "
                    "AND (wait_event_type = 'Lock' OR starts_with(state, 'idle in transaction'))"
                )))  # fmt: skip

        return f"children: {children}\nwaiting or open transactions: {self.run(sessions)}"

    def close(self) -> None:
        self.run(self.client.close)
        self.run(self.engine.dispose)


@pytest.fixture(scope="module")
def lab_pc(compose_lab: ComposeLab) -> Iterator[LabPC]:
    compose_lab.up()
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


def test_an_online_session_runs_across_sim_eeg_learner_and_a_worker_host(
    lab_pc: LabPC, compose_lab: ComposeLab
) -> None:
    """The virtual subject, accelerated: a calibration session (its recording validated by
    the EEG service, then the eeg_calibration job: a classifier), then an online session:
    the worker host drives the sim, the EEG service decodes, the learner updates pi_HF."""
    url = f"http://{compose_lab.lab.hosts['api']}:8000/api/v1"
    headers = {"Authorization": f"Bearer {lab_pc.client.token}"}

    def post(path: str, body: dict[str, Any]) -> dict[str, Any]:
        response = lab_pc.call(lambda: httpx.post(url + path, json=body, headers=headers))
        assert response.status_code == 201, response.text
        return response.json()

    subject = post("/subjects", {"code": "S-LIVE"})
    hosts: set[str] = set()
    now = datetime.now(UTC)  # sessions start `hour` hours from now (a past start needs allow_past)

    def session(kind: str, hour: int, options: dict[str, Any]) -> dict[str, Any]:
        when = (now + timedelta(hours=hour)).isoformat()
        lab = post("/sessions", {"subject_id": subject["id"], "kind": kind, "scheduled_at": when})
        run = post(f"/sessions/{lab['id']}/start", options)

        def watch() -> None:
            for job in lab_pc.rows(Job, id=run["job_id"]):
                if job.lease_owner:
                    hosts.add(job.lease_owner.rsplit("-", 1)[0])

        job = lab_pc.wait_job(run["job_id"], watch=watch)
        assert job.status == "succeeded", job.error
        (row,) = lab_pc.rows(LiveRun, id=run["id"])
        assert row.status == "completed", row.error
        return {"run": row, "session_id": lab["id"]}

    calibration = session("calibration", 9, {
        "accelerated": True, "n_actions": 60, "virtual_quality": 1.0, "seed": 1,
        "calibration_max_passes": 5,
    })["run"]  # fmt: skip
    (recording,) = lab_pc.rows(Recording, id=calibration.recording_id)
    assert recording.validation_status == "valid" and recording.synthetic
    follow_up = lab_pc.wait_job(calibration.follow_up_job_id)
    assert follow_up.status == "succeeded", follow_up.error
    (classifier,) = lab_pc.rows(Classifier, job_id=follow_up.id)

    online = session("online", 11, {
        "accelerated": True, "classifier_id": classifier.id, "label_budget": 12,
        "virtual_quality": 1.0,
    })  # fmt: skip
    run = online["run"]
    assert run.result["labels"] == 12 and run.hf_model_id is not None
    assert len(lab_pc.rows(FeedbackLabel, session_id=online["session_id"])) == 12
    assert len(lab_pc.rows(LiveDecision, run_id=run.id)) == run.result["actions"]
    assert hosts and hosts <= set(WORKER_HOSTS)  # the sessions ran on worker hosts


def running_children(pc: LabPC, parent_id: str, checkpointed: bool = True) -> list[Job]:
    """The parent's runs running now (with a checkpoint written, if asked)."""
    return [
        child
        for child in pc.jobs(parent_id=parent_id, status="running")
        if child.lease_owner and (child.checkpoint_artifact_id or not checkpointed)
    ]


def wait_for(what: str, ready: Callable[[], Any], timeout: float = 90.0) -> Any:
    deadline = time.monotonic() + timeout
    while not (found := ready()):
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} after {timeout} s")
        time.sleep(0.2)
    return found


def test_a_worker_host_cut_off_mid_job_its_run_finishes_on_the_other_host(
    lab_pc: LabPC, compose_lab: ComposeLab, reference_records: list[dict[str, Any]]
) -> None:
    job = lab_pc.call(lambda: lab_pc.client.submit_job("reproduce", REPRODUCE))
    child = wait_for("checkpointed run", lambda: running_children(lab_pc, job.id))[0]
    assert child.lease_owner is not None
    cut = child.lease_owner.rsplit("-", 1)[0]
    assert cut in WORKER_HOSTS
    compose_lab.lab.cable(cut, up=False)
    try:
        done = lab_pc.wait_job(job.id)
        moved = lab_pc.jobs(id=child.id)[0]
    finally:
        compose_lab.lab.cable(cut, up=True)
    assert done.status == "succeeded", done.error
    assert moved.status == "succeeded" and moved.attempts >= 2
    assert moved.resumed_from_step is not None  # resumed from the cut host's checkpoint
    assert run_records(lab_pc, job.id) == reference_records


def test_redis_and_postgresql_restarted_mid_job_lose_nothing(
    lab_pc: LabPC, compose_lab: ComposeLab, reference_records: list[dict[str, Any]]
) -> None:
    job = lab_pc.call(lambda: lab_pc.client.submit_job("reproduce", REPRODUCE))
    wait_for("running run", lambda: running_children(lab_pc, job.id, checkpointed=False))
    compose_lab.kill("redis", signal.SIGTERM)  # its append-only file keeps the queue
    compose_lab.start_redis()
    wait_for("checkpointed run", lambda: running_children(lab_pc, job.id))
    compose_lab.kill("postgres", signal.SIGINT)  # fast shutdown: sessions cut
    compose_lab.start_postgres()
    try:  # the client's reads wait out the api's 503s while PostgreSQL starts
        done = lab_pc.wait_job(job.id)
    finally:  # a job left running would write into the next tests' store
        with contextlib.suppress(Exception):
            lab_pc.call(lambda: lab_pc.client.cancel_job(job.id))
    assert done.status == "succeeded", done.error
    assert run_records(lab_pc, job.id) == reference_records


def test_the_api_killed_mid_upload_leaves_no_half_file(
    lab_pc: LabPC, compose_lab: ComposeLab
) -> None:
    subject = lab_pc.call(lambda: lab_pc.client.create_subject("S-NETNS"))
    when = datetime.now(UTC)
    session = lab_pc.call(lambda: lab_pc.client.schedule_session(subject.id, "calibration", when))
    sent = threading.Event()

    def body() -> Iterator[bytes]:
        for i in range(4000):
            if i == 64:
                sent.set()
            yield b"\0" * 65536
            if i >= 64:
                time.sleep(0.01)

    def upload() -> None:
        url = f"http://{compose_lab.lab.hosts['api']}:8000"
        path = f"/api/v1/sessions/{session.id}/recordings?filename=cut.bdf"
        headers = {"Authorization": f"Bearer {lab_pc.client.token}",
                   "Content-Type": "application/octet-stream"}  # fmt: skip
        with contextlib.suppress(httpx.HTTPError):
            httpx.post(url + path, content=body(), headers=headers, timeout=30)

    artifacts = compose_lab.volume("artifacts", "api")

    def stored_files() -> set[Path]:  # the recordings: jobs of other tests may still write
        return {p for p in (artifacts / "recording").rglob("*") if p.is_file()}

    before = stored_files()
    uploading = threading.Thread(target=lambda: lab_pc.call(upload))
    uploading.start()
    assert sent.wait(30)
    wait_for("part file", lambda: list(artifacts.glob(".tmp/*.part")), timeout=30)
    compose_lab.kill("api")  # SIGKILL: the api's process and its uvicorn processes
    uploading.join(timeout=60)
    compose_lab.start("api")
    compose_lab.wait_healthy("api")
    assert stored_files() == before  # no half file in the store
    url = f"http://{compose_lab.lab.hosts['api']}:8000/api/v1/recordings?session_id={session.id}"
    headers = {"Authorization": f"Bearer {lab_pc.client.token}"}
    recordings = lab_pc.call(lambda: httpx.get(url, headers=headers, timeout=10))
    assert recordings.json()["items"] == []
    assert list(artifacts.glob(".tmp/*.part")) == []  # the restarted api cleaned the cut part
