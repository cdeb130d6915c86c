"""Where scripts find the api and their stored credentials (``BGRL_API_URL``, ``bgrl login``)."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.core.settings import ENV_PREFIX

DEFAULT_API_URL = "http://127.0.0.1:8000"


def _default_credentials_file() -> Path:
    return Path.home() / ".config" / "bgrl" / "credentials.json"


class ClientSettings(BaseSettings):
    """Client configuration from ``BGRL_`` environment variables."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore")

    api_url: str | None = Field(
        None,
        description="Base URL of the platform api (BGRL_API_URL); default: the URL saved by "
        f"`bgrl login`, else {DEFAULT_API_URL}.",
    )
    api_token: SecretStr | None = Field(
        None,
        description="API token to use instead of the saved credentials (BGRL_API_TOKEN), "
        "e.g. in CI.",
    )
    credentials_file: Path = Field(
        default_factory=_default_credentials_file,
        description="Where `bgrl login` keeps the API token (mode 600) "
        "(BGRL_CREDENTIALS_FILE; default ~/.config/bgrl/credentials.json).",
    )


@dataclass(frozen=True)
class Credentials:
    """What `bgrl login` saved: the api's URL, the account and its API token."""

    api_url: str
    email: str
    token: str
    token_id: int | None = None


class CredentialsError(ValueError):
    """The credentials file is missing or unreadable; the message says what to do."""


def save_credentials(path: Path, credentials: Credentials) -> None:
    """Write ``credentials`` to ``path`` readable by its owner only (mode 600), atomically."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    partial = path.with_name(f".{path.name}.{os.getpid()}.part")
    fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            json.dump(asdict(credentials), out, indent=2)
            out.write("\n")
        os.chmod(partial, 0o600)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def load_credentials(path: Path) -> Credentials:
    """The credentials saved at ``path``; :class:`CredentialsError` if there are none."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return Credentials(
            api_url=str(data["api_url"]),
            email=str(data["email"]),
            token=str(data["token"]),
            token_id=data.get("token_id"),
        )
    except FileNotFoundError:
        raise CredentialsError(f"not signed in ({path} does not exist): run `bgrl login`") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CredentialsError(
            f"cannot read {path} ({type(exc).__name__}): run `bgrl login` again"
        ) from None
