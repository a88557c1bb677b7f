"""Service settings, read from ``VIEWLOC_*`` environment variables when the app is built."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Everything an operator can configure (all optional).

    Environment variables carry the ``VIEWLOC_`` prefix, e.g.
    ``VIEWLOC_DATA_DIR=/data``, ``VIEWLOC_API_KEYS=key1,key2``.
    """

    model_config = SettingsConfigDict(env_prefix="VIEWLOC_", extra="ignore")

    data_dir: Path = Field(default=Path("./var"), description="Root of the model store.")
    api_keys: str = Field(
        default="", description="Comma-separated API keys; empty = no authentication."
    )
    max_mesh_bytes: int = Field(default=64 * 1024 * 1024, gt=0, description="Largest mesh upload.")
    max_image_bytes: int = Field(default=32 * 1024 * 1024, gt=0, description="Largest image file.")
    max_image_pixels: int = Field(
        default=40_000_000, gt=0, description="Largest width*height of an image."
    )
    max_images: int = Field(default=500, gt=0, description="Most images in one from-images upload.")
    max_images_total_bytes: int = Field(
        default=512 * 1024 * 1024, gt=0, description="Largest from-images request body."
    )
    max_images_decoded_bytes: int = Field(
        default=1024 * 1024 * 1024, gt=0,
        description="Largest decoded size (all pixels, bytes) of one from-images upload; the "
        "images are stored decoded, so this bounds memory and disk per object.",
    )
    job_workers: int = Field(default=1, ge=1, description="Learning jobs executing at once.")
    job_backend: Literal["local", "redis"] = Field(
        default="local", description="Where learning jobs run."
    )
    redis_url: str = Field(default="redis://localhost:6379/0", description="Redis backend address.")
    job_stale_after_s: float = Field(
        default=30.0, gt=0, description="Heartbeat age after which a job runner counts as dead."
    )
    job_cancel_grace_s: float = Field(
        default=5.0, ge=0, description="Time a cancelled job gets before its process is killed."
    )
    model_cache_size: int = Field(default=16, ge=0, description="Learned models kept in memory.")
    prepare_models: bool = Field(
        default=True,
        description="Load and prepare ready models in the background (at start-up and when a "
        "job has learned one), up to model_cache_size, so that no localization waits for it.",
    )
    log_level: str = Field(default="INFO", description="Python logging level.")
    log_json: bool = Field(default=True, description="Structured JSON logs on stderr.")

    @property
    def api_key_list(self) -> list[str]:
        """The configured API keys (whitespace trimmed, empties dropped)."""
        return [k.strip() for k in self.api_keys.split(",") if k.strip()]
