"""The smoothness prior (``categorical_kernel``): labels are evidence about nearby states."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from services.learner.feedback import FeedbackConfig, FeedbackLearner, HFPolicy
from services.learner.kernel_prior import KernelEvidence, label_log_likelihood
from tests.learner.conftest import box_normalizer

C = 0.6


def test_label_log_likelihood_is_the_categorical_noisy_label_model() -> None:
    assert np.allclose(np.exp(label_log_likelihood(1, True, 0.7, 0.8)), [0.2, 0.7, 0.2])
    assert np.allclose(np.exp(label_log_likelihood(0, False, 0.7, 0.8)), [0.3, 0.8, 0.8])


def test_evidence_is_the_kernel_weighted_sum_in_any_order() -> None:
    rng = np.random.default_rng(0)
    data = [(rng.uniform(-1, 1, 3), int(rng.integers(3)), bool(rng.integers(2))) for _ in range(30)]
    kernel = KernelEvidence(3, bandwidth=0.5, noise_model=(C, C))
    for x, action, label in data:
        kernel.add(x, action, label)
    xs = np.array([x for x, _, _ in data])
    lls = np.array([label_log_likelihood(a, f, C, C) for _, a, f in data])
    weights = np.exp(-((xs[:, None] - xs[None]) ** 2).mean(-1) / (2 * 0.5**2))
    assert np.allclose(kernel.evidence[:30], weights @ lls)


def test_labels_on_one_state_move_a_near_identical_state_and_not_a_far_one() -> None:
    """30 "correct" labels of action 0 at A, one "correct" of action 1 at B (next to A) and
    at F (far away): alone B's label says 1; the prior makes B's posterior say 0 (its
    neighbour's evidence), and leaves F's saying 1."""
    a, b, far = np.zeros(3), np.full(3, 0.02), np.full(3, 0.9)
    kernel = KernelEvidence(3, bandwidth=0.1, noise_model=(C, C))
    for _ in range(30):
        kernel.add(a, 0, True)
    kernel.add(b, 1, True)
    kernel.add(far, 1, True)
    posterior = kernel.posterior(np.array([30, 31])).numpy()
    assert posterior[0].argmax() == 0 and posterior[0][0] > 0.9  # B: A's evidence
    assert posterior[1].argmax() == 1 and posterior[1][1] < 0.6  # F: its own label only

    # Fhat: A and B far apart for the MLP, near for a wide kernel (h = 1: w(A, B) = 0.61)
    a, b = np.full(3, -0.5, np.float32), np.full(3, 0.5, np.float32)

    def fit(method: str) -> int:
        config = FeedbackConfig(
            method=method,
            good_accuracy=C,
            bad_accuracy=C,
            validation_fraction=0.0,
            kernel_bandwidth=1.0,
        )
        learner = FeedbackLearner(box_normalizer(), config, seed=0)
        for i in range(40):  # 30 labels at A say 0, 10 at B say 1
            state, action = (a, 0) if i % 4 else (b, 1)
            learner.add(state, action, True)
        return HFPolicy(learner.model, method=method).act(b)

    assert fit("categorical") == 1  # without the prior B follows its own labels
    assert fit("categorical_kernel") == 0  # with it, the evidence next door outweighs them


def test_kernel_learner_resumes_bit_for_bit_and_saves_plain_tensors() -> None:
    config = FeedbackConfig(replay_updates=2, method="categorical_kernel")
    rng = np.random.default_rng(5)
    data = [
        (rng.uniform(-1, 1, 3).astype(np.float32), int(rng.integers(3)), bool(rng.integers(2)))
        for _ in range(40)
    ]
    whole = FeedbackLearner(box_normalizer(), config, seed=2)
    part = FeedbackLearner(box_normalizer(), config, seed=2)
    for i, (obs, action, label) in enumerate(data):
        if i == 20:
            buffer = io.BytesIO()
            torch.save(part.state_dict(), buffer)
            buffer.seek(0)
            restored = FeedbackLearner(box_normalizer(), config, seed=2)
            restored.load_state_dict(torch.load(buffer, weights_only=True))
            part = restored
        whole.add(obs, action, label)
        part.add(obs, action, label)
    for p, q in zip(whole.model.parameters(), part.model.parameters(), strict=True):
        assert torch.equal(p, q)
    assert whole.kernel is not None and part.kernel is not None
    assert np.array_equal(whole.kernel.evidence[:40], part.kernel.evidence[:40])


def test_bad_bandwidth_is_refused() -> None:
    with pytest.raises(ValueError, match="kernel_bandwidth"):
        FeedbackConfig(method="categorical_kernel", kernel_bandwidth=0.0)
    with pytest.raises(ValueError, match="bandwidth"):
        KernelEvidence(3, bandwidth=-1.0, noise_model=(C, C))
