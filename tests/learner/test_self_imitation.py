"""Self-imitation of successful episodes (``sil_coef``): returns, the loss, resume, default off."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo import ActorCritic, PPOConfig, train
from services.learner.ppo.self_imitation import (
    SuccessReplay,
    replay_episode,
    self_imitation_update,
)
from tests.learner.conftest import toy_config
from tests.learner.test_ppo_stabilisers import _params_equal, _StopAfterUpdates


def test_returns_to_go_are_discounted_and_the_oldest_transitions_go_first() -> None:
    replay = SuccessReplay(n_obs=2, capacity=4)
    replay.add_episode(np.zeros((3, 2)), np.array([0, 1, 2]), np.array([-0.01, -0.01, 1.0]), 0.9)
    assert replay.returns == pytest.approx([-0.01 + 0.9 * (-0.01 + 0.9), -0.01 + 0.9, 1.0])
    replay.add_episode(np.ones((2, 2)), np.array([2, 0]), np.array([0.0, 1.0]), 0.5)
    assert len(replay) == 4  # capacity: the first episode's first transition is gone
    assert replay.actions.tolist() == [1, 2, 2, 0]
    assert replay.returns == pytest.approx([-0.01 + 0.9, 1.0, 0.5, 1.0])
    restored = SuccessReplay(n_obs=2, capacity=4)
    restored.load_state_dict(replay.state_dict())
    assert np.array_equal(restored.obs, replay.obs) and np.array_equal(
        restored.returns, replay.returns
    )
    with pytest.raises(ValueError, match="capacity"):
        SuccessReplay(n_obs=2, capacity=0)


def _agent() -> tuple[ActorCritic, FlatAdam]:
    torch.manual_seed(0)
    agent = ActorCritic(ObsNormalizer(np.zeros(2), np.ones(2)), 3, (16,))
    return agent, FlatAdam(agent.parameters(), lr=1e-2, eps=1e-5)


def test_it_imitates_what_did_better_than_expected_and_ignores_the_rest() -> None:
    config = PPOConfig(sil_coef=1.0, sil_updates=20, sil_value_coef=0.01)
    obs = torch.tensor([[0.5, -0.5]])

    def probability_and_value(agent: ActorCritic) -> tuple[float, float]:
        with torch.no_grad():
            logits, value = agent(obs)
        return float(torch.softmax(logits, -1)[0, 2]), float(value[0])

    agent, optimizer = _agent()
    before, value_before = probability_and_value(agent)
    good = SuccessReplay(2, 100)
    good.add_episode(obs.numpy(), np.array([2]), np.array([1.0]), 0.99)  # R = 1 > V ~ 0
    metrics = self_imitation_update(agent, optimizer, good, config, np.random.default_rng(0))
    after, value_after = probability_and_value(agent)
    assert after > before + 0.2 and value_after > value_before  # pi(a|s) and V move up
    assert metrics["charts/sil_positive_fraction"] > 0 and metrics["charts/sil_transitions"] == 1

    agent, optimizer = _agent()
    weights = [p.detach().clone() for p in agent.parameters()]
    bad = SuccessReplay(2, 100)
    bad.add_episode(obs.numpy(), np.array([2]), np.array([-5.0]), 0.99)  # R < V: loss 0
    self_imitation_update(agent, optimizer, bad, config, np.random.default_rng(0))
    assert all(torch.equal(w, p) for w, p in zip(weights, agent.parameters(), strict=True))
    assert self_imitation_update(agent, optimizer, SuccessReplay(2, 10), config, None) == {}


def test_an_episode_is_read_back_from_its_seed_and_actions(toy_env_id) -> None:
    import gymnasium as gym

    with gym.make(toy_env_id) as env:
        obs, _ = env.reset(seed=7)
        played, rewards = [obs], []
        for action in (0, 1, 0):
            obs, reward, *_ = env.step(action)
            played.append(obs)
            rewards.append(reward * 0.01)
        observations, scaled = replay_episode(env, 7, [0, 1, 0], 0.01)
    assert np.array_equal(observations, np.array(played[:3], np.float32))
    assert scaled == pytest.approx(rewards)


def test_off_changes_nothing_and_on_resumes_bit_for_bit(toy_env_id, tmp_path) -> None:
    config = toy_config(toy_env_id, total_steps=1536, n_epochs=4, eval_every=256)
    plain = train(config)
    assert not any("charts/sil_transitions" in m for m in plain.metrics)
    sil = replace(config, sil_coef=1.0, sil_updates=4)
    full = train(sil)
    stored = [m["charts/sil_transitions"] for m in full.metrics if "charts/sil_transitions" in m]
    assert stored and stored[-1] > 0  # the toy's random walk reaches its goal
    assert not _params_equal(full.agent, plain.agent)
    first = next(i for i, m in enumerate(full.metrics) if "charts/sil_transitions" in m)
    assert first < 5  # the buffer holds successes when the run below stops (its checkpoint)
    checkpoint = tmp_path / "run.pt"
    train(sil, _StopAfterUpdates(6), checkpoint_path=checkpoint)
    resumed = train(sil, checkpoint_path=checkpoint)
    assert resumed.curve == full.curve and _params_equal(resumed.agent, full.agent)


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="sil_coef"):
        PPOConfig(sil_coef=-1.0)
    with pytest.raises(ValueError, match="sil_capacity"):
        PPOConfig(sil_capacity=0)
