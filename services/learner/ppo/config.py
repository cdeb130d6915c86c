"""The hyperparameters of (guided) PPO and the schedule of pi_HF's guidance (eps_HF)."""

from __future__ import annotations

import math
import numbers
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

from pydantic import Field, TypeAdapter, ValidationError

from services.core.ppo_bounds import SETTING_BOUNDS
from services.learner.seeding import evaluation_reset_seeds

HFTreatment = Literal["authors", "truncated_is"]
EpisodeRecord = tuple[int, int, bool, bool, bool]
"""A training episode: (end step, length, reached the goal, collided, followed pi_HF)."""


@dataclass
class PPOConfig:
    """Hyperparameters of (guided) PPO; defaults follow the authors' public code."""

    env_id: str = "services.sim:BrainNav-SSSG-v0"
    """Gymnasium id of the task (its TimeLimit applies)."""
    env_kwargs: dict[str, Any] = field(default_factory=lambda: {"reward_mode": "sparse"})
    """Keyword arguments of ``gymnasium.make`` (reward_mode, map_path, ...)."""
    seed: int = 0
    """Seed of the run: the entropy of the ``SeedSequence`` whose children seed the network
    init, sampling, minibatches and training resets (``services.learner.seeding``)."""
    total_steps: int = 40_000
    """Environment steps of training (the paper's budget)."""
    n_steps: int = 128
    """Rollout length per update (one env)."""
    n_epochs: int = 64
    """Passes over each rollout (a very high replay ratio, as the authors)."""
    minibatch_size: int = 64
    """Minibatch size of the PPO update."""
    learning_rate: float = 3e-4
    """Adam learning rate (the initial one with ``anneal_lr``)."""
    anneal_lr: bool = False
    """Anneal the learning rate linearly to 0 over the updates of the run (CleanRL's
    ``anneal_lr``); off by default, as the authors' constant rate."""
    adam_eps: float = 1e-5
    """Adam epsilon."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    clip_coef: float = 0.2
    """PPO ratio clip."""
    ent_coef: float = 0.02
    """Entropy bonus coefficient."""
    vf_coef: float = 0.5
    """Value loss coefficient."""
    max_grad_norm: float = 25.0
    """Global gradient-norm clip."""
    target_kl: float | None = None
    """Early stop of an update: the remaining minibatch steps of the ``n_epochs`` are skipped
    once a minibatch's approx KL to the rollout policy exceeds this (checked before its
    step, as SB3 does, without SB3's factor 1.5). None (default): all epochs, as the
    authors."""
    norm_adv: bool = True
    """Normalise advantages per minibatch (CleanRL default)."""
    reward_scale: float = 0.01
    """Multiplier of every reward before learning; identical for all methods."""
    hidden_sizes: tuple[int, ...] = (64, 64)
    """Hidden layers of the (separate) actor and critic MLPs, tanh activations."""
    eval_every: int = 2000
    """Evaluate the greedy pi_RL every this many env steps (and at step 0)."""
    eval_seeds: tuple[int, ...] = evaluation_reset_seeds(1)
    """Reset seeds of the fixed evaluation starts (see ``evaluation.eval_seeds``)."""
    hf_eps_init: float = 0.8
    """eps_HF at the end of the warm-up: probability that an episode follows pi_HF."""
    hf_t_trans_fraction: float = 0.5
    """eps_HF reaches 0 at this fraction of ``total_steps``."""
    hf_warmup_steps: int = 0
    """Initial steps during which every episode follows pi_HF."""
    hf_treatment: HFTreatment = "authors"
    """How PPO uses the steps pi_HF chose: ``authors`` or ``truncated_is`` (see the doc of
    :mod:`services.learner.ppo`)."""
    is_clip: float = 1.0
    """rho-bar, the truncation of the importance weight of the surrogate (truncated_is)."""
    hf_guide_sampling: bool = False
    """HF episodes sample from pi_HF's softened distribution instead of its argmax (the
    paper's greedy pi_HF is the default; a factor studied in docs/reproduction.md)."""
    hf_prior_coef: float = 0.0
    """Weight of pi_HF as a prior on pi_RL (kickstarting, Schmitt et al. 2018): the
    cross-entropy from pi_HF's softened distribution to pi_RL on every rollout state, HF and
    RL steps alike, scaled by eps_HF / ``hf_eps_init`` so that it fades with the guidance.
    0 (default): off."""
    hf_handover_on_revisit: bool = False
    """A pi_HF episode that comes back to an observation it has already acted at (pi_HF is
    going round in a loop) follows pi_RL for the rest of the episode. False (default):
    pi_HF to the end."""
    hf_hold_until_success: bool = False
    """eps_HF stays at ``hf_eps_init`` until a training episode first reaches the goal; the
    linear decay to 0 (over ``hf_t_trans_fraction`` of the budget, less the warm-up) starts
    there. False (default): the paper's schedule, counted from step 0."""
    hf_withdraw_after: int = 0
    """Guidance stops for good (eps_HF = 0) once this many pi_HF episodes in a row ended
    without reaching the goal: a pi_HF that does not find the goal hands exploration over to
    pi_RL. 0 (default): never, the paper's schedule alone."""
    explore_coef: float = 0.0
    """Count-based exploration bonus (Strehl and Littman 2008): every step that does not end
    the episode also earns ``explore_coef / sqrt(N)`` (in env-reward units, scaled by
    ``reward_scale`` like the reward), N the run's visits so far, this one included, of the
    pose cell it reaches (the env's ``observation_cell(obs, size_m)``, which BrainNavEnv
    has). HF and RL steps alike; episode returns and self-imitation keep the env's reward.
    0 (default): off."""
    explore_cell_m: float = 0.5
    """Grid size of the exploration bonus's pose cells (m)."""
    sil_coef: float = 0.0
    """Weight of the self-imitation loss on the transitions of past successful episodes
    (:mod:`services.learner.ppo.self_imitation`); 0 (default): off, plain (guided) PPO."""
    sil_updates: int = 8
    """Self-imitation minibatch steps (of ``minibatch_size``) after every PPO update."""
    sil_value_coef: float = 0.01
    """Weight of the self-imitation value term (SIL's beta, 0.01)."""
    sil_capacity: int = 20_000
    """Most transitions of successful episodes kept (the oldest are dropped)."""

    def __post_init__(self) -> None:
        check_settings(vars(self))
        for name in _SETTING_TYPES:
            setattr(self, name, _plain(getattr(self, name)))
        if self.n_steps % self.minibatch_size != 0:
            raise ValueError(
                f"n_steps ({self.n_steps}) must be a multiple of minibatch_size "
                f"({self.minibatch_size})"
            )
        if self.total_steps < self.n_steps:
            raise ValueError("total_steps must be at least n_steps")
        if not self.eval_seeds:
            raise ValueError("eval_seeds must not be empty")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PPOConfig:
        """Rebuild from ``asdict`` output (e.g. JSON)."""
        return cls(**data)


_SETTING_TYPES: dict[str, Any] = typing.get_type_hints(PPOConfig)
BOUND_ERRORS = frozenset({"greater_than", "greater_than_equal", "less_than_equal", "finite_number"})
"""pydantic's error types of a number outside a setting's bounds."""


def _setting_adapter(name: str, hint: Any) -> TypeAdapter[Any]:
    """pydantic's validator of setting ``name``: its type (``hint``) and, for a numeric
    setting, its :data:`SETTING_BOUNDS` (on each entry of a tuple), finite."""
    if name not in SETTING_BOUNDS:
        return TypeAdapter(hint)
    low, high, low_open = SETTING_BOUNDS[name]
    limits: dict[str, Any] = {"gt" if low_open else "ge": low}
    if math.isfinite(high):
        limits["le"] = high
    integer = Annotated[int, Field(**limits)]
    number = Annotated[float, Field(**limits, allow_inf_nan=False)]
    bounded = {int: integer, float: number, float | None: number | None, tuple[int, ...]: (
        tuple[integer, ...]
    )}  # fmt: skip
    return TypeAdapter(bounded[hint])


_SETTING_ADAPTERS = {name: _setting_adapter(name, hint) for name, hint in _SETTING_TYPES.items()}


def _describe_schema(schema: dict[str, Any]) -> str:
    """A JSON Schema's type in words: ``{"type": "integer"}`` -> "an integer",
    ``float | None``'s -> "a number or null", a ``Literal``'s -> "one of [...]"."""
    words = {
        "integer": ("an integer", "integers"),
        "number": ("a number", "numbers"),
        "boolean": ("true or false", "true or false values"),
        "string": ("a string", "strings"),
        "null": ("null", "nulls"),
        "object": ("an object", "objects"),
    }
    if "enum" in schema:
        return f"one of {schema['enum']}"
    if "anyOf" in schema:
        return " or ".join(_describe_schema(option) for option in schema["anyOf"])
    if schema.get("type") == "array":
        items = schema.get("items", {})
        return f"a list of {words[items['type']][1] if items.get('type') in words else 'values'}"
    return words.get(schema.get("type", ""), ("a value", ""))[0]


def check_settings(settings: Mapping[str, Any]) -> None:
    """Refuse a PPO setting of the wrong type or outside :data:`SETTING_BOUNDS` with a
    ValueError naming it (``gamma must be in [0, 1], not 1.5``), checked by pydantic in
    strict mode (a bool is not a number, a number in text is not a number; an integer is
    a float; numpy's numbers count as the numbers they are, a list as a tuple). Names that
    are not settings are left to the constructor; rules between settings are
    :class:`PPOConfig`'s."""
    for name, value in settings.items():
        adapter = _SETTING_ADAPTERS.get(name)
        if adapter is None:
            continue
        try:
            adapter.validate_python(_plain(value), strict=True)
        except ValidationError as exc:
            raise ValueError(_setting_message(name, value, exc.errors()[0])) from None


def _setting_message(name: str, value: Any, error: Any) -> str:
    """The message of setting ``name``'s first pydantic ``error``: its bounds for a number
    outside them (an integer too large for a float too), else the type it must have."""
    number = error.get("input", value)
    too_large = (
        error["type"] == "float_type"
        and isinstance(number, numbers.Integral)
        and not isinstance(number, bool)
    )
    if error["type"] not in BOUND_ERRORS and not too_large:
        described = _describe_schema(TypeAdapter(_SETTING_TYPES[name]).json_schema())
        return f"{name} must be {described}, not {value!r}"
    low, high, low_open = SETTING_BOUNDS[name]
    interval = "({:g}, {}" if low_open else "[{:g}, {}"
    upper = f"{high:g}]" if math.isfinite(high) else "inf)"
    what = f"every entry of {name}" if error["loc"] else name
    return f"{what} must be in {interval.format(low, upper)}, not {number!r}"


def _plain(value: Any) -> Any:
    """Python's own numbers and tuples for numpy scalars and lists (what JSON and
    checkpoints store)."""
    if isinstance(value, bool | str | dict) or value is None:
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real) and not isinstance(value, float):
        return float(value)
    if isinstance(value, list | tuple):
        return tuple(_plain(v) for v in value)
    return value


def hf_epsilon(global_step: int, config: PPOConfig, first_success_step: int | None = None) -> float:
    """eps_HF at a step: 1 in the warm-up, then linear from eps_init to 0 at t_trans (with
    ``hf_hold_until_success``: eps_init until ``first_success_step``, the end step of the
    first training episode that reached the goal, and the decay shifted to start there)."""
    if global_step < config.hf_warmup_steps:
        return 1.0
    if config.hf_hold_until_success:
        if first_success_step is None:
            return config.hf_eps_init
        held = max(0, min(global_step, first_success_step) - config.hf_warmup_steps)
        global_step -= held
    t_trans = config.hf_t_trans_fraction * config.total_steps
    span = t_trans - config.hf_warmup_steps
    if span <= 0:
        return 0.0
    progress = (global_step - config.hf_warmup_steps) / span
    return max(0.0, config.hf_eps_init * (1.0 - progress))


def first_success_step(episodes: Sequence[EpisodeRecord]) -> int | None:
    """End step of the first training episode that reached the goal (None: none yet)."""
    return next((end for end, _, success, _, _ in episodes if success), None)


def guidance_withdrawn(episodes: Sequence[EpisodeRecord], config: PPOConfig) -> bool:
    """Whether the last ``hf_withdraw_after`` pi_HF episodes all ended without reaching the
    goal (always False when ``hf_withdraw_after`` is 0). ``episodes`` are the run's
    ``(end step, length, success, collision, followed pi_HF)`` records, oldest first."""
    if config.hf_withdraw_after <= 0:
        return False
    failed = 0
    for _, _, success, _, is_hf in reversed(episodes):
        if not is_hf:
            continue
        if success:
            return False
        failed += 1
        if failed >= config.hf_withdraw_after:
            return True
    return False


def episode_epsilon(
    global_step: int, episodes: Sequence[EpisodeRecord], config: PPOConfig
) -> float:
    """eps_HF of an episode starting at ``global_step`` after ``episodes``: the schedule,
    held until a first success (``hf_hold_until_success``), 0 once guidance is withdrawn
    (``hf_withdraw_after``)."""
    if guidance_withdrawn(episodes, config):
        return 0.0
    held_until = first_success_step(episodes) if config.hf_hold_until_success else None
    return hf_epsilon(global_step, config, held_until)


def prior_weight(eps_hf: float, config: PPOConfig) -> float:
    """Weight of pi_HF's prior term at an update where eps_HF is ``eps_hf``
    (``hf_prior_coef`` faded like eps_HF)."""
    if config.hf_prior_coef == 0.0 or config.hf_eps_init == 0.0:
        return 0.0
    return config.hf_prior_coef * eps_hf / config.hf_eps_init
