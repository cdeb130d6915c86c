"""Request and response bodies of the EEG service.

Request bodies subclass :class:`~services.core.schemas.StrictRequest` (an unknown field, a
``NaN``, ``Infinity`` or ``1e400`` is a 422 naming the field); ``*Public`` models are what
the service answers and stores.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import AllowInfNan, BaseModel, Field, model_validator

from services.core.schemas import StrictRequest

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
"""A job's status; the last three are final."""
ChannelName = Annotated[str, Field(min_length=1, max_length=64)]
Sample = Annotated[float, Field(strict=True), AllowInfNan(True)]
"""A sample value: a JSON number (``true`` or ``"1"`` are refused), NaN and infinities
accepted here and handled by the endpoint."""
FINAL_JOB_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})

HEX_ID = "^[0-9a-f]+$"


class RecordingPublic(BaseModel):
    """A stored, validated recording."""

    id: str = Field(description="The file's sha256 (hex).")
    filename: str = Field(description="Name the file was uploaded under (a label only).")
    format: Literal["bdf", "edf", "fif", "brainvision", "eeglab", "xdf"] = Field(
        description="Format detected from the file's content (not from its name); "
        "brainvision: a zip of the .vhdr, .vmrk and .eeg; eeglab: a .set, or a zip of the "
        ".set and its .fdt."
    )
    sha256: str
    size_bytes: int
    sfreq: float
    n_channels: int
    duration_s: float
    n_actions: int
    n_errors: int
    synthetic: bool
    uploaded_at: str
    notes: list[str] = Field(
        default_factory=list,
        description="Things to know, e.g. a file name whose suffix names another format.",
    )


class JobCreate(StrictRequest):
    """Start calibration training on a stored recording."""

    recording_id: str = Field(min_length=8, max_length=64, pattern=HEX_ID)
    seed: int = Field(
        0, strict=True, ge=0, le=2**31 - 1, description="Seeds the split and the training."
    )
    max_passes: int = Field(
        300,
        strict=True,
        ge=1,
        description="Most training passes over the training split (early stopping may end "
        "sooner); at most the service's BGRL_EEG_MAX_TRAINING_PASSES.",
    )


class JobPublic(BaseModel):
    """A calibration job and, once it succeeded, the classifier it produced."""

    id: str
    recording_id: str
    seed: int
    max_passes: int
    status: JobStatus
    cancel_requested: bool = Field(
        False, description="POST /jobs/{id}/cancel was called; a running job stops soon."
    )
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    classifier_id: str | None = None
    error: str | None = Field(None, description="Why the job failed, in one line.")
    traceback: str | None = Field(None, description="Traceback of the failure, if any.")
    metrics: dict[str, Any] | None = None

    @model_validator(mode="before")
    @classmethod
    def _read_older_records(cls, data: Any) -> Any:
        """Job records written before the rename (``state``/``done``, ``max_epochs``)."""
        if isinstance(data, dict) and "state" in data and "status" not in data:
            data = dict(data)
            state = data.pop("state")
            data["status"] = "succeeded" if state == "done" else state
            data.setdefault("max_passes", data.pop("max_epochs", 300))
        return data


class ClassifierPublic(BaseModel):
    """A trained ErrP classifier."""

    id: str
    recording_id: str | None
    synthetic: bool
    ch_names: list[str]
    sfreq_in: float
    epoch_shape: tuple[int, int]
    metrics: dict[str, Any]


class EpochClassify(StrictRequest):
    """One preprocessed epoch in volts, channels x times."""

    epoch: list[list[Sample]] = Field(
        description="Rows in ch_names order, in volts (not microvolts); NaN is refused."
    )
    ch_names: list[str] = Field(description="Channel of each row, in order.")
    sfreq: float = Field(gt=0, description="Sampling rate of the epoch (the features' rate).")


class Feedback(BaseModel):
    """Decoded feedback for one action (or why there is none)."""

    status: Literal["ok", "rejected"]
    p_error: float | None = None
    feedback: Literal["correct", "error"] | None = None
    log_likelihood_ratio: float | None = Field(
        None,
        description="log P(epoch | error) / P(epoch | correct) from the classifier's "
        "calibrated posterior: the soft label (null without a calibration, or when rejected).",
    )
    reason: str | None = None
    onset: float | None = None
    step: int | None = None
    session_id: str | None = None
    classifier_id: str | None = Field(
        description="Null when the live source has no classifier (recording only)."
    )
    synthetic: bool


class LiveConnect(StrictRequest):
    """Connect an LSL EEG stream for live decoding."""

    classifier_id: str | None = Field(
        None,
        min_length=1,
        max_length=64,
        description="Classifier decoding the markers; none: record only (calibration).",
    )
    stream_name: str = Field("BrainNav-EEG", min_length=1, max_length=200)
    marker_stream: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="Also classify every marker of this LSL marker stream (the sim's is "
        "BrainNav-Markers); otherwise markers come through POST /live/markers.",
    )
    channel_map: dict[ChannelName, ChannelName] | None = Field(
        None,
        max_length=512,
        description="The rig's {device channel name: standard 10-20/10-10 name} (or "
        "'Status' for the trigger channel); unlisted channels are read as standard names, "
        "case-insensitively. A mapped channel missing from the stream, or a cap without "
        "Fz, Cz and one of FCz/FC1/FC2, is refused with the reason.",
    )


class StreamIssuePublic(BaseModel):
    """A problem detected in the live stream (times on the stream clock, s)."""

    kind: str
    start: float
    end: float | None = Field(description="Null while a disconnect lasts.")
    detail: str


class LiveRecordingStart(StrictRequest):
    """Start recording the live stream and its markers."""

    name: str = Field(
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$",
        description="Name of the recording (its file is <name>.bdf); the name of an "
        "interrupted recording continues it.",
    )


class LiveRecordingPublic(BaseModel):
    """A live recording in progress."""

    name: str
    started_at: str
    resumed: bool = Field(description="It continues a recording interrupted by a crash.")
    n_channels: int
    sfreq: float
    n_samples: int = Field(description="Samples received (flushed to disk or buffered).")
    duration_s: float
    n_markers: int
    synthetic: bool
    error: str | None = Field(None, description="Why it stopped taking data, if it did.")


class LiveStatus(BaseModel):
    """The live source and what its integrity checks found."""

    connected: bool = Field(description="Data are arriving and no background task failed.")
    source: Literal["lsl", "websocket"] | None = None
    classifier_id: str | None = None
    stream_name: str | None = None
    marker_stream: str | None = None
    n_samples: int = 0
    latest_timestamp: float | None = None
    error: str | None = Field(
        None, description="Why the source stopped (a background task failed), if it did."
    )
    issues: list[StreamIssuePublic] = Field(
        default_factory=list, description="The last 100 issues, oldest first."
    )
    issues_dropped: int = Field(0, description="Older issues no longer listed.")
    recording: LiveRecordingPublic | None = Field(
        None, description="The live recording in progress, if any."
    )
    unfinished_recordings: list[str] = Field(
        default_factory=list,
        description="Recordings interrupted by a crash: DELETE /live/recording?name= "
        "finalises one, POST /live/recording with its name continues it.",
    )


class IngestHeader(StrictRequest):
    """First message of ``WS /live/ingest``: the stream's channels and rate."""

    ch_names: list[Annotated[str, Field(min_length=1, max_length=64)]] = Field(
        min_length=1, max_length=1024
    )
    sfreq: float = Field(gt=0, le=100_000)
    synthetic: bool = Field(
        False, description="The samples are generated (a virtual subject), not recorded."
    )


class IngestChunk(StrictRequest):
    """Every later message of ``WS /live/ingest``: consecutive samples of the stream."""

    first_timestamp: float = Field(description="LSL-clock time (s) of the first sample.")
    samples: list[list[Sample]] = Field(
        description="n_times x n_channels, volts; NaN marks bad samples (reported as issues)."
    )
