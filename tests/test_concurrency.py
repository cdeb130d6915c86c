"""Services under concurrent load in one process: 8 sim sessions created and stepped from 8
threads while an EEG calibration trains beside them.

Checks what used to break: stdout and stderr still reach their files afterwards (env
construction once redirected them with an unlocked ``dup2``), every session's results equal
the same seeds stepped one after the other, calibration leaves torch's thread count alone,
and the ~126 MB oracle lattice is built once (cold starts used to build one each).
"""

from __future__ import annotations

import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest
import torch

import services.sim.oracle as oracle_module
from services.eeg.decoding.calibration import TrainingConfig, calibrate
from services.eeg.virtual.subject import simulate_recording
from services.sim.app import create_app
from services.sim.settings import SimSettings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # starlette asks for httpx2; httpx works
    from fastapi.testclient import TestClient

N_SESSIONS = 8
N_STEPS = 30


def drive(client: TestClient, seed: int, start: threading.Barrier | None = None) -> list[Any]:
    """Open a VSSG session with ``seed``, take ``N_STEPS`` seeded random actions (resetting
    when an episode ends), close it; returns everything the service answered."""
    if start is not None:
        start.wait()
    created = client.post("/sessions", json={"seed": seed, "task": "vssg"})
    assert created.status_code == 201, created.text
    body = created.json()
    sid = body["id"]
    trace: list[Any] = [body["observation"], body["info"]["shortest_path_steps"]]
    actions = np.random.default_rng(seed).integers(3, size=N_STEPS).tolist()
    for action in actions:
        step = client.post(f"/sessions/{sid}/step", json={"action": action}).json()
        marker = step["marker"]
        trace.append((step["observation"], step["reward"], marker["step"], marker["correct"]))
        if step["terminated"] or step["truncated"]:
            reset = client.post(f"/sessions/{sid}/reset", json={}).json()
            trace.append(reset["observation"])
    trace.append(client.get(f"/sessions/{sid}/oracle").json())
    assert client.delete(f"/sessions/{sid}").status_code == 204
    return trace


@pytest.mark.slow
def test_sessions_and_calibration_run_concurrently(
    capfd: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    builds: list[str] = []
    real_build = oracle_module.build_cost_to_go

    def counting_build(nav_map):
        builds.append(nav_map.name)
        return real_build(nav_map)

    monkeypatch.setattr(oracle_module, "build_cost_to_go", counting_build)
    oracle_module.Oracle.clear_memory()  # every session starts cold, at the same moment
    torch_threads = torch.get_num_threads()
    labels = [i % 3 != 0 for i in range(40)]
    recording = simulate_recording(labels, quality=1.0, seed=0, sfreq=256.0)
    config = TrainingConfig(max_passes=3, patience=3)

    settings = SimSettings(lsl_markers=False, max_sessions=N_SESSIONS, log_level="WARNING")
    with TestClient(create_app(settings)) as client, ThreadPoolExecutor(N_SESSIONS + 1) as pool:
        start = threading.Barrier(N_SESSIONS)
        calibration = pool.submit(calibrate, recording, seed=0, config=config, report=False)
        concurrent = list(pool.map(lambda s: drive(client, s, start), range(N_SESSIONS)))
        result = calibration.result()
        sequential = [drive(client, seed) for seed in range(N_SESSIONS)]

    assert concurrent == sequential
    assert len({str(trace[0]) for trace in concurrent}) == N_SESSIONS  # VSSG starts differ
    assert builds == ["default"]  # one lattice for 8 cold starts (and none afterwards)
    assert torch.get_num_threads() == torch_threads
    assert result.metrics["passes_run"] == 3
    capfd.readouterr()
    os.write(1, b"stdout works\n")
    os.write(2, b"stderr works\n")
    assert capfd.readouterr() == ("stdout works\n", "stderr works\n")
