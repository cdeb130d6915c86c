"""The soft label channel: Fhat's update from a decoder's likelihood ratio."""

from __future__ import annotations

import io
import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from services.learner.feedback import (
    FeedbackConfig,
    FeedbackLearner,
    collect_feedback,
    soft_label,
)
from services.learner.feedback_sources import (
    DecodedLabel,
    OracleFeedbackSource,
    ReplayFeedbackSource,
)
from services.learner.hf_methods import mean_label_loss
from services.learner.kernel_prior import KernelEvidence
from tests.learner.conftest import box_normalizer


def test_soft_label_is_p_correct_at_even_odds() -> None:
    # an epoch three times likelier after an error than after a correct action
    assert soft_label(math.log(3.0)) == pytest.approx(0.25)
    assert soft_label(0.0) == 0.5
    assert soft_label(1e6) == pytest.approx(1e-6)


def test_categorical_likelihood_of_a_soft_label_against_hand_numbers() -> None:
    # uniform Fhat (p = 1/3 for the taken action), r = 0.25:
    # P(epoch) ~ r p + (1 - r)(1 - p) = 0.25 / 3 + 0.75 * 2 / 3 = 7 / 12
    r = torch.tensor([0.25])
    loss = mean_label_loss(torch.zeros(1, 3), torch.tensor([0]), torch.ones(1), "categorical", r, r)
    assert float(loss) == pytest.approx(-math.log(7 / 12), rel=1e-6)


def test_kernel_evidence_of_a_soft_label_against_hand_numbers() -> None:
    evidence = KernelEvidence(n_obs=2, bandwidth=0.1, noise_model=(0.6, 0.6))
    evidence.add(np.zeros(2), action=0, label=False, p_correct=soft_label(math.log(3.0)))
    # P(x | optimal = k) ~ r for k = 0 (the taken action), 1 - r otherwise: [1, 3, 3] / 7
    posterior = evidence.posterior(np.array([0])).numpy()[0]
    np.testing.assert_allclose(posterior, [1 / 7, 3 / 7, 3 / 7], rtol=1e-6)


@pytest.mark.parametrize("method", ["categorical", "noise_aware", "categorical_kernel"])
def test_a_soft_label_with_the_hard_labels_likelihood_ratio_updates_fhat_as_the_hard_label(
    method: str,
) -> None:
    """The hard label is the soft channel's special case: a "correct" label under (g, b) has
    likelihood ratio (1 - b) / g, an "error" label b / (1 - g)."""
    good, bad = 0.7, 0.6
    hard = FeedbackLearner(
        box_normalizer(),
        FeedbackConfig(method=method, good_accuracy=good, bad_accuracy=bad, replay_updates=3),
        seed=4,
    )
    soft = FeedbackLearner(
        box_normalizer(),
        FeedbackConfig(method=method, replay_updates=3, label_channel="soft"),
        seed=4,
    )
    rng = np.random.default_rng(0)
    for _ in range(20):
        obs = rng.uniform(-1, 1, 3).astype(np.float32)
        action, correct = int(rng.integers(3)), bool(rng.random() < 0.5)
        ratio = (1 - bad) / good if correct else bad / (1 - good)
        hard.add(obs, action, correct)
        soft.add(obs, action, correct, log_likelihood_ratio=math.log(ratio))
    for name, weights in hard.model.state_dict().items():
        torch.testing.assert_close(soft.model.state_dict()[name], weights, rtol=1e-4, atol=1e-5)


def test_soft_labels_that_disagree_with_the_hard_label_move_fhat_the_other_way() -> None:
    """Two soft labels of one action, the same hard label "error", opposite evidence."""

    def p_optimal(log_ratio: float) -> float:
        learner = FeedbackLearner(
            box_normalizer(),
            FeedbackConfig(
                method="categorical",
                label_channel="soft",
                validation_fraction=0,
                replay_updates=4,
            ),
            seed=0,
        )
        for _ in range(30):
            learner.add(np.zeros(3, np.float32), 1, False, log_likelihood_ratio=log_ratio)
        return float(learner.policy.scores(np.zeros(3, np.float32))[1])

    assert p_optimal(-1.0) > 0.6 > 0.2 > p_optimal(1.0)


def test_the_soft_channel_refuses_hard_labels() -> None:
    learner = FeedbackLearner(box_normalizer(), FeedbackConfig(label_channel="soft"), seed=0)
    with pytest.raises(ValueError, match="needs each label's log-likelihood ratio"):
        learner.add(np.zeros(3, np.float32), 0, True)
    with pytest.raises(ValueError, match="finite"):
        learner.add(np.zeros(3, np.float32), 0, True, log_likelihood_ratio=math.nan)
    with pytest.raises(ValueError, match="label_channel"):
        FeedbackConfig(label_channel="fuzzy")


def test_soft_collection_replays_and_resumes_bit_for_bit(toy_env_id) -> None:
    class Decoded:
        """A decoder stand-in: the oracle's truth with evidence of strength 0.4 nats."""

        def __init__(self) -> None:
            self.rng = np.random.default_rng(3)

        def feedback(self, obs, action, optimal):
            llr = float(self.rng.normal(-0.4 if optimal else 0.4, 1.0))
            return DecodedLabel(correct=llr < 0, log_likelihood_ratio=llr)

    config = FeedbackConfig(method="categorical_kernel", label_channel="soft", replay_updates=2)
    with gym.make(toy_env_id) as env:
        first = collect_feedback(env, Decoded(), 60, config=config, seed=2)
        replay = ReplayFeedbackSource.from_records(first.records)
        again = collect_feedback(env, replay, 60, config=config, seed=2)
        with pytest.raises(ValueError, match="log-likelihood ratio"):
            collect_feedback(env, OracleFeedbackSource(0.6, seed=0), 5, config=config, seed=2)
    assert all(r.log_likelihood_ratio is not None for r in first.records)
    for name, weights in first.model.state_dict().items():
        torch.testing.assert_close(again.model.state_dict()[name], weights, rtol=0, atol=0)

    # a learner restored from its state continues exactly (the soft labels are in it)
    rng = np.random.default_rng(5)
    labels = [
        (rng.uniform(-1, 1, 3).astype(np.float32), int(rng.integers(3)), float(rng.normal()))
        for _ in range(30)
    ]
    a = FeedbackLearner(box_normalizer(), config, seed=1)
    for obs, action, llr in labels[:20]:
        a.add(obs, action, llr < 0, log_likelihood_ratio=llr)
    saved = io.BytesIO()
    torch.save(a.state_dict(), saved)
    saved.seek(0)
    b = FeedbackLearner(box_normalizer(), config, seed=1)
    b.load_state_dict(torch.load(saved, weights_only=True))
    for obs, action, llr in labels[20:]:
        a.add(obs, action, llr < 0, log_likelihood_ratio=llr)
        b.add(obs, action, llr < 0, log_likelihood_ratio=llr)
    for name, weights in a.model.state_dict().items():
        torch.testing.assert_close(b.model.state_dict()[name], weights, rtol=0, atol=0)
