"""The classical decoder beside EEGNet: window-mean shrinkage LDA, selection, service use."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from services.eeg.decoding.calibration import (
    TrainingConfig,
    calibrate,
    stratified_split,
    train_classifier,
)
from services.eeg.decoding.classical import (
    ERRP_CHANNELS,
    WindowMeanLDA,
    fit_window_lda,
    window_index,
)
from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.recordings.epochs import epochs_from_raw
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from services.eeg.virtual.subject import simulate_recording
from tests.eeg.patterned import CH_NAMES, patterned_epochs

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_windows_are_50_ms() -> None:
    index = window_index(103, 128.0)
    assert index[:7] == [0] * 7 and index[7] == 1  # 6.4 samples a window
    assert max(index) == 15 and len(index) == 103
    model = WindowMeanLDA(64, 103, [CH_NAMES.index(c) for c in ERRP_CHANNELS], index)
    x = torch.zeros(1, 64, 103)
    x[0, CH_NAMES.index("F1"), :7] = 1.0  # the first channel's first window
    features = model.features(x)
    assert features.shape == (1, 9 * 16)
    assert features[0, 0] == pytest.approx(1.0) and features[0, 1:].abs().sum() == 0.0
    assert sum(p.numel() for p in model.parameters()) == 145


def test_module_matches_scikit_learn_lda() -> None:
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    epochs = patterned_epochs(["FCz", "Cz"], n=120)
    X = epochs.X * 1e5
    fit = fit_window_lda(X, epochs.y, CH_NAMES, 128.0, seed=0)
    assert fit.channels == list(ERRP_CHANNELS) and len(fit.cv_accuracy) == 5
    with torch.no_grad():
        features = fit.model.features(torch.from_numpy(X)).double().numpy()
        p_torch = torch.softmax(fit.model(torch.from_numpy(X)), dim=1)[:, 1].numpy()
    reference = LinearDiscriminantAnalysis(solver="lsqr", shrinkage="auto", priors=[0.5, 0.5])
    p_sklearn = reference.fit(features, epochs.y).predict_proba(features)[:, 1]
    np.testing.assert_allclose(p_torch, p_sklearn, atol=1e-5)


def test_lda_beats_chance_on_a_short_simulated_recording() -> None:
    labels = np.random.default_rng(5).random(300) >= 0.4
    epochs = epochs_from_raw(simulate_recording(labels, quality=1.0, seed=5))
    split = stratified_split(epochs.y, seed=5, fractions=(0.6, 0.15, 0.25))
    config = TrainingConfig(decoders=("lda",))
    result = train_classifier(epochs, seed=5, split=split, config=config)
    lda = result.metrics["decoders"]["lda"]
    assert result.metrics["decoder"] == "lda" and result.classifier.architecture == "WindowMeanLDA"
    assert lda["roc_auc"] > 0.62 and lda["balanced_accuracy"] > 0.6, lda  # chance: 0.5
    assert lda["cv_accuracy_mean"] > 0.6, lda


@pytest.mark.parametrize(
    ("channels", "max_passes", "expected"),
    [(["FCz", "Cz", "Fz"], 1, "lda"), (["O1", "O2", "Oz", "POz"], 60, "eegnet")],
)
def test_calibration_keeps_the_better_decoder_on_validation(channels, max_passes, expected):
    """An ErrP-like deflection on fronto-central sites against a one-pass EEGNet: the LDA
    wins; a deflection on occipital sites, which the LDA does not look at: EEGNet wins."""
    epochs = patterned_epochs(channels, n=240, seed=1)
    config = TrainingConfig(max_passes=max_passes, decoders=("eegnet", "lda"))
    result = train_classifier(epochs, seed=1, config=config)
    m = result.metrics
    decoders = m["decoders"]
    assert set(decoders) == set(result.candidates) == {"eegnet", "lda"}
    assert m["decoder"] == expected, decoders
    other = "eegnet" if expected == "lda" else "lda"
    assert decoders[expected]["val_accuracy"] > decoders[other]["val_accuracy"]
    assert result.classifier is result.candidates[expected]
    assert m["test_accuracy"] == decoders[expected]["test_accuracy"]
    assert m["n_params"] == decoders[expected]["n_params"] == result.classifier.n_params
    np.testing.assert_allclose(
        result.classifier.predict_proba(epochs.X[result.split.test]), result.test_proba, atol=1e-6
    )


def test_the_service_classifies_with_a_classical_decoder(tmp_path) -> None:
    epochs = patterned_epochs(["FCz", "Cz"], n=100)
    settings = EEGSettings(data_dir=tmp_path)
    with TestClient(create_app(settings)) as client:
        store = client.app.state.service.classifiers
        job_id = "ab" * 8
        result = calibrate(
            epochs,
            seed=0,
            out_dir=store.staging(job_id),
            config=TrainingConfig(decoders=("lda",)),
            report=False,
        )
        classifier_id = store.publish(job_id, "cd" * 8)
        listed = client.get(f"/classifiers/{classifier_id}").json()
        assert listed["metrics"]["decoder"] == "lda"
        for i in (0, 1, 2):
            body = {"epoch": epochs.X[i].tolist(), "ch_names": CH_NAMES, "sfreq": 128.0}
            response = client.post(f"/classifiers/{classifier_id}/classify", json=body)
            assert response.status_code == 200, response.text
            expected = result.classifier.predict_proba(epochs.X[i])[0]
            assert response.json()["p_error"] == pytest.approx(expected, abs=1e-6)
        bad = client.post(
            f"/classifiers/{classifier_id}/classify",
            json={"epoch": epochs.X[0].tolist(), "ch_names": CH_NAMES, "sfreq": 256.0},
        )
        assert bad.status_code == 422  # bound to its channel set and rate


def test_an_unknown_architecture_is_refused(tmp_path) -> None:
    epochs = patterned_epochs(["FCz"], n=60)
    calibrate(epochs, out_dir=tmp_path, config=TrainingConfig(decoders=("lda",)), report=False)
    config = tmp_path / "classifier.json"
    config.write_text(config.read_text().replace('"WindowMeanLDA"', '"Magic"'))
    with pytest.raises(ValueError, match="unknown classifier architecture 'Magic'"):
        ErrPClassifier.load(tmp_path)
    with pytest.raises(ValueError, match="decoders"):
        TrainingConfig(decoders=("svm",))
