"""End-to-end feedback: the virtual subject's sessions, its decoder, the quality search and
the records of runs whose labels it makes."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from services.eeg.decoding.calibration import TrainingConfig
from services.eeg.signal.preprocessing import PreprocessingParams
from services.eeg.virtual.source import VirtualEEGSource
from services.learner.feedback_sources import DecodedLabel
from services.learner.nstar import NStarJob, nstar_run, row_key
from services.learner.pool import sweep_row_key
from services.learner.runs import HFPolicySpec, RunRecord, hf_policy_run, run_lockstep
from services.learner.specs import RunSpec, with_feedback
from services.learner.stage2_report import summary_table
from services.worker.e2e_feedback import (
    ACCURACY_TOLERANCE,
    DecoderFacts,
    Session,
    SubjectEpochs,
    SubjectRecording,
    VirtualSubjectFactory,
    VirtualSubjectFeedback,
    calibrate_subject,
    find_quality,
)

LDA = TrainingConfig(decoders=("lda",))


def _small_subject(seed: int = 0, n_cal: int = 90, n_held: int = 60) -> SubjectEpochs:
    """A subject's two sessions at quality 0 and 1, short (real generator, few epochs)."""
    rng = np.random.default_rng(seed)
    y_cal = (rng.random(n_cal) < 0.3).astype(np.int64)
    y_held = rng.permutation(np.arange(n_held) % 2).astype(np.int64)
    cal, held = [], []
    for quality in (0.0, 1.0):
        cal.append(SubjectRecording(quality, seed, Session.CALIBRATION).epochs(y_cal))
        held.append(SubjectRecording(quality, seed, Session.HELD_OUT).epochs(y_held))
    recording = SubjectRecording(0.0, seed, Session.CALIBRATION)
    return SubjectEpochs(
        seed,
        recording.ch_names,
        PreprocessingParams(),
        recording.source.sfreq,
        (cal[0], cal[1]),
        (held[0], held[1]),
        y_cal,
        y_held,
    )


def test_a_subjects_epochs_are_linear_in_quality_and_its_sessions_differ() -> None:
    labels = np.array([0, 1, 1, 0, 1])
    x0, x1, xq = (
        SubjectRecording(q, 3, Session.CALIBRATION).epochs(labels) for q in (0.0, 1.0, 0.35)
    )
    np.testing.assert_allclose(xq, x0 + 0.35 * (x1 - x0), atol=1e-11)
    assert np.abs(x1 - x0)[labels == 1].max() > 1e-6  # the ErrP is there
    other = SubjectRecording(0.35, 3, Session.FEEDBACK).epochs(labels)
    assert np.abs(other - xq).mean() > 1e-6  # another session: new background
    # session 0 is the source as it was before sessions existed
    a = VirtualEEGSource(quality=0.3, seed=1).generate_until(2.0)[0]
    b = VirtualEEGSource(quality=0.3, seed=1, session=0).generate_until(2.0)[0]
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="session"):
        VirtualEEGSource(quality=0.3, seed=1, session=-1)


def test_quality_search_hits_the_target_caches_it_and_says_when_it_cannot(
    tmp_path, small_subject
) -> None:
    epochs = small_subject
    search = find_quality(0, 0.65, LDA, tolerance=0.05, cache_dir=tmp_path, epochs=epochs)
    assert abs(search.facts.decoder_accuracy - 0.65) <= 0.05
    assert search.steps[-1]["quality"] == search.facts.quality
    assert calibrate_subject(epochs, search.facts.quality, LDA).facts == search.facts
    (cached,) = tmp_path.iterdir()
    assert json.loads(cached.read_text())["facts"]["quality"] == search.facts.quality
    # the second search is the cache's: no epochs are simulated (none are given)
    again = find_quality(0, 0.65, LDA, tolerance=0.05, cache_dir=tmp_path)
    assert again.facts == search.facts
    with pytest.raises(ValueError, match="closest was"):
        find_quality(0, 0.99, LDA, tolerance=0.005, epochs=epochs, max_steps=2)


def test_a_missed_target_is_kept_at_the_closest_quality_and_refused_only_when_strict(
    tmp_path, small_subject, monkeypatch
) -> None:
    """docs/protocol.md: a subject whose decoder misses 0.60 +- 0.02 is reported and kept (its
    run records the measured accuracy); ``strict`` searches still refuse it."""
    missed = find_quality(
        0, 0.9, LDA, cache_dir=tmp_path, epochs=small_subject, max_steps=2, strict=False
    )
    assert not missed.reached and len(missed.steps) == 2
    assert missed.facts.decoder_accuracy == max(s["decoder_accuracy"] for s in missed.steps)
    assert missed.facts.decoder_accuracy < 0.9 - ACCURACY_TOLERANCE  # the closest, kept
    (cached,) = tmp_path.iterdir()
    assert json.loads(cached.read_text())["reached"] is False
    with pytest.raises(ValueError, match="closest was"):
        find_quality(0, 0.9, LDA, cache_dir=tmp_path)  # the cached miss, strict
    monkeypatch.setattr(SubjectEpochs, "simulate", classmethod(lambda cls, seed: small_subject))
    factory = VirtualSubjectFactory(decoders=LDA.decoders, cache_dir=str(tmp_path))
    feedback = factory(0, 0.9)  # was a ValueError: the run failed
    assert feedback.decoder_accuracy == missed.facts.decoder_accuracy
    assert feedback.subject_quality == missed.facts.quality


def test_the_subjects_feedback_is_its_decoders_reading_of_each_action(toy_subject_factory) -> None:
    subject = toy_subject_factory.subject
    first, second = VirtualSubjectFeedback(subject), VirtualSubjectFeedback(subject)
    truths = [True, False] * 15
    labels = [first.feedback(np.zeros(13), 0, t) for t in truths]
    assert labels == [second.feedback(np.zeros(13), 0, t) for t in truths]  # per seed
    assert all(isinstance(label, DecodedLabel) for label in labels)
    epoch = SubjectRecording(1.0, 0, Session.FEEDBACK).epoch(True)
    p_error, llr = subject.classifier.decode_epoch(epoch)
    assert labels[0] == DecodedLabel(p_error < 0.5, llr)
    llrs = np.array([label.log_likelihood_ratio for label in labels])
    truth = np.array(truths)
    assert llrs[~truth].mean() > llrs[truth].mean()  # errors speak for errors
    assert first.noise_model == (subject.facts.recall_correct, subject.facts.recall_error)
    with pytest.raises(ValueError, match="oracle's truth"):
        first.feedback(np.zeros(13), 0, None)


def test_a_virtual_subject_run_records_its_feedback(toy_subject_factory) -> None:
    spec = HFPolicySpec(
        "sssg",
        None,
        seed=0,
        n_labels=25,
        method="categorical",
        feedback="virtual_subject",
        label_channel="soft",
        decoder_accuracy=0.8,
    )
    row = hf_policy_run(spec, feedback_factory=toy_subject_factory)
    facts = toy_subject_factory.subject.facts
    assert row["n_labels"] == 25 and row["config"]["label_channel"] == "soft"
    assert (row["feedback"], row["label_channel"], row["accuracy"]) == (
        "virtual_subject",
        "soft",
        None,
    )
    assert row["decoder_accuracy"] == facts.decoder_accuracy
    assert row["subject_quality"] == facts.quality and row["decoder_accuracy_target"] == 0.8
    assert sweep_row_key(row) == spec.key  # a sweep resumes past it
    assert "| categorical | SSSG | subject@0.8 soft | 25 | 1 |" in summary_table([row])
    with pytest.raises(ValueError, match="feedback-source factory"):
        hf_policy_run(spec)


def test_an_nstar_collection_on_the_soft_channel_records_its_feedback(toy_subject_factory) -> None:
    job = NStarJob("sssg", None, 0, "bayes_query", (8, 16), "virtual_subject", "soft", 0.8)
    rows = nstar_run(job, feedback_factory=toy_subject_factory)
    facts = toy_subject_factory.subject.facts
    assert [r["n_labels"] for r in rows] == [8, 16]
    for row in rows:
        assert (row["feedback"], row["label_channel"], row["accuracy"]) == (
            "virtual_subject",
            "soft",
            None,
        )
        assert (row["decoder_accuracy"], row["subject_quality"]) == (
            facts.decoder_accuracy,
            facts.quality,
        )
        assert row["decoder_accuracy_target"] == 0.8 and row_key(row) == job.key
    with pytest.raises(ValueError, match="feedback-source factory"):
        nstar_run(job)


def test_a_lockstep_run_with_the_virtual_subjects_feedback_records_it(toy_subject_factory) -> None:
    spec = RunSpec(
        "sssg",
        "hf_sparse",
        0,
        n_labels=20,
        ppo_overrides={"total_steps": 256},
        feedback="virtual_subject",
        label_channel="soft",
        decoder_accuracy=0.8,
    )
    (record,) = run_lockstep([spec], feedback_factory=toy_subject_factory)
    assert isinstance(record, RunRecord), record
    facts = toy_subject_factory.subject.facts
    assert (record.feedback, record.label_channel, record.n_labels) == (
        "virtual_subject",
        "soft",
        20,
    )
    assert (record.decoder_accuracy, record.subject_quality) == (
        facts.decoder_accuracy,
        facts.quality,
    )
    assert record.accuracy is None and record.hf is not None
    assert RunRecord.from_dict(record.to_dict()) == record


def test_specs_take_the_virtual_subjects_feedback() -> None:
    specs = [
        RunSpec("sssg", "rl_sparse", 0),
        RunSpec("sssg", "hf_sparse", 0, accuracy=0.6),
    ]
    rl, hf = with_feedback(specs, "virtual_subject", "soft")
    assert rl == specs[0]
    assert (hf.accuracy, hf.decoder_accuracy, hf.label_channel) == (None, 0.6, "soft")
    assert hf.key != specs[1].key and "subject@0.6 soft" in hf.label
    assert RunSpec.from_dict(hf.to_dict()) == hf
    with pytest.raises(ValueError, match="soft label channel needs"):
        replace(specs[1], label_channel="soft")
    with pytest.raises(ValueError, match="decoder_accuracy is required"):
        replace(hf, decoder_accuracy=None)


@pytest.fixture(scope="module")
def small_subject() -> SubjectEpochs:
    return _small_subject()


class _ToySubjectFactory:
    """A factory whose subject was calibrated once on a short session (quick)."""

    def __init__(self, epochs: SubjectEpochs) -> None:
        self.subject = calibrate_subject(epochs, 1.0, LDA)

    def __call__(self, seed: int, decoder_accuracy: float) -> VirtualSubjectFeedback:
        return VirtualSubjectFeedback(self.subject)


@pytest.fixture(scope="module")
def toy_subject_factory(small_subject) -> _ToySubjectFactory:
    return _ToySubjectFactory(small_subject)


def test_a_cached_subject_reproduces_when_only_the_ece_moves_in_its_last_bits() -> None:
    """A recalibration on another CPU moves the ECE by ~1e-5 (seen: 0.120943 against
    0.120954), never a decision: the cache is the same subject. Any count-based figure,
    the quality, the decoder or an ECE 1e-3 away is another subject."""
    facts = DecoderFacts(
        seed=1017,
        quality=0.625,
        decoder="eegnet",
        decoder_accuracy=0.595,
        recall_correct=0.628,
        recall_error=0.562,
        test_ece=0.12094341429779902,
    )
    assert facts.reproduces(replace(facts, test_ece=0.12095406741202915))
    assert not facts.reproduces(replace(facts, test_ece=0.1225))
    assert not facts.reproduces(replace(facts, test_ece=None))
    assert replace(facts, test_ece=None).reproduces(replace(facts, test_ece=None))
    for changed in ({"decoder_accuracy": 0.596}, {"recall_error": 0.561}, {"quality": 0.5},
                    {"decoder": "lda"}, {"seed": 1018}):  # fmt: skip
        assert not facts.reproduces(replace(facts, **changed))
