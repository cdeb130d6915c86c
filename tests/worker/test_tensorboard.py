"""A training job's TensorBoard event files: written by the worker as the job runs (CleanRL's
metric names, the SPL of every evaluation), downloaded from the api as a zip, and read back
with TensorBoard's own reader."""

from __future__ import annotations

import hashlib
import io
import zipfile
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from services.worker.runtime import Runtime
from tests.api.conftest import Api
from tests.worker.test_outside_use import GUIDED, add_job, lab, row, run

__all__ = ["lab"]  # the fixture, used by name


def test_a_guided_job_writes_tensorboard_events_the_api_zips(
    lab: tuple[Api, Runtime], tmp_path: Path
) -> None:
    api, runtime = lab
    job_id = add_job(runtime, "guided_ppo", {**GUIDED, "total_steps": 512})
    viewer = api.as_("viewer")
    before = api.client.get(f"/api/v1/jobs/{job_id}/tensorboard", headers=viewer)
    assert before.status_code == 404
    assert before.json() == {
        "detail": f"job {job_id} (queued) has no TensorBoard events",
        "field": "job_id",
    }
    assert run(runtime, job_id) == "succeeded"
    response = api.client.get(f"/api/v1/jobs/{job_id}/tensorboard", headers=viewer)
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    assert response.headers["x-checksum-sha256"] == hashlib.sha256(response.content).hexdigest()
    zipfile.ZipFile(io.BytesIO(response.content)).extractall(tmp_path)
    (folder,) = tmp_path.iterdir()
    assert folder.name == f"job-{job_id}"
    events = EventAccumulator(str(folder))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"charts/SPL", "charts/episodic_return", "losses/value_loss", "losses/policy_loss",
            "losses/approx_kl", "charts/SPS"} <= tags  # fmt: skip
    spl = [[e.step, e.value] for e in events.Scalars("charts/SPL")]  # float32 in the file
    curve = row(runtime, job_id).curve
    assert [step for step, _ in spl] == [step for step, _ in curve] == [0, 256, 512]
    assert [value for _, value in spl] == pytest.approx([value for _, value in curve], abs=1e-6)
