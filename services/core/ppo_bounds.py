"""The bounds of PPO's numeric settings: plain numbers, no torch, so that the learner's
``PPOConfig`` (which enforces them) and the platform's job configs (which take theirs from
them) read one table and cannot disagree."""

from __future__ import annotations

import math

SETTING_BOUNDS: dict[str, tuple[float, float, bool]] = {
    "seed": (0, math.inf, False),
    "total_steps": (1, math.inf, False),
    "n_steps": (1, math.inf, False),
    "n_epochs": (1, math.inf, False),
    "minibatch_size": (1, math.inf, False),
    "learning_rate": (0, math.inf, True),
    "adam_eps": (0, math.inf, True),
    "gamma": (0, 1, False),
    "gae_lambda": (0, 1, False),
    "clip_coef": (0, math.inf, True),
    "ent_coef": (0, math.inf, False),
    "vf_coef": (0, math.inf, False),
    "max_grad_norm": (0, math.inf, True),
    "target_kl": (0, math.inf, True),
    "reward_scale": (0, math.inf, True),
    "hidden_sizes": (1, math.inf, False),
    "eval_every": (1, math.inf, False),
    "eval_seeds": (0, math.inf, False),
    "hf_eps_init": (0, 1, False),
    "hf_t_trans_fraction": (0, 1, True),
    "hf_warmup_steps": (0, math.inf, False),
    "is_clip": (0, math.inf, True),
    "hf_prior_coef": (0, math.inf, False),
    "hf_withdraw_after": (0, math.inf, False),
    "explore_coef": (0, math.inf, False),
    "explore_cell_m": (0, math.inf, True),
    "sil_coef": (0, math.inf, False),
    "sil_updates": (0, math.inf, False),
    "sil_value_coef": (0, math.inf, False),
    "sil_capacity": (1, math.inf, False),
}
"""(low, high, low excluded) of every numeric setting of
``services.learner.ppo.PPOConfig`` (of each entry of
``hidden_sizes`` and ``eval_seeds``); values must also be finite."""
