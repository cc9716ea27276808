"""``FACECAST_*`` settings that code outside a running server reads too (``facecast render``, tests).

``LocalSettings`` holds them; ``api.config.ServerConfig`` extends it with the server's own, so every
setting is one typed field with its default in one place (the README's table lists them all).
``settings()`` is what the library reads (parsed again only when the environment changed), and
``load(cls)`` turns a malformed variable into one ``InputError`` line that names it.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

from pydantic import Field, ValidationError, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from .errors import InputError

#: Longest audio file accepted by default, seconds.
MAX_AUDIO_SECONDS = 3600.0


def default_cache() -> Path:
    """``~/.cache/facecast``."""
    return Path.home() / ".cache" / "facecast"


class LocalSettings(BaseSettings):
    """Settings of the library itself, from ``FACECAST_<FIELD>`` variables; an empty one means unset."""

    model_config = SettingsConfigDict(env_prefix="FACECAST_", extra="ignore")

    cache: Path = Field(
        default_factory=default_cache
    )  # built faces, operators, annotations, kernels
    shared_data: Path | None = None  # the shared data folder (tests, benches); else ../shared/data
    max_audio_seconds: float = Field(default=MAX_AUDIO_SECONDS, gt=0, allow_inf_nan=False)

    @field_validator("cache", "shared_data", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: Any, info: ValidationInfo) -> Any:
        if value == "":
            return default_cache() if info.field_name == "cache" else None
        return value


S = TypeVar("S", bound=BaseSettings)


def load(cls: type[S], **overrides: Any) -> S:
    """``cls`` from the environment and ``overrides``; a malformed variable raises one ``InputError``:
    ``environment: FACECAST_X='value': what is wrong; fix or unset the variable``."""
    try:
        return cls(**overrides)
    except ValidationError as e:
        problems = "; ".join(
            f"FACECAST_{'_'.join(map(str, err['loc'])).upper()}={err.get('input')!r}: {err['msg']}"
            for err in e.errors()
        )
        raise InputError(f"{problems}; fix or unset the variable", where="environment") from None


def settings() -> LocalSettings:
    """The library's settings from the current environment (raises ``InputError`` when malformed)."""
    return _parsed(
        tuple(sorted((k, v) for k, v in os.environ.items() if k.startswith("FACECAST_")))
    )


@lru_cache(maxsize=8)
def _parsed(environment: tuple[tuple[str, str], ...]) -> LocalSettings:
    """``LocalSettings`` for one state of the ``FACECAST_*`` variables (the cache key)."""
    return load(LocalSettings)
