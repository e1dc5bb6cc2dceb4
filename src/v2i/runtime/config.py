"""Configuration and data files: frozen pydantic models loaded from YAML.

One path for service configs (YAML plus CLI overrides) and for bundled data such as
scenarios and link profiles (a bundled name or a file path); every error names the
file and the bad field.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from v2i.core.files import FileRefused, MiB, read_text

M = TypeVar("M", bound=BaseModel)

# A service's config file: a few kB of fields; 1 MiB leaves room and bounds what a wrong path
# (``/dev/zero``, a FIFO, a log file) can cost before it is refused.
CONFIG_LIMIT_BYTES = 1 * MiB


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
    await_start: bool = Field(False, description="after the ready line, wait for the start line on stdin "
                              "(v2i.runtime.process.read_start_line) for time zero; not with start_at_ns")
    duration_s: float | None = Field(None, gt=0, description="default: the scenario's duration")

    @model_validator(mode="after")
    def _one_time_zero(self):
        if self.await_start and self.start_at_ns is not None:
            raise ValueError("start_at_ns and await_start exclude each other: time zero comes from one of them")
        return self


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping key given twice in one YAML mapping; ``problem_mark`` is the second one."""


class _UniqueKeys:
    """Constructor mixin that rejects a mapping key given twice, at any depth.

    Plain PyYAML keeps the last of two equal keys, so a second ``rsu:`` silently replaces the
    first. Merge keys (``<<: *anchor``) still override as YAML specifies.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first: dict[Any, yaml.Node] = {}  # key -> the node of its first occurrence
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                earlier = first.setdefault(key, key_node)
            except TypeError:
                continue  # an unhashable key: the base constructor rejects it with its own message
            if earlier is not key_node:
                raise DuplicateKeyError(
                    None, None, f"duplicate key {key!r} (first at line {earlier.start_mark.line + 1})",
                    key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


class UniqueKeyLoader(_UniqueKeys, yaml.SafeLoader):
    """``yaml.SafeLoader`` (pure Python) that rejects a mapping key given twice, at any depth."""


# The same over libyaml's parser (~5-8x faster on a scenario); PyYAML built without libyaml
# has no CSafeLoader, and then the pure-Python loader does the work.
FastUniqueKeyLoader: type = (
    type("FastUniqueKeyLoader", (_UniqueKeys, yaml.CSafeLoader), {}) if hasattr(yaml, "CSafeLoader")
    else UniqueKeyLoader)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _yaml_problem(file: str, exc: yaml.YAMLError) -> str:
    """``file:line: problem`` of a PyYAML error (lines 1-based; context, if any, in brackets)."""
    if not isinstance(exc, yaml.MarkedYAMLError) or exc.problem_mark is None:
        return f"{file}: invalid YAML: {_one_line(exc)}"
    mark = exc.problem_mark
    if isinstance(exc, DuplicateKeyError):
        return f"{file}:{mark.line + 1}: {exc.problem}"
    context = ""
    if exc.context:
        where = f" at line {exc.context_mark.line + 1}" if exc.context_mark is not None else ""
        context = f" ({_one_line(exc.context)}{where})"
    return f"{file}:{mark.line + 1}:{mark.column + 1}: invalid YAML: {_one_line(exc.problem)}{context}"


def parse_yaml(text: str, file: str, error: type[ConfigError] = ConfigError) -> Any:
    """YAML ``text`` read from ``file`` as Python data; ``error("file:line: problem")`` when it is
    malformed or repeats a key (``UniqueKeyLoader``).

    libyaml parses; text it refuses is parsed again by the pure-Python loader, so that errors
    (and anything only the pure-Python parser accepts) are exactly the pure-Python loader's.
    """
    try:
        return yaml.load(text, Loader=FastUniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError:
        pass
    try:
        return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as exc:
        raise error(_yaml_problem(file, exc)) from None


_PARSED_MAX = 64
_parsed: dict[str, Any] = {}  # YAML text -> its data (models are validated from it, never mutate it)


def _parse_cached(text: str, file: str, error: type[ConfigError]) -> Any:
    """``parse_yaml(text, file, error)``, parsed once per distinct text: an offline run loads its
    scenario several times (runner, each OBU's config) and a 30 KB scenario takes ~10-80 ms to
    parse. Keyed by the text itself, so an edited file is parsed again; errors are not cached."""
    data = _parsed.get(text)
    if data is None:
        data = parse_yaml(text, file, error)
        if len(_parsed) >= _PARSED_MAX:
            _parsed.clear()
        _parsed[text] = data
    return data


def read_yaml(path: str | Path, kind: str, error: type[ConfigError] = ConfigError, *, limit_bytes: int) -> Any:
    """The YAML file at ``path`` as Python data: a regular file of at most ``limit_bytes`` (each
    reader states its own); ``error`` naming ``kind``, the file and the line when it cannot be read
    or parsed."""
    return parse_yaml(_read(Path(path), kind, limit_bytes, error), str(path), error)


def _problem(e: dict, names: dict[str, str]) -> str:
    loc = [names.get(str(e["loc"][0]), e["loc"][0]), *e["loc"][1:]] if e["loc"] else []
    where = ".".join(str(p) for p in loc)
    message = str(e["ctx"]["error"]) if e["type"] == "value_error" and "error" in e.get("ctx", {}) else e["msg"]
    return _one_line(f"{where}: {message}" if where else message)


def validation_problems(exc: ValidationError, most: int = 3, names: dict[str, str] | None = None) -> str:
    """``field.path: message; ...`` of a pydantic error on one line: the first ``most`` problems,
    then a count; top-level field names replaced by ``names`` where it has them."""
    errors = exc.errors(include_url=False)
    more = f"; and {len(errors) - most} more" if len(errors) > most else ""
    return "; ".join(_problem(e, names or {}) for e in errors[:most]) + more


def one_line_error(exc: Exception, names: dict[str, str] | None = None) -> str:
    """A user-facing line for an error of bad input: pydantic errors as ``field: message``
    (top-level fields renamed by ``names``, e.g. to their CLI flags), OS errors as
    ``reason: file``, anything else as its message with line breaks folded."""
    if isinstance(exc, ValidationError):
        return validation_problems(exc, names=names)
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    return _one_line(exc)


def validate(model: type[M], data: Any, source: str, error: type[ConfigError] = ConfigError) -> M:
    """``data`` (a mapping) as ``model``; ``error`` naming ``source`` and the bad field otherwise."""
    if data is None:
        raise error(f"{source} is empty")
    if not isinstance(data, dict):
        raise error(f"{source} must be a mapping, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise error(f"invalid {source}: {validation_problems(exc)}") from None


def _read(path: Path, kind: str, limit_bytes: int, error: type[ConfigError]) -> str:
    """The text of the regular file ``path`` of at most ``limit_bytes`` (``v2i.core.files``);
    ``error`` naming ``kind`` and the file otherwise."""
    try:
        return read_text(path, limit_bytes, kind)
    except FileRefused as exc:
        raise error(str(exc)) from None


def load_config(model: type[M], path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> M:
    """YAML file (optional) updated by non-None ``overrides``, validated by ``model``."""
    data: dict[str, Any] = {}
    source = model.__name__
    if path is not None:
        loaded = read_yaml(path, "config", ConfigError, limit_bytes=CONFIG_LIMIT_BYTES)
        if loaded is not None and not isinstance(loaded, dict):
            raise ConfigError(f"config {path} must be a mapping, got {type(loaded).__name__}")
        data.update(loaded or {})
        source = f"{model.__name__} (config {path} and command line)"
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return validate(model, data, source)


def bundled_names(package: str, folder: str) -> list[str]:
    """Names of the ``*.yaml`` files shipped in ``package/folder``, sorted."""
    directory = resources.files(package) / folder
    return sorted(p.name.removesuffix(".yaml") for p in directory.iterdir() if p.name.endswith(".yaml"))


def load_bundled_or_file(
    model: type[M], name_or_path: str | Path, package: str, folder: str, kind: str, error: type[ConfigError], *,
    limit_bytes: int,
) -> M:
    """A bundled YAML by name (``package/folder/<name>.yaml``) or a YAML file by path, as ``model``;
    either a regular file of at most ``limit_bytes``.

    ``kind`` names the sort of file in messages ("scenario", "link profile"); an unknown
    name lists the bundled ones.
    """
    names = bundled_names(package, folder)
    if str(name_or_path) in names:
        source = f"bundled {kind} {str(name_or_path)!r}"
        path = Path(str(resources.files(package) / folder / f"{name_or_path}.yaml"))
        data = _parse_cached(_read(path, kind, limit_bytes, error), str(path), error)
    elif os.path.exists(name_or_path):  # a FIFO or a device too: refused by _read, by what it is
        source = f"{kind} {name_or_path}"
        data = _parse_cached(_read(Path(name_or_path), kind, limit_bytes, error), str(name_or_path), error)
    else:
        raise error(f"unknown {kind} {str(name_or_path)!r}: neither a bundled one ({', '.join(names)}) nor an existing file")
    return validate(model, data, source, error)
