"""The one configuration loader: defaults < file < environment < command line.

A service's settings are one pydantic model, :class:`ServiceConfig` or a subclass that adds
the service's own typed section::

    class GeometrySection(ConfigSection):
        voxel_size_m: float = Field(0.02, gt=0)

    class GeometryConfig(ServiceConfig):
        geometry: GeometrySection = GeometrySection()

    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    cfg = config_from_args(parser.parse_args(), GeometryConfig)

Sources, later ones win (each leaf value separately; lists are replaced, not merged):

1. defaults in the model;
2. a file: ``--config FILE`` or ``OPENFUSION_CONFIG=FILE``; TOML (``.toml``), JSON (``.json``) or
   YAML (``.yaml``/``.yml``, only when PyYAML is installed). Top-level keys are field names,
   sections are tables: ``map_id = "lab"``, ``[zenoh] connect = ["tcp/10.0.0.2:7447"]``,
   ``[geometry] voxel_size_m = 0.02``. One file may serve several services: a *table* whose
   name is no field of this model (another service's section) is ignored; anything else
   unknown is an error;
3. environment: ``OPENFUSION_<FIELD>`` and ``OPENFUSION_<SECTION>__<FIELD>`` (double
   underscore between levels, case-insensitive), e.g. ``OPENFUSION_MAP_ID=lab``,
   ``OPENFUSION_ZENOH__CONNECT=tcp/10.0.0.2:7447,tcp/10.0.0.3:7447`` (list fields take a comma
   list or a JSON list), ``OPENFUSION_GEOMETRY__VOXEL_SIZE_M=0.05``. Variables whose first
   level is no field of the model are ignored (``OPENFUSION_VENV`` belongs to dev.sh); an
   empty value sets an optional field to None;
4. command line: the standard options (:func:`add_config_arguments`) and ``--set KEY=VALUE``
   with a dotted key (``--set geometry.voxel_size_m=0.05``), values parsed like environment ones.

Everything is validated in one place; a :class:`ConfigError` names the field, the value and
the source it came from (``zenoh.mode = 'bogus' (from environment OPENFUSION_ZENOH__MODE)``).

Zenoh discovery (:func:`zenoh_config`): mode, connect/listen endpoints and multicast scouting
are applied over Zenoh's defaults (or over ``--zenoh-config FILE``) only when set. Decision:
multicast scouting is left at Zenoh's default (ON for peers, so two services on a LAN find
each other with no configuration); the embedded run, deployments with a router and every test
pass ``--no-multicast`` with explicit loopback endpoints so that several runs on one machine
never discover each other.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from openfusion.errors import UserError
from openfusion.wire.keys import DEFAULT_PREFIX, KeySpace, validate_map_id, validate_prefix

logger = logging.getLogger(__name__)

ENV_PREFIX = "OPENFUSION_"
ENV_CONFIG_FILE = "OPENFUSION_CONFIG"
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
_ENDPOINT = re.compile(r"^[a-z][a-z0-9\-]*/\S+$")

C = TypeVar("C", bound="ServiceConfig")


class ConfigError(UserError, ValueError):
    """Invalid configuration; the message names field, value and source."""


class ConfigSection(BaseModel):
    """Base of a typed config section: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ZenohSettings(ConfigSection):
    """How the service joins the Zenoh network. None / empty = Zenoh's default (or the file's)."""

    config_file: Path | None = None
    mode: Literal["peer", "client", "router"] | None = None
    connect: list[str] = Field(default_factory=list)
    listen: list[str] = Field(default_factory=list)
    multicast_scouting: bool | None = None
    #: Zenoh shared memory between processes on one host (``transport/shared_memory/enabled``). None =
    #: Zenoh's default, which is on in 1.x: a message over 3 KB to a process on the same host goes
    #: through a shared-memory pool instead of the TCP link (measured in the README); across hosts
    #: Zenoh sends the bytes over the network anyway. False turns it off (debugging, a host whose
    #: /dev/shm is too small).
    shared_memory: bool | None = None

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, endpoints: list[str]) -> list[str]:
        for ep in endpoints:
            if not _ENDPOINT.match(ep):
                raise ValueError(f"endpoint {ep!r} is not of the form PROTOCOL/ADDRESS (e.g. tcp/127.0.0.1:7447)")
        return endpoints


class ServiceConfig(ConfigSection):
    """Settings every service and client shares. Subclass and add a typed section per service."""

    map_id: str = "default"
    prefix: str = DEFAULT_PREFIX
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    health_period_s: float = Field(default=1.0, gt=0, le=3600)
    log_level: str = "INFO"

    @field_validator("map_id")
    @classmethod
    def _map_id(cls, value: str) -> str:
        return validate_map_id(value)

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        return validate_prefix(value)

    @field_validator("log_level")
    @classmethod
    def _log_level(cls, value: str) -> str:
        level = value.upper()
        if level not in LOG_LEVELS:
            raise ValueError(f"log level {value!r} is not one of {', '.join(LOG_LEVELS)}")
        return level

    @property
    def keys(self) -> KeySpace:
        """The key space of this map."""
        return KeySpace(self.prefix, self.map_id)


# ------------------------------------------------------------------------------------ sources

Path_ = tuple[str, ...]


def one_of(value: str, known: Sequence[str], what: str) -> str:
    """``value`` when it is one of ``known``; else a ValueError naming ``what`` and the known values
    (a field validator's body: pydantic reports it with the field's path)."""
    if value not in known:
        raise ValueError(f"unknown {what} {value!r}; known: {', '.join(known)}")
    return value


def _unwrap_optional(annotation: Any) -> Any:
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return annotation


def _field_info(model: type[BaseModel], path: Path_) -> tuple[Any, bool] | None:
    """(annotation, accepts None) of the field at ``path``, or None when there is no such field."""
    current: Any = model
    for i, name in enumerate(path):
        if not (isinstance(current, type) and issubclass(current, BaseModel)) or name not in current.model_fields:
            return None
        annotation = current.model_fields[name].annotation
        if i == len(path) - 1:
            args = typing.get_args(annotation)
            return _unwrap_optional(annotation), type(None) in args
        current = _unwrap_optional(annotation)
    return None


def _is_list_type(annotation: Any) -> bool:
    return typing.get_origin(annotation) in (list, tuple, set) or annotation in (list, tuple, set)


def _parse_text_value(model: type[BaseModel], path: Path_, text: str) -> Any:
    """A string from the environment or ``--set`` as the value of the field at ``path``."""
    info = _field_info(model, path)
    annotation, optional = info if info is not None else (None, False)
    stripped = text.strip()
    if stripped == "" and optional:
        return None
    if stripped.startswith(("[", "{")):
        try:
            return json.loads(stripped)
        except json.JSONDecodeError:
            if annotation is not None and _is_list_type(annotation):
                raise ConfigError(f"{'.'.join(path)}: {text!r} is not a valid JSON list") from None
    if annotation is not None and _is_list_type(annotation):
        return [item.strip() for item in text.split(",") if item.strip()]
    return text


def _flatten(data: Mapping[str, Any], source: str, prefix: Path_ = ()) -> dict[Path_, tuple[Any, str]]:
    out: dict[Path_, tuple[Any, str]] = {}
    for key, value in data.items():
        path = (*prefix, str(key))
        if isinstance(value, Mapping) and value:
            out.update(_flatten(value, source, path))
        else:
            out[path] = (value, source)
    return out


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The mapping in a TOML / JSON / YAML file; ConfigError naming the file when unreadable."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"config file {path} is not UTF-8 text") from None
    suffix = path.suffix.lower()
    if suffix == ".toml":
        try:
            data: Any = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    elif suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"config file {path} is not valid JSON: {exc}") from None
    elif suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise ConfigError(f"config file {path} is YAML but PyYAML is not installed; use TOML or JSON") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    else:
        raise ConfigError(f"config file {path} must end in .toml, .json, .yaml or .yml")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must contain a table/object at the top, got {type(data).__name__}")
    return data


def _file_layer(model: type[BaseModel], path: Path) -> dict[Path_, tuple[Any, str]]:
    data = read_config_file(path)
    layer = {}
    for key, value in data.items():
        if key not in model.model_fields and isinstance(value, Mapping):
            logger.debug("config file %s: section [%s] is not used by %s", path, key, model.__name__)
            continue
        layer.update(_flatten({key: value}, f"file {path}"))
    return layer


def _env_layer(model: type[BaseModel], environ: Mapping[str, str]) -> dict[Path_, tuple[Any, str]]:
    layer = {}
    for name, text in environ.items():
        if not name.upper().startswith(ENV_PREFIX) or name.upper() == ENV_CONFIG_FILE:
            continue
        path = tuple(part.lower() for part in name[len(ENV_PREFIX) :].split("__"))
        if path[0] not in model.model_fields or any(p == "" for p in path):
            continue
        layer[path] = (_parse_text_value(model, path, text), f"environment {name}")
    return layer


def _overrides_layer(model: type[BaseModel], overrides: Sequence[str]) -> dict[Path_, tuple[Any, str]]:
    layer = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set zenoh.mode=client")
        path = tuple(key.split("."))
        layer[path] = (_parse_text_value(model, path, text), f"--set {key}")
    return layer


def _nest(flat: Mapping[Path_, tuple[Any, str]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for path, (value, _source) in flat.items():
        node = out
        for name in path[:-1]:
            child = node.get(name)
            if not isinstance(child, dict):
                child = node[name] = {}
            node = child
        node[path[-1]] = value
    return out


def _describe_errors(exc: ValidationError, flat: Mapping[Path_, tuple[Any, str]]) -> str:
    lines = []
    for err in exc.errors(include_url=False):
        loc = tuple(str(p) for p in err["loc"])
        source, value = "defaults", None
        for n in range(len(loc), 0, -1):
            if loc[:n] in flat:
                value, source = flat[loc[:n]]
                break
        where = ".".join(loc) or "<config>"
        shown = f" = {value!r}" if value is not None else ""
        msg = err["msg"].removeprefix("Value error, ")
        lines.append(f"{where}{shown} (from {source}): {msg}")
    return "invalid configuration: " + "; ".join(lines)


def _layers(
    model: type[BaseModel],
    *,
    config_file: str | Path | None,
    environ: Mapping[str, str] | None,
    cli: Mapping[str, Any] | None,
    overrides: Sequence[str],
) -> dict[Path_, tuple[Any, str]]:
    environ = os.environ if environ is None else environ
    if config_file is None and environ.get(ENV_CONFIG_FILE):
        config_file = environ[ENV_CONFIG_FILE]
    flat: dict[Path_, tuple[Any, str]] = {}
    if config_file is not None:
        flat.update(_file_layer(model, Path(config_file)))
    flat.update(_env_layer(model, environ))
    if cli:
        flat.update(_flatten(cli, "command line"))
    flat.update(_overrides_layer(model, overrides))
    return flat


def _validate(model: type[C], flat: Mapping[Path_, tuple[Any, str]]) -> C:
    try:
        return model.model_validate(_nest(flat))
    except ValidationError as exc:
        raise ConfigError(_describe_errors(exc, flat)) from None


def load_config(
    model: type[C] = ServiceConfig,  # type: ignore[assignment]
    *,
    config_file: str | Path | None = None,
    environ: Mapping[str, str] | None = None,
    cli: Mapping[str, Any] | None = None,
    overrides: Sequence[str] = (),
) -> C:
    """Merge defaults < ``config_file`` (or ``$OPENFUSION_CONFIG``) < ``environ`` (default
    ``os.environ``) < ``cli`` (nested mapping of explicitly given values) < ``overrides``
    (``KEY=VALUE`` strings) and validate. Raises :class:`ConfigError`."""
    flat = _layers(model, config_file=config_file, environ=environ, cli=cli, overrides=overrides)
    return _validate(model, flat)


def explain_config(
    model: type[C] = ServiceConfig,  # type: ignore[assignment]
    *,
    config_file: str | Path | None = None,
    environ: Mapping[str, str] | None = None,
    cli: Mapping[str, Any] | None = None,
    overrides: Sequence[str] = (),
) -> tuple[C, list[tuple[str, Any, str]]]:
    """The config :func:`load_config` gives, and for every leaf parameter ``(dotted name, effective
    value, where it came from)``: ``default``, ``file PATH``, ``environment NAME``, ``command line``
    or ``--set KEY`` (what ``openfusion config --show`` prints)."""
    flat = _layers(model, config_file=config_file, environ=environ, cli=cli, overrides=overrides)
    config = _validate(model, flat)
    rows: list[tuple[str, Any, str]] = []

    def walk(obj: BaseModel, prefix: Path_) -> None:
        for name in type(obj).model_fields:
            value = getattr(obj, name)
            path = (*prefix, name)
            if isinstance(value, BaseModel):
                walk(value, path)
                continue
            source = "default"
            for n in range(len(path), 0, -1):
                if path[:n] in flat:
                    source = flat[path[:n]][1]
                    break
            rows.append((".".join(path), value, source))

    walk(config, ())
    return config, rows


# ----------------------------------------------------------------------------- command line


def add_config_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the standard options (all default to "not given", so lower sources stay in effect)."""
    group = parser.add_argument_group("configuration (defaults < --config file < OPENFUSION_* env < options)")
    group.add_argument("--config", metavar="FILE", help="TOML/JSON/YAML config file (or $OPENFUSION_CONFIG)")
    group.add_argument("--map", dest="map_id", metavar="MAP_ID", help="map id (one key segment)")
    group.add_argument("--prefix", metavar="PREFIX", help=f"key prefix (default {DEFAULT_PREFIX})")
    group.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file to start from")
    group.add_argument("--mode", choices=["peer", "client", "router"], help="Zenoh mode (default peer)")
    group.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)"
    )
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)")
    group.add_argument(
        "--multicast",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="Zenoh multicast scouting (default: Zenoh's, on)",
    )
    group.add_argument("--log-level", metavar="LEVEL", help=f"one of {', '.join(LOG_LEVELS)}")
    group.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override any setting by dotted key, e.g. --set zenoh.mode=client (repeatable)",
    )
    return parser


def cli_values(args: argparse.Namespace) -> dict[str, Any]:
    """The explicitly given standard options of ``args`` as a nested mapping."""
    zenoh: dict[str, Any] = {}
    out: dict[str, Any] = {}
    for attr, key in (("map_id", "map_id"), ("prefix", "prefix"), ("log_level", "log_level")):
        if getattr(args, attr, None) is not None:
            out[key] = getattr(args, attr)
    for attr, key in (
        ("zenoh_config", "config_file"),
        ("mode", "mode"),
        ("connect", "connect"),
        ("listen", "listen"),
        ("multicast", "multicast_scouting"),
    ):
        if getattr(args, attr, None) is not None:
            zenoh[key] = getattr(args, attr)
    if zenoh:
        out["zenoh"] = zenoh
    return out


def option_flag(model: type[BaseModel], name: str) -> str:
    """The command-line flag of a section field: ``--voxel-size-m`` for ``voxel_size_m``, or the
    field's own ``json_schema_extra={"flag": ...}`` (``--semantic-every`` for ``every_k``)."""
    extra = model.model_fields[name].json_schema_extra
    flag = extra.get("flag") if isinstance(extra, dict) else None
    return str(flag) if flag else "--" + name.replace("_", "-")


def _option_help(info: Any) -> str:
    text = info.description or ""
    default = info.get_default(call_default_factory=True)
    shown = "none" if default is None else default
    return f"{text} (default {shown})" if text else f"default {shown}"


def _metavar(name: str, annotation: Any) -> str:
    for suffix in ("_m", "_s", "_hz", "_px"):
        if name.endswith(suffix):
            return suffix[1:].upper()
    return {int: "N", float: "X", Path: "PATH"}.get(annotation, "VALUE")


def add_section_options(
    parser: argparse.ArgumentParser,
    model: type[BaseModel],
    section: str,
    *,
    fields: Sequence[str] | None = None,
    title: str | None = None,
) -> None:
    """One flag per field of a config section (``section`` is its name in the config), typed and
    documented from the field itself; every flag defaults to "not given", so lower sources
    (file, environment) stay in effect. ``fields``: only these (in this order). The values come
    back with :func:`section_values`."""
    group = parser.add_argument_group(title or f"{section} (also [{section}] in a config file, "
                                      f"OPENFUSION_{section.upper()}__<NAME> in the environment)")
    names = list(fields) if fields is not None else list(model.model_fields)
    for name in names:
        info = model.model_fields[name]
        annotation = _unwrap_optional(info.annotation)
        kwargs: dict[str, Any] = {"dest": f"{section}__{name}", "default": None, "help": _option_help(info)}
        if annotation is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif typing.get_origin(annotation) is Literal:
            kwargs["choices"] = [str(v) for v in typing.get_args(annotation)]
        elif annotation in (int, float, Path):
            kwargs["type"] = annotation
            kwargs["metavar"] = _metavar(name, annotation)
        elif _is_list_type(annotation):
            kwargs["type"] = lambda text: [item.strip() for item in text.split(",") if item.strip()]
            kwargs["metavar"] = "A,B"
        else:
            kwargs["metavar"] = "TEXT"
        group.add_argument(option_flag(model, name), **kwargs)


def section_values(args: argparse.Namespace, section: str) -> dict[str, Any]:
    """The explicitly given flags of ``section`` (added by :func:`add_section_options`)."""
    head = f"{section}__"
    return {k[len(head):]: v for k, v in vars(args).items() if k.startswith(head) and v is not None}


def config_from_args(
    args: argparse.Namespace,
    model: type[C] = ServiceConfig,  # type: ignore[assignment]
    *,
    sections: Sequence[str] = (),
    environ: Mapping[str, str] | None = None,
) -> C:
    """The validated config of a parser built with :func:`add_config_arguments` (and
    :func:`add_section_options` for each of ``sections``)."""
    cli = cli_values(args)
    for section in sections:
        given = section_values(args, section)
        if given:
            cli.setdefault(section, {}).update(given)
    return load_config(
        model,
        config_file=getattr(args, "config", None),
        environ=environ,
        cli=cli,
        overrides=getattr(args, "overrides", None) or (),
    )


# ---------------------------------------------------------------------------------- zenoh


def zenoh_config(config: ServiceConfig) -> Any:
    """The ``zenoh.Config`` of ``config``: the Zenoh file (if any), then mode, endpoints and
    multicast scouting where set. Raises ConfigError naming the file or the setting Zenoh refused."""
    import zenoh

    settings = config.zenoh
    if settings.config_file is not None:
        try:
            conf = zenoh.Config.from_file(str(settings.config_file))
        except zenoh.ZError as exc:
            raise ConfigError(f"zenoh config file {settings.config_file}: {exc}") from None
    else:
        conf = zenoh.Config()
    items = []
    if settings.mode is not None:
        items.append(("mode", settings.mode))
    if settings.connect:
        items.append(("connect/endpoints", settings.connect))
    if settings.listen:
        items.append(("listen/endpoints", settings.listen))
    if settings.multicast_scouting is not None:
        items.append(("scouting/multicast/enabled", settings.multicast_scouting))
    if settings.shared_memory is not None:
        items.append(("transport/shared_memory/enabled", settings.shared_memory))
    for key, value in items:
        try:
            conf.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:
            raise ConfigError(f"zenoh setting {key} = {value!r} refused: {exc}") from None
    return conf


def setup_logging(level: str = "INFO") -> None:
    """Log to stderr with time, level and logger name (idempotent)."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger().setLevel(getattr(logging, level.upper(), logging.INFO))
