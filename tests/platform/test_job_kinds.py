"""The job contract: one registry of job kinds, whose names are spelled nowhere else, and
whose PPO bounds are the learner's."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import get_args

import pytest
from pydantic import ValidationError

from services.core.hf_methods import HF_METHOD_NAMES
from services.learner.hf_methods import HF_METHODS
from services.learner.pool import LOCKSTEP_MAX_RUNS
from services.learner.ppo import SETTING_BOUNDS, PPOConfig, check_settings
from services.learner.specs import METHODS, RUN_FIXED_PPO_FIELDS, TASK_ENV_IDS, TREATMENTS
from services.learner.specs import PRESETS as LEARNER_PRESETS
from services.platform.jobs import GUIDED_PPO, JOB_KINDS, job_kind
from services.platform.jobs.ppo import PRESETS, Method, PPOOverrides, Task, Treatment
from services.platform.jobs.reproduce import MAX_BATCH_RUNS

ROOT = Path(__file__).resolve().parents[2]
REGISTRY = ROOT / "services" / "platform" / "jobs"
MIGRATIONS = ROOT / "services" / "core" / "db" / "migrations"
NOT_KINDS = {("services/cli/learner.py", "reproduce")}
"""The same word, not the kind: the ``bgrl reproduce`` command."""


def _spelled(name: str) -> re.Pattern[str]:
    """The kind's name as a string literal (``"guided_ppo"``, ``'guided_ppo'``)."""
    return re.compile(rf"""(["']){re.escape(name)}\1""")


def test_no_kind_is_spelled_outside_the_registry() -> None:
    """Code names a kind through the registry (``GUIDED_PPO.name``), never by its text."""
    found = []
    for path in sorted((ROOT / "services").rglob("*.py")):
        if path.is_relative_to(REGISTRY) or path.is_relative_to(MIGRATIONS):
            continue
        text = path.read_text(encoding="utf-8")
        for name in JOB_KINDS:
            if (path.relative_to(ROOT).as_posix(), name) in NOT_KINDS:
                continue
            if _spelled(name).search(text):
                found.append(f"{path.relative_to(ROOT)}: {name}")
    assert found == []


def test_the_spelling_check_finds_a_spelled_kind() -> None:
    assert _spelled("guided_ppo").search("kind == 'guided_ppo'")
    assert not _spelled("guided_ppo").search("services.worker.training:guided_ppo")


def test_every_kind_has_a_summary_of_its_stored_config() -> None:
    config = GUIDED_PPO.parse({"task": "SSSG", "method": "hf_sparse", "accuracy": 0.7})
    stored = config.model_dump(mode="json", exclude_none=True)
    assert GUIDED_PPO.summary(stored) == "SSSG hf_sparse C=0.7 seed 0, 40,000 steps"
    for kind in JOB_KINDS.values():
        assert isinstance(kind.summary({}), str), kind.name


def test_an_unknown_kind_names_the_known_ones() -> None:
    with pytest.raises(ValueError, match="unknown job kind 'ppo'; use one of guided_ppo, "):
        job_kind("ppo")


def test_stage2_methods_presets_tasks_and_treatments_are_the_learners() -> None:
    assert set(HF_METHOD_NAMES) == set(HF_METHODS)
    assert PRESETS == LEARNER_PRESETS
    assert get_args(Method) == METHODS
    assert set(get_args(Task)) == set(TASK_ENV_IDS)
    assert get_args(Treatment) == TREATMENTS


def test_a_reproduce_batch_is_at_most_the_learners_lockstep_batch() -> None:
    assert MAX_BATCH_RUNS == LOCKSTEP_MAX_RUNS


def test_ppo_overrides_are_the_settings_a_run_may_change() -> None:
    settings = {f.name for f in dataclasses.fields(PPOConfig)} - RUN_FIXED_PPO_FIELDS
    assert set(PPOOverrides.model_fields) == settings


def _limits(schema: dict) -> tuple[float, bool, float]:
    """(low, low excluded, high) of a JSON Schema number (``anyOf`` with null, or items)."""
    for option in schema.get("anyOf", [schema]):
        option = option.get("items", option)
        if "minimum" in option or "exclusiveMinimum" in option:
            low_open = "exclusiveMinimum" in option
            low = option["exclusiveMinimum"] if low_open else option["minimum"]
            return low, low_open, option.get("maximum", math.inf)
    raise AssertionError(f"no bounds in {schema}")


def test_ppo_bounds_are_the_learners_capped_for_jobs() -> None:
    """Each override's lower bound is PPOConfig's, its upper bound PPOConfig's or lower; what
    a job accepts, PPOConfig accepts."""
    properties = PPOOverrides.model_json_schema()["properties"]
    for name in PPOOverrides.model_fields:
        if name not in SETTING_BOUNDS:
            continue  # a switch (bool)
        low, low_open, high = _limits(properties[name])
        assert (low, low_open) == (SETTING_BOUNDS[name][0], SETTING_BOUNDS[name][2]), name
        assert high <= SETTING_BOUNDS[name][1], name
        check_settings({name: [high] if name == "hidden_sizes" else high})


def test_the_worker_refuses_what_the_api_refuses() -> None:
    """One model: a gamma above the learner's 1 is refused naming the field."""
    with pytest.raises(ValidationError, match=r"ppo\.gamma"):
        GUIDED_PPO.parse({"task": "sssg", "method": "rl_sparse", "ppo": {"gamma": 1.5}})
