"""One PPO run's envs, networks, generators and progress: what :func:`~services.learner.ppo.train`
(one run) and :func:`~services.learner.ppo.train_lockstep` (many runs in one batch) share.

:class:`PPORun` does everything of a run but the rollout's forward passes and the minibatch
updates: its setup or resume from a checkpoint, the evaluations and the best weights, the
checkpoints, the per-update metrics and callbacks, the self-imitation buffer and the
:class:`~services.learner.ppo.result.TrainResult`. Its ``agent`` and ``optimizer`` hold the
run's weights and Adam state: the single-run path trains them, the lockstep path copies its
batch's row into them before anything here reads them.
"""

from __future__ import annotations

import time
from contextlib import ExitStack, closing
from dataclasses import asdict
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from services.learner.checkpoint import Checkpoint, RunState, load_checkpoint, save_checkpoint
from services.learner.collection import GuidingHFPolicy
from services.learner.evaluation import evaluate_spl
from services.learner.feedback import HFPolicy
from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig, episode_epsilon, prior_weight
from services.learner.ppo.result import Callback, TrainResult
from services.learner.ppo.rollout import Rollout, begin_episode
from services.learner.ppo.self_imitation import SuccessReplay, replay_episode
from services.learner.ppo.update import update_metrics
from services.learner.seeding import RunSeeds, Stream


class PPORun:
    """A run set up (or resumed from ``checkpoint_path``) and evaluated at step 0.

    The envs are closed by ``stack``; ``eval_env``, for the evaluations and the replays of
    successful episodes, may be shared by runs of one task (every use resets it with its
    own seed), else the run makes its own. ``keep_going`` turns False once a hook asks to stop;
    :attr:`running` says whether another update is due. Without ``evaluate_first`` the
    evaluation at step 0 (of a run not resumed) is the caller's (the lockstep runner's,
    batched over its runs).
    """

    def __init__(
        self,
        config: PPOConfig,
        stack: ExitStack,
        *,
        callback: Callback | None = None,
        hf_policy: HFPolicy | None = None,
        checkpoint_path: str | Path | None = None,
        checkpoint_every: int = 10,
        eval_env: gym.Env | None = None,
        evaluate_first: bool = True,
    ) -> None:
        self.start_time = time.perf_counter()
        self.config = config
        self.callback = callback or Callback()
        # pi_HF no longer learns here: its greedy actions are remembered per observation
        self.hf_policy = GuidingHFPolicy(hf_policy) if hf_policy is not None else None
        self.guided = hf_policy is not None
        self.checkpoint = Path(checkpoint_path) if checkpoint_path is not None else None
        self.checkpoint_every = checkpoint_every
        self.env = stack.enter_context(closing(gym.make(config.env_id, **config.env_kwargs)))
        if eval_env is None:  # evaluations and replays reset it with their seed each time
            eval_env = stack.enter_context(closing(gym.make(config.env_id, **config.env_kwargs)))
        self.eval_env = eval_env
        env = self.env
        # ---- networks, optimiser and the run's random streams -----------------------------
        n_actions = int(env.action_space.n)
        if config.explore_coef > 0 and not hasattr(env.unwrapped, "observation_cell"):
            raise ValueError(
                f"explore_coef needs an env with observation_cell(obs, size_m) (BrainNav "
                f"envs have it); {config.env_id} has none"
            )
        seeds = RunSeeds(config.seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seeds.int_seed(Stream.TORCH_INIT))
            self.agent = ActorCritic(
                ObsNormalizer.from_space(env.observation_space), n_actions, config.hidden_sizes
            )
        self.optimizer = FlatAdam(
            self.agent.parameters(), lr=config.learning_rate, eps=config.adam_eps
        )
        self.rng = seeds.generator(Stream.ACTIONS)
        self.resets = seeds.training_resets()
        self.state = RunState()
        self.best_agent: dict[str, torch.Tensor] | None = None  # weights at state.best_step
        self.success_replay = (
            SuccessReplay(env.observation_space.shape[0], config.sil_capacity)
            if config.sil_coef > 0
            else None
        )
        if self.checkpoint is not None and self.checkpoint.exists():
            restored = load_checkpoint(self.checkpoint, asdict(config), asdict(PPOConfig()))
            self.state = restored.restore(
                self.agent, self.optimizer, self.rng, self.resets, hf_policy
            )
            self.best_agent = restored.best_agent
            if self.success_replay is not None and restored.success_replay is not None:
                self.success_replay.load_state_dict(restored.success_replay)
            self.obs, _ = env.reset(seed=self.state.episode_seed)
            for action in self.state.episode_actions:  # replay the episode in progress
                self.obs, *_ = env.step(action)
        else:
            self.obs = begin_episode(env, self.state, self.resets, self.rng, config, self.guided)
        self.keep_going = True
        if evaluate_first and not self.state.curve:
            self.keep_going = self.evaluate()
        self.rollout = Rollout.empty(config.n_steps, env.observation_space.shape[0])

    @property
    def running(self) -> bool:
        """Whether another rollout and update are due (no hook stopped it, budget left)."""
        return self.keep_going and self.state.global_step < self.config.total_steps

    @property
    def final_evaluation_due(self) -> bool:
        """Whether the budget is spent and the last evaluation came before its end (a
        ``total_steps`` that is not a multiple of ``eval_every``): the trained policy is
        then evaluated once more, so ``final_spl`` is its own. With a multiple (the paper's
        40k / 2k) the evaluation due at ``total_steps`` is the last and none is added.
        Evaluations draw from no training stream; a run resumed between its last update and
        this evaluation makes it on resuming."""
        state, budget = self.state, self.config.total_steps
        return state.global_step >= budget and bool(state.curve) and state.curve[-1][0] < budget

    def greedy(self, obs: np.ndarray) -> int:
        """pi_RL's greedy action."""
        with torch.inference_mode():
            logits, _ = self.agent(torch.as_tensor(obs))
        return int(torch.argmax(logits))

    def evaluate(self) -> bool:
        """SPL of the greedy pi_RL on the evaluation starts, kept in the curve (and the
        weights if it is the best so far); the ``on_eval`` hook's answer."""
        return self.record_evaluation(
            evaluate_spl(self.eval_env, self.greedy, self.config.eval_seeds)
        )

    def record_evaluation(self, spl: float) -> bool:
        """Keep the SPL of an evaluation at this step in the curve (and the weights if it is
        the best so far); the ``on_eval`` hook's answer."""
        state = self.state
        state.curve.append((state.global_step, spl))
        if state.best_spl is None or spl > state.best_spl:  # the first of equal bests
            state.best_step, state.best_spl = state.global_step, spl
            self.best_agent = {k: v.detach().clone() for k, v in self.agent.state_dict().items()}
        return self.callback.on_eval(state.global_step, spl)

    def save(self) -> None:
        """Write the checkpoint (atomically)."""
        assert self.checkpoint is not None
        replay = self.success_replay
        save_checkpoint(
            self.checkpoint,
            Checkpoint.capture(
                asdict(self.config), self.agent, self.optimizer, self.rng, self.resets,
                self.state, self.hf_policy, best_agent=self.best_agent,
                success_replay=None if replay is None else replay.state_dict(),
            ),
        )  # fmt: skip

    def eps_hf(self) -> float:
        """eps_HF at the update about to be made (0 if not guided)."""
        if not self.guided:
            return 0.0
        return episode_epsilon(self.state.global_step, self.state.episodes, self.config)

    def prior(self, eps_hf: float) -> tuple[np.ndarray | None, float]:
        """(pi_HF's action distribution at every rollout state, its weight) while pi_HF is a
        prior on pi_RL (``hf_prior_coef``); (None, weight) otherwise."""
        weight = prior_weight(eps_hf, self.config)
        if self.hf_policy is None or weight <= 0.0:
            return None, weight
        return self.hf_policy.sampling_probs(self.rollout.obs), weight

    def remember_successes(self, successes: list[tuple[int, list[int]]]) -> None:
        """Put the episodes that reached the goal in the self-imitation buffer (replayed in
        the evaluation env from their reset seed and actions)."""
        assert self.success_replay is not None
        for seed, actions in successes:
            observations, rewards = replay_episode(
                self.eval_env, seed, actions, self.config.reward_scale
            )
            self.success_replay.add_episode(
                observations, np.asarray(actions), rewards, self.config.gamma
            )

    def end_update(
        self,
        metrics: dict[str, float],
        *,
        returns: np.ndarray,
        episode_returns: list[float],
        eps_hf: float,
        rollout_start: float,
        rollout_seconds: float,
        update_start: float,
    ) -> None:
        """Count the update, complete and keep its metrics, call ``on_update`` and write the
        checkpoint when due (every ``checkpoint_every`` updates and when stopping)."""
        state, config = self.state, self.config
        state.n_updates += 1
        metrics.update(
            update_metrics(
                state.global_step, self.rollout, returns, episode_returns, self.guided,
                self.optimizer.lr, eps_hf,
            )
        )  # fmt: skip
        if config.explore_coef > 0:
            metrics["charts/explored_cells"] = float(len(state.visits))
        metrics["charts/SPS"] = config.n_steps / max(time.perf_counter() - rollout_start, 1e-9)
        metrics["charts/rollout_seconds"] = rollout_seconds
        metrics["charts/update_seconds"] = time.perf_counter() - update_start
        state.metrics.append(metrics)
        self.keep_going &= self.callback.on_update(state.global_step, metrics)
        if self.checkpoint is not None and (
            state.n_updates % self.checkpoint_every == 0 or not self.keep_going
        ):
            self.save()

    def finish(self) -> TrainResult:
        """Write the last checkpoint (if any) and give the result."""
        if self.checkpoint is not None:
            self.save()
        state = self.state
        return TrainResult(
            config=self.config,
            agent=self.agent,
            curve=list(state.curve),
            metrics=state.metrics,
            global_step=state.global_step,
            n_episodes=state.n_episodes,
            n_hf_episodes=state.n_hf_episodes,
            episodes=[tuple(e) for e in state.episodes],
            stopped_early=state.global_step < self.config.total_steps,
            wall_seconds=time.perf_counter() - self.start_time,
            best_step=state.best_step,
            best_agent=self.best_agent,
        )
