"""Configuration and data files: frozen pydantic models loaded from YAML.

One path for service configs (YAML plus CLI overrides) and for bundled data such as
scenarios and link profiles (a bundled name or a file path); every error names the
file and the bad field.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

M = TypeVar("M", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration or data file that cannot be used; the message names the bad field."""


class ServiceConfig(BaseModel):
    """Fields every simulated service shares: where it connects and which run it belongs to.

    Services that must agree on the simulated world (RSU, OBU) share scenario, seed and
    start time; each subclass adds its own id, listen endpoints and settings.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    connect: list[str] = Field(default_factory=list)
    scenario: str = "red-light-runner"
    seed: int = Field(0, ge=0)
    start_at_ns: int | None = Field(None, description="scenario time zero (true clock); default: start-up time")
    duration_s: float | None = Field(None, gt=0, description="default: the scenario's duration")


def validation_problems(exc: ValidationError) -> str:
    """``field.path: message; ...`` of a pydantic error."""
    return "; ".join(f"{'.'.join(str(p) for p in e['loc']) or '<root>'}: {e['msg']}" for e in exc.errors())


def validate(model: type[M], data: Any, source: str, error: type[ConfigError] = ConfigError) -> M:
    """``data`` (a mapping) as ``model``; ``error`` naming ``source`` and the bad field otherwise."""
    if not isinstance(data, dict):
        raise error(f"{source} must be a mapping, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise error(f"invalid {source}: {validation_problems(exc)}") from None


def _parse_yaml(text: str, source: str, error: type[ConfigError]) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise error(f"{source} is not valid YAML: {exc}") from exc


def _read(path: Path, source: str, error: type[ConfigError]) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(f"cannot read {source}: {exc}") from exc


def load_config(model: type[M], path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> M:
    """YAML file (optional) updated by non-None ``overrides``, validated by ``model``."""
    data: dict[str, Any] = {}
    if path is not None:
        source = f"config {path}"
        loaded = _parse_yaml(_read(Path(path), source, ConfigError), source, ConfigError)
        if loaded is not None and not isinstance(loaded, dict):
            raise ConfigError(f"{source} must be a mapping, got {type(loaded).__name__}")
        data.update(loaded or {})
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return validate(model, data, model.__name__)


def bundled_names(package: str, folder: str) -> list[str]:
    """Names of the ``*.yaml`` files shipped in ``package/folder``, sorted."""
    directory = resources.files(package) / folder
    return sorted(p.name.removesuffix(".yaml") for p in directory.iterdir() if p.name.endswith(".yaml"))


def load_bundled_or_file(
    model: type[M], name_or_path: str | Path, package: str, folder: str, kind: str, error: type[ConfigError]
) -> M:
    """A bundled YAML by name (``package/folder/<name>.yaml``) or a YAML file by path, as ``model``.

    ``kind`` names the sort of file in messages ("scenario", "link profile"); an unknown
    name lists the bundled ones.
    """
    names = bundled_names(package, folder)
    if str(name_or_path) in names:
        source = f"bundled {kind} {str(name_or_path)!r}"
        text = (resources.files(package) / folder / f"{name_or_path}.yaml").read_text(encoding="utf-8")
    elif Path(name_or_path).is_file():
        source = f"{kind} {name_or_path}"
        text = _read(Path(name_or_path), source, error)
    else:
        raise error(f"unknown {kind} {str(name_or_path)!r}: neither a bundled one ({', '.join(names)}) nor an existing file")
    return validate(model, _parse_yaml(text, source, error), source, error)
