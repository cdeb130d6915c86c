"""Calibration: split, metrics, a real training run on the virtual subject, save/load."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from services.eeg.decoding.calibration import (
    Split,
    TrainingConfig,
    calibrate,
    classification_metrics,
    roc_auc,
    stratified_split,
    train_classifier,
)
from services.eeg.decoding.classifier import ONNX_FILE, TORCHSCRIPT_FILE, ErrPClassifier
from services.eeg.recordings.epochs import EpochSet
from services.eeg.signal.preprocessing import PreprocessingParams
from services.eeg.virtual.subject import eeg_channel_names, simulate_recording

CH_NAMES = eeg_channel_names()


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _toy_epochs(n: int = 120, seed: int = 0) -> EpochSet:
    """Test data (not EEG): white noise with a fixed pattern added to class-1 epochs."""
    rng = np.random.default_rng(seed)
    y = (rng.random(n) < 0.3).astype(np.int64)
    X = rng.normal(scale=10e-6, size=(n, 64, 103)).astype(np.float32)
    X[y == 1, 10:20, 30:50] += 8e-6
    return EpochSet(X, y, CH_NAMES, PreprocessingParams(), 2048.0, synthetic=True)


def test_stratified_split_fractions_and_determinism() -> None:
    y = np.array([1] * 200 + [0] * 500)
    split = stratified_split(y, seed=3)
    assert (split.train.size, split.val.size, split.test.size) == (560, 84, 56)
    assert y[split.test].sum() == 16 and y[split.val].sum() == 24
    all_idx = np.concatenate([split.train, split.val, split.test])
    assert np.array_equal(np.sort(all_idx), np.arange(y.size))
    again = stratified_split(y, seed=3)
    assert np.array_equal(split.test, again.test)
    assert not np.array_equal(split.test, stratified_split(y, seed=4).test)


def test_roc_auc_and_metrics() -> None:
    y = np.array([0, 0, 1, 1])
    assert roc_auc(y, np.array([0.1, 0.2, 0.8, 0.9])) == 1.0
    assert roc_auc(y, np.array([0.9, 0.8, 0.2, 0.1])) == 0.0
    assert roc_auc(y, np.array([0.5, 0.5, 0.5, 0.5])) == 0.5
    assert roc_auc(y, np.array([0.1, 0.4, 0.35, 0.8])) == 0.75
    m = classification_metrics(np.array([0, 0, 0, 1, 1]), np.array([0.1, 0.6, 0.2, 0.7, 0.4]))
    assert m["confusion_matrix"] == [[2, 1], [1, 1]]
    assert m["test_accuracy"] == pytest.approx(0.6)
    assert m["balanced_accuracy"] == pytest.approx((2 / 3 + 1 / 2) / 2)


def test_training_refuses_single_class() -> None:
    epochs = _toy_epochs()
    one_class = EpochSet(epochs.X, np.zeros_like(epochs.y), CH_NAMES, epochs.params, 2048.0)
    with pytest.raises(ValueError, match="both correct and error"):
        train_classifier(one_class)


def test_calibration_on_virtual_subject_beats_chance() -> None:
    """A clean SYNTHETIC subject: the held-out ROC AUC and balanced accuracy exceed chance."""
    from services.eeg.recordings.epochs import epochs_from_raw

    labels = np.random.default_rng(5).random(300) >= 0.4
    epochs = epochs_from_raw(simulate_recording(labels, quality=1.0, seed=5))
    split = stratified_split(epochs.y, seed=5, fractions=(0.6, 0.15, 0.25))
    result = train_classifier(epochs, seed=5, split=split, config=TrainingConfig(max_passes=60))
    m = result.metrics
    assert m["n_test"] == 75
    assert m["roc_auc"] > 0.7, m
    assert m["balanced_accuracy"] > 0.6, m


@pytest.mark.parametrize(
    ("decoders", "kept", "n_params"),
    [
        (("eegnet",), "eegnet", 786),
        (("lda",), "lda", 145),
        (("xdawn_rg",), "xdawn_rg", 769),
        (("eegnet", "lda"), None, None),
    ],
)
def test_save_load_round_trip_and_torchscript(tmp_path, decoders, kept, n_params) -> None:
    epochs = _toy_epochs()
    config = TrainingConfig(max_passes=4, decoders=decoders)
    result = calibrate(epochs, seed=1, out_dir=tmp_path, config=config)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for key in ("test_accuracy", "balanced_accuracy", "roc_auc", "n_epochs", "n_params"):
        assert key in metrics
    assert set(metrics["decoders"]) == set(decoders)
    kept = kept or metrics["decoder"]
    assert metrics["decoder"] == kept
    assert metrics["n_params"] == (n_params or metrics["decoders"][kept]["n_params"])
    assert metrics["n_epochs"] == 120
    assert (tmp_path / "report.png").stat().st_size > 10_000
    assert "SYNTHETIC" in (tmp_path / "report.html").read_text()

    loaded = ErrPClassifier.load(tmp_path)
    assert loaded.ch_names == CH_NAMES and loaded.params == PreprocessingParams()
    assert loaded.metrics["roc_auc"] == pytest.approx(result.metrics["roc_auc"], nan_ok=True)
    p = result.classifier.predict_proba(epochs.X[:7])
    np.testing.assert_allclose(loaded.predict_proba(epochs.X[:7]), p, rtol=1e-6)
    scripted = torch.jit.load(str(tmp_path / TORCHSCRIPT_FILE))
    np.testing.assert_allclose(
        scripted(torch.from_numpy(epochs.X[:7])).detach().numpy(), p, rtol=1e-5, atol=1e-6
    )
    assert loaded.predict_proba(epochs.X[0]).shape == (1,)


def test_output_json_is_strict_a_figure_without_a_value_is_null(tmp_path) -> None:
    """A test split of one class has no ROC AUC (NaN): metrics.json says null, which strict
    JSON readers take, instead of the NaN token they refuse."""
    from services.eeg.decoding.outputs import write_outputs

    result = calibrate(_toy_epochs(), seed=1, config=TrainingConfig(decoders=("lda",)))
    result.metrics["roc_auc"] = float("nan")
    result.history["val_loss"] = [float("inf")]
    write_outputs(result, tmp_path / "out", report=False, onnx=False)

    def refuse(token: str) -> None:
        raise ValueError(f"not JSON: {token}")

    for name in ("metrics.json", "history.json"):
        text = (tmp_path / "out" / name).read_text()
        parsed = json.loads(text, parse_constant=refuse)
        assert parsed["roc_auc" if name == "metrics.json" else "val_loss"] in (None, [None])


def test_onnx_export_matches_torch(tmp_path) -> None:
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime checks the exported graph")
    epochs = _toy_epochs()
    result = calibrate(
        epochs,
        seed=2,
        out_dir=tmp_path,
        config=TrainingConfig(max_passes=2),
        report=False,
        onnx=True,
    )
    session = ort.InferenceSession(str(tmp_path / ONNX_FILE))
    for n in (1, 5):  # the batch dimension is dynamic
        (p_onnx,) = session.run(None, {"epochs": epochs.X[:n]})
        np.testing.assert_allclose(
            p_onnx, result.classifier.predict_proba(epochs.X[:n]), rtol=1e-4, atol=1e-6
        )


def test_mismatched_data_is_refused() -> None:
    epochs = _toy_epochs(60)
    split = Split(np.arange(40), np.arange(40, 50), np.arange(50, 60))
    clf = train_classifier(epochs, split=split, config=TrainingConfig(max_passes=1)).classifier
    clf.check_compatible(CH_NAMES, 2048.0)
    with pytest.raises(ValueError, match="missing \\['Cz'\\]"):
        clf.check_compatible([c for c in CH_NAMES if c != "Cz"], 2048.0)
    with pytest.raises(ValueError, match="different order"):
        clf.check_compatible(CH_NAMES[::-1], 2048.0)
    with pytest.raises(ValueError, match="sampling rate"):
        clf.check_compatible(CH_NAMES, 1024.0)
    with pytest.raises(ValueError, match="shape"):
        clf.predict_proba(np.zeros((2, 63, 103), dtype=np.float32))
    with pytest.raises(ValueError, match="NaN"):
        clf.predict_proba(np.full((1, 64, 103), np.nan, dtype=np.float32))


def test_load_refuses_missing_classifier(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"classifier\.json"):
        ErrPClassifier.load(tmp_path)


def test_calibration_leaves_process_state_alone_and_is_repeatable(tmp_path) -> None:
    """No global seed, no thread count: the global RNGs and torch's threads are untouched."""
    epochs = _toy_epochs(60)
    threads = torch.get_num_threads()
    torch_state = torch.random.get_rng_state()
    numpy_state = np.random.get_state()[1].copy()
    config = TrainingConfig(max_passes=3)
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / ONNX_FILE).write_text("an earlier run's model")  # not made this time
    (tmp_path / "a" / "notes.txt").write_text("the user's")
    first = calibrate(epochs, seed=3, out_dir=tmp_path / "a", config=config, report=False)
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [
        "classifier.json",
        "history.json",
        "metrics.json",
        "model.pt",
        "model.pt2",
        "model.torchscript.pt",
        "notes.txt",
    ]
    assert torch.get_num_threads() == threads
    assert torch.equal(torch.random.get_rng_state(), torch_state)
    np.testing.assert_array_equal(np.random.get_state()[1], numpy_state)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]  # no staging folder left
    torch.manual_seed(12345)  # whatever the global generator holds does not matter
    second = train_classifier(epochs, seed=3, config=config)
    assert second.history == first.history
    np.testing.assert_array_equal(second.test_proba, first.test_proba)
    assert first.metrics["passes_run"] == 3 and first.metrics["training_config"]["max_passes"] == 3


def test_concurrent_calibrations_give_their_sequential_results() -> None:
    from concurrent.futures import ThreadPoolExecutor

    epochs = _toy_epochs(60)
    config = TrainingConfig(max_passes=3)
    alone = [train_classifier(epochs, seed=s, config=config).history for s in (1, 2)]
    with ThreadPoolExecutor(2) as pool:
        together = list(pool.map(lambda s: train_classifier(epochs, seed=s, config=config), (1, 2)))
    for result, history in zip(together, alone, strict=True):
        np.testing.assert_allclose(result.history["val_loss"], history["val_loss"], rtol=1e-5)


def test_should_stop_cancels_between_passes_and_leaves_nothing(tmp_path) -> None:
    from services.eeg.decoding.calibration import CalibrationCancelled

    calls = []

    def stop_on_third_call() -> bool:
        calls.append(1)
        return len(calls) == 3

    out = tmp_path / "model"
    with pytest.raises(CalibrationCancelled, match=r"^calibration cancelled after 1 of at most 50"):
        calibrate(
            _toy_epochs(60),
            out_dir=out,
            config=TrainingConfig(max_passes=50),
            should_stop=stop_on_third_call,
        )
    assert len(calls) == 3  # once before preprocessing, then before passes 0 and 1
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(CalibrationCancelled, match="before it started"):
        calibrate(_toy_epochs(60), should_stop=lambda: True)


def test_a_classifier_stays_bound_to_its_cap_and_rate(tmp_path) -> None:
    """Trained on a 32-channel cap at 500 Hz: other caps and rates are refused by reason."""
    from services.eeg.recordings.epochs import epochs_from_raw
    from tests.eeg.caps import CAP_8, CAP_32, virtual_recording

    raw = virtual_recording(500.0, CAP_32, labels=[True, False] * 20, seed=8)
    epochs = epochs_from_raw(raw)
    assert epochs.X.shape == (40, 32, 103)
    split = Split(np.arange(30), np.arange(30, 36), np.arange(36, 40))
    clf = train_classifier(epochs, split=split, config=TrainingConfig(max_passes=1)).classifier
    clf.save(tmp_path)
    loaded = ErrPClassifier.load(tmp_path)
    assert (loaded.ch_names, loaded.sfreq_in) == (CAP_32, 500.0)
    loaded.check_compatible(CAP_32, 500.0)
    with pytest.raises(
        ValueError, match=r"sampling rate 250\.0 Hz does not match the classifier's 500\.0 Hz"
    ):
        loaded.check_compatible(CAP_32, 250.0)
    with pytest.raises(ValueError, match=r"missing \['Fp1', 'AF3', 'F7', 'F3', 'FC5'"):
        loaded.check_compatible(CAP_8, 500.0)
    np.testing.assert_allclose(
        loaded.predict_proba(epochs.X[36:]), clf.predict_proba(epochs.X[36:]), atol=1e-6
    )
