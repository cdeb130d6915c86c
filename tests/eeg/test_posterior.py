"""Calibrated decoder output: Platt scaling, ECE, the likelihood ratio, and their storage."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import special

from services.eeg.decoding.calibration import TrainingConfig, calibrate
from services.eeg.decoding.classifier import CONFIG_FILE, ErrPClassifier
from services.eeg.decoding.posterior import (
    PosteriorCalibration,
    expected_calibration_error,
    fit_platt,
    reliability_bins,
)
from services.eeg.recordings.epochs import EpochSet
from services.eeg.signal.preprocessing import PreprocessingParams
from services.eeg.virtual.subject import eeg_channel_names


def _scores(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Labels with a true P(error) = sigmoid(z), and a decoder score that is overconfident
    and shifted: sigmoid(3 z + 1)."""
    rng = np.random.default_rng(seed)
    z = rng.normal(-0.8, 1.5, n)
    y = (rng.random(n) < special.expit(z)).astype(np.int64)
    return y, special.expit(3.0 * z + 1.0)


def test_ece_and_reliability_bins_against_hand_numbers() -> None:
    y = np.array([0, 0, 1, 1])
    p = np.array([0.1, 0.15, 0.8, 0.95])
    # bins: [0.1, 0.2) holds 0.1 and 0.15 (mean 0.125, no error); [0.8, 0.9) holds 0.8
    # (an error: gap 0.2); [0.9, 1] holds 0.95 (gap 0.05): (2 * 0.125 + 0.2 + 0.05) / 4
    assert expected_calibration_error(y, p) == pytest.approx(0.125)
    bins = reliability_bins(y, p)
    assert [(b["low"], b["count"]) for b in bins] == [(0.1, 2), (0.8, 1), (0.9, 1)]
    assert bins[0]["mean_p_error"] == pytest.approx(0.125) and bins[0]["error_fraction"] == 0
    assert expected_calibration_error(np.array([1, 0]), np.array([1.0, 0.0])) == 0.0


def test_platt_scaling_fixes_a_miscalibrated_score() -> None:
    y, raw = _scores(400, seed=0)
    calibration = fit_platt(y, raw)
    # the true map is sigmoid(logit(raw) / 3 - 1/3)
    assert calibration.slope == pytest.approx(1 / 3, abs=0.1)
    assert calibration.intercept == pytest.approx(-1 / 3, abs=0.25)
    y_new, raw_new = _scores(4000, seed=1)
    assert expected_calibration_error(y_new, raw_new) > 0.1
    assert expected_calibration_error(y_new, calibration.posterior(raw_new)) < 0.03
    assert calibration.prior_error == pytest.approx(y.mean())


def test_likelihood_ratio_removes_the_calibration_sessions_error_rate() -> None:
    calibration = PosteriorCalibration(slope=1.0, intercept=0.0, prior_error=0.3, n_fit=10)
    # a posterior of 0.5 at a 30 % error rate: odds 1 against prior odds 3/7
    assert calibration.log_likelihood_ratio(np.array([0.5]))[0] == pytest.approx(math.log(7 / 3))
    scaled = PosteriorCalibration(slope=2.0, intercept=-1.0, prior_error=0.5, n_fit=10)
    # logit(0.8) = log 4: 2 log 4 - 1, prior odds 1
    assert scaled.log_likelihood_ratio(np.array([0.8]))[0] == pytest.approx(2 * math.log(4) - 1)
    assert scaled.posterior(np.array([0.8]))[0] == pytest.approx(special.expit(2 * math.log(4) - 1))


def test_platt_refuses_one_class_and_bad_entries() -> None:
    with pytest.raises(ValueError, match="both correct and error"):
        fit_platt(np.zeros(5), np.full(5, 0.4))
    with pytest.raises(ValueError, match="prior_error"):
        PosteriorCalibration(1.0, 0.0, prior_error=0.0, n_fit=3)
    with pytest.raises(ValueError, match="malformed"):
        PosteriorCalibration.from_dict({"slope": 1.0})


def test_calibration_stores_the_posterior_with_the_classifier(tmp_path) -> None:
    rng = np.random.default_rng(0)
    y = (rng.random(150) < 0.3).astype(np.int64)
    X = rng.normal(scale=10e-6, size=(150, 64, 103)).astype(np.float32)
    X[y == 1, 10:20, 30:50] += 4e-6
    epochs = EpochSet(X, y, eeg_channel_names(), PreprocessingParams(), 2048.0, synthetic=True)
    result = calibrate(epochs, seed=0, out_dir=tmp_path, config=TrainingConfig(decoders=("lda",)))
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    report = metrics["calibration"]
    assert report["method"] == "platt" and report["n_fit"] == result.split.val.size
    assert report["test_ece"] == pytest.approx(
        expected_calibration_error(
            y[result.split.test], result.classifier.posterior(X[result.split.test])
        )
    )
    assert "test ECE, calibrated" in (tmp_path / "report.html").read_text()

    loaded = ErrPClassifier.load(tmp_path)
    assert loaded.calibration == result.classifier.calibration
    p_error, llr = loaded.decode_epoch(X[0])
    assert p_error == pytest.approx(float(result.classifier.predict_proba(X[0])[0]), rel=1e-6)
    assert llr == pytest.approx(float(result.classifier.log_likelihood_ratio(X[:1])[0]))

    # a classifier saved before calibrated outputs existed still loads, and says so
    config = json.loads((tmp_path / CONFIG_FILE).read_text())
    del config["calibration"]
    (tmp_path / CONFIG_FILE).write_text(json.dumps(config))
    old = ErrPClassifier.load(tmp_path)
    assert old.calibration is None and old.decode_epoch(X[0])[1] is None
    with pytest.raises(ValueError, match="no posterior calibration"):
        old.posterior(X[:2])
