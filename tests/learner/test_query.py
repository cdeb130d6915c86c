"""The ``bayes`` collection: exact per-state posterior, leave-one-out prior, query rule."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from services.learner.feedback import FeedbackConfig, FeedbackLearner
from services.learner.query import (
    PathPosterior,
    PathQuery,
    hard_evidence,
    map_log_odds,
    soft_evidence,
    top_two_thompson,
)
from tests.learner.conftest import box_normalizer


def test_hard_posterior_after_k_labels_is_the_hand_value() -> None:
    """Flat prior, C = 0.6: 3 "correct" and 1 "error" on action 0, 1 "error" on action 2:
    e = (2 log 1.5, 0, -log 1.5), so q = (2.25, 1, 1/1.5) / sum."""
    posterior = PathPosterior("flat")
    for label in (True, True, True, False):
        posterior.add("s", 0, hard_evidence(label, 0.6, 0.6))
    posterior.add("s", 2, hard_evidence(False, 0.6, 0.6))
    hand = np.array([2.25, 1.0, 1.0 / 1.5])
    np.testing.assert_allclose(posterior.posterior("s"), hand / hand.sum(), rtol=1e-12)
    assert posterior.n_labels[0].tolist() == [4, 0, 1]


def test_asymmetric_and_soft_evidence_are_log_likelihood_ratios() -> None:
    assert hard_evidence(True, 0.7, 0.6) == pytest.approx(math.log(0.7 / 0.4))
    assert hard_evidence(False, 0.7, 0.6) == pytest.approx(math.log(0.3 / 0.6))
    # lambda = P(epoch | error) / P(epoch | correct) = 0.5: evidence for "optimal" log 2
    assert soft_evidence(math.log(0.5)) == pytest.approx(math.log(2.0))
    assert soft_evidence(1e6) == pytest.approx(-13.8)


def test_hierarchical_prior_never_counts_a_states_own_labels() -> None:
    """One state: its prior stays alpha / sum(alpha) however many labels it has. Two states:
    B's prior is (alpha + q_A) / (sum(alpha) + 1) and its labels do not enter it."""
    alpha = np.array([2.0, 1.0, 1.0])
    posterior = PathPosterior("hierarchical", alpha)
    for _ in range(30):
        posterior.add("a", 0, hard_evidence(True, 0.6, 0.6))
    evidence_a = 30 * math.log(1.5)
    hand_a = np.array([2.0 * math.exp(evidence_a), 1.0, 1.0])
    np.testing.assert_allclose(posterior.posterior("a"), hand_a / hand_a.sum(), rtol=1e-9)
    posterior.add("b", 1, hard_evidence(True, 0.6, 0.6))
    q_a = posterior.posterior("a")
    prior_b = (alpha + q_a) / (alpha.sum() + 1.0)
    hand_b = prior_b * np.array([1.0, 1.5, 1.0])
    np.testing.assert_allclose(posterior.posterior("b"), hand_b / hand_b.sum(), rtol=1e-6)
    # a state without labels gets the prior from every labelled state
    unseen = (alpha + posterior.q.sum(axis=0)) / (alpha.sum() + 2.0)
    np.testing.assert_allclose(posterior.posterior("c"), unseen, rtol=1e-9)


def test_map_log_odds_stays_finite_when_certain() -> None:
    log_q = np.log(np.array([0.9, 0.05, 0.05]))
    assert map_log_odds(log_q) == pytest.approx(math.log(9.0))
    assert map_log_odds(np.array([0.0, -800.0, -900.0])) == pytest.approx(800.0)


def test_top_two_thompson_probabilities() -> None:
    """P(execute 0) = beta q0 + (1 - beta) sum_{k != 0} q_k q0 / (1 - q_k)."""
    q = np.array([0.9, 0.05, 0.05])
    rng = np.random.default_rng(0)
    draws = np.array([top_two_thompson(q, rng) for _ in range(20000)])
    expected = 0.5 * 0.9 + 0.5 * 2 * 0.05 * 0.9 / 0.95
    assert abs(np.mean(draws == 0) - expected) < 0.012
    assert top_two_thompson(np.array([1.0, 0.0, 0.0]), rng) == 0


def _query(certainty: float = 0.95) -> PathQuery:
    return PathQuery(PathPosterior("flat"), certainty, 0.5, (0.6, 0.6))


def test_query_crosses_certain_states_and_asks_at_uncertain_ones() -> None:
    query = _query()
    certain, uncertain = np.array([0.1, 0.1]), np.array([0.9, 0.9])
    for _ in range(40):  # log-odds 40 log 1.5 - log 2 > log 19
        query.posterior.add(query_key(query, certain), 2, hard_evidence(True, 0.6, 0.6))
    rng = np.random.default_rng(0)
    for _ in range(50):
        query.new_episode()
        assert query.action(certain, rng) == 2 and not query.wants_label
        query.action(uncertain, rng)
        assert query.wants_label
    # a certain state seen again in the same episode is a loop: asked, not crossed
    query.action(certain, rng)
    assert query.wants_label


def query_key(query: PathQuery, obs: np.ndarray) -> tuple[int, ...]:
    from services.learner.query import state_key

    return state_key(obs, query.cell_m)


def test_an_episode_without_labels_raises_the_threshold_to_its_least_certain_state() -> None:
    query = _query()
    a, b = np.array([0.1, 0.1]), np.array([0.9, 0.9])
    for _ in range(40):
        query.posterior.add(query_key(query, a), 0, hard_evidence(True, 0.6, 0.6))
    for _ in range(50):
        query.posterior.add(query_key(query, b), 0, hard_evidence(True, 0.6, 0.6))
    rng = np.random.default_rng(0)
    query.new_episode()
    query.action(a, rng), query.action(b, rng)
    assert not query.wants_label
    query.new_episode()  # that episode spent no label
    query.action(a, rng)
    assert query.wants_label  # the least certain state is asked next
    query.action(b, rng)
    assert not query.wants_label


def test_a_query_off_the_map_action_leaves_the_path() -> None:
    query = _query()
    obs = np.array([0.1, 0.1])
    for _ in range(3):
        query.add(obs, 0, True, None)
    assert not query.leaves_path
    query.add(obs, 1, False, None)
    assert query.leaves_path


@pytest.mark.parametrize("method", ["bayes_query", "bayes_query_flat"])
def test_learner_fits_pi_hf_to_the_posterior_and_restores_its_state(method: str) -> None:
    """Four states (quadrants), optimal action = quadrant index mod 3, C = 0.8: pi_HF (Fhat)
    follows the posterior's MAP, and a restored learner continues identically."""
    config = FeedbackConfig(method=method, good_accuracy=0.8, bad_accuracy=0.8, query_cell_m=1.0)
    learner = FeedbackLearner(box_normalizer(2), config, seed=0)
    rng = np.random.default_rng(1)
    centres = np.array([[-0.5, -0.5], [-0.5, 0.5], [0.5, -0.5], [0.5, 0.5]], np.float32)

    def feed(learner: FeedbackLearner, n: int) -> None:
        for _ in range(n):
            state = int(rng.integers(4))
            action = learner.collection_action(centres[state], rng)
            truth = action == state % 3
            learner.add(centres[state], action, truth != (rng.random() < 0.2), truth)

    feed(learner, 200)
    restored = FeedbackLearner(box_normalizer(2), config, seed=0)
    restored.load_state_dict(learner.state_dict())
    np.testing.assert_allclose(restored.query.posterior.q, learner.query.posterior.q)
    assert not learner.validation  # every label informs the posterior
    learner.finish()
    maps = [
        int(np.argmax(learner.query.posterior.posterior(k)))
        for k in [(-1, -1), (-1, 0), (0, -1), (0, 0)]
    ]
    assert maps == [0, 1, 2, 0]
    with torch.no_grad():
        greedy = learner.model(torch.from_numpy(centres)).argmax(dim=-1).tolist()
    assert greedy == maps


def test_bayes_collection_asks_only_for_the_budget_and_is_deterministic(toy_env_id) -> None:
    """Transit moves are steps without a label: exactly N labels are asked for (the source
    is called N times), the collection repeats bit for bit, and crossing certain states
    makes more steps than labels."""
    import gymnasium as gym

    from services.learner.feedback import collect_feedback
    from services.learner.feedback_sources import OracleFeedbackSource

    config = FeedbackConfig(method="bayes_query", good_accuracy=0.9, bad_accuracy=0.9)

    class Counting(OracleFeedbackSource):
        calls = 0

        def feedback(self, obs, action, optimal):  # type: ignore[no-untyped-def]
            Counting.calls += 1
            return super().feedback(obs, action, optimal)

    def run():
        Counting.calls = 0
        result = collect_feedback(
            gym.make(toy_env_id), Counting(0.9, seed=3), 137, config=config, seed=5
        )
        return result, Counting.calls

    (first, calls), (second, _) = run(), run()
    assert len(first.records) == 137 and calls == 137
    assert first.n_steps > 137  # some states were crossed without a label
    assert [r.action for r in first.records] == [r.action for r in second.records]
    for p, q in zip(first.model.parameters(), second.model.parameters(), strict=True):
        assert torch.equal(p, q)
