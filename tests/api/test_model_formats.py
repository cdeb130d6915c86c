"""Trained models downloaded through the api in every format (``?format=torchscript|pt2|onnx``)
and run where users run them: ``torch.jit.load``, ``torch.export.load`` and onnxruntime, on
random observations (or epochs), each compared with the torch module it was written from."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from services.core.db.models import Artifact, Classifier, HFModel, Job
from services.core.model_formats import MODEL_FORMATS, SUFFIXES
from services.eeg.decoding.classifier import ONNX_FILE, PT2_FILE, TORCHSCRIPT_FILE, ErrPClassifier
from services.eeg.decoding.eegnet import EEGNet
from services.eeg.decoding.riemannian import fit_xdawn_riemann
from services.learner.feedback import FeedbackModel
from services.learner.networks import ObsNormalizer
from services.learner.policy_files import ActorLogits, write_beside_torchscript
from services.learner.ppo import ActorCritic
from services.learner.ppo.result import PolicyExport
from services.learner.service.export import HFPolicyExport, policy_files
from services.sim.env import OBS_SIZE
from tests.api.conftest import Api
from tests.eeg.patterned import patterned_epochs

ort = pytest.importorskip("onnxruntime", reason="onnxruntime runs the downloaded ONNX files")

TOLERANCE = 1e-5
"""Largest absolute difference allowed between a file's output and the torch module's."""


def store(api: Api, data: bytes, name: str) -> str:
    """``data`` in the api's artifact store; its artifact id."""
    stored = api.client.app.state.store.put_bytes(data, kind="model", name=name)
    with api.client.app.state.sessions() as db:
        artifact = Artifact(
            kind="model", relpath=stored.relpath, sha256=stored.sha256, size_bytes=stored.size_bytes
        )
        db.add(artifact)
        db.commit()
        return artifact.id


def add_row(api: Api, row: object) -> object:
    with api.client.app.state.sessions() as db:
        db.add(row)
        db.commit()
        return row.id  # type: ignore[attr-defined]


def download(api: Api, url: str, tmp_path: Path, name: str) -> Path:
    response = api.client.get(url, headers=api.as_("viewer"))
    assert response.status_code == 200, response.text
    assert f'filename="{name}"' in response.headers["content-disposition"]
    path = tmp_path / name
    path.write_bytes(response.content)
    return path


def outputs(path: Path, fmt: str, x: np.ndarray) -> np.ndarray:
    """What the file at ``path`` computes for ``x``, loaded as a user of ``fmt`` loads it."""
    if fmt == "onnx":
        session = ort.InferenceSession(str(path))
        return session.run(None, {session.get_inputs()[0].name: x})[0]
    load = {"pt2": lambda p: torch.export.load(p).module(), "torchscript": torch.jit.load}[fmt]
    module = load(str(path))
    with torch.no_grad():
        return module(torch.from_numpy(x)).numpy()


def random_observations(seed: int, n: int = 64) -> np.ndarray:
    """Raw observations around and outside the env's ranges (normalisation is inside)."""
    return np.random.default_rng(seed).normal(0.0, 3.0, size=(n, OBS_SIZE)).astype(np.float32)


def normalizer() -> ObsNormalizer:
    rng = np.random.default_rng(0)
    return ObsNormalizer(rng.normal(size=OBS_SIZE), rng.uniform(0.5, 2.0, size=OBS_SIZE))


def test_guided_ppo_policy_in_every_format(api: Api, tmp_path: Path) -> None:
    torch.manual_seed(0)
    agent = ActorCritic(normalizer(), 3, (64, 64)).eval()
    torchscript = tmp_path / "written" / "policy.pt"
    torchscript.parent.mkdir()
    meta = {"checkpoint": "best", "spl": 0.5}
    torch.jit.script(PolicyExport(agent)).save(
        str(torchscript), _extra_files={"bgrl_meta.json": json.dumps(meta)}
    )
    written = write_beside_torchscript(agent, torchscript)
    files = {"torchscript": torchscript, **written}
    ids = {fmt: store(api, path.read_bytes(), path.name) for fmt, path in files.items()}
    job_id = add_row(
        api,
        Job(
            kind="guided_ppo",
            status="succeeded",
            model_artifact_id=ids["torchscript"],
            model_pt2_artifact_id=ids["pt2"],
            model_onnx_artifact_id=ids["onnx"],
        ),
    )
    x = random_observations(1)
    with torch.no_grad():
        expected = ActorLogits(agent)(torch.from_numpy(x)).numpy()
    for fmt in MODEL_FORMATS:
        name = f"policy-{job_id}{SUFFIXES[fmt]}"
        path = download(api, f"/api/v1/jobs/{job_id}/model?format={fmt}", tmp_path, name)
        assert np.abs(outputs(path, fmt, x) - expected).max() < TOLERANCE, fmt
        assert np.abs(outputs(path, fmt, x[:1]) - expected[:1]).max() < TOLERANCE, fmt
    extra = {"bgrl_meta.json": ""}
    torch.export.load(str(written["pt2"]), extra_files=extra)
    assert json.loads(extra["bgrl_meta.json"]) == meta
    onnx_meta = ort.InferenceSession(str(written["onnx"])).get_modelmeta()
    assert json.loads(onnx_meta.custom_metadata_map["bgrl_meta.json"]) == meta


def test_pi_hf_in_every_format_the_onnx_one_included(api: Api, tmp_path: Path) -> None:
    torch.manual_seed(1)
    model = FeedbackModel(normalizer()).eval()
    files = policy_files(model, {"kind": "hf_policy", "labels": 0})
    ids = {fmt: store(api, data, f"hf{SUFFIXES[fmt]}") for fmt, data in files.items()}
    hf_model_id = add_row(
        api,
        HFModel(
            name="pi_HF",
            task="sssg",
            torchscript_artifact_id=ids["torchscript"],
            pt2_artifact_id=ids["pt2"],
            onnx_artifact_id=ids["onnx"],
        ),
    )
    listed = api.client.get(f"/api/v1/hf-models/{hf_model_id}", headers=api.as_("viewer")).json()
    assert listed["pt2_artifact_id"] == ids["pt2"] and listed["onnx_artifact_id"] == ids["onnx"]
    x = random_observations(2)
    with torch.no_grad():
        expected = HFPolicyExport(model)(torch.from_numpy(x)).numpy()
    for fmt in MODEL_FORMATS:
        url = f"/api/v1/hf-models/{hf_model_id}/download?format={fmt}"
        path = download(api, url, tmp_path, f"hf-model-{hf_model_id}{SUFFIXES[fmt]}")
        assert np.abs(outputs(path, fmt, x) - expected).max() < TOLERANCE, fmt
    # the greedy pi_HF from the ONNX file alone is the module's
    onnx_path = tmp_path / f"hf-model-{hf_model_id}.onnx"
    assert np.array_equal(outputs(onnx_path, "onnx", x).argmax(-1), expected.argmax(-1))


def classifier_files(clf: ErrPClassifier, directory: Path) -> dict[str, Path]:
    clf.save(directory)
    files = {"torchscript": directory / TORCHSCRIPT_FILE, "pt2": clf.export_pt2(directory)}
    if clf.exports_onnx:
        files["onnx"] = clf.export_onnx(directory)
    return files


@pytest.mark.parametrize("architecture", ["EEGNet", "XdawnRiemann"])
def test_eeg_decoder_in_every_format_it_has(api: Api, tmp_path: Path, architecture: str) -> None:
    training = patterned_epochs(["FCz", "Cz"], n=80, seed=3)
    params, ch_names = training.params, training.ch_names
    torch.manual_seed(2)
    if architecture == "EEGNet":
        decoder = EEGNet(len(ch_names), 2, params.n_times_epoch)
    else:  # fitted: an unfitted one has no covariance reference to project on
        decoder = fit_xdawn_riemann(training.X * 1e5, training.y, seed=0).model
    clf = ErrPClassifier(decoder, params, ch_names, 2048.0, input_scale=1e5)
    rng = np.random.default_rng(4)  # random epochs, as large as the training ones
    epochs = rng.normal(0.0, training.X.std(), size=(16, *training.X.shape[1:]))
    epochs = epochs.astype(np.float32)
    files = classifier_files(clf, tmp_path / "written")
    ids = {fmt: store(api, path.read_bytes(), path.name) for fmt, path in files.items()}
    classifier_id = add_row(
        api,
        Classifier(
            name=architecture,
            torchscript_artifact_id=ids["torchscript"],
            pt2_artifact_id=ids["pt2"],
            onnx_artifact_id=ids.get("onnx"),
        ),
    )
    expected = clf.predict_proba(epochs)
    for fmt in files:
        url = f"/api/v1/classifiers/{classifier_id}/download?format={fmt}"
        path = download(api, url, tmp_path, f"classifier-{classifier_id}{SUFFIXES[fmt]}")
        assert np.abs(outputs(path, fmt, epochs) - expected).max() < TOLERANCE, fmt
    if architecture == "XdawnRiemann":  # no ONNX form: a 404 naming the format
        missing = api.client.get(
            f"/api/v1/classifiers/{classifier_id}/download?format=onnx", headers=api.as_("viewer")
        )
        assert missing.status_code == 404
        assert missing.json() == {
            "detail": f"classifier {classifier_id} has no onnx file",
            "field": "format",
        }
    assert {PT2_FILE, TORCHSCRIPT_FILE} <= {p.name for p in files.values()}
    assert ONNX_FILE in {p.name for p in files.values()} or architecture == "XdawnRiemann"


def test_an_unknown_format_is_a_422_and_a_missing_one_a_404(api: Api) -> None:
    data = b"a TorchScript policy"
    job_id = add_row(
        api, Job(kind="guided_ppo", status="succeeded", model_artifact_id=store(api, data, "p.pt"))
    )
    viewer = api.as_("viewer")
    unknown = api.client.get(f"/api/v1/jobs/{job_id}/model?format=savedmodel", headers=viewer)
    assert unknown.status_code == 422 and unknown.json()["detail"][0]["field"] == "format"
    missing = api.client.get(f"/api/v1/jobs/{job_id}/model?format=onnx", headers=viewer)
    assert missing.status_code == 404
    assert missing.json() == {"detail": f"job {job_id} has no onnx file", "field": "format"}
    assert api.client.get(f"/api/v1/jobs/{job_id}/model", headers=viewer).content == data
