"""The best-evaluated checkpoint kept beside the last, target-KL early stop, LR annealing."""

from __future__ import annotations

import json
from dataclasses import replace

import gymnasium as gym
import pytest
import torch

from services.cli.learner import parse_ppo_overrides
from services.learner.evaluation import evaluate_spl
from services.learner.ppo import Callback, PPOConfig, train
from tests.learner.conftest import toy_config


def _learning_config(toy_env_id: str, **overrides) -> PPOConfig:
    """A toy run whose SPL goes from 0 to 1 (the rich toy reward)."""
    return toy_config(
        toy_env_id, env_kwargs={"reward_mode": "rich"}, total_steps=4096, n_epochs=10,
        eval_every=256, **overrides,
    )  # fmt: skip


def _params_equal(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters(), strict=True))


def test_the_best_evaluation_is_kept_beside_the_last(toy_env_id, tmp_path) -> None:
    result = train(_learning_config(toy_env_id))
    spls = [spl for _, spl in result.curve]
    first_best = spls.index(max(spls))
    assert result.best_spl == max(spls) == 1.0
    assert result.best_step == result.curve[first_best][0] < result.global_step
    best = result.best_policy()
    with gym.make(toy_env_id) as env:

        def greedy(obs):
            with torch.no_grad():
                return int(torch.argmax(best(torch.as_tensor(obs))[0]))

        assert evaluate_spl(env, greedy, result.config.eval_seeds) == result.best_spl
    assert not _params_equal(best, result.agent)  # training went on after the best
    path = result.export_torchscript(tmp_path / "best.pt", which="best")
    extra = {"bgrl_meta.json": ""}
    module = torch.jit.load(str(path), _extra_files=extra)
    meta = json.loads(extra["bgrl_meta.json"])
    assert meta["checkpoint"] == "best" and meta["step"] == result.best_step
    assert meta["spl"] == meta["best_spl"] == 1.0 and meta["final_spl"] == result.final_spl
    obs = torch.tensor([1.0, 2.0, 1.0, 0.0, 1.0])
    assert torch.equal(module(obs), best(obs)[0].detach())
    with pytest.raises(ValueError, match="which"):
        result.export_torchscript(tmp_path / "x.pt", which="median")


class _StopAfterUpdates(Callback):
    def __init__(self, n: int) -> None:
        self.n, self.updates = n, 0

    def on_update(self, global_step: int, metrics: dict[str, float]) -> bool:
        self.updates += 1
        return self.updates < self.n


def test_resume_keeps_the_best_checkpoint(toy_env_id, tmp_path) -> None:
    config = _learning_config(toy_env_id, target_kl=0.01, anneal_lr=True, learning_rate=1e-3)
    full = train(config)
    checkpoint = tmp_path / "run.pt"
    stopped = train(config, _StopAfterUpdates(20), checkpoint_path=checkpoint)
    assert 0 < stopped.best_step == full.best_step < stopped.global_step  # best before the stop
    assert min(m["losses/update_epochs"] for m in full.metrics) < config.n_epochs
    resumed = train(config, checkpoint_path=checkpoint)
    assert resumed.curve == full.curve and resumed.best_step == full.best_step
    assert _params_equal(resumed.best_policy(), full.best_policy())
    assert _params_equal(resumed.agent, full.agent)


def test_target_kl_stops_the_epoch_loop_and_none_changes_nothing(toy_env_id) -> None:
    config = toy_config(toy_env_id, total_steps=512, n_epochs=8)
    plain = train(config)
    assert all(m["losses/update_epochs"] == 8.0 for m in plain.metrics)
    loose = train(replace(config, target_kl=1e9))  # checked every minibatch, never hit
    assert loose.curve == plain.curve and _params_equal(loose.agent, plain.agent)
    assert [m["losses/value_loss"] for m in loose.metrics] == [
        m["losses/value_loss"] for m in plain.metrics
    ]
    tight = train(replace(config, target_kl=1e-4))
    epochs = [m["losses/update_epochs"] for m in tight.metrics]
    assert min(epochs) < 8.0 and all(e >= 0.0 for e in epochs)
    # the stop comes before the step of the minibatch that went too far: the first
    # minibatch of an update is at the rollout policy (KL 0), so at least one step is made
    assert all(e >= 0.5 for e in epochs)


def test_learning_rate_annealing(toy_env_id) -> None:
    config = toy_config(toy_env_id, total_steps=640, learning_rate=1e-3)
    constant = [m["charts/learning_rate"] for m in train(config).metrics]
    assert constant == [1e-3] * 5
    annealed = [m["charts/learning_rate"] for m in train(replace(config, anneal_lr=True)).metrics]
    assert annealed == pytest.approx([1e-3 * (1 - k / 5) for k in range(5)])


def test_settings_are_checked_and_parsed() -> None:
    with pytest.raises(ValueError, match="target_kl"):
        PPOConfig(target_kl=0.0)
    assert parse_ppo_overrides(["target_kl=0.02", "anneal_lr=true"]) == {
        "target_kl": 0.02,
        "anneal_lr": True,
    }
    assert parse_ppo_overrides(["target_kl=none"]) == {"target_kl": None}
    with pytest.raises(ValueError, match="target_kl: 'tight' is not a valid number"):
        parse_ppo_overrides(["target_kl=tight"])
    with pytest.raises(ValueError, match="target_kl"):
        parse_ppo_overrides(["target_kl=-1"])
