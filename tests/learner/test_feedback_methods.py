"""Stage-2 methods: noise-aware and categorical likelihoods, active queries, budgets."""

from __future__ import annotations

from typing import get_args

import gymnasium as gym
import numpy as np
import pytest
import torch

from services.core.hf_methods import HFMethodName
from services.learner.feedback import (
    FeedbackConfig,
    FeedbackLearner,
    HFPolicy,
    collect_feedback,
)
from services.learner.feedback_sources import OracleFeedbackSource
from services.learner.hf_methods import (
    HF_METHODS,
    RECOMMENDED_METHOD,
    expected_information,
    label_nll,
    most_informative_action,
    p_judged_correct,
)
from tests.learner.conftest import box_normalizer


@pytest.mark.parametrize("method", sorted(HF_METHODS))
def test_each_method_learns_a_separable_labelling_under_known_noise(method: str) -> None:
    """Optimal action = argmax(obs); labels flipped with probability 0.2 (C = 0.8 known)."""
    rng = np.random.default_rng(1)
    config = FeedbackConfig(
        replay_updates=2, lr=3e-3, method=method, good_accuracy=0.8, bad_accuracy=0.8
    )
    learner = FeedbackLearner(box_normalizer(), config, seed=0)
    for _ in range(800):
        obs = rng.uniform(-1, 1, 3).astype(np.float32)
        action = learner.collection_action(obs, rng) if rng.random() < 0.5 else int(rng.integers(3))
        truth = action == int(np.argmax(obs))
        learner.add(obs, action, bool(truth) != bool(rng.random() < 0.2), truth)
    policy = HFPolicy(learner.model, method=method)
    test_obs = rng.uniform(-1, 1, (300, 3)).astype(np.float32)
    hits = [policy.act(o) == int(np.argmax(o)) for o in test_obs]
    assert np.mean(hits) > 0.8, method


def _fit_single_state(likelihood: str, p_true: float, c: float) -> float:
    """Fit one free logit per action to many noisy labels of action 0; return P(optimal)."""
    n = 4000
    rng = np.random.default_rng(0)
    optimal = rng.random(n) < p_true
    labels = torch.tensor(np.where(rng.random(n) < c, optimal, ~optimal), dtype=torch.float32)
    logits = torch.zeros(1, 3, requires_grad=True)
    optimizer = torch.optim.Adam([logits], lr=0.05)
    actions = torch.zeros(n, dtype=torch.long)
    for _ in range(800):
        loss = label_nll(logits.expand(n, 3), actions, labels, likelihood, c, c).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return float(torch.sigmoid(logits[0, 0].detach()))


@pytest.mark.parametrize("p_true", [0.9, 0.15])
def test_noise_aware_loss_recovers_clean_probability_where_bce_is_pulled_to_half(
    p_true: float,
) -> None:
    """Known truth: P(optimal) = p_true, labels at C = 0.7. Noisy-label rate is
    0.7 p + 0.3 (1 - p): BCE converges there (toward 0.5); forward correction to p."""
    c = 0.7
    noisy_rate = c * p_true + (1 - c) * (1 - p_true)
    bce = _fit_single_state("bce", p_true, c)
    forward = _fit_single_state("forward", p_true, c)
    assert abs(bce - noisy_rate) < 0.03
    assert abs(forward - p_true) < 0.04
    assert abs(forward - 0.5) > abs(bce - 0.5) + 0.1


def test_categorical_wrong_verdict_on_one_action_is_evidence_for_the_others() -> None:
    logits = torch.zeros(1, 3, requires_grad=True)
    loss = label_nll(logits, torch.tensor([0]), torch.tensor([0.0]), "categorical", 0.7, 0.7)
    loss.sum().backward()
    # gradient descent lowers action 0's logit and raises the two others'
    assert logits.grad[0, 0] > 0 and logits.grad[0, 1] < 0 and logits.grad[0, 2] < 0


def test_categorical_keeps_an_optimal_argmax_where_two_actions_are_optimal() -> None:
    """Actions 0 and 1 are both optimal (labels of either say correct at C = 0.8)."""
    rng = np.random.default_rng(0)
    n = 3000
    actions = torch.tensor(rng.integers(0, 3, n))
    truth = actions < 2
    labels = torch.tensor(np.where(rng.random(n) < 0.8, truth, ~truth), dtype=torch.float32)
    logits = torch.zeros(1, 3, requires_grad=True)
    optimizer = torch.optim.Adam([logits], lr=0.05)
    for _ in range(500):
        loss = label_nll(logits.expand(n, 3), actions, labels, "categorical", 0.8, 0.8).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    q = torch.softmax(logits[0], -1).detach().numpy()
    assert int(np.argmax(q)) in (0, 1) and q[2] < 0.1
    assert abs(q[0] - q[1]) < 0.15  # the mass splits between the two optimal actions


def test_active_query_picks_the_most_informative_action_on_a_hand_built_ensemble() -> None:
    # members agree on action 0 (all say likely optimal) and on 2 (all say not), disagree on 1
    p_optimal = np.array([[0.7, 0.9, 0.0], [0.7, 0.1, 0.0], [0.7, 0.9, 0.0], [0.7, 0.1, 0.0]])
    info = expected_information(p_judged_correct(p_optimal, 0.7, 0.7))
    assert np.isclose(info[0], 0.0) and np.isclose(info[2], 0.0) and info[1] > 0.01
    assert most_informative_action(p_optimal, 0.7, 0.7) == 1
    # an implausible action (mean P(optimal) under half the best) is never queried
    implausible = np.array([[0.9, 0.3, 0.0], [0.9, 0.0, 0.0]])
    assert most_informative_action(implausible, 0.7, 0.7) == 0


@pytest.mark.parametrize(
    "method",
    [
        "paper",
        RECOMMENDED_METHOD,
        "categorical_thompson",
        "categorical_info",
        "categorical_onpolicy",
        "categorical_kernel",
    ],
)
def test_label_budget_is_exact_and_collection_is_deterministic(toy_env_id, method) -> None:
    config = FeedbackConfig(replay_updates=2, method=method, good_accuracy=0.7, bad_accuracy=0.7)

    def run():
        return collect_feedback(
            gym.make(toy_env_id), OracleFeedbackSource(0.7, seed=3), 137, config=config, seed=5
        )

    first, second = run(), run()
    assert len(first.records) == 137 and first.n_steps == 137  # every labelled action counts
    assert [r.action for r in first.records] == [r.action for r in second.records]
    for p, q in zip(first.model.parameters(), second.model.parameters(), strict=True):
        assert torch.equal(p, q)
    assert first.summary()["config"]["method"] == method


def test_ensemble_learner_resumes_bit_for_bit() -> None:
    config = FeedbackConfig(replay_updates=3, method="categorical_thompson")
    rng = np.random.default_rng(2)
    data = [
        (rng.uniform(-1, 1, 3).astype(np.float32), int(rng.integers(3)), bool(rng.integers(2)))
        for _ in range(60)
    ]
    whole = FeedbackLearner(box_normalizer(), config, seed=4)
    part = FeedbackLearner(box_normalizer(), config, seed=4)
    actions_whole, actions_part = [], []
    for i, (obs, action, label) in enumerate(data):
        if i == 30:
            restored = FeedbackLearner(box_normalizer(), config, seed=4)
            restored.load_state_dict(part.state_dict())
            part = restored
        actions_whole.append(whole.collection_action(obs, np.random.default_rng(i)))
        actions_part.append(part.collection_action(obs, np.random.default_rng(i)))
        whole.add(obs, action, label)
        part.add(obs, action, label)
    assert actions_whole == actions_part
    for p, q in zip(whole.model.parameters(), part.model.parameters(), strict=True):
        assert torch.equal(p, q)
    assert whole.ensemble is not None and part.ensemble is not None
    for p, q in zip(whole.ensemble.parameters(), part.ensemble.parameters(), strict=True):
        assert torch.equal(p, q)


def test_bad_method_or_noise_model_is_refused_naming_the_field() -> None:
    with pytest.raises(ValueError, match="unknown stage-2 method 'nope'"):
        FeedbackConfig(method="nope")
    with pytest.raises(ValueError, match="good_accuracy"):
        FeedbackConfig(method="noise_aware", good_accuracy=1.5)
    with pytest.raises(ValueError, match="must exceed 1"):
        FeedbackConfig(method="categorical", good_accuracy=0.5, bad_accuracy=0.4)
    FeedbackConfig(method="paper", good_accuracy=0.5, bad_accuracy=0.4)  # BCE ignores it


def test_method_names_of_the_request_schema_are_the_registry() -> None:
    assert set(get_args(HFMethodName)) == set(HF_METHODS) and RECOMMENDED_METHOD in HF_METHODS


def test_onpolicy_collection_takes_the_argmax_and_samples_only_on_a_revisited_observation() -> None:
    config = FeedbackConfig(method="categorical_onpolicy", revisit_window=3)
    learner = FeedbackLearner(box_normalizer(), config, seed=0)
    with torch.no_grad():  # Fhat prefers action 2 everywhere, clearly but not overwhelmingly
        learner.model.output.weight.zero_()
        learner.model.output.bias.copy_(torch.tensor([0.0, 0.0, 0.3]))
    fresh = [np.full(3, v, np.float32) for v in (0.1, 0.2, 0.3, 0.4)]
    rng = np.random.default_rng(0)
    before = rng.bit_generator.state
    assert [learner.collection_action(o, rng) for o in fresh] == [2, 2, 2, 2]
    assert rng.bit_generator.state == before  # greedy: no draw
    # 0.4 is among the last 3 observations: a loop, so the softmax is sampled
    draws = [learner.collection_action(fresh[3], np.random.default_rng(i)) for i in range(200)]
    assert set(draws) == {0, 1, 2}
    # 0.1 left the window of the last 3: greedy again
    assert learner.collection_action(fresh[0], rng) == 2 and rng.bit_generator.state == before


def test_onpolicy_learner_resumes_with_its_recent_observations() -> None:
    config = FeedbackConfig(replay_updates=2, method="categorical_onpolicy", revisit_window=4)
    rng = np.random.default_rng(3)
    states = [rng.uniform(-1, 1, 3).astype(np.float32) for _ in range(5)]
    whole = FeedbackLearner(box_normalizer(), config, seed=1)
    part = FeedbackLearner(box_normalizer(), config, seed=1)
    actions_whole, actions_part = [], []
    for i in range(40):
        obs = states[int(rng.integers(5))]  # few states: revisits happen
        if i == 20:
            restored = FeedbackLearner(box_normalizer(), config, seed=1)
            restored.load_state_dict(part.state_dict())
            part = restored
        actions_whole.append(whole.collection_action(obs, np.random.default_rng(i)))
        actions_part.append(part.collection_action(obs, np.random.default_rng(i)))
        label = bool(rng.integers(2))
        whole.add(obs, actions_whole[-1], label)
        part.add(obs, actions_part[-1], label)
    assert actions_whole == actions_part
    for p, q in zip(whole.model.parameters(), part.model.parameters(), strict=True):
        assert torch.equal(p, q)
