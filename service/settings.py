"""The service's settings: every field from a ``NEUDF_*`` environment variable, nothing read at import.

``Settings`` extends the queue settings the workers share (data folder, database, broker, time limits)
with what only the API needs (upload limits, tokens, the embedded worker). ``get_settings()`` is the
cached dependency routes use; ``create_app(settings)`` overrides it, so tests never touch the process
environment.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import NoDecode, SettingsConfigDict

from worker.settings import QueueSettings


class Settings(QueueSettings):
    model_config = SettingsConfigDict(env_prefix="NEUDF_", extra="ignore")

    host: str = Field("127.0.0.1", description="Address `neudf serve` listens on.")
    port: int = Field(8000, ge=1, le=65535, description="Port `neudf serve` listens on.")
    max_upload_mb: float = Field(1024.0, gt=0, description="Largest accepted upload; larger ones get 413.")
    auth_tokens: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Comma-separated bearer tokens. Set: every /api/jobs call needs one, and sees only its own jobs.",
    )
    embedded_worker: bool = Field(False, description="Start a local Celery worker with the API (`neudf serve` sets it).")
    default_preset: str | None = Field(None, description="Training preset of a job that names none (default: the "
                                       "worker's device's, quick on a CPU, gpu on CUDA).")
    video_max_seconds: float = Field(1800.0, gt=0, description="Longest accepted video.")
    video_min_frames: int = Field(8, ge=1, description="Fewest decodable frames an accepted video must have.")
    video_max_pixels: int = Field(8192 * 8192, gt=0, description="Largest accepted frame (width x height).")
    secret_key: SecretStr | None = Field(None, description="Key that turns tokens into the owner keys stored with "
                                         "jobs; default a random key kept in DATA_DIR/secret.key.")
    auth_fail_limit: int = Field(10, ge=1, description="Bad tokens one client address may send per window; more get 429.")
    auth_fail_window_s: float = Field(60.0, gt=0, description="The window of auth_fail_limit.")
    max_unfinished_jobs: int = Field(10, ge=1, description="Queued or running jobs one token may have (everyone "
                                     "together without tokens); more get 429.")
    min_free_disk_mb: float = Field(1024.0, ge=0, description="Free disk the data folder must keep after an upload; "
                                    "less gets 507.")
    db_wait_s: float = Field(5.0, gt=0, description="How long an API write waits for the job store before 503.")

    @field_validator("auth_tokens", mode="before")
    @classmethod
    def _split_tokens(cls, value: object) -> object:
        if isinstance(value, str):
            return [t.strip() for t in value.split(",") if t.strip()]
        return value

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    @property
    def uploads_dir(self) -> Path:
        return self.root / "uploads"

    @property
    def auth_enabled(self) -> bool:
        return bool(self.auth_tokens)


@lru_cache
def get_settings() -> Settings:
    return Settings()
