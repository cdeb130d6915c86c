"""What a job kind is: its name, its config model and how a job of it is summarised."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from pydantic import ConfigDict, ValidationError

from services.core.schemas import StrictRequest


class JobConfig(StrictRequest):
    """The config of a job kind: unknown fields, non-finite numbers and values of another
    JSON type (``"256"`` or ``true`` for an integer) are refused, by the api and the worker
    alike."""

    model_config = ConfigDict(strict=True)


def form_hints(
    *, shown_when: Mapping[str, list[Any]] | None = None, references: str | None = None
) -> dict[str, Any]:
    """Extension keywords of a config field's JSON Schema for the forms built from it (the
    dashboard's job form): ``x-shown-when`` (the field applies only while each named sibling
    field holds one of the values listed; ``None``: left empty) and ``x-references`` (the
    field is the id of an item of ``GET /api/v1/<references>``, offered as a choice)."""
    hints: dict[str, Any] = {}
    if shown_when is not None:
        hints["x-shown-when"] = {name: list(values) for name, values in shown_when.items()}
    if references is not None:
        hints["x-references"] = references
    return hints


Summary = Callable[[Mapping[str, Any]], str]
"""One line saying what a job runs, from its stored config."""


@dataclass(frozen=True)
class JobKind:
    """One kind of job: what the registry knows of it (its handler lives in the worker,
    registered there by :attr:`name`)."""

    name: str
    """The kind as stored on the job row and sent to the worker (``bgrl.jobs.<name>``)."""
    title: str
    """What the dashboard and the CLI call it."""
    config: type[JobConfig] | None
    """The model of a submitted config; None: jobs of this kind are created by the
    platform (a reproduction's runs, a lab session's live loop), not submitted."""
    summary: Summary
    """One line saying what a job of this kind runs."""
    counts_steps: bool = False
    """Its progress is environment steps (and it has a learning curve)."""

    @property
    def submittable(self) -> bool:
        """Whether a user may submit jobs of this kind."""
        return self.config is not None

    def parse(self, config: Mapping[str, Any]) -> JobConfig:
        """The config checked against the kind's model (a ValidationError naming the field)."""
        if self.config is None:
            raise ValueError(f"{self.name} jobs are created by the platform, not submitted")
        return self.config.model_validate(dict(config))


def config_error(exc: ValidationError) -> str:
    """A ValidationError as one line naming each field and the value refused
    (``ppo.gamma: Input should be less than or equal to 1, not 5``)."""
    return "; ".join(_field_error(err) for err in exc.errors())


def _field_error(err: Any) -> str:
    message = str(err["msg"]).removeprefix("Value error, ")
    if not err["loc"]:
        return message
    where = ".".join(str(part) for part in err["loc"])
    if err["type"] in ("extra_forbidden", "missing"):
        return f"{where}: {message}"
    return f"{where}: {message}, not {err['input']!r}"
