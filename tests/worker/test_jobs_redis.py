"""The deployment's brokers: jobs through Redis and PostgreSQL, and a worker "on another host"
that is given only the broker URL, the database URL and the shared artifact store."""

from __future__ import annotations

import shutil
from collections.abc import Iterator

import pytest

from tests.worker.conftest import (
    FAST_LEASE,
    REDIS_URL,
    TINY_PPO,
    WORKER_TUNING,
    Platform,
    pg_url,
    postgres_database,
    redis_available,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def redis_platform(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Platform]:
    reason = redis_available() or postgres_database()
    if reason:
        pytest.skip(reason)
    import redis

    redis.Redis.from_url(REDIS_URL).flushdb()  # this Redis database is the tests' own
    root = tmp_path_factory.mktemp("redis-platform")
    platform = Platform(
        root,
        {
            "BGRL_BROKER_URL": REDIS_URL,
            "BGRL_DATABASE_URL": pg_url(),
            "BGRL_ARTIFACT_DIR": str(root / "shared-artifacts"),
        },
    )
    platform.prewarm_oracle()
    try:
        yield platform
    finally:
        platform.close()


def test_a_second_host_needs_only_broker_database_and_artifact_store(
    redis_platform: Platform,
) -> None:
    local = redis_platform.start_worker("local")
    remote_home = redis_platform.root / "remote-host"
    remote_home.mkdir()
    remote_env = {
        "BGRL_BROKER_URL": REDIS_URL,
        "BGRL_DATABASE_URL": pg_url(),
        "BGRL_ARTIFACT_DIR": str(redis_platform.root / "shared-artifacts"),
        **FAST_LEASE,
        **WORKER_TUNING,
    }
    # Its own data folder (./data, the default) holds only caches; seed the oracle cache as
    # a host that ran jobs before would have it (building it takes seconds).
    shutil.copytree(redis_platform.root / "data" / "sim", remote_home / "data" / "sim")
    remote = redis_platform.start_worker("remote", env=remote_env, cwd=remote_home)
    config = {"task": "SSSG", "method": "rl_sparse", "total_steps": 512, "ppo": TINY_PPO}
    jobs = [redis_platform.submit("guided_ppo", {**config, "seed": seed}) for seed in range(4)]
    done = [redis_platform.wait(job_id, {"succeeded", "failed"}, timeout=150) for job_id in jobs]
    assert [job.status for job in done] == ["succeeded"] * 4, [job.error for job in done]
    assert [job.attempts for job in done] == [1] * 4
    assert [job.result["seed"] for job in done] == [0, 1, 2, 3]
    remote_log, local_log = redis_platform.log(remote), redis_platform.log(local)
    ran_remote = [job_id for job_id in jobs if f"job {job_id} (guided_ppo)" in remote_log]
    ran_local = [job_id for job_id in jobs if f"job {job_id} (guided_ppo)" in local_log]
    assert ran_remote, "the remote worker took no job"
    assert sorted(ran_remote + ran_local) == sorted(jobs)  # each job ran exactly once
    assert not (remote_home / "data" / "bgrl.db").exists()  # it used the shared database
    store = redis_platform.settings.resolved_artifact_dir
    for job_id in ran_remote:  # and the shared artifact store
        assert (store / f"checkpoint/job-{job_id}/checkpoint.pt").is_file()
