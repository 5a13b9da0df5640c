"""Experiment configs: YAML -> dotted overrides -> validated, frozen pydantic model.

A config file names its experiment at the top level (``experiment: valid_region``);
that name picks the experiment and so its pydantic model
(:func:`selfid_jax.runner.registry.load`; this module knows no experiment). Every model forbids unknown keys, checks
types strictly (``3`` is not a string, ``2.0`` is not an integer) and is frozen.
Any problem raises :class:`ConfigError` whose message names the file, the dotted
key, the problem, the offending value and what is allowed, before any compute.

Overrides use one syntax everywhere: ``a.b=value`` (CLI ``--set a.b=value``);
the value is parsed as a YAML scalar or flow list (``--set systems=[ur5e]``).

Config objects never reach traced code: an experiment turns one into static
values and numeric parameter arrays before ``jit`` (STYLE.md rule 6).
"""

from __future__ import annotations

import re
import reprlib
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import annotated_types
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo

from selfid_jax.runner.errors import ConfigError

__all__ = [
    "STRICT",
    "BaseConfig",
    "ConfigError",
    "apply_overrides",
    "dump_config",
    "flatten_dict",
    "load_config",
    "parse_override",
    "read_config",
    "stop_after_start",
    "unique",
    "validate",
    "yaml_load",
]


# --------------------------------------------------------------------------- YAML

class _Loader(yaml.SafeLoader):
    """SafeLoader that reads ``1e-3`` / ``1E6`` as floats (YAML 1.2), not strings, and refuses duplicate keys."""

    def construct_mapping(self, node: Any, deep: bool = False) -> dict[Any, Any]:
        """The mapping of ``node``; a key written twice in one mapping (any depth) is an error naming both lines."""
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *base' may be overridden key by key
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    line = first.get(key)
                except TypeError:  # an unhashable key: the base class reports it
                    continue
                first[key] = key_node.start_mark.line
                if line is not None:
                    raise yaml.constructor.ConstructorError(
                        None, None,
                        f"duplicate key {_summary(key)} (line {line + 1} and line {key_node.start_mark.line + 1}); "
                        "each key may appear once in a mapping",
                        key_node.start_mark,
                    )
        return super().construct_mapping(node, deep=deep)


_FLOAT_RE = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.X,
)
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_RE, list("-+0123456789."))


def yaml_load(text: str) -> Any:
    """Parse YAML text safely: exponent floats such as ``1e-3`` as floats; a duplicate key raises ``yaml.YAMLError``."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - _Loader is a SafeLoader


MAX_VALUES = 1_000_000
"""Most values (scalars, list items, mapping entries) a config may expand to; YAML aliases can multiply them."""

_REPR = reprlib.Repr()
_REPR.maxstring, _REPR.maxother, _REPR.maxlist, _REPR.maxdict, _REPR.maxlevel = 60, 60, 6, 6, 3


def _summary(value: Any, limit: int = 200) -> str:
    """A bounded ``repr`` of ``value`` for error messages (never a dump of a large or alias-expanded tree)."""
    text = _REPR.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def read_text_utf8(path: Path) -> str:
    """The file's text decoded as UTF-8; :class:`ConfigError` naming the file and the first bad byte otherwise."""
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{data[err.start]:02x} at offset {err.start}); "
                          "save the file as UTF-8") from None


# --------------------------------------------------------------------------- models

# Every float field is finite (allow_inf_nan=False): .inf/.nan are refused with the key's name.
STRICT = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class BaseConfig(BaseModel):
    """Fields every experiment config has."""

    model_config = STRICT

    experiment: str
    seed: int = Field(0, ge=0, le=2**32 - 1, description="PRNG seed (JAX keys hold 32 bits)")
    chunk_size: int = Field(256, gt=0, le=10**7, description="rollouts per compiled chunk")
    name: str | None = None

    def input_files(self) -> dict[str, str]:
        """Files the run reads, path -> SHA-256, for its fingerprint; none here (experiment configs add theirs)."""
        return {}


def stop_after_start(stop: float, info: ValidationInfo) -> float:
    """Field validator of a grid's ``stop``: ``ValueError`` unless it is greater than the ``start`` field."""
    start = info.data.get("start")
    if start is not None and not stop > start:
        raise ValueError(f"must be greater than start ({start})")
    return stop


def unique(values: list, what: str) -> list:
    """``values`` if no item repeats, else ``ValueError`` naming the repeated ones (for field validators)."""
    dup = sorted({str(v) for v in values if values.count(v) > 1})
    if dup:
        raise ValueError(f"{what} must be unique, repeated: {', '.join(dup)}")
    return values


# --------------------------------------------------------------------------- overrides

_INDEX = re.compile(r"\[(\d+)\]")


def parse_override(text: str) -> tuple[tuple[str, ...], Any]:
    """``"a.b=1e-3"`` -> ``(("a", "b"), 0.001)``; the value is parsed as YAML.

    List entries are reached by index, as ``systems.0.controller.steps`` or
    ``systems[0].controller.steps`` (both give ``("systems", "0", "controller", "steps")``).
    """
    key, sep, raw = text.partition("=")
    key = _INDEX.sub(r".\1", key.strip())
    parts = tuple(key.split("."))
    if not sep or not key or any(not p.strip() for p in parts):
        raise ValueError(f"--set {text!r}: expected KEY=VALUE with a dotted KEY, e.g. controller.tol=0.001 "
                         "or systems.0.controller.steps=300")
    try:
        value = yaml_load(raw) if raw.strip() else ""
    except yaml.YAMLError as err:
        raise ValueError(f"--set {text!r}: value is not valid YAML ({err})") from None
    return tuple(p.strip() for p in parts), value


def _child(node: Any, part: str, text: str, where: str, *, create: bool) -> Any:
    """The entry ``part`` of ``node`` (a mapping key or a list index), created as ``{}`` if missing and ``create``."""
    if isinstance(node, list):
        if not part.isdigit():
            raise ValueError(f"--set {text!r}: {where or 'the top level'} is a list of {len(node)} entries; "
                             f"index it by number ({where}.0 .. {where}.{len(node) - 1}), not {part!r}")
        i = int(part)
        if i >= len(node):
            raise ValueError(f"--set {text!r}: {where} has {len(node)} entries (indices 0 .. {len(node) - 1}), "
                             f"no entry {i}")
        return node[i]
    nxt = node.get(part)
    if nxt is None and create:
        nxt = node[part] = {}
    return nxt


def apply_overrides(data: dict, overrides: Iterable[str]) -> dict:
    """Return a deep copy of ``data`` with each ``a.b=value`` override set (``a.0.b``: entry 0 of the list ``a``).

    Missing intermediate mappings are created (validation then reports the key
    as unknown if the model has no such key); a list index must exist.
    """
    out = _deepcopy(data)
    for text in overrides:
        parts, value = parse_override(text)
        node: Any = out
        for i, part in enumerate(parts[:-1]):
            where = ".".join(parts[:i])
            nxt = _child(node, part, text, where, create=True)
            if not isinstance(nxt, dict | list):
                dotted = ".".join(parts[: i + 1])
                raise ValueError(f"--set {text!r}: key {dotted!r} holds {_summary(nxt, 80)}, not a mapping or list")
            node = nxt
        last = parts[-1]
        if isinstance(node, list):
            _child(node, last, text, ".".join(parts[:-1]), create=False)
            node[int(last)] = value
        else:
            node[last] = value
    return out


def _deepcopy(x: Any, budget: list[int] | None = None) -> Any:
    """A copy of nested dicts and lists; ``ValueError`` past :data:`MAX_VALUES` values (an alias bomb)."""
    budget = [MAX_VALUES] if budget is None else budget
    budget[0] -= 1
    if budget[0] < 0:
        raise ValueError(f"the config expands to more than {MAX_VALUES:,} values (YAML aliases repeating "
                         "large nodes?); write it out without them")
    if isinstance(x, dict):
        return {k: _deepcopy(v, budget) for k, v in x.items()}
    if isinstance(x, list):
        return [_deepcopy(v, budget) for v in x]
    return x


# --------------------------------------------------------------------------- loading

def read_config(path: str | Path, overrides: Sequence[str] = ()) -> tuple[dict, dict[str, str]]:
    """Read a YAML config file and apply ``a.b=value`` overrides.

    Returns:
      ``(data, set_keys)``: the mapping with the overrides applied, and the
      dotted keys the overrides set (each with its override text, for error messages).

    Raises:
      ConfigError: missing/unreadable file, bad YAML, a top level that is not a
        mapping, or a bad override; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found" if not path.exists() else f"{path}: not a file")
    text = read_text_utf8(path)
    try:
        data = yaml_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: invalid YAML: {_summary_text(str(err))}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping of keys, got {type(data).__name__}")
    try:
        data = apply_overrides(data, overrides)
    except ValueError as err:
        raise ConfigError(f"{path}: {err}") from None
    return data, {_dotted([int(p) if p.isdigit() else p for p in parse_override(o)[0]]): o for o in overrides}


def validate(model: type[BaseConfig], data: Mapping, path: str | Path, set_keys: Mapping[str, str] = {}) -> BaseConfig:
    """``model`` validated from ``data`` (read from ``path``); :class:`ConfigError` naming file, key and what is
    allowed."""
    path = Path(path)
    try:
        return model.model_validate(data, context={"config_dir": path.parent.resolve()})
    except ValidationError as err:
        lines = [_format_error(path, model, e, set_keys) for e in err.errors()]
        more = len(lines) - MAX_ERROR_LINES
        lines = lines[:MAX_ERROR_LINES] + ([f"{path}: ... and {more} more errors"] if more > 0 else [])
        raise ConfigError("\n".join(lines)) from None


def load_config(path: str | Path, overrides: Sequence[str] = (), *, model: type[BaseConfig]) -> BaseConfig:
    """Read a YAML config, apply ``a.b=value`` overrides and validate it against ``model``.

    :func:`selfid_jax.runner.registry.load` picks the model from the file's
    ``experiment`` key instead.

    Returns:
      The frozen, validated config model instance.

    Raises:
      ConfigError: missing/unreadable file, bad YAML, bad override, unknown
        key, wrong type or out-of-range value. The message names the file and
        the dotted key and says what is allowed.
    """
    data, set_keys = read_config(path, overrides)
    return validate(model, data, path, set_keys)


def dump_config(cfg: BaseModel) -> dict:
    """The resolved config as plain YAML/JSON-ready data (every default filled in)."""
    return cfg.model_dump(mode="json")


def flatten_dict(d: Mapping, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists stay values)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping) and v:
            out.update(flatten_dict(v, key + "."))
        else:
            out[key] = v
    return out


# --------------------------------------------------------------------------- messages

def _dotted(loc: Sequence[Any]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _unwrap(tp: Any) -> tuple[Any, list[Any]]:
    """Strip ``Annotated`` and ``X | None``; return ``(type, metadata)``."""
    meta: list[Any] = []
    while True:
        if typing.get_origin(tp) is Annotated:
            tp, *extra = typing.get_args(tp)
            for m in extra:
                meta.extend(getattr(m, "metadata", []) or [m])
            continue
        if typing.get_origin(tp) in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp, meta


def _locate(model: type[BaseModel], loc: Sequence[Any]) -> tuple[type[BaseModel] | None, Any, list[Any], str | None]:
    """Follow ``loc`` through ``model``: ``(parent model, annotation, metadata, description)``."""
    parent: type[BaseModel] | None = None
    tp: Any = model
    meta: list[Any] = []
    doc: str | None = None
    for part in loc:
        tp, _ = _unwrap(tp)
        if isinstance(part, int):
            if typing.get_origin(tp) in (list, tuple):
                args = typing.get_args(tp)
                tp, meta, doc, parent = (args[0] if args else Any), [], None, None
                continue
            return None, None, [], None
        if isinstance(tp, type) and issubclass(tp, BaseModel) and part in tp.model_fields:
            parent = tp
            field = tp.model_fields[part]
            tp, meta, doc = field.annotation, list(field.metadata), field.description
            continue
        return (tp if isinstance(tp, type) and issubclass(tp, BaseModel) else None), None, [], None
    return parent, tp, meta, doc


MAX_ERROR_LINES = 20
"""Most validation errors one :class:`ConfigError` lists (then a count of the rest)."""


def _summary_text(text: str, limit: int = 500) -> str:
    """``text`` cut to ``limit`` characters."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


_TYPE_NAMES = {int: "integer", float: "number", str: "string", bool: "true/false"}


def _describe(tp: Any, meta: list[Any], doc: str | None = None) -> str:
    """Human description of what a field accepts, e.g. ``'integer >= 1'``."""
    nullable = typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in typing.get_args(tp)
    tp, inner_meta = _unwrap(tp)
    meta = list(meta) + inner_meta
    origin = typing.get_origin(tp)
    if origin is Literal:
        desc = "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    elif origin in (list, tuple):
        args = typing.get_args(tp)
        desc = "list of " + (f"({_describe(args[0], [])})" if args else "values")
    elif isinstance(tp, type) and issubclass(tp, BaseModel):
        desc = "mapping with keys " + ", ".join(tp.model_fields)
    else:
        desc = _TYPE_NAMES.get(tp, getattr(tp, "__name__", str(tp)))
    bounds = []
    for m in meta:
        for attr, sym in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            v = getattr(m, attr, None)
            if v is not None and isinstance(m, annotated_types.BaseMetadata):
                bounds.append(f"{sym} {v}")
        if isinstance(m, annotated_types.MinLen) and m.min_length:
            bounds.append(f"with at least {m.min_length} item{'s' if m.min_length > 1 else ''}")
    if bounds:
        desc += " " + " and ".join(bounds)
    if doc:
        desc += f" ({doc})"
    if nullable:
        desc += " or null"
    return desc


def _format_error(path: Path, model: type[BaseModel], err: Mapping[str, Any], set_keys: Mapping[str, str]) -> str:
    # union members are tagged "<name>" (e.g. systems.spec.SystemSpec): not part of the user's key
    loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("<")))
    key = _dotted(loc) or "(top level)"
    kind = err["type"]
    msg = str(err["msg"])
    msg = msg.removeprefix("Value error, ")
    msg = msg[:1].lower() + msg[1:]
    parent, tp, meta, doc = _locate(model, loc)
    if kind == "extra_forbidden":
        allowed = ", ".join(parent.model_fields) if parent is not None else "?"
        level = _dotted(loc[:-1])
        where = f" at '{level}'" if level else ""
        text = f"unknown key; allowed keys{where}: {allowed}"
    elif kind == "missing":
        text = "required key is missing"
        if tp is not None:
            text += f"; allowed: {_describe(tp, meta, doc)}"
    else:
        text = f"{_summary_text(msg)} (got {_summary(err.get('input'))})"
        if tp is not None and kind != "literal_error":
            text += f"; allowed: {_describe(tp, meta, doc)}"
    source = ""
    for dotted, override in set_keys.items():
        if key == dotted or key.startswith((dotted + ".", dotted + "[")) or dotted.startswith((key + ".", key + "[")):
            source = f" (from --set {override})"
    return f"{path}: key '{key}': {text}{source}"
