"""Configuration from the environment (DRIFTLAB_*), with an embedded SQLite default."""

from __future__ import annotations

from pathlib import Path

from platformdirs import user_data_dir
from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


def default_db_url() -> str:
    """Return the SQLite URL of the embedded default store under the user's data directory."""
    path = Path(user_data_dir("driftlab", appauthor=False)) / "driftlab.sqlite"
    return f"sqlite:///{path}"


class Settings(BaseSettings):
    """Settings read from DRIFTLAB_* environment variables."""

    model_config = SettingsConfigDict(env_prefix="DRIFTLAB_", extra="ignore")

    db_url: str = ""
    api_token: str = ""
    api_host: str = "127.0.0.1"
    api_port: int = 8765
    #: VISA backend of the instruments: "@py" (pyvisa-py, pure Python), "@sim" or "FILE.yaml@sim"
    #: (pyvisa-sim), "@ivi" (the vendor VISA pyvisa finds), or the path of a vendor VISA library
    visa_library: str = "@py"
    #: the largest request body the API accepts (413 beyond; a model document is tens of kilobytes)
    api_max_body_bytes: int = 8 << 20
    #: seconds a client of `driftlab serve` has for a request's head, then for its body (closed beyond)
    api_header_timeout_s: float = Field(default=10.0, gt=0.0, le=3600.0)
    api_body_timeout_s: float = Field(default=30.0, gt=0.0, le=3600.0)
    #: seconds an idle kept-alive connection stays open between requests
    api_keep_alive_s: int = Field(default=5, ge=1, le=3600)
    #: seconds before a failed job's first retry (the n-th retry waits n times it); see driftlab.jobs.policy
    job_retry_wait_s: float = 30.0
    #: when the PostgreSQL workers look for machines with campaigns newer than their model (cron; "" = never)
    refit_cron: str = "17 2 * * *"

    def resolved_db_url(self) -> str:
        """Return the configured database URL, or the embedded SQLite default."""
        return self.db_url or default_db_url()


def get_settings() -> Settings:
    """Return settings freshly read from the environment."""
    return Settings()
