"""The stage-2 method of a ``guided_ppo`` job (``hf_method``) and the presets of
``guided_ppo`` and ``reproduce`` jobs run through a real ``bgrl worker`` on the embedded
platform."""

from __future__ import annotations

import json

import pytest
from sqlalchemy import select

from services.core.db.models import Artifact, Job
from services.learner.hf_methods import PAPER_METHOD, RECOMMENDED_METHOD
from services.platform.jobs import REPRODUCE_BATCH
from services.worker.reproduce import specs_from_config
from services.worker.runtime import JobConfigError
from tests.worker.conftest import TINY_PPO, Platform

pytestmark = pytest.mark.slow

HF_JOB = {
    "task": "SSSG", "method": "hf_sparse", "accuracy": 0.7, "seed": 1, "n_labels": 200,
    "total_steps": 256, "ppo": TINY_PPO,
}  # fmt: skip


@pytest.fixture(scope="module")
def worker(fs_platform: Platform):
    return fs_platform.start_worker("methods")


@pytest.mark.parametrize(
    ("asked", "used"),
    [("noise_aware", "noise_aware"), (PAPER_METHOD, PAPER_METHOD), (None, RECOMMENDED_METHOD)],
)
def test_guided_ppo_learns_pi_hf_with_the_method_asked_for(
    fs_platform: Platform, worker, asked: str | None, used: str
) -> None:
    config = HF_JOB if asked is None else {**HF_JOB, "hf_method": asked}
    job = fs_platform.wait(fs_platform.submit("guided_ppo", config), {"succeeded", "failed"}, 120)
    assert job.status == "succeeded", job.error
    assert job.result["spec"]["hf_method"] == used


@pytest.mark.parametrize("method", ["hf_sparse", "rl_sparse"])
def test_guided_ppo_with_the_platform_preset(fs_platform: Platform, worker, method: str) -> None:
    config = {**HF_JOB, "method": method, "preset": "platform"}
    if method != "hf_sparse":
        del config["accuracy"], config["n_labels"]
    job = fs_platform.wait(fs_platform.submit("guided_ppo", config), {"succeeded", "failed"}, 120)
    assert job.status == "succeeded", job.error
    spec = job.result["spec"]
    assert spec["hf_treatment"] == ("truncated_is" if method == "hf_sparse" else None)
    assert spec["ppo_overrides"]["sil_coef"] == 1.0  # every method alike, as in reproduce
    assert spec["ppo_overrides"]["hf_guide_sampling"] is True
    if method == "hf_sparse":  # what is given stays
        given = {**config, "ppo": {**TINY_PPO, "sil_coef": 0.5}}
        job = fs_platform.wait(
            fs_platform.submit("guided_ppo", given), {"succeeded", "failed"}, 120
        )
        assert job.status == "succeeded", job.error
        assert job.result["spec"]["ppo_overrides"]["sil_coef"] == 0.5


def test_reproduce_with_the_platform_preset(fs_platform: Platform, worker) -> None:
    config = {
        "seeds": 1, "tasks": ["sssg"], "methods": ["rl_sparse", "hf_sparse"],
        "accuracies": [0.7], "preset": "platform", "ppo": {**TINY_PPO, "total_steps": 256},
        "n_labels": 200,
    }  # fmt: skip
    job_id = fs_platform.submit("reproduce", config)
    job = fs_platform.wait(job_id, {"succeeded", "failed"}, timeout=240)
    assert job.status == "succeeded", job.error
    with fs_platform.sessions() as session:
        children = session.scalars(select(Job).where(Job.parent_id == job_id)).all()
        results = session.get(Artifact, job.result["artifacts"]["results.json"])
    # one lockstep batch of the two runs (batch_runs 8 by default)
    assert [child.kind for child in children] == [REPRODUCE_BATCH.name]
    specs = {run["method"]: run for run in children[0].config["runs"]}
    assert set(specs) == {"rl_sparse", "hf_sparse"}
    # what `bgrl reproduce --preset platform` runs: truncated_is, guide sampling, the method,
    hf = specs["hf_sparse"]
    assert (hf["hf_treatment"], hf["hf_method"]) == ("truncated_is", RECOMMENDED_METHOD)
    assert hf["ppo_overrides"]["hf_guide_sampling"] is True
    # self-imitation for every method of the reproduction alike
    assert hf["ppo_overrides"]["sil_coef"] == specs["rl_sparse"]["ppo_overrides"]["sil_coef"] == 1.0
    assert specs["rl_sparse"]["hf_method"] is None
    assert (hf["n_labels"], specs["rl_sparse"]["n_labels"]) == (200, 1000)
    data = json.loads((fs_platform.settings.resolved_artifact_dir / results.relpath).read_text())
    by_method = {run["method"]: run["spec"] for run in data["runs"]}
    assert by_method["hf_sparse"]["hf_method"] == RECOMMENDED_METHOD


@pytest.mark.parametrize("n_labels", [0, -5, "many", True, 2.5])
def test_reproduce_refuses_a_bad_label_count_naming_it(n_labels) -> None:
    with pytest.raises(
        JobConfigError,
        match=r"^n_labels: Input should be (a valid integer|greater than or equal to 1), not ",
    ):
        specs_from_config({"quick": True, "n_labels": n_labels})
