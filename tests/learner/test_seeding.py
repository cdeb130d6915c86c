"""Seeds: one SeedSequence per run; training, evaluation and label streams never overlap."""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import pytest

from services.learner.evaluation import eval_seeds
from services.learner.ppo import PPOConfig, train
from services.learner.seeding import (
    TAG_SHIFT,
    RunSeeds,
    Stream,
    evaluation_reset_seeds,
    stream_of,
)
from tests.learner.conftest import ToyGridEnv

N_SEEDS = 100
N_EPISODES = 10_000


def test_training_evaluation_and_label_seeds_never_overlap() -> None:
    training = np.concatenate(
        [RunSeeds(seed).training_resets().take(N_EPISODES) for seed in range(N_SEEDS)]
    )
    labels = {
        stream: {RunSeeds(seed).int_seed(stream) for seed in range(N_SEEDS)}
        for stream in (Stream.LABEL_NOISE, Stream.LABEL_COLLECTION, Stream.TORCH_INIT)
    }
    evaluation = set(evaluation_reset_seeds(1000))
    assert len(evaluation) == 1000  # 1000 distinct starts
    assert set(eval_seeds("vssg", 5)) <= evaluation and set(eval_seeds("sssg")) <= evaluation
    assert len(np.unique(training)) == N_SEEDS * N_EPISODES  # no repeat within or across runs
    groups = [set(training.tolist()), evaluation, *labels.values()]
    assert sum(len(g) for g in groups) == len(set().union(*groups))  # pairwise disjoint
    # by construction: each integer seed names its stream in its top bits
    assert {stream_of(s) for s in evaluation} == {None}
    assert np.all(training >> TAG_SHIFT == Stream.TRAINING_RESETS + 1)
    for stream, values in labels.items():
        assert {stream_of(s) for s in values} == {stream}


def test_seed_streams_are_fixed_functions_of_the_seed() -> None:
    assert evaluation_reset_seeds(3) == evaluation_reset_seeds(5)[:3]
    resets = RunSeeds(7).training_resets()
    one_by_one = [resets.next() for _ in range(50)]
    assert one_by_one == RunSeeds(7).training_resets().take(50).tolist()
    assert RunSeeds(7).int_seed(Stream.LABEL_NOISE) == RunSeeds(7).int_seed(Stream.LABEL_NOISE)
    assert RunSeeds(7).int_seed(Stream.LABEL_NOISE) != RunSeeds(8).int_seed(Stream.LABEL_NOISE)
    # children of one SeedSequence, spawned in Stream order
    root_children = np.random.SeedSequence(7).spawn(len(Stream))
    assert RunSeeds(7).generator(Stream.ACTIONS).random() == (
        np.random.default_rng(root_children[Stream.ACTIONS]).random()
    )
    with pytest.raises(ValueError, match="non-negative"):
        RunSeeds(-1)


class _RecordingGrid(ToyGridEnv):
    resets: ClassVar[list[int | None]] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        _RecordingGrid.resets.append(seed)
        return super().reset(seed=seed, options=options)


def test_train_resets_on_the_run_streams_only() -> None:
    env_id = "LearnerRecordingGrid-v0"
    if env_id not in gym.registry:
        gym.register(env_id, entry_point=_RecordingGrid, max_episode_steps=30)
    _RecordingGrid.resets = []
    starts = evaluation_reset_seeds(2)
    config = PPOConfig(
        env_id=env_id, total_steps=256, n_epochs=1, eval_every=128, eval_seeds=starts, seed=1
    )
    result = train(config)
    training = [s for s in _RecordingGrid.resets if s not in starts]
    evaluations = [s for s in _RecordingGrid.resets if s in starts]
    assert len(evaluations) == 2 * len(result.curve)  # every evaluation, both starts
    n_resets = result.n_episodes + 1  # the first reset and one after each episode
    assert training == RunSeeds(1).training_resets().take(n_resets).tolist()
