"""The api's copies of the learner's lists (it cannot import the learner) equal the learner's."""

from __future__ import annotations

import dataclasses
from typing import get_args

from services.api.schemas.jobs import (
    PRESETS,
    Method,
    PPOOverrides,
    Task,
    Treatment,
)
from services.core.hf_methods import HF_METHOD_NAMES
from services.learner.hf_methods import HF_METHODS
from services.learner.ppo import SETTING_BOUNDS, PPOConfig, check_settings
from services.learner.specs import METHODS, RUN_FIXED_PPO_FIELDS, TASK_ENV_IDS, TREATMENTS
from services.learner.specs import PRESETS as LEARNER_PRESETS


def test_stage2_methods_are_the_learners() -> None:
    assert set(HF_METHOD_NAMES) == set(HF_METHODS)
    assert len(HF_METHOD_NAMES) == len(HF_METHODS)


def test_presets_methods_tasks_and_treatments_are_the_learners() -> None:
    assert PRESETS == LEARNER_PRESETS
    assert get_args(Method) == METHODS
    assert set(get_args(Task)) == set(TASK_ENV_IDS)
    assert get_args(Treatment) == TREATMENTS


def test_ppo_overrides_are_the_settings_a_run_may_change() -> None:
    settings = {f.name for f in dataclasses.fields(PPOConfig)} - RUN_FIXED_PPO_FIELDS
    assert set(PPOOverrides.model_fields) == settings


def test_ppo_override_bounds_lie_within_the_learners() -> None:
    """What the api accepts, PPOConfig accepts too (a job is not refused only by its worker)."""
    for name, (low, high, low_open) in SETTING_BOUNDS.items():
        if name not in PPOOverrides.model_fields:
            continue  # set per run
        limits = {type(m).__name__: m for m in PPOOverrides.model_fields[name].metadata}
        if name == "hidden_sizes":  # bounds per layer, in the api's validator
            assert PPOOverrides(hidden_sizes=[1]).hidden_sizes == [1]
            continue
        given_low = getattr(limits.get("Gt"), "gt", None)
        api_low_open = given_low is not None
        given_low = given_low if api_low_open else limits["Ge"].ge
        assert given_low > low or (given_low == low and (api_low_open or not low_open)), name
        assert limits["Le"].le <= high, name
        check_settings({name: limits["Le"].le})
