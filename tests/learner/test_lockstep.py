"""Runs in lockstep: the same records as alone, bit for bit; per-run ends, failures and
checkpoints inside a batch; the batched optimiser's per-run arithmetic."""

from __future__ import annotations

import math
from contextlib import closing
from typing import Any

import gymnasium as gym
import pytest
import torch

from services.learner import pool
from services.learner.feedback import FeedbackConfig, HFPolicy, collect_feedback
from services.learner.feedback_sources import OracleFeedbackSource
from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo import Callback, PPOConfig, TrainResult, train, train_lockstep
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.lockstep import BatchedActorCritic, BatchedAdam
from services.learner.runs import RunFailure, run_lockstep, run_one
from services.learner.specs import RunSpec
from tests.learner.conftest import TOY_ENV_ID, toy_config


def _hf_policy() -> HFPolicy:
    with closing(gym.make(TOY_ENV_ID)) as env:
        source = OracleFeedbackSource(0.9, seed=0)
        return collect_feedback(env, source, 150, config=FeedbackConfig(replay_updates=2)).policy


def _batch(**options: Any) -> tuple[list[PPOConfig], list[HFPolicy | None]]:
    """Four runs of one PPO shape that differ in what a batch allows: seed, reward,
    treatment of pi_HF's steps, pi_HF or none (512 steps each unless ``options`` say)."""
    options = {"total_steps": 512, **options}
    configs = [
        toy_config(seed=1, **options),
        toy_config(seed=2, env_kwargs={"reward_mode": "rich"}, **options),
        toy_config(seed=3, hf_treatment="truncated_is", **options),
        toy_config(seed=4, **options),
    ]
    return configs, [None, None, _hf_policy(), _hf_policy()]


def _same_floats(a: dict[str, float], b: dict[str, float]) -> bool:
    timing = ("charts/SPS", "charts/rollout_seconds", "charts/update_seconds")
    keys = set(a) - set(timing)
    return keys == set(b) - set(timing) and all(
        a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k])) for k in keys
    )


def assert_identical(alone: TrainResult, batched: TrainResult | Exception) -> None:
    """Curve, episodes, per-update metrics (timings aside) and weights equal bit for bit."""
    assert isinstance(batched, TrainResult), batched
    assert batched.curve == alone.curve
    assert batched.episodes == alone.episodes
    assert (batched.best_step, batched.global_step) == (alone.best_step, alone.global_step)
    assert len(batched.metrics) == len(alone.metrics)
    assert all(_same_floats(a, b) for a, b in zip(alone.metrics, batched.metrics, strict=True))
    weights = zip(
        alone.agent.state_dict().values(), batched.agent.state_dict().values(), strict=True
    )
    assert all(torch.equal(p, q) for p, q in weights)


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"hf_guide_sampling": True, "hf_prior_coef": 0.5, "hf_handover_on_revisit": True},
        {"sil_coef": 1.0, "explore_coef": 0.5},
        {"target_kl": 1e-5, "anneal_lr": True, "max_grad_norm": 0.05},
        {"total_steps": 640, "eval_every": 512},  # the trained policy evaluated at its end
    ],
    ids=["paper", "guidance-options", "self-imitation", "stabilisers", "budget-not-multiple"],
)
def test_a_run_in_a_batch_gives_the_records_it_gives_alone(options) -> None:
    configs, policies = _batch(**options)
    batched = train_lockstep(configs, hf_policies=policies)
    alone = [train(c, hf_policy=p) for c, p in zip(configs, policies, strict=True)]
    for a, b in zip(alone, batched, strict=True):
        assert_identical(a, b)
    metrics = [m for result in alone for m in result.metrics]
    if options.get("sil_coef"):  # the options under test were exercised
        assert any(m.get("charts/sil_transitions", 0) > 0 for m in metrics)
    if options.get("target_kl"):
        assert any(m["losses/update_epochs"] < configs[0].n_epochs for m in metrics)
    if options.get("hf_prior_coef"):
        assert any("losses/hf_prior_cross_entropy" in m for m in metrics)
    if options.get("eval_every"):
        assert [step for step, _ in alone[0].curve] == [0, 512, 640]


def test_a_batch_is_deterministic() -> None:
    configs = [toy_config(seed=s, total_steps=512) for s in (5, 6, 7)]
    first, second = train_lockstep(configs), train_lockstep(configs)
    for a, b in zip(first, second, strict=True):
        assert isinstance(a, TrainResult)
        assert_identical(a, b)
    assert first[0].curve != first[1].curve or first[0].episodes != first[1].episodes


class _StopAfterUpdates(Callback):
    def __init__(self, n: int) -> None:
        self.n = n

    def on_update(self, global_step: int, metrics: dict[str, float]) -> bool:
        self.n -= 1
        return self.n > 0


class _FailAtStep(Callback):
    def __init__(self, step: int) -> None:
        self.step = step

    def on_step(self, global_step: int, info: dict[str, Any]) -> bool:
        if global_step == self.step:
            raise RuntimeError(f"env broke at step {global_step}")
        return True


def test_runs_that_stop_or_fail_leave_the_batch_and_the_others_go_on() -> None:
    configs = [toy_config(seed=s, total_steps=512) for s in (1, 2, 3)]
    outcomes = train_lockstep(configs, callbacks=[_StopAfterUpdates(2), _FailAtStep(300), None])
    stopped, failed, whole = outcomes
    assert_identical(train(configs[0], _StopAfterUpdates(2)), stopped)
    assert isinstance(stopped, TrainResult) and stopped.stopped_early
    assert stopped.global_step == 2 * configs[0].n_steps
    assert isinstance(failed, RuntimeError) and "step 300" in str(failed)
    assert_identical(train(configs[2]), whole)


def test_each_run_resumes_from_its_checkpoint_inside_a_batch(tmp_path) -> None:
    configs = [toy_config(seed=s, total_steps=768) for s in (1, 2, 3)]
    paths = [tmp_path / f"run{i}.pt" for i in range(3)]
    # A worker killed mid-batch: runs 0 and 1 wrote checkpoints after 2 and 3 updates.
    train_lockstep(
        configs[:2], callbacks=[_StopAfterUpdates(2), _StopAfterUpdates(3)],
        checkpoint_paths=paths[:2],
    )  # fmt: skip
    # Resumed together with a fresh run (the three at different steps), and alone.
    resumed = train_lockstep(configs, checkpoint_paths=paths, checkpoint_every=1)
    for config, result in zip(configs, resumed, strict=True):
        assert_identical(train(config), result)
    # The checkpoints are the single run's: run 2's, written in the batch, resumes alone.
    assert_identical(train(configs[2]), train(configs[2], checkpoint_path=paths[2]))


def test_only_runs_of_one_ppo_shape_share_a_batch() -> None:
    with pytest.raises(ValueError, match="share every PPO setting"):
        train_lockstep([toy_config(seed=1), toy_config(seed=2, n_epochs=8)])
    with pytest.raises(ValueError, match="one callback"):
        train_lockstep([toy_config(seed=1)], callbacks=[None, None])
    assert train_lockstep([]) == []


def test_a_batch_of_other_shapes_names_the_setting_that_differs() -> None:
    configs = [toy_config(seed=s) for s in (1, 2)] + [toy_config(seed=3, n_epochs=8)]
    with pytest.raises(ValueError, match=r"n_epochs: .* \(run 0\) but 8 \(run 2\)"):
        train_lockstep(configs)


def test_two_runs_of_a_batch_cannot_share_a_checkpoint(tmp_path) -> None:
    """Each would resume from the other's state (or refuse it) after an interruption."""
    configs = [toy_config(seed=s, total_steps=256) for s in (1, 2)]
    shared = tmp_path / "run.pt"
    with pytest.raises(ValueError, match=r"run\.pt: the checkpoint of runs 0 and 1"):
        train_lockstep(configs, checkpoint_paths=[shared, tmp_path / "." / "run.pt"])
    assert not shared.exists()


def test_run_lockstep_refuses_other_shapes_before_any_stage_2(monkeypatch) -> None:
    """Not after minutes of learning every run's pi_HF."""

    def no_stage_2(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("stage 2 ran for a batch that cannot train together")

    monkeypatch.setattr("services.learner.runs.run_guidances", no_stage_2)
    specs = [
        RunSpec("sssg", "hf_sparse", 0, 0.7, n_labels=20),
        RunSpec("sssg", "rl_sparse", 0, ppo_overrides={"n_epochs": 8}),
    ]
    with pytest.raises(ValueError, match="n_epochs"):
        run_lockstep(specs)


def test_batched_clip_and_adam_are_each_runs_own() -> None:
    """Three runs with gradients of very different norms: each is clipped by its own norm
    and stepped with its own step count, as FlatAdam alone (a global clip would scale the
    small one too)."""
    space = gym.spaces.Box(low=-torch.ones(4).numpy(), high=torch.ones(4).numpy())
    agents = [ActorCritic(ObsNormalizer.from_space(space), 3, (8,)) for _ in range(3)]
    singles = [FlatAdam(a.parameters(), lr=1e-2, eps=1e-5) for a in agents]
    model = BatchedActorCritic(agents)
    batched = BatchedAdam(model, singles)
    obs = torch.randn(3, 5, 4)
    scales = torch.tensor([1.0, 1e4, 1e-3])
    logits, values = model(obs)
    batched.zero_grad()
    ((logits.sum((1, 2)) + values.sum(1)) * scales).sum().backward()
    norms = batched.clip_grad_norm_(1.0)
    batched.step([0, 1])  # run 2 skips this step
    for row, (agent, single) in enumerate(zip(agents, singles, strict=True)):
        single.zero_grad()
        run_logits, run_values = agent(obs[row])
        ((run_logits.sum() + run_values.sum()) * scales[row]).backward()
        assert torch.equal(norms[row], single.clip_grad_norm_(1.0))
        if row < 2:
            single.step()
        mirror = ActorCritic(ObsNormalizer.from_space(space), 3, (8,))
        mirror_adam = FlatAdam(mirror.parameters(), lr=1e-2, eps=1e-5)
        model.copy_run_to(row, mirror)
        batched.copy_run_to(row, mirror_adam)
        pairs = zip(agent.parameters(), mirror.parameters(), strict=True)
        assert all(torch.equal(p, q) for p, q in pairs)
        assert mirror_adam.n_steps == single.n_steps == (1 if row < 2 else 0)
        assert torch.equal(mirror_adam.exp_avg, single.exp_avg)
    assert norms[1] > 1.0 > norms[2]  # clipped, and not


TINY = {"total_steps": 128, "eval_every": 128, "n_epochs": 1}


def test_run_lockstep_gives_run_ones_records_on_the_real_env() -> None:
    specs = [  # stage 2 of the two hf_sparse runs in lockstep too
        RunSpec("sssg", "rl_sparse", 0, ppo_overrides=TINY),
        RunSpec("vssg", "hf_sparse", 3, 0.7, "truncated_is", n_labels=40, ppo_overrides=TINY),
        RunSpec("sssg", "hf_sparse", 4, 0.6, "truncated_is", n_labels=40, ppo_overrides=TINY),
    ]
    timings = {"wall_seconds": 0, "hf": None}  # wall times differ (stage 2's in hf too)
    for alone, batched in zip(map(run_one, specs), run_lockstep(specs), strict=True):
        assert alone.to_dict() | timings == batched.to_dict() | timings
        if alone.hf is not None:
            assert {**alone.hf, "wall_seconds": 0} == {**batched.hf, "wall_seconds": 0}


def _in_process(function, specs, *, workers, on_result, on_failure) -> None:
    """``run_isolated`` without worker processes (quick; failures are not isolated)."""
    for spec in specs:
        on_result(function(spec))


def test_a_reproduction_keeps_each_runs_checkpoint_until_its_record(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(pool, "run_isolated", _in_process)
    spec = RunSpec("sssg", "rl_sparse", 0, ppo_overrides=TINY)
    folder = tmp_path / pool.CHECKPOINT_FOLDER
    folder.mkdir()
    # what a worker killed mid-batch left behind, here damaged: the batch reads it
    pool.checkpoint_path(folder, spec).write_bytes(b"not a checkpoint")
    [failure] = pool.reproduce(tmp_path, [spec], workers=1).failed
    assert "not a readable checkpoint" in failure.message
    pool.checkpoint_path(folder, spec).unlink()
    results = pool.reproduce(tmp_path, [spec], workers=1)
    assert [r.run_spec for r in results.runs] == [spec] and results.failed == []
    assert not folder.exists()  # the run's checkpoint went with its record, then the folder


def test_a_sweep_is_dealt_into_lockstep_batches_of_one_ppo_shape() -> None:
    paper = [RunSpec("sssg", "rl_sparse", seed) for seed in range(5)]
    epochs = [RunSpec("vssg", "rl_rich", seed, ppo_overrides={"n_epochs": 8}) for seed in (0, 1)]
    batches = pool.lockstep_batches([*paper, *epochs], workers=2, max_runs=2)
    # paper settings: 5 runs in 3 batches of at most 2, dealt round-robin; the other shape apart
    assert [[s.seed for s in b.specs] for b in batches] == [[0, 3], [1, 4], [2], [0], [1]]
    assert {b.specs[0].ppo_overrides.get("n_epochs") for b in batches[3:]} == {8}
    failures = batches[0].failures(RunFailure("spec", "label", "BrokenProcessPool", "died", ""))
    assert [f.spec for f in failures] == [paper[0].to_dict(), paper[3].to_dict()]
    assert failures[1].label == paper[3].label and failures[1].error_type == "BrokenProcessPool"


class _KilledAtEvaluation(Callback):
    def __init__(self, step: int) -> None:
        self.step = step

    def on_eval(self, global_step: int, spl: float) -> bool:
        if global_step == self.step:
            raise KeyboardInterrupt  # the worker killed: the batch ends
        return True


def test_a_batch_killed_before_its_final_evaluation_resumes_to_it(tmp_path) -> None:
    """Budget 640, evaluations every 512: killed after the last update, before the
    evaluation at its end; resumed in a batch or alone, the records of an uninterrupted run."""
    configs = [toy_config(seed=s, total_steps=640, eval_every=512) for s in (1, 2)]
    paths = [tmp_path / f"run{i}.pt" for i in range(2)]
    with pytest.raises(KeyboardInterrupt):
        train_lockstep(
            configs, callbacks=[_KilledAtEvaluation(640), None], checkpoint_paths=paths,
            checkpoint_every=1,
        )  # fmt: skip
    alone = train(configs[0])
    assert [step for step, _ in alone.curve] == [0, 512, 640]
    kept = tmp_path / "alone.pt"  # the interrupted state, resumed alone
    kept.write_bytes(paths[0].read_bytes())
    assert_identical(alone, train(configs[0], checkpoint_path=kept))
    for config, result in zip(
        configs, train_lockstep(configs, checkpoint_paths=paths), strict=True
    ):
        assert_identical(train(config), result)


@pytest.mark.parametrize(
    "first_lockstep", [True, False], ids=["batch-then-alone", "alone-then-batch"]
)
def test_a_reproduction_resumes_a_run_from_the_other_paths_checkpoint(
    tmp_path, monkeypatch, first_lockstep
) -> None:
    """`bgrl reproduce` interrupted in lockstep and rerun with --single-run (or the other way
    round): the run resumes from its checkpoint in OUT/checkpoints, to the records of an
    uninterrupted run, and the file goes with its record."""
    monkeypatch.setattr(pool, "run_isolated", _in_process)
    spec = RunSpec("sssg", "rl_sparse", 0, ppo_overrides=TINY_RESUMED)
    folder = tmp_path / pool.CHECKPOINT_FOLDER
    folder.mkdir()
    path = pool.checkpoint_path(folder, spec)
    if first_lockstep:  # a worker stopped after two updates of its batch
        run_lockstep([spec], callbacks=[_StopAfterUpdates(2)], checkpoint_paths=[path])
    else:
        run_one(spec, callback=_StopAfterUpdates(2), checkpoint_path=path)
    assert path.exists()
    [record] = pool.reproduce(tmp_path, [spec], workers=1, lockstep=not first_lockstep).runs
    timings = {"wall_seconds": 0}
    assert record.to_dict() | timings == run_one(spec).to_dict() | timings
    assert not folder.exists()  # the run's checkpoint went with its record, then the folder


def test_a_run_alone_reads_its_checkpoint(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(pool, "run_isolated", _in_process)
    spec = RunSpec("sssg", "rl_sparse", 0, ppo_overrides=TINY)
    (tmp_path / pool.CHECKPOINT_FOLDER).mkdir()
    pool.checkpoint_path(tmp_path / pool.CHECKPOINT_FOLDER, spec).write_bytes(b"damaged")
    with pytest.raises(ValueError, match="not a readable checkpoint"):  # in-process: raised
        pool.reproduce(tmp_path, [spec], workers=1, lockstep=False)


TINY_RESUMED = {"total_steps": 512, "eval_every": 256, "n_epochs": 1}
