"""Fhat, the feedback replay buffer, pi_HF and the feedback sources."""

from __future__ import annotations

import queue

import gymnasium as gym
import numpy as np
import pytest
import torch

from services.learner.collection import GuidingHFPolicy
from services.learner.feedback import (
    FeedbackConfig,
    FeedbackLearner,
    FeedbackModel,
    HFPolicy,
    collect_feedback,
)
from services.learner.feedback_buffer import FeedbackReplayBuffer
from services.learner.feedback_sources import (
    FeedbackSource,
    OracleFeedbackSource,
    ReplayFeedbackSource,
    StreamFeedbackSource,
)
from services.learner.hf_methods import label_nll
from services.learner.networks import ObsNormalizer
from tests.learner.conftest import box_normalizer


def test_normalizer_maps_bounds_to_unit_interval_and_keeps_infinite_dims() -> None:
    space = gym.spaces.Box(
        low=np.array([0.0, -np.pi, -np.inf], np.float32),
        high=np.array([13.0, np.pi, np.inf], np.float32),
    )
    norm = ObsNormalizer.from_space(space)
    out = norm(torch.tensor([[0.0, np.pi, 5.0], [13.0, -np.pi, -2.0]]))
    assert torch.allclose(out, torch.tensor([[-1.0, 1.0, 5.0], [1.0, -1.0, -2.0]]), atol=1e-6)


def test_loss_only_backpropagates_through_the_taken_action() -> None:
    model = FeedbackModel(box_normalizer(4), hidden_size=16)
    obs = torch.rand(8, 4)
    actions = torch.full((8,), 2)
    label_nll(model(obs), actions, torch.ones(8), "bce", 0.6, 0.6).mean().backward()
    grad = model.output.weight.grad
    assert torch.all(grad[:2] == 0) and torch.any(grad[2] != 0)


def test_replay_buffer_recency_rule() -> None:
    buffer = FeedbackReplayBuffer(n_obs=2)
    for i in range(500):
        buffer.add(np.zeros(2), i % 3, True)
    rng = np.random.default_rng(0)
    newest = np.arange(500 - 32, 500)
    counts = np.zeros(500)
    n_newest_batches = 0
    for _ in range(2000):
        idx = buffer.sample_indices(rng, 32, newest_fraction=0.3)
        n_newest_batches += np.array_equal(idx, newest)
        np.add.at(counts, idx, 1)
    assert 0.26 < n_newest_batches / 2000 < 0.34
    # A label among the newest 32 is replayed ~7x as often as an old one.
    assert counts[-32:].mean() > 5 * counts[:468].mean()
    with pytest.raises(ValueError, match="empty"):
        FeedbackReplayBuffer(2).sample_indices(rng, 4, 0.3)


def test_fhat_learns_a_separable_labelling_and_holds_out_validation() -> None:
    """Label: action a is 'correct' iff a == argmax(obs[:3]) (a separable rule)."""
    rng = np.random.default_rng(1)
    learner = FeedbackLearner(box_normalizer(3), FeedbackConfig(replay_updates=2, lr=3e-3), seed=0)
    for _ in range(500):
        obs = rng.uniform(-1, 1, 3).astype(np.float32)
        action = int(rng.integers(3))
        truth = action == int(np.argmax(obs))
        learner.add(obs, action, truth, truth)
    acc_noisy, acc_true = learner.validation_accuracy()
    assert 0.1 < len(learner.validation) / 500 < 0.3
    assert len(learner.buffer) + len(learner.validation) == 500
    assert acc_true is not None and acc_true > 0.8 and acc_noisy == acc_true  # all-False: 0.67
    policy = HFPolicy(learner.model)
    hits = [policy.act(o) == int(np.argmax(o)) for o in rng.uniform(-1, 1, (200, 3)).astype("f4")]
    assert np.mean(hits) > 0.8


def test_hf_policy_sampling_is_softened_and_greedy_is_argmax() -> None:
    model = FeedbackModel(box_normalizer(4), hidden_size=16)
    with torch.no_grad():
        model.output.bias.copy_(torch.tensor([2.0, 0.0, -2.0]))
        model.output.weight.zero_()
    policy = HFPolicy(model, beta=8.0)
    obs = np.zeros(4, np.float32)
    probs = policy.sampling_probs(obs)
    assert np.isclose(probs.sum(), 1.0) and probs[0] > probs[1] > probs[2] > 0.0
    assert policy.act(obs) == 0
    rng = np.random.default_rng(0)
    samples = [policy.act(obs, rng) for _ in range(500)]
    assert set(samples) >= {0, 1}


def test_a_guiding_hf_policy_acts_as_its_policy_with_one_forward_an_observation() -> None:
    model = FeedbackModel(box_normalizer(4), hidden_size=16)
    policy = HFPolicy(model, beta=8.0)
    guiding = GuidingHFPolicy(policy)
    forwards = []
    model.register_forward_hook(lambda *_: forwards.append(1))
    observations = np.random.default_rng(0).uniform(-1, 1, (50, 4))
    expected = [int(np.argmax(policy.scores(obs))) for obs in observations]
    assert len(set(expected)) > 1
    forwards.clear()
    for _ in range(3):
        assert [guiding.act(obs) for obs in observations] == expected
    assert len(forwards) == len(observations)  # each observation's forward once
    rng_a, rng_b = np.random.default_rng(1), np.random.default_rng(1)
    samples = [(policy.act(o, rng_a), guiding.act(o, rng_b)) for o in observations]
    assert all(a == b for a, b in samples)  # sampling as the policy's


def test_oracle_source_matches_its_accuracy() -> None:
    source = OracleFeedbackSource(0.7, seed=3)
    assert isinstance(source, FeedbackSource)
    agree = np.mean([source.feedback(np.zeros(13), 0, True) for _ in range(4000)])
    assert 0.67 < agree < 0.73
    with pytest.raises(ValueError, match="truth"):
        source.feedback(np.zeros(13), 0, None)


def test_stream_and_replay_sources() -> None:
    q: queue.Queue[bool] = queue.Queue()
    q.put(True)
    stream = StreamFeedbackSource(q, timeout_s=0.01)
    assert stream.feedback(np.zeros(3), 0, None) is True
    assert stream.feedback(np.zeros(3), 0, None) is None  # nothing arrived in time
    assert StreamFeedbackSource(lambda timeout: False).feedback(np.zeros(3), 1, None) is False
    replay = ReplayFeedbackSource([True, None, False])
    assert [replay.feedback(np.zeros(3), 0, None) for _ in range(3)] == [True, None, False]
    with pytest.raises(IndexError, match="replayed"):
        replay.feedback(np.zeros(3), 0, None)


def test_collect_feedback_on_toy_env_and_replay_reproduces_the_session(toy_env_id) -> None:
    env = gym.make(toy_env_id)
    config = FeedbackConfig(replay_updates=4)
    result = collect_feedback(env, OracleFeedbackSource(0.8, seed=0), 300, config=config)
    assert len(result.records) == 300
    assert 0.72 < result.label_accuracy < 0.88
    assert result.validation_accuracy_true is not None
    assert result.validation_accuracy_true > result.label_accuracy - 0.1
    again = collect_feedback(
        gym.make(toy_env_id),
        ReplayFeedbackSource.from_records(result.records),
        300,
        config=config,
    )
    assert [r.obs for r in again.records] == [r.obs for r in result.records]
    for p, q in zip(result.model.parameters(), again.model.parameters(), strict=True):
        assert torch.equal(p, q)
