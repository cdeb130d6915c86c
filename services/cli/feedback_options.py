"""Options of ``bgrl reproduce`` and ``bgrl hf-sweep`` that choose where labels come from.

``--feedback oracle`` (default) is the paper's simulated feedback, the noisy oracle at each
``--accuracies`` C. ``--feedback virtual_subject`` makes every label end to end: the virtual
subject of each run seed watches the action and its own calibrated decoder decodes the epoch
(``services.worker.e2e_feedback``); ``--decoder-accuracy`` lists the target held-out
accuracies of that decoder (the quality knob is found per subject and cached in
``OUT/virtual_subjects``), and ``--label-channel`` says whether Fhat reads the hard decisions
or the calibrated likelihood ratios.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from services.worker.e2e_feedback import VirtualSubjectFactory

FEEDBACK_CACHE = "virtual_subjects"
"""Subfolder of a study's output folder holding each virtual subject's quality search."""

FeedbackOption = Annotated[
    str,
    typer.Option(
        help="oracle: the noisy oracle at each --accuracies C (the paper's simulated "
        "feedback); virtual_subject: the virtual subject decoded end to end by its own "
        "calibrated decoder, at each --decoder-accuracy."
    ),
]
DecoderAccuracyOption = Annotated[
    str | None,
    typer.Option(
        help="virtual_subject: comma-separated target held-out accuracies of the subject's "
        "decoder (each found within 0.02 by the subject's quality, recorded beside it)."
    ),
]
LabelChannelOption = Annotated[
    str,
    typer.Option(
        help="hard: Fhat reads the thresholded labels (the paper); soft: the decoder's "
        "calibrated likelihood ratios (virtual_subject only)."
    ),
]
DecodersOption = Annotated[
    str,
    typer.Option(
        help="virtual_subject: comma-separated decoders the subject's calibration trains "
        "(eegnet,lda,xdawn_rg; the best on validation is kept). EEGNet costs ~1 min of CPU "
        "per calibration, and the quality search calibrates ~5 times per subject."
    ),
]


def feedback_settings(
    feedback: str,
    label_channel: str,
    decoder_accuracy: str | None,
    accuracies: list[float],
) -> list[float]:
    """The accuracies the specs are built with: C for the oracle, the decoder's targets for
    the virtual subject (``typer.BadParameter`` naming the option otherwise)."""
    from services.learner.specs import FEEDBACKS, check_feedback

    if feedback not in FEEDBACKS:
        raise typer.BadParameter(f"expected one of {FEEDBACKS}", param_hint="--feedback")
    try:
        check_feedback(True, feedback, label_channel)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--label-channel") from None
    if feedback == "oracle":
        if decoder_accuracy is not None:
            raise typer.BadParameter(
                "applies to --feedback virtual_subject only", param_hint="--decoder-accuracy"
            )
        return accuracies
    if decoder_accuracy is None:
        raise typer.BadParameter(
            "give the target accuracies of the subject's decoder, e.g. 0.6",
            param_hint="--decoder-accuracy",
        )
    targets = []
    for entry in [e.strip() for e in decoder_accuracy.split(",") if e.strip()]:
        try:
            target = float(entry)
        except ValueError:
            raise typer.BadParameter(
                f"{entry!r} is not a number", param_hint="--decoder-accuracy"
            ) from None
        if not 0.5 < target < 1.0:
            raise typer.BadParameter(
                f"{entry!r} is not in (0.5, 1)", param_hint="--decoder-accuracy"
            )
        targets.append(target)
    if not targets or len(set(targets)) < len(targets):
        raise typer.BadParameter("give each target once", param_hint="--decoder-accuracy")
    return targets


def feedback_factory(feedback: str, decoders: str, out: Path) -> VirtualSubjectFactory | None:
    """The factory of the virtual subject's feedback (None for the oracle's)."""
    if feedback != "virtual_subject":
        return None
    from services.eeg.decoding.training_config import TrainingConfig
    from services.worker.e2e_feedback import VirtualSubjectFactory

    names = tuple(d.strip() for d in decoders.split(",") if d.strip())
    try:
        TrainingConfig(decoders=names)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--decoders") from None
    return VirtualSubjectFactory(decoders=names, cache_dir=str(out / FEEDBACK_CACHE))
