"""How well each subject's soft label is calibrated on its own held-out session.

For virtual subjects SEEDS at target decoder accuracy TARGET (their cached quality searches
in docs/results/nstar_soft/virtual_subjects, the sLDA), the decoder is calibrated as for the
N* runs and, on the 1000 held-out epochs (half errors, so the empirical log-odds of an error
equal the true log-likelihood ratio), the soft label's log-likelihood ratio is regressed
(logistic) on the truth: slope 1 = calibrated, < 1 overconfident, <= 0 evidence of the
wrong sign. Also the Platt fit behind it (slope, epochs fitted on) and the ratio's spread.

Usage (from the repository root): ``PYTHONPATH=. python
docs/results/nstar_soft/soft_calibration.py 100,101,102,103,104 0.6 OUT.json``.
"""

from __future__ import annotations

import json
import sys

from sklearn.linear_model import LogisticRegression

from services.eeg.decoding.training_config import TrainingConfig
from services.worker.e2e_feedback import SubjectEpochs, calibrate_subject

CACHE = "docs/results/nstar_soft/virtual_subjects"


def main(seeds: list[int], target: str, out: str) -> None:
    config = TrainingConfig(decoders=("lda",))
    rows = []
    for seed in seeds:
        with open(f"{CACHE}/subject{seed}_acc{target}_lda_p300.json") as handle:
            facts = json.load(handle)["facts"]
        subject = calibrate_subject(SubjectEpochs.simulate(seed), facts["quality"], config)
        calibration = subject.classifier.calibration
        assert calibration is not None
        llr = calibration.log_likelihood_ratio(
            subject.classifier.predict_proba(subject.held_out_epochs)
        )
        fit = LogisticRegression(C=1e6).fit(llr.reshape(-1, 1), subject.held_out_truth)
        row = {
            "seed": seed,
            "target": float(target),
            "quality": facts["quality"],
            "decoder_accuracy": facts["decoder_accuracy"],
            "platt_slope": calibration.slope,
            "platt_n_fit": calibration.n_fit,
            "llr_sd": float(llr.std()),
            "held_out_slope": float(fit.coef_[0, 0]),
        }
        print(row, flush=True)
        rows.append(row)
    with open(out, "w") as handle:
        json.dump(rows, handle, indent=1)


if __name__ == "__main__":
    main([int(s) for s in sys.argv[1].split(",")], sys.argv[2], sys.argv[3])
