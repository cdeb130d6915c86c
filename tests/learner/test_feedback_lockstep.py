"""Stage 2 in lockstep: each session's Fhat, records and figures bit for bit as alone; a
session that fails leaves the batch; the methods that run alone are refused."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

from services.learner.feedback import FeedbackCollection, FeedbackConfig, HFResult
from services.learner.feedback_lockstep import (
    SIGMOID_VECTOR_BLOCK,
    collect_feedback_lockstep,
    lockstep_feedback_key,
    sigmoid_as_alone,
)
from services.learner.feedback_sources import DecodedLabel, OracleFeedbackSource
from services.learner.runs import HFPolicySpec, hf_policy_run, hf_policy_runs
from tests.learner.conftest import TOY_ENV_ID


class _Decoded:
    """A decoder stand-in: the oracle's truth with evidence of strength 0.4 nats."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def feedback(self, obs: Any, action: int, optimal: bool | None) -> DecodedLabel:
        llr = float(self.rng.normal(-0.4 if optimal else 0.4, 1.0))
        return DecodedLabel(correct=llr < 0, log_likelihood_ratio=llr)


def _sessions(method: str, channel: str, n_labels: int = 50) -> list[FeedbackCollection]:
    """Four sessions of one method that differ in seed, C (where the loss does not read
    it) and labels; minibatches of 1 to 12 labels, below and above the batched size."""
    sessions = []
    for seed, accuracy in zip(range(4), (0.6, 0.9, 0.6, 0.75), strict=True):
        if method in ("categorical", "categorical_onpolicy"):
            accuracy = 0.75  # its loss reads the noise model: one C per batch
        source = (
            _Decoded(seed) if channel == "soft" else OracleFeedbackSource(accuracy, seed=seed + 10)
        )
        config = FeedbackConfig(
            method=method, good_accuracy=accuracy, bad_accuracy=accuracy, label_channel=channel,
            batch_size=12, replay_updates=4,
        )  # fmt: skip
        env = gym.make(TOY_ENV_ID)
        sessions.append(FeedbackCollection(env, source, n_labels + seed, config, seed, 10_000))
    return sessions


def _assert_same(alone: HFResult, batched: HFResult | Exception) -> None:
    assert isinstance(batched, HFResult), batched
    assert batched.records == alone.records
    assert (batched.n_steps, batched.n_episodes) == (alone.n_steps, alone.n_episodes)
    assert batched.validation_accuracy_noisy == alone.validation_accuracy_noisy
    mine, theirs = batched.model.state_dict(), alone.model.state_dict()
    assert all(torch.equal(mine[k], theirs[k]) for k in theirs)


@pytest.mark.parametrize(
    ("method", "channel"),
    [
        ("paper", "hard"),
        ("paper", "soft"),
        ("categorical", "hard"),
        ("categorical_kernel", "soft"),
        ("categorical_onpolicy", "hard"),
    ],
)
def test_a_session_in_a_batch_learns_what_it_learns_alone(method: str, channel: str) -> None:
    alone = [session.run() for session in _sessions(method, channel)]
    batched = collect_feedback_lockstep(_sessions(method, channel))
    for a, b in zip(alone, batched, strict=True):
        _assert_same(a, b)
    assert alone[0].records != alone[1].records  # the sessions differ


def test_a_failing_session_leaves_the_batch_and_the_others_go_on() -> None:
    sessions = _sessions("paper", "hard")

    def cancel(record: Any) -> None:
        if len(sessions[1].records) == 30:
            raise RuntimeError("cancelled at label 30")

    sessions[1].on_label = cancel
    outcomes = collect_feedback_lockstep(sessions)
    assert isinstance(outcomes[1], RuntimeError) and "label 30" in str(outcomes[1])
    for alone, batched in zip(_sessions("paper", "hard"), outcomes, strict=True):
        if batched is not outcomes[1]:
            _assert_same(alone.run(), batched)


def test_only_batched_methods_of_equal_settings_share_a_batch() -> None:
    assert lockstep_feedback_key(FeedbackConfig(method="thompson")) is None
    assert lockstep_feedback_key(FeedbackConfig(method="noise_aware")) is None
    paper = [FeedbackConfig(good_accuracy=c, bad_accuracy=c) for c in (0.6, 0.7)]
    assert lockstep_feedback_key(paper[0]) == lockstep_feedback_key(paper[1])
    categorical = [
        FeedbackConfig(method="categorical", good_accuracy=c, bad_accuracy=c) for c in (0.6, 0.7)
    ]
    assert lockstep_feedback_key(categorical[0]) != lockstep_feedback_key(categorical[1])
    with pytest.raises(ValueError, match="one batched stage-2 method"):
        collect_feedback_lockstep(_sessions("paper", "hard")[:1] + _sessions("thompson", "hard"))


def test_sigmoid_as_alone_is_each_rows_own_sigmoid() -> None:
    for n in (1, 5, SIGMOID_VECTOR_BLOCK, SIGMOID_VECTOR_BLOCK + 3):
        x = torch.randn(7, n) * 4
        alone = torch.stack([torch.sigmoid(row.clone()) for row in x])
        assert torch.equal(sigmoid_as_alone(x), alone)


def test_an_hf_sweeps_rows_are_those_of_each_run_alone() -> None:
    specs = [
        HFPolicySpec("sssg", 0.7, 0, n_labels=30),
        HFPolicySpec("vssg", 0.6, 1, n_labels=30),
        HFPolicySpec("sssg", 0.7, 2, n_labels=30, method="thompson"),  # runs alone
    ]
    timing = {"wall_seconds": None}
    for spec, row in zip(specs, hf_policy_runs(specs), strict=True):
        assert isinstance(row, dict), row
        alone = hf_policy_run(spec)
        assert row | timing == alone | timing
