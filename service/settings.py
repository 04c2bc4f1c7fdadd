"""Service settings: every knob in one place, read from ``POSE_*`` environment variables.

Tests and the CLI pass a ``Settings(...)`` directly; a deployment sets environment variables
(``POSE_CACHE_DIR=/data/cache``, ``POSE_TEMPLATE_GRID='{"tilt_step_deg": 15}'``, ...).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

MB = 1024 * 1024
LOG_LEVELS = ("critical", "error", "warning", "info", "debug")
# No deadline unless one is asked for: the same frame then gets the same answer whatever the machine's
# load or the process's past; a cell that needs an answer by a time sets POSE_DEADLINE_MS or the option.
DEFAULT_DEADLINE_MS = 0.0


class Settings(BaseSettings):
    # env_ignore_empty: POSE_X= (what compose's ${POSE_X:-} gives when unset) means the default
    model_config = SettingsConfigDict(env_prefix="POSE_", extra="ignore", env_ignore_empty=True)

    cache_dir: Path = Field(Path("templates_cache"), description="template cache directory (diskcache)")
    store: str | None = Field(
        None, description="where models, banks and build status live: unset = diskcache in cache_dir; "
        "redis://host:6379/0 = a Redis shared by API replicas and `python -m service worker` processes")
    bank_cache_mb: float = Field(
        256, gt=0, description="template banks each process keeps loaded (least recently used dropped), MB")
    max_mesh_bytes: int = Field(100 * MB, gt=0, description="largest accepted mesh upload, bytes")
    max_image_bytes: int = Field(50 * MB, gt=0, description="largest accepted image upload, bytes")
    max_image_pixels: int = Field(50_000_000, gt=0, description="largest accepted image, width * height")
    build_workers: int = Field(1, ge=1, description="template-build processes per service process")
    build_memory_mb: int = Field(
        4096, ge=256, description="address-space cap of one template-build process, MiB; a build that needs "
        "more fails with a sentence instead of taking the host")
    build_lease_s: float = Field(
        30.0, gt=0, description="a build's (or a calibration's) lock expires this long after its process "
        "stops renewing it (a crashed build is taken over by another process after at most this long)")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    workers: int = Field(1, ge=1, description="uvicorn worker processes (they share the cache dir)")
    threads: int | None = Field(
        None, ge=1, description="per process: threads of numba's parallel kernels, and background threads "
        "(refinement, view renders); unset: all cores. Budget: workers x threads ~ cores "
        "(service.vision.threads)")
    log_level: str = Field("info", description="critical, error, warning, info or debug (JSON lines, stdout)")
    api_key: SecretStr | None = Field(
        None, description="when set, every route but /health and /metrics requires this value in the "
        "X-API-Key header; unset or empty: no authentication")
    deadline_ms: float = Field(
        DEFAULT_DEADLINE_MS, ge=0, description="an estimate's time budget when its options give none, ms "
        "(the search is anytime: it answers with the best verified result by then, and always checks its "
        "best proposal first); 0 (the default): no deadline, the search runs to its end")
    warm_up: bool = Field(
        True, description="at start-up, run the pipeline once on a synthetic scene in the background so "
        "the first real estimate does not pay ~0.5 s of kernel loading")
    plane_calibration_scenes: int = Field(
        12, ge=0, description="rendered scenes each ready part is calibrated on, in the background, for "
        "parts on a plane (its visible edges' agreement; about a minute a part on 2 cores); 0: none, parts "
        "on a plane are judged on shading and region alone")
    template_grid: dict[str, Any] = Field(
        default_factory=dict,
        description="template-grid defaults (keys of service.vision.model.grid.GRID_DEFAULTS); an upload's "
        "`templates` JSON overrides them key by key")

    @field_validator("store", mode="before")
    @classmethod
    def _store_url(cls, v: Any) -> Any:
        if v is None or (isinstance(v, str) and not v.strip()):
            return None
        if not str(v).startswith(("redis://", "rediss://", "unix://")):
            raise ValueError(f"store must be a redis://, rediss:// or unix:// URL (or unset for the "
                             f"diskcache in cache_dir), not {v!r}")
        return str(v).strip()

    @property
    def store_location(self) -> str:
        """What ``open_store(...)`` opens: the Redis URL, else the cache directory."""
        return self.store or str(self.cache_dir)

    @property
    def shared_store(self) -> bool:
        return self.store is not None

    @field_validator("api_key", mode="before")
    @classmethod
    def _empty_key_means_none(cls, v: Any) -> Any:
        # compose passes ${POSE_API_KEY:-} as an empty string when the operator sets no key
        return None if v is None or (isinstance(v, str) and not v.strip()) else v

    @field_validator("log_level")
    @classmethod
    def _known_level(cls, v: str) -> str:
        level = v.strip().lower()
        if level not in LOG_LEVELS:
            raise ValueError(f"log_level must be one of {', '.join(LOG_LEVELS)}, not {v!r}")
        return level
