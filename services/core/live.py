"""Options of a live session (issue 10) and the latency figures computed from its rows.

Shared by the api (which validates ``POST /api/v1/sessions/{id}/start``) and the worker's
``live_session`` runner (which reads the same options from its job config), so both accept
exactly the same fields.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

from pydantic import Field, model_validator

from services.core.feedback import LabelChannel
from services.core.hf_methods import HFMethodName
from services.core.schemas import StrictRequest

DEFAULT_ACTIONS = {"calibration": 600, "test": 200}
"""Actions of a calibration (the paper's ~600) and of a test session when not given."""
ONLINE_ACTIONS_PER_LABEL = 3
"""An online session stops after this many actions per label of its budget at the latest
(rejected epochs give no label)."""


def soft_channel_refusal(classifier_metrics: Mapping[str, Any] | None) -> str | None:
    """Why a platform classifier (by its ``metrics``) cannot feed the soft channel, or None
    if its calibrated posterior can (every ``eeg_calibration`` since 2026-12-03 fits one).

    A Platt slope <= 0 means the calibration's validation epochs found the decoder's score
    running against the truth or carrying nothing: its likelihood ratios would point away
    from the truth. At decoder accuracy 0.6 a fit on ~70 validation epochs came out so for 2
    of 5 virtual subjects (docs/stage2.md, "N*(C) per label channel"); the hard decisions of
    such a decoder still carry its held-out accuracy.
    """
    calibration = (classifier_metrics or {}).get("calibration")
    if not calibration:
        return "has no calibrated posterior"
    fit = calibration if isinstance(calibration, Mapping) else {}
    slope = fit.get("slope")
    if isinstance(slope, bool) or not isinstance(slope, int | float) or not slope > 0:
        return (
            f"has a calibrated posterior whose Platt slope is {slope} (fitted on "
            f"{fit.get('n_fit', '?')} validation epochs), so its soft labels would not point "
            "toward the truth"
        )
    return None


def has_calibrated_posterior(classifier_metrics: Mapping[str, Any] | None) -> bool:
    """Whether a platform classifier's calibrated posterior can feed the soft channel
    (:func:`soft_channel_refusal` finds nothing against it)."""
    return soft_channel_refusal(classifier_metrics) is None


def default_label_channel(calibrated: bool) -> LabelChannel:
    """An online session's label channel when none is asked for: ``soft`` if its classifier
    has a usable calibrated posterior (the soft label carried 1.26-1.80x the hard label's
    bits in each of 20 virtual subjects decoded at 0.6, docs/stage2.md), else ``hard``."""
    return "soft" if calibrated else "hard"


class LiveOptions(StrictRequest):
    """How a lab session's live loop runs (the body of ``POST /sessions/{id}/start``)."""

    classifier_id: int | None = Field(
        None, ge=1, description="Platform classifier decoding live (required for test/online)."
    )
    n_actions: int | None = Field(
        None,
        ge=1,
        le=100_000,
        description="Actions to execute (calibration 600, test 200; online: until the budget).",
    )
    period_s: float = Field(1.5, ge=0.05, le=60.0, description="Seconds per action (paced).")
    accelerated: bool = Field(
        False,
        description="No wall-clock pacing: the virtual subject generates on a virtual clock "
        "advancing period_s per action (virtual EEG only).",
    )
    eeg_source: Literal["virtual", "lsl"] = Field(
        "virtual", description="virtual: the synthetic virtual subject; lsl: a headset stream."
    )
    virtual_quality: float = Field(0.7, ge=0.0, le=1.0, description="ErrP strength (virtual).")
    virtual_seed: int | None = Field(
        None, ge=0, le=2**31 - 1, description="Virtual subject's seed (default: the subject id)."
    )
    stream_name: str | None = Field(
        None, min_length=1, max_length=200, description="LSL EEG stream name (eeg_source lsl)."
    )
    label_budget: int = Field(1000, ge=1, le=100_000, description="Labels of an online session.")
    hf_method: HFMethodName | None = Field(
        None,
        description="Stage-2 method learning an online session's pi_HF (docs/stage2.md; "
        "default: the learner's recommended method). The run records the method used.",
    )
    label_channel: LabelChannel | None = Field(
        None,
        description="How an online session's labels enter Fhat: 'soft', the calibrated "
        "classifier's log-likelihood ratio (the default when the classifier has a calibrated "
        "posterior: more bits per label, docs/live.md); 'hard', the thresholded feedback (the "
        "paper; the default otherwise). The run records the channel used.",
    )
    task: Literal["sssg", "vssg"] = "sssg"
    map: str | None = Field(None, max_length=1024, description="Sim map (default map if None).")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seeds the sim, random policy, Fhat.")
    calibration_max_passes: int | None = Field(
        None, ge=1, le=10_000, description="Training passes of the eeg_calibration job."
    )

    @model_validator(mode="after")
    def _consistent(self) -> LiveOptions:
        if self.eeg_source == "lsl" and self.stream_name is None:
            raise ValueError("stream_name is required when eeg_source is lsl")
        if self.eeg_source == "lsl" and self.accelerated:
            raise ValueError("accelerated needs eeg_source virtual (a headset runs in real time)")
        return self


def percentile(values: Sequence[float], q: float) -> float | None:
    """The ``q``-th percentile (linear interpolation, as numpy's default); None if empty."""
    data = sorted(v for v in values if math.isfinite(v))
    if not data:
        return None
    rank = (len(data) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(data) - 1)
    return data[low] + (data[high] - data[low]) * (rank - low)


def latency_summary(samples: dict[str, list[float]]) -> dict[str, dict[str, float | int | None]]:
    """``{name: {n, p50_ms, p99_ms, max_ms}}`` of latencies given in seconds."""
    out: dict[str, dict[str, float | int | None]] = {}
    for name, values in samples.items():
        p50, p99 = percentile(values, 50), percentile(values, 99)
        out[name] = {
            "n": len(values),
            "p50_ms": None if p50 is None else round(p50 * 1000, 3),
            "p99_ms": None if p99 is None else round(p99 * 1000, 3),
            "max_ms": round(max(values) * 1000, 3) if values else None,
        }
    return out


def timeline_latencies(
    markers: dict[int, tuple[float, float]],
    decisions: dict[int, tuple[float | None, float]],
    versions: dict[int, tuple[float, float | None]],
    frames_minus_marker: list[float],
) -> dict[str, list[float]]:
    """Per-action latencies (s) of a live run from its rows, by step.

    ``markers``: step -> (marker_ts, executed wall time); ``decisions``: step ->
    (epoch_end_ts, decided_ts); ``versions``: step -> (updated_ts, next_ready_ts);
    ``frames_minus_marker``: frame shown minus action executed (wall clock) per action.
    """
    out: dict[str, list[float]] = {
        "marker_to_epoch_end": [],
        "epoch_end_to_decision": [],
        "decision_to_update": [],
        "update_to_next_action": [],
        "epoch_end_to_next_action": [],
        "marker_to_frame_shown": list(frames_minus_marker),
    }
    for step, (epoch_end, decided) in decisions.items():
        marker = markers.get(step)
        if epoch_end is not None:
            if marker is not None:
                out["marker_to_epoch_end"].append(epoch_end - marker[0])
            out["epoch_end_to_decision"].append(decided - epoch_end)
        version = versions.get(step)
        if version is None:
            continue
        updated, ready = version
        out["decision_to_update"].append(updated - decided)
        if ready is not None:
            out["update_to_next_action"].append(ready - updated)
            if epoch_end is not None:
                out["epoch_end_to_next_action"].append(ready - epoch_end)
    return out


def pace_drift(marker_ts: list[float], period_s: float) -> dict[str, float | None]:
    """How far a paced run's actions strayed from one every ``period_s``: interval error
    percentiles (ms) and the last action's offset from the schedule (ms)."""
    if len(marker_ts) < 2:
        return {"interval_error_p50_ms": None, "interval_error_p99_ms": None, "drift_ms": None}
    errors = [abs(b - a - period_s) for a, b in itertools.pairwise(marker_ts)]
    drift = marker_ts[-1] - (marker_ts[0] + (len(marker_ts) - 1) * period_s)
    p50, p99 = percentile(errors, 50), percentile(errors, 99)
    return {
        "interval_error_p50_ms": None if p50 is None else round(p50 * 1000, 3),
        "interval_error_p99_ms": None if p99 is None else round(p99 * 1000, 3),
        "drift_ms": round(drift * 1000, 3),
    }
