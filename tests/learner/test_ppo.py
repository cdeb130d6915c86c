"""Guided PPO: GAE, the loss, the eps_HF schedule, determinism, resume, export, learning."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import asdict, replace

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn

from services.learner.checkpoint import RunState
from services.learner.feedback import FeedbackConfig, collect_feedback
from services.learner.feedback_sources import OracleFeedbackSource
from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo import (
    SETTING_BOUNDS,
    ActorCritic,
    Callback,
    PPOConfig,
    check_settings,
    compute_advantages,
    hf_epsilon,
    ppo_loss,
    train,
)
from services.learner.ppo.config import episode_epsilon, guidance_withdrawn, prior_weight
from services.learner.ppo.rollout import Rollout, begin_episode, collect_rollout
from services.learner.seeding import RunSeeds, Stream
from tests.learner.conftest import ToyGridEnv, toy_config


def test_gae_matches_hand_computed_values() -> None:
    rewards = np.array([1.0, 0.0, 2.0])
    values = np.array([0.5, 0.4, 0.3])
    ends = np.array([0.0, 1.0, 0.0])
    adv = compute_advantages(rewards, values, ends, 0.6, gamma=0.9, gae_lambda=0.8)
    # t=2: 2 + 0.9*0.6 - 0.3 = 2.24; t=1 ends: 0 - 0.4; t=0: 1 + 0.36 - 0.5 + 0.72 * -0.4
    assert np.allclose(adv, [0.572, -0.4, 2.24])
    cut = compute_advantages(
        rewards, np.zeros(3), np.zeros(3), 0.0, 1.0, 1.0, traces=np.array([1.0, 0.5, 0.0])
    )
    # A2 = 2; A1 = 0 + 0 * A2 = 0; A0 = 1 + 0.5 * A1 = 1
    assert np.allclose(cut, [1.0, 0.0, 2.0])


def test_ppo_loss_on_a_tiny_batch() -> None:
    space = gym.spaces.Box(low=-np.ones(2, np.float32), high=np.ones(2, np.float32))
    torch.manual_seed(0)
    agent = ActorCritic(ObsNormalizer.from_space(space), 3, (8,))
    config = PPOConfig(norm_adv=False, ent_coef=0.0, vf_coef=0.5, clip_coef=0.2)
    obs = torch.tensor([[0.1, -0.2], [0.3, 0.4]])
    actions = torch.tensor([0, 2])
    with torch.no_grad():
        logits, values = agent(obs)
        logp = torch.log_softmax(logits, -1).gather(-1, actions[:, None]).squeeze(-1)
    adv = torch.tensor([1.0, -2.0])
    returns = values + 1.0
    ones = torch.ones(2)
    # ratio 1: policy loss = -mean(A) = 0.5, value loss = 0.5 * 1.
    loss, stats = ppo_loss(agent, obs, actions, logp, adv, returns, ones, config)
    assert math.isclose(stats["losses/policy_loss"], 0.5, abs_tol=1e-6)
    assert math.isclose(stats["losses/value_loss"], 0.5, abs_tol=1e-6)
    assert math.isclose(float(loss.detach()), 0.5 + 0.5 * 0.5, abs_tol=1e-6)
    # old log-prob lower by 0.5 -> ratio e^0.5 = 1.65: A>0 clipped at 1.2, A<0 unclipped.
    _, stats = ppo_loss(agent, obs, actions, logp - 0.5, adv, returns, ones, config)
    expected = (-1.0 * 1.2 + 2.0 * math.exp(0.5)) / 2
    assert math.isclose(stats["losses/policy_loss"], expected, rel_tol=1e-5)
    assert stats["losses/clipfrac"] == 1.0
    # importance weights scale each step's surrogate
    weights = torch.tensor([0.5, 0.0])
    _, stats = ppo_loss(agent, obs, actions, logp, adv, returns, weights, config)
    assert math.isclose(stats["losses/policy_loss"], -0.25, abs_tol=1e-6)


def test_hf_prior_adds_its_weighted_cross_entropy_and_pulls_pi_rl_towards_pi_hf() -> None:
    space = gym.spaces.Box(low=-np.ones(2, np.float32), high=np.ones(2, np.float32))
    torch.manual_seed(0)
    agent = ActorCritic(ObsNormalizer.from_space(space), 3, (8,))
    config = PPOConfig(norm_adv=False)
    obs = torch.tensor([[0.1, -0.2], [0.3, 0.4]])
    actions = torch.tensor([0, 2])
    with torch.no_grad():
        logits, values = agent(obs)
        log_pi = torch.log_softmax(logits, -1)
    batch = (obs, actions, log_pi.gather(-1, actions[:, None]).squeeze(-1),
             torch.tensor([1.0, -2.0]), values + 1.0, None, config)  # fmt: skip
    prior = torch.tensor([[0.0, 1.0, 0.0], [0.2, 0.3, 0.5]])
    plain, _ = ppo_loss(agent, *batch)
    unweighted, _ = ppo_loss(agent, *batch, prior, 0.0)
    assert float(unweighted) == float(plain)
    weighted, stats = ppo_loss(agent, *batch, prior, 0.25)
    cross_entropy = float(-(prior * log_pi).sum(-1).mean())
    assert stats["losses/hf_prior_cross_entropy"] == pytest.approx(cross_entropy, rel=1e-6)
    assert float(weighted) == pytest.approx(float(plain) + 0.25 * cross_entropy, rel=1e-6)
    # with only the prior term, gradient steps move pi_RL to pi_HF's distribution
    optimizer = torch.optim.Adam(agent.parameters(), lr=0.05)
    for _ in range(300):
        logits, _ = agent(obs)
        loss = -(prior * torch.log_softmax(logits, -1)).sum(-1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert torch.allclose(torch.softmax(agent(obs)[0], -1), prior, atol=0.05)


def test_prior_weight_fades_with_the_guidance() -> None:
    config = PPOConfig(total_steps=40_000, hf_prior_coef=0.5)
    assert prior_weight(episode_epsilon(0, [], config), config) == pytest.approx(0.5)
    assert prior_weight(episode_epsilon(10_000, [], config), config) == pytest.approx(0.25)
    assert prior_weight(episode_epsilon(20_000, [], config), config) == 0.0
    assert prior_weight(episode_epsilon(0, [], PPOConfig()), PPOConfig()) == 0.0
    with pytest.raises(ValueError, match="hf_prior_coef"):
        PPOConfig(hf_prior_coef=-1.0)


def test_eps_hf_schedule() -> None:
    config = PPOConfig(total_steps=40_000)
    assert hf_epsilon(0, config) == pytest.approx(0.8)
    assert hf_epsilon(10_000, config) == pytest.approx(0.4)
    assert hf_epsilon(20_000, config) == 0.0 and hf_epsilon(39_000, config) == 0.0
    warm = replace(config, hf_warmup_steps=1000)
    assert hf_epsilon(999, warm) == 1.0
    assert hf_epsilon(1000, warm) == pytest.approx(0.8)
    assert hf_epsilon(10_500, warm) == pytest.approx(0.4)


def test_eps_hf_held_until_the_first_success_then_decays_from_there() -> None:
    held = PPOConfig(total_steps=40_000, hf_hold_until_success=True)
    fail, success = (100, 30, False, True, True), (5000, 40, True, False, False)
    assert episode_epsilon(30_000, [fail] * 50, held) == pytest.approx(0.8)  # no success yet
    # the decay starts at the first success (an RL episode's too) and lasts as long
    assert episode_epsilon(15_000, [fail, success, fail], held) == pytest.approx(0.4)
    assert episode_epsilon(25_000, [fail, success], held) == 0.0
    warm = replace(held, hf_warmup_steps=1000)
    assert hf_epsilon(500, warm, 200) == 1.0
    assert hf_epsilon(5000, warm) == hf_epsilon(5000, warm, 5000) == pytest.approx(0.8)
    assert hf_epsilon(14_500, warm, 5000) == pytest.approx(0.4)
    # off (the default): the paper's schedule, successes or not
    assert episode_epsilon(10_000, [success], PPOConfig()) == pytest.approx(0.4)


def test_guidance_withdrawn_after_a_streak_of_failed_hf_episodes() -> None:
    config = PPOConfig(total_steps=40_000, hf_withdraw_after=3)
    hf_fail, hf_win, rl_fail = (0, 9, False, True, True), (0, 9, True, False, True), (
        0, 9, False, True, False)  # fmt: skip
    assert not guidance_withdrawn([hf_fail, hf_fail, rl_fail], config)
    assert guidance_withdrawn([hf_win, hf_fail, rl_fail, hf_fail, rl_fail, hf_fail], config)
    assert not guidance_withdrawn([hf_fail, hf_fail, hf_fail, hf_win], config)
    assert episode_epsilon(1000, [hf_fail] * 3, config) == 0.0
    assert episode_epsilon(1000, [hf_fail] * 3, replace(config, hf_withdraw_after=0)) > 0.7
    with pytest.raises(ValueError, match="hf_withdraw_after"):
        PPOConfig(hf_withdraw_after=-1)


def test_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="multiple"):
        PPOConfig(n_steps=100, minibatch_size=64)
    with pytest.raises(ValueError, match="hf_treatment"):
        PPOConfig(hf_treatment="magic")
    with pytest.raises(ValueError, match="explore_coef"):
        PPOConfig(explore_coef=-1.0)
    with pytest.raises(ValueError, match="explore_cell_m"):
        PPOConfig(explore_cell_m=0.0)
    with pytest.raises(ValueError, match=r"minibatch_size must be in \[1, inf\), not 0"):
        PPOConfig(minibatch_size=0)  # was a ZeroDivisionError
    with pytest.raises(ValueError, match=r"n_epochs must be an integer, not 'ten'"):
        PPOConfig(n_epochs="ten")
    with pytest.raises(ValueError, match=r"anneal_lr must be true or false, not 1"):
        PPOConfig(anneal_lr=1)
    with pytest.raises(ValueError, match=r"every entry of hidden_sizes must be in \[1, inf\)"):
        PPOConfig(hidden_sizes=(64, 0))
    with pytest.raises(ValueError, match=r"learning_rate must be in \(0, inf\), not nan"):
        PPOConfig(learning_rate=math.nan)
    with pytest.raises(ValueError, match=r"gamma must be in \[0, 1\], not 10{400}"):
        PPOConfig(gamma=10**400)  # an int too large for a float: named, no OverflowError
    with pytest.raises(ValueError, match=r"target_kl must be a number or null, not '0.1'"):
        PPOConfig(target_kl="0.1")


def test_every_numeric_setting_has_bounds_and_the_defaults_are_within_them() -> None:
    defaults = PPOConfig()
    numeric = {
        name
        for name, value in vars(defaults).items()
        if not isinstance(value, bool) and isinstance(value, int | float | tuple | type(None))
    }
    assert numeric == set(SETTING_BOUNDS)
    check_settings(vars(defaults))


def test_numpy_numbers_and_lists_become_plain_python_values() -> None:
    config = PPOConfig(
        seed=np.int64(3), learning_rate=np.float32(0.5), hidden_sizes=[np.int32(8), 8],
        gamma=1, total_steps=np.uint16(256),
    )  # fmt: skip
    assert type(config.seed) is int and type(config.total_steps) is int
    assert type(config.learning_rate) is float and config.learning_rate == 0.5
    assert config.hidden_sizes == (8, 8) and all(type(v) is int for v in config.hidden_sizes)
    assert config.gamma == 1
    assert PPOConfig.from_dict(json.loads(json.dumps(asdict(config)))) == config


def test_training_is_deterministic_under_a_seed(toy_env_id) -> None:
    config = toy_config(toy_env_id, total_steps=512)
    a, b = train(config), train(config)
    assert a.curve == b.curve
    assert [m["losses/value_loss"] for m in a.metrics] == [
        m["losses/value_loss"] for m in b.metrics
    ]
    for p, q in zip(a.agent.parameters(), b.agent.parameters(), strict=True):
        assert torch.equal(p, q)
    c = train(replace(config, seed=1))
    assert any(
        not torch.equal(p, q)
        for p, q in zip(a.agent.parameters(), c.agent.parameters(), strict=True)
    )


class _StopAfterUpdates(Callback):
    def __init__(self, n: int) -> None:
        self.n = n
        self.updates = 0

    def on_update(self, global_step: int, metrics: dict[str, float]) -> bool:
        self.updates += 1
        return self.updates < self.n


@pytest.mark.parametrize(
    "guidance",
    [
        {},
        {"hf_prior_coef": 0.5},
        {"hf_hold_until_success": True, "hf_withdraw_after": 5, "hf_handover_on_revisit": True},
        {"explore_coef": 2.0},
    ],
    ids=["paper", "prior", "held", "explore"],
)
def test_checkpoint_resumes_to_the_same_result(toy_env_id, tmp_path, guidance) -> None:
    env = gym.make(toy_env_id)
    hf = collect_feedback(
        env, OracleFeedbackSource(0.9, seed=0), 150, config=FeedbackConfig(replay_updates=2)
    )
    config = toy_config(toy_env_id, hf_treatment="truncated_is", **guidance)
    full = train(config, hf_policy=hf.policy)
    with_prior = ["losses/hf_prior_cross_entropy" in m for m in full.metrics]
    assert with_prior[0] == ("hf_prior_coef" in guidance) and not with_prior[-1]  # it fades
    checkpoint = tmp_path / "run.pt"
    stopped = train(config, _StopAfterUpdates(3), hf_policy=hf.policy, checkpoint_path=checkpoint)
    assert stopped.stopped_early and stopped.global_step == 3 * config.n_steps
    resumed = train(config, hf_policy=hf.policy, checkpoint_path=checkpoint)
    assert resumed.curve == full.curve
    assert resumed.n_hf_episodes == full.n_hf_episodes > 0
    for p, q in zip(full.agent.parameters(), resumed.agent.parameters(), strict=True):
        assert torch.equal(p, q)
    with pytest.raises(ValueError, match=r"different PPOConfig \(seed\)"):
        train(replace(config, seed=5), checkpoint_path=checkpoint)


def test_a_checkpoint_from_before_a_setting_existed_resumes_at_its_default(
    toy_env_id, tmp_path
) -> None:
    config = toy_config(toy_env_id, total_steps=768)
    full = train(config)
    checkpoint = tmp_path / "run.pt"
    train(config, _StopAfterUpdates(2), checkpoint_path=checkpoint)
    payload = torch.load(checkpoint, weights_only=False)
    for newer_setting in ("explore_coef", "explore_cell_m", "hf_prior_coef"):
        del payload["config"][newer_setting]  # as written by the code before these settings
    torch.save(payload, checkpoint)
    with pytest.raises(ValueError, match=r"different PPOConfig \(explore_coef\)"):
        train(replace(config, explore_coef=1.0), checkpoint_path=checkpoint)
    resumed = train(config, checkpoint_path=checkpoint)
    assert resumed.curve == full.curve
    for p, q in zip(full.agent.parameters(), resumed.agent.parameters(), strict=True):
        assert torch.equal(p, q)


class _StepRecorder(gym.Wrapper):
    """Keeps (next observation, terminated) of every step."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.steps: list[tuple[np.ndarray, bool]] = []

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps.append((obs.copy(), bool(terminated)))
        return obs, reward, terminated, truncated, info


def _first_rollout(config: PPOConfig) -> tuple[Rollout, _StepRecorder, RunState]:
    env = _StepRecorder(gym.make(config.env_id))
    seeds = RunSeeds(config.seed)
    torch.manual_seed(0)
    agent = ActorCritic(ObsNormalizer.from_space(env.observation_space), 3, config.hidden_sizes)
    rng, resets, state = seeds.generator(Stream.ACTIONS), seeds.training_resets(), RunState()
    obs = begin_episode(env, state, resets, rng, config, guided=False)
    rollout = Rollout.empty(config.n_steps, env.observation_space.shape[0])
    collect_rollout(
        env, agent, obs, rollout, state, config=config, hf_policy=None, rng=rng, resets=resets,
        on_step=lambda step, info: True, evaluate=lambda: True,
    )  # fmt: skip
    return rollout, env, state


def test_exploration_bonus_is_coef_over_sqrt_visits_of_the_cell_reached(toy_env_id) -> None:
    config = toy_config(toy_env_id, explore_coef=2.0, explore_cell_m=2.0)
    with_bonus, recorder, state = _first_rollout(config)
    plain, _, _ = _first_rollout(replace(config, explore_coef=0.0))
    assert np.array_equal(with_bonus.actions, plain.actions)  # same draws, same agent
    visits: dict[tuple[int, int, int], int] = {}
    expected = np.zeros(config.n_steps)
    for t, (next_obs, terminated) in enumerate(recorder.steps):
        if terminated:  # the goal or a collision: no bonus
            continue
        cell = (int(next_obs[0] // 2), int(next_obs[1] // 2), int(next_obs[2]))
        visits[cell] = visits.get(cell, 0) + 1
        expected[t] = 2.0 * config.reward_scale / math.sqrt(visits[cell])
    assert np.allclose(with_bonus.rewards - plain.rewards, expected, rtol=0, atol=1e-12)
    assert state.visits == visits
    assert expected.max() == pytest.approx(0.02) and 0 < expected[expected > 0].min() < 0.02


def test_exploration_bonus_needs_an_env_that_names_its_cells() -> None:
    config = PPOConfig(env_id="CartPole-v1", env_kwargs={}, total_steps=128, explore_coef=1.0)
    with pytest.raises(ValueError, match="observation_cell"):
        train(config)


def test_rich_reward_run_improves(toy_env_id) -> None:
    config = toy_config(
        toy_env_id, env_kwargs={"reward_mode": "rich"}, total_steps=4096, n_epochs=10,
        eval_every=512,
    )  # fmt: skip
    result = train(config)
    assert result.curve[0][1] == 0.0
    assert max(spl for _, spl in result.curve[-3:]) == 1.0


@pytest.mark.parametrize("sampling", [False, True])
def test_guided_training_uses_the_hf_policy_then_stops(toy_env_id, sampling) -> None:
    env = gym.make(toy_env_id)
    hf = collect_feedback(
        env, OracleFeedbackSource(1.0, seed=0), 150, config=FeedbackConfig(replay_updates=2)
    )
    config = toy_config(
        toy_env_id,
        total_steps=2048,
        hf_warmup_steps=256,
        hf_guide_sampling=sampling,
        hf_treatment="truncated_is",
    )
    result = train(config, hf_policy=hf.policy)
    fractions = [m["charts/hf_step_fraction"] for m in result.metrics]
    assert fractions[0] == 1.0  # warm-up: only pi_HF
    assert fractions[-1] == 0.0  # after t_trans: only pi_RL
    assert result.n_hf_episodes > 0


class _Spinner:
    """A pi_HF that only ever turns left: it comes back to its first observation in 4 steps."""

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> int:
        return 1

    def sampling_probs(self, obs: np.ndarray) -> np.ndarray:
        return np.array([0.0, 1.0, 0.0])


@pytest.mark.parametrize("handover", [False, True])
def test_a_looping_pi_hf_hands_its_episode_over_to_pi_rl(toy_env_id, handover) -> None:
    config = toy_config(
        toy_env_id, total_steps=256, n_steps=128, minibatch_size=64, hf_warmup_steps=256,
        hf_treatment="truncated_is", hf_handover_on_revisit=handover,
    )  # fmt: skip
    result = train(config, hf_policy=_Spinner())  # type: ignore[arg-type]
    fractions = [m["charts/hf_step_fraction"] for m in result.metrics]
    assert result.n_hf_episodes == result.n_episodes > 0  # every episode began with pi_HF
    if handover:  # 4 turns, then pi_RL until the episode ends (30 steps at most)
        assert all(0 < f <= 4 * (result.n_episodes + 2) / 256 for f in fractions)
        assert all(length > 4 for _, length, *_ in result.episodes)
    else:  # spinning until the time limit
        assert fractions == [1.0, 1.0]
        assert all(length == 30 for _, length, *_ in result.episodes)


def test_torchscript_export_loads_without_the_project(toy_env_id, tmp_path) -> None:
    result = train(toy_config(toy_env_id, total_steps=256))
    path = result.export_torchscript(tmp_path / "policy.pt")
    obs = np.array([1, 2, 1, 0, 1], dtype=np.float32)
    code = (
        "import sys; sys.modules['services'] = None\n"
        "import torch\n"
        f"m = torch.jit.load({str(path)!r})\n"
        f"x = torch.tensor({obs.tolist()})\n"
        "print(int(m.act(x)), m(x).tolist())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path
    ).stdout.split(maxsplit=1)
    assert int(out[0]) == result.act(obs)
    with torch.no_grad():
        expected, _ = result.agent(torch.as_tensor(obs))
    assert np.allclose(eval(out[1]), expected.numpy(), atol=1e-6)


def test_flat_adam_matches_torch_clip_and_adam() -> None:
    from services.learner.networks import TwinMLP

    def make() -> TwinMLP:
        torch.manual_seed(3)
        return TwinMLP(13, (64, 64), 3)

    ours, reference = make(), make()
    flat = FlatAdam(ours.parameters(), lr=3e-4, eps=1e-5)
    adam = torch.optim.Adam(reference.parameters(), lr=3e-4, eps=1e-5)
    generator = torch.Generator().manual_seed(0)
    for step in range(5):
        x = torch.randn(64, 13, generator=generator) * (10.0 if step == 2 else 1.0)
        flat.zero_grad()
        ours(x).square().sum().backward()
        norm = flat.clip_grad_norm_(0.5)  # small: the clip is active
        flat.step()
        adam.zero_grad()
        reference(x).square().sum().backward()
        reference_norm = nn.utils.clip_grad_norm_(reference.parameters(), 0.5)
        adam.step()
        assert torch.allclose(norm, reference_norm, rtol=1e-5)
    for mine, theirs in zip(ours.parameters(), reference.parameters(), strict=True):
        assert torch.allclose(mine, theirs, rtol=1e-5, atol=1e-7)
    # its state_dict is torch.optim.Adam's, both ways
    restored = FlatAdam(make().parameters(), lr=3e-4, eps=1e-5)
    restored.load_state_dict(adam.state_dict())
    assert torch.allclose(restored.exp_avg_sq, flat.exp_avg_sq, rtol=1e-5, atol=1e-12)
    assert restored.n_steps == 5
    adam.load_state_dict(flat.state_dict())


class _ClosingGrid(ToyGridEnv):
    opened = 0
    closed = 0

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        _ClosingGrid.opened += 1

    def close(self) -> None:
        _ClosingGrid.closed += 1
        super().close()


class _FailAt(Callback):
    def on_step(self, global_step: int, info: dict) -> bool:
        if global_step == 50:
            raise RuntimeError("boom")
        return True


def test_train_closes_its_envs_when_it_fails() -> None:
    env_id = "LearnerClosingGrid-v0"
    if env_id not in gym.registry:
        gym.register(env_id, entry_point=_ClosingGrid, max_episode_steps=30)
    _ClosingGrid.opened = _ClosingGrid.closed = 0
    with pytest.raises(RuntimeError, match="boom"):
        train(toy_config(env_id), _FailAt())
    assert (_ClosingGrid.opened, _ClosingGrid.closed) == (2, 2)
    train(toy_config(env_id, total_steps=128))
    assert (_ClosingGrid.opened, _ClosingGrid.closed) == (4, 4)


class _KilledAtEvaluation(Callback):
    """A worker killed at the evaluation of ``step`` (after the update that reached it)."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_eval(self, global_step: int, spl: float) -> bool:
        if global_step == self.step:
            raise KeyboardInterrupt
        return True


def test_a_budget_that_is_not_a_multiple_of_eval_every_ends_with_an_evaluation(
    toy_env_id, tmp_path
) -> None:
    """final_spl is the trained policy's, not the one evaluated before the last updates; a
    run killed between its last update and that evaluation resumes to the same records."""
    config = toy_config(toy_env_id, total_steps=384)  # evaluations every 256 steps
    full = train(config)
    assert [step for step, _ in full.curve] == [0, 256, 384]
    assert full.final_spl == full.curve[-1][1] and full.global_step == 384
    checkpoint = tmp_path / "run.pt"
    with pytest.raises(KeyboardInterrupt):
        train(config, _KilledAtEvaluation(384), checkpoint_path=checkpoint, checkpoint_every=1)
    resumed = train(config, checkpoint_path=checkpoint)
    assert resumed.curve == full.curve and resumed.episodes == full.episodes
    for p, q in zip(full.agent.parameters(), resumed.agent.parameters(), strict=True):
        assert torch.equal(p, q)
    # a budget that is a multiple: its last evaluation is the one due at the budget's step
    assert [step for step, _ in train(toy_config(toy_env_id, total_steps=512)).curve] == [
        0, 256, 512
    ]  # fmt: skip
