"""The client's typed objects mirror the api's ``*Public`` schemas field for field.

The client keeps its own models (it ignores unknown fields, so a newer server does not break
an older script, and it does not import the api's server-side packages); this test is what
keeps the two copies from drifting: a field added to, removed from or retyped in one of them
fails here until the other follows.
"""

from __future__ import annotations

from typing import Any

import pytest
from pydantic import BaseModel

from services.api.schemas import (
    artifacts,
    auth,
    classifiers,
    hf_models,
    jobs,
    sessions,
    subjects,
    users,
)
from services.client import schemas as client

MIRRORS: list[tuple[type[BaseModel], type[BaseModel]]] = [
    (client.AccessToken, auth.AccessToken),
    (client.User, users.UserPublic),
    (client.ApiToken, auth.ApiTokenCreated),
    (client.Subject, subjects.SubjectPublic),
    (client.LabSession, sessions.SessionPublic),
    (client.Job, jobs.JobPublic),
    (client.JobLog, jobs.JobLogPublic),
    (client.JobLogEntry, jobs.JobLogEntry),
    (client.Curve, jobs.CurvePublic),
    (client.Artifact, artifacts.ArtifactPublic),
    (client.HFModel, hf_models.HFModelPublic),
    (client.Classifier, classifiers.ClassifierPublic),
]

WIDER_ON_THE_CLIENT: dict[tuple[str, str], str] = {
    ("AccessToken", "token_type"): "a plain str, so a server with another token type still parses",
    ("ApiToken", "token"): "optional: the client reads listed tokens (no secret) with it too",
    ("JobLog", "items"): "a list of the client's own JobLogEntry (mirrored above)",
}
"""Fields whose client type differs on purpose, and why."""


def _fields(model: type[BaseModel]) -> dict[str, Any]:
    """Every field a model's JSON carries, computed fields included, with its type."""
    found: dict[str, Any] = {name: f.annotation for name, f in model.model_fields.items()}
    found.update({name: f.return_type for name, f in model.model_computed_fields.items()})
    return found


@pytest.mark.parametrize(("client_model", "api_model"), MIRRORS, ids=lambda m: m.__name__)
def test_the_client_model_has_every_field_of_the_api_model_with_its_type(
    client_model: type[BaseModel], api_model: type[BaseModel]
) -> None:
    client_fields, api_fields = _fields(client_model), _fields(api_model)
    assert set(client_fields) == set(api_fields), (
        f"{client_model.__name__} lacks {sorted(set(api_fields) - set(client_fields))}, "
        f"has extra {sorted(set(client_fields) - set(api_fields))}"
    )
    retyped = {
        name: (client_fields[name], api_fields[name])
        for name in api_fields
        if client_fields[name] != api_fields[name]
        and (client_model.__name__, name) not in WIDER_ON_THE_CLIENT
    }
    assert not retyped, f"{client_model.__name__}: client vs api types differ: {retyped}"


def test_every_public_schema_of_the_api_has_its_mirror_or_is_not_for_clients() -> None:
    """A new ``*Public`` schema gets a client object (or a reason here why the client has none)."""
    from services.api.schemas import audit, recordings, rigs

    not_mirrored = {
        audit.AuditEntryPublic: "the Python client has no audit-log method (REST, dashboard)",
        recordings.RecordingPublic: "the Python client has no recordings method (REST, bgrl)",
        rigs.RigPublic: "the Python client has no rigs method (REST, dashboard)",
        jobs.JobKindPublic: "job kinds come from the job contract the client imports",
        auth.ApiTokenPublic: "its fields are ApiTokenCreated's without the secret",
    }
    mirrored = {api_model for _, api_model in MIRRORS}
    public = {
        model
        for module in (
            artifacts,
            audit,
            auth,
            classifiers,
            hf_models,
            jobs,
            recordings,
            rigs,
            sessions,
            subjects,
            users,
        )
        for name, model in vars(module).items()
        if name.endswith("Public") and isinstance(model, type) and issubclass(model, BaseModel)
    } | set(not_mirrored)
    assert public - mirrored - set(not_mirrored) == set()
