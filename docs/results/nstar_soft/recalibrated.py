"""A diagnostic, not a platform setting: N* of the soft channel when the soft label's Platt
scaling is fitted on the subject's 1000 held-out epochs instead of the calibration
session's 72 validation epochs (as a longer calibration session would allow).

Everything else is the `bgrl hf-nstar --feedback virtual_subject --label-channel soft` run of
docs/stage2.md: the same subjects (cached quality searches), decoders, seeds and budgets;
only ``classifier.calibration`` is refitted. The rows go to OUT/nstar_rows.json; tables
with ``bgrl hf-nstar --out OUT --report-only ...``.

Usage (from the repository root): ``PYTHONPATH=. python
docs/results/nstar_soft/recalibrated.py OUT TARGETS SEEDS METHOD BUDGETS WORKERS``, e.g.
``docs/results/nstar_soft/recalibrated 0.6 100-104 bayes_query 250,500,1000 2``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from services.eeg.decoding.posterior import fit_platt
from services.learner.nstar import NStarJob, run_jobs
from services.worker.e2e_feedback import (
    SubjectEpochs,
    VirtualSubjectFactory,
    VirtualSubjectFeedback,
)

CACHE = "docs/results/nstar_soft/virtual_subjects"


@dataclass(frozen=True)
class HeldOutCalibrated(VirtualSubjectFactory):
    """The run's virtual subject, its P(error) recalibrated on its 1000 held-out epochs."""

    def __call__(self, seed: int, decoder_accuracy: float) -> VirtualSubjectFeedback:
        feedback = super().__call__(seed, decoder_accuracy)
        epochs = SubjectEpochs.simulate(seed)
        _, held_out = epochs.at(feedback.subject_quality)
        p_raw = feedback.classifier.predict_proba(held_out)
        feedback.classifier.calibration = fit_platt(epochs.y_held_out, p_raw)
        return feedback


def main(out: str, targets: str, seeds: str, method: str, budgets: str, workers: str) -> None:
    first, _, last = seeds.partition("-")
    jobs = [
        NStarJob(
            "sssg",
            None,
            seed,
            method,
            tuple(int(n) for n in budgets.split(",")),
            "virtual_subject",
            "soft",
            float(target),
        )
        for target in targets.split(",")
        for seed in range(int(first), int(last) + 1)
    ]
    Path(out).mkdir(parents=True, exist_ok=True)
    factory = HeldOutCalibrated(decoders=("lda",), cache_dir=CACHE)
    run_jobs(jobs, Path(out) / "nstar_rows.json", int(workers), feedback_factory=factory)


if __name__ == "__main__":
    main(*sys.argv[1:7])
