"""xDAWN + Riemannian geometry beside EEGNet and the sLDA: the torch module against
pyriemann/scikit-learn, TorchScript without the project, selection, report and metrics."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from services.eeg.decoding.calibration import DECODERS, TrainingConfig, calibrate, train_classifier
from services.eeg.decoding.classifier import ONNX_FILE, TORCHSCRIPT_FILE, ErrPClassifier
from services.eeg.decoding.riemannian import XdawnRiemann, fit_xdawn_riemann, xdawn_riemann_pipeline
from services.eeg.decoding.split import stratified_split
from services.eeg.recordings.epochs import epochs_from_raw
from services.eeg.virtual.subject import simulate_recording
from tests.eeg.patterned import CH_NAMES, patterned_epochs

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_module_matches_pyriemann_and_scikit_learn_on_held_out_epochs() -> None:
    epochs = patterned_epochs(["FCz", "Cz"], n=200, seed=3)
    X = epochs.X * 1e5  # any fixed scale (calibration uses 1 / training SD)
    train, held_out = slice(0, 150), slice(150, None)
    fit = fit_xdawn_riemann(X[train], epochs.y[train], seed=0)
    assert len(fit.cv_accuracy) == 5 and fit.model.hparams["n_filters"] == 2
    reference = xdawn_riemann_pipeline().fit(X[train].astype(np.float64), epochs.y[train])
    p_reference = reference.predict_proba(X[held_out].astype(np.float64))[:, 1]
    assert p_reference.min() > 0.02 and p_reference.max() < 0.98  # not saturated: a real check
    with torch.no_grad():
        p_torch = torch.softmax(fit.model(torch.from_numpy(X[held_out])), dim=1)[:, 1].numpy()
        features = fit.model.tangent_vectors(torch.from_numpy(X[held_out])).numpy()
    np.testing.assert_allclose(p_torch, p_reference, atol=1e-6)
    covariances, tangent = reference.steps[0][1], reference.steps[1][1]
    expected = tangent.transform(covariances.transform(X[held_out].astype(np.float64)))
    np.testing.assert_allclose(features, expected, rtol=1e-5, atol=1e-6)
    scripted = torch.jit.script(fit.model)
    with torch.no_grad():
        logits = scripted(torch.from_numpy(X[held_out]))
    np.testing.assert_allclose(torch.softmax(logits, dim=1)[:, 1].numpy(), p_reference, atol=1e-6)


def test_torchscript_file_decodes_without_the_project_pyriemann_or_scikit_learn(
    tmp_path,
) -> None:
    epochs = patterned_epochs(["FCz", "Cz"], n=120)
    config = TrainingConfig(decoders=("xdawn_rg",))
    result = calibrate(epochs, seed=0, out_dir=tmp_path / "clf", config=config, report=False)
    assert result.classifier.architecture == "XdawnRiemann"
    np.save(tmp_path / "epochs.npy", epochs.X[:6])
    script = textwrap.dedent(
        f"""
        import sys
        for name in ("services", "pyriemann", "sklearn"):
            sys.modules[name] = None  # any import of them fails
        import numpy as np, torch
        model = torch.jit.load({str(tmp_path / "clf" / TORCHSCRIPT_FILE)!r})
        x = torch.from_numpy(np.load({str(tmp_path / "epochs.npy")!r}))
        print(" ".join(repr(float(p)) for p in model(x).detach()))
        """
    )
    done = subprocess.run(
        [sys.executable, "-I", "-c", script],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    p = np.array([float(v) for v in done.stdout.split()])
    np.testing.assert_allclose(p, result.classifier.predict_proba(epochs.X[:6]), atol=1e-6)


def test_calibration_report_and_metrics_name_all_three_decoders(tmp_path) -> None:
    epochs = patterned_epochs(["FCz", "Cz"], n=150, seed=2)
    result = calibrate(epochs, seed=2, out_dir=tmp_path, config=TrainingConfig(max_passes=3))
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert tuple(metrics["decoders"]) == DECODERS == ("eegnet", "lda", "xdawn_rg")
    assert set(result.candidates) == set(DECODERS)
    xdawn = metrics["decoders"]["xdawn_rg"]
    for key in ("val_accuracy", "test_accuracy", "balanced_accuracy", "roc_auc", "n_params"):
        assert key in xdawn
    assert xdawn["cv_folds"] == 5 and 0.0 <= xdawn["cv_accuracy_mean"] <= 1.0
    page = (tmp_path / "report.html").read_text()
    for name in ("EEGNet", "window-mean sLDA", "xDAWN + RG"):
        assert name in page
    assert (tmp_path / "report.png").stat().st_size > 10_000


def test_xdawn_is_kept_where_it_wins_on_validation_and_has_no_onnx(tmp_path) -> None:
    """A deflection on occipital sites (outside the sLDA's channels) against a one-pass
    EEGNet: xDAWN, which filters all channels, is kept; it is written without model.onnx."""
    epochs = patterned_epochs(["O1", "O2", "Oz", "POz"], n=240, seed=1)
    result = calibrate(
        epochs, seed=1, out_dir=tmp_path, config=TrainingConfig(max_passes=1), onnx=True
    )
    m = result.metrics
    assert m["decoder"] == "xdawn_rg", m["decoders"]
    others = [m["decoders"][d]["val_accuracy"] for d in ("eegnet", "lda")]
    assert m["decoders"]["xdawn_rg"]["val_accuracy"] > max(others)
    assert result.classifier is result.candidates["xdawn_rg"]
    assert m["test_accuracy"] == m["decoders"]["xdawn_rg"]["test_accuracy"]
    assert m["n_params"] == result.classifier.n_params == 4 * 64 + 4 * 103 + 8 * 8 + 36 + 1
    np.testing.assert_allclose(
        result.classifier.predict_proba(epochs.X[result.split.test]), result.test_proba, atol=1e-6
    )
    assert not (tmp_path / ONNX_FILE).exists() and (tmp_path / TORCHSCRIPT_FILE).exists()
    with pytest.raises(ValueError, match="XdawnRiemann classifier has no ONNX form"):
        result.classifier.export_onnx(tmp_path)
    loaded = ErrPClassifier.load(tmp_path)
    assert loaded.architecture == "XdawnRiemann" and not loaded.exports_onnx
    np.testing.assert_allclose(
        loaded.predict_proba(epochs.X[:5]), result.classifier.predict_proba(epochs.X[:5])
    )
    loaded.check_compatible(CH_NAMES, 2048.0)
    with pytest.raises(ValueError, match="sampling rate"):
        loaded.check_compatible(CH_NAMES, 1000.0)
    with pytest.raises(ValueError, match="missing"):
        loaded.check_compatible(CH_NAMES[:32], 2048.0)


def test_xdawn_beats_chance_on_a_short_simulated_recording() -> None:
    labels = np.random.default_rng(5).random(300) >= 0.4
    epochs = epochs_from_raw(simulate_recording(labels, quality=1.0, seed=5))
    split = stratified_split(epochs.y, seed=5, fractions=(0.6, 0.15, 0.25))
    config = TrainingConfig(decoders=("xdawn_rg",))
    result = train_classifier(epochs, seed=5, split=split, config=config)
    xdawn = result.metrics["decoders"]["xdawn_rg"]
    assert result.metrics["decoder"] == "xdawn_rg"
    assert xdawn["roc_auc"] > 0.62 and xdawn["balanced_accuracy"] > 0.6, xdawn  # chance: 0.5


def test_module_refuses_impossible_shapes() -> None:
    with pytest.raises(ValueError, match="n_filters"):
        XdawnRiemann(4, 103, n_filters=5)
    with pytest.raises(ValueError, match="both correct"):
        fit_xdawn_riemann(np.zeros((20, 4, 30)), np.zeros(20))
