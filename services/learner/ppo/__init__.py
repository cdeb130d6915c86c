"""Stage 3 of Brain-Guided RL: PPO from sparse reward, with pi_HF guiding exploration.

Akinola et al., ICRA 2020, §Efficient Sparse-Reward RL with Guided Exploration and
Algorithm 1 (``Train the RL policy``). In the style of CleanRL's ``ppo.py`` (one env,
explicit GAE, clipped surrogate), exposed as ``train(config, callback) -> TrainResult``.

Guided exploration. At the start of every episode the behaviour policy is the greedy pi_HF
with probability ``eps_HF(t)``, else pi_RL. ``eps_HF`` is 1 during an optional HF-only
warm-up of ``hf_warmup_steps``, then falls linearly from ``hf_eps_init`` (0.8) to 0 at
``hf_t_trans_fraction`` (50 %) of ``total_steps``. Without an HF policy this is plain PPO, so
RL-sparse, RL-rich and HF+sparse share the network, the hyperparameters and this code.

Two treatments of the steps that pi_HF chose (``hf_treatment``):

* ``"authors"`` - what the authors' code does: the step is stored with pi_RL's log-prob of
  the HF action and used as if pi_RL had sampled it (no importance correction). This is
  biased: the surrogate pushes up pi_RL(a_HF|s) in proportion to the advantage, i.e. it acts
  like advantage-weighted imitation of pi_HF.
* ``"truncated_is"`` - off-policy-correct: the behaviour policy mu is stored per step
  (mu(a_HF|s) = 1 for the greedy pi_HF, mu = pi_RL for RL steps). Advantages use traces cut
  by ``c_t = min(1, pi_old/mu)`` (Retrace, Munos et al. 2016), the surrogate of each step is
  weighted by ``rho_t = min(is_clip, pi_old/mu)`` and the value target is
  ``V + rho_t * A_t`` (V-trace, Espeholt et al. 2018); the PPO clip is taken against the
  policy that collected the batch (decoupled PPO, Hilton et al. 2022). On RL steps
  ``pi_old/mu = 1`` and everything reduces to standard PPO.

Reward scale. Rewards are multiplied by ``reward_scale`` before GAE, identically for every
method (0.01 by default: +-100 terminal rewards become +-1; a 2-D
mock-up only learned with 1/100). Time-limit truncation is bootstrapped with
``gamma * V(s_T)``.

Stabilisers (off by default, so the paper's setting is unchanged): ``target_kl`` ends an
update's epoch loop early once a minibatch's approx KL to the rollout policy exceeds it, and
``anneal_lr`` anneals the learning rate linearly to 0 over the run (CleanRL, SB3).

Self-imitation (off by default, ``sil_coef > 0``): after each update, extra minibatch steps
imitate the transitions of past successful episodes where they did better than the value
function expects (SIL, Oh et al. 2018; :mod:`~services.learner.ppo.self_imitation`), so a
rare success is learned from more than once.

Best checkpoint. Like SB3's ``EvalCallback``, training keeps the weights of the best
evaluation (the first of equal bests) beside the last: ``TrainResult.best_agent`` and
``best_step``; both are in the checkpoint, so a resumed run keeps them too.

Determinism and resume. All randomness comes from ``config.seed`` through one
``numpy.random.SeedSequence`` (:mod:`services.learner.seeding`): torch init (under a forked
RNG), a numpy Generator for sampling and minibatches, and the training reset seeds are
separate child streams, disjoint from the evaluation starts. Checkpoints
(:mod:`services.learner.checkpoint`) are written at update boundaries; a resumed run ends
exactly as an uninterrupted one.

Speed. The actor and critic are evaluated together (:class:`~services.learner.networks.TwinMLP`)
and optimised by :class:`~services.learner.optimizer.FlatAdam` (clip + Adam on one flat
buffer); the tests check both against a plain ``nn.Linear`` / ``torch.optim.Adam`` /
``Categorical`` PPO to a tolerance.

Sweeps. :func:`train_lockstep` trains many runs of one PPO shape as one batch (one
``baddbmm`` per layer for all runs' networks, one optimiser with per-run clipping and Adam,
each run's envs, streams, evaluations and checkpoints its own); each run's records are
bit-identical to :func:`train`'s (:mod:`~services.learner.ppo.lockstep`).

Reading order, one module a concern: :mod:`~services.learner.ppo.config` (:class:`PPOConfig`,
:func:`hf_epsilon`), :mod:`~services.learner.ppo.agent` (:class:`ActorCritic`), then
:func:`train` in :mod:`~services.learner.ppo.loop`, top to bottom as CleanRL's ``ppo.py``:
1. the rollout with the behaviour policy (:mod:`~services.learner.ppo.rollout`), 2. advantages
and returns (:mod:`~services.learner.ppo.advantages`), 3. minibatch updates of the clipped
loss (:mod:`~services.learner.ppo.update`); what a run keeps besides is
:class:`~services.learner.ppo.run.PPORun`. Every name is importable from here.
"""

from services.learner.ppo.advantages import advantages_and_returns, compute_advantages
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import (
    SETTING_BOUNDS,
    HFTreatment,
    PPOConfig,
    check_settings,
    hf_epsilon,
)
from services.learner.ppo.lockstep import (
    PER_RUN_SETTINGS,
    check_one_shape,
    lockstep_key,
    train_lockstep,
)
from services.learner.ppo.loop import train
from services.learner.ppo.result import Callback, TrainResult
from services.learner.ppo.rollout import Rollout, begin_episode, collect_rollout
from services.learner.ppo.update import ppo_loss, update_metrics, update_policy

__all__ = [
    "PER_RUN_SETTINGS",
    "SETTING_BOUNDS",
    "ActorCritic",
    "Callback",
    "HFTreatment",
    "PPOConfig",
    "Rollout",
    "TrainResult",
    "advantages_and_returns",
    "begin_episode",
    "check_one_shape",
    "check_settings",
    "collect_rollout",
    "compute_advantages",
    "hf_epsilon",
    "lockstep_key",
    "ppo_loss",
    "train",
    "train_lockstep",
    "update_metrics",
    "update_policy",
]
