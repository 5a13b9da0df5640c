"""Generate docs/config_reference.md from the pydantic schemas: every config key of every experiment and command.

One section per shipped experiment (the entry points of ``pyproject.toml``,
in that order, each schema its ``Experiment.config``), then the configs of
the ``online`` and ``robot-sim`` commands. Each section is a table of keys:
nested sections as dotted keys (``controller.max_step``, what ``--set``
takes), the fields of a model inside a list or a choice of forms as
``key[].field`` under the form's name (``systems[] (MjcfSystem).site``),
each with its type, its bounds, its default (``required`` when it has none)
and its description.

    python scripts/config_keys.py          # write docs/config_reference.md
    python scripts/config_keys.py --check  # exit 1 if docs/config_reference.md differs

``tests/test_docs.py`` checks that the file equals this script's output and
names every field of every schema.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tomllib
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "config_reference.md"
GROUP = "selfid_jax.experiments"
# Commands that read a YAML config of their own (not an experiment): (command, "module:model").
COMMANDS = (
    ("online", "selfid_jax.sessions.online_config:OnlineConfig"),
    ("robot-sim", "selfid_jax.sessions.online_sim:RobotSimConfig"),
)

HEADER = """# Config reference

Every key of every shipped experiment's config, and of the `online` and `robot-sim` commands' configs, read from
their pydantic schemas by `python scripts/config_keys.py` (`tests/test_docs.py` checks that this page is current
and names every field). A nested key is written dotted, as `--set` takes it (`--set controller.max_step=0.002`);
`key[]` is an item of a list, and `(Name)` one of the forms a key accepts, by its schema's name; a default that
is a list of sections is given by its length (the shipped configs show full ones). Every schema
forbids unknown keys and checks types strictly (`3` is not a string, `2.0` is not an integer); bounds are
inclusive unless written `>` or `<`. The [user guide](user_guide.md) shows how configs are run and overridden.
"""


def shipped() -> list[tuple[str, str]]:
    """``(name, "module:attribute")`` of the entry points of ``pyproject.toml``, in file order."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    return list(config["project"]["entry-points"][GROUP].items())


def load(target: str) -> Any:
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _strip(tp: Any) -> tuple[Any, list[Any]]:
    """``(inner type, constraint metadata)`` of a possibly ``Annotated`` type."""
    meta: list[Any] = []
    while typing.get_origin(tp) is typing.Annotated:
        args = typing.get_args(tp)
        tp, meta = args[0], meta + list(args[1:])
    return tp, meta


def _bounds(meta: list[Any]) -> str:
    """Constraints as text: ``> 0``, ``>= 1, <= 1000``, ``length >= 1``."""
    out = []
    for m in meta:
        if isinstance(m, FieldInfo):
            out.append(_bounds(list(m.metadata)))
            continue
        for attr, sym in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            if isinstance(m, getattr(annotated_types, attr.capitalize())):
                out.append(f"{sym} {getattr(m, attr)}")
        if isinstance(m, annotated_types.MinLen):
            out.append(f"length >= {m.min_length}")
        if isinstance(m, annotated_types.MaxLen):
            out.append(f"length <= {m.max_length}")
        if isinstance(m, annotated_types.Interval):
            out.append(_bounds([annotated_types.Gt(m.gt) if m.gt is not None else None,
                                annotated_types.Ge(m.ge) if m.ge is not None else None,
                                annotated_types.Lt(m.lt) if m.lt is not None else None,
                                annotated_types.Le(m.le) if m.le is not None else None]))
    return ", ".join(s for s in out if s)


def type_text(tp: Any) -> str:
    """A type as a reader of YAML sees it: ``float (> 0)``, ``list[int (>= 0)]``, ``'native' | 'mjx'``."""
    tp, meta = _strip(tp)
    bounds = _bounds(meta)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Literal:
        text = " | ".join(repr(a) for a in args)
    elif origin in (typing.Union, types.UnionType):
        text = " | ".join(type_text(a) for a in args)
    elif origin in (list, tuple, set, frozenset) or origin is typing.Sequence:
        name = "list" if origin in (list, typing.Sequence) else origin.__name__
        inner = ", ".join("..." if a is Ellipsis else type_text(a) for a in args)
        text = f"{name}[{inner}]"
    elif origin is dict:
        text = f"dict[{', '.join(type_text(a) for a in args)}]"
    elif tp is type(None):
        text = "null"
    elif isinstance(tp, type):
        text = tp.__name__
    else:
        text = str(tp).replace("typing.", "")
    return f"{text} ({bounds})" if bounds else text


def _models_in(tp: Any) -> Iterator[tuple[str, type[BaseModel]]]:
    """``(suffix, model)`` of every pydantic model a type holds: ``""`` for the type itself, ``"[]"`` for items."""
    tp, _ = _strip(tp)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if _is_model(tp):
        yield "", tp
    elif origin in (typing.Union, types.UnionType):
        for a in args:
            yield from _models_in(a)
    elif origin in (list, tuple, set, frozenset) or origin is typing.Sequence:
        for a in args:
            if a is not Ellipsis:
                for suffix, model in _models_in(a):
                    yield "[]" + suffix, model
    elif origin is dict and args:
        for suffix, model in _models_in(args[-1]):
            yield "[key]" + suffix, model


def _optional(tp: Any) -> bool:
    tp, _ = _strip(tp)
    return typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in typing.get_args(tp)


def _section(tp: Any) -> type[BaseModel] | None:
    """The model of a nested section: a type that is one pydantic model, or that model or null; else None."""
    tp, _ = _strip(tp)
    if _is_model(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and _is_model(_strip(args[0])[0]):
            return _strip(args[0])[0]
    return None


def _yaml(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, BaseModel):
        return _yaml(value.model_dump())
    if isinstance(value, list | tuple):
        if value and all(isinstance(v, BaseModel | dict) for v in value):  # a list of sections: too long to inline
            return f"[{len(value)} entries]"
        return "[" + ", ".join(_yaml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_yaml(v)}" for k, v in value.items()) + "}"
    if isinstance(value, str):
        return repr(value)
    return repr(value)


def default_text(field: FieldInfo) -> str:
    """The field's default as YAML, ``required`` when it has none."""
    if field.default_factory is not None:
        return _yaml(field.default_factory())  # type: ignore[call-arg]
    if field.default is PydanticUndefined:
        return "required"
    return _yaml(field.default)


def rows(model: type[BaseModel], prefix: str = "", seen: tuple[type, ...] = ()) -> list[tuple[str, str, str, str]]:
    """``(key, type, default, description)`` of every field of ``model`` and of the models nested in it."""
    out = []
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}"
        nested = [(s, m) for s, m in _models_in(field.annotation) if m not in seen]
        description = " ".join((field.description or "").split())
        bounds = _bounds(list(field.metadata))
        sub = _section(field.annotation)
        if sub is not None:
            doc = " ".join((sub.__doc__ or "").strip().split("\n\n")[0].split())
            tp = f"section ({sub.__name__})" + (" | null" if _optional(field.annotation) else "")
            out.append((key, tp, default_text(field), description or doc))
        else:
            tp = type_text(field.annotation)
            out.append((key, f"{tp} ({bounds})" if bounds else tp, default_text(field), description))
        many = len({m for _, m in nested}) > 1
        for suffix, sub in nested:
            form = f" ({sub.__name__})" if many else ""
            out += rows(sub, f"{key}{suffix}{form}.", seen + (model,))
    return out


def _cell(text: str) -> str:
    return text.replace("|", r"\|").replace("*", r"\*").replace("\n", " ")


def section(title: str, intro: str, model: type[BaseModel]) -> str:
    lines = [f"## {title}", ""]
    if intro:
        lines += [intro, ""]
    lines += ["| key | type | default | description |", "| --- | --- | --- | --- |"]
    for key, tp, default, description in rows(model):
        lines.append(f"| `{_cell(key)}` | {_cell(tp)} | `{_cell(default)}` | {_cell(description)} |")
    return "\n".join(lines) + "\n"


def schemas() -> list[tuple[str, str, type[BaseModel]]]:
    """``(title, intro, model)`` of every documented config: the experiments, then the commands."""
    out = []
    for name, target in shipped():
        exp = load(target)
        desc = exp.description[0].upper() + exp.description[1:] + "." if exp.description else ""
        out.append((name, f"`experiment: {name}` ({exp.config.__name__}). {desc}".strip(), exp.config))
    for command, target in COMMANDS:
        model = load(target)
        out.append((f"selfid-jax {command}", f"The config of `selfid-jax {command} CONFIG` ({model.__name__}).",
                    model))
    return out


def render() -> str:
    return "\n".join([HEADER] + [section(*s) for s in schemas()])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/config_reference.md is out of date")
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        current = OUT.read_text(encoding="utf-8") if OUT.exists() else ""
        if current != text:
            print(f"{OUT.relative_to(ROOT)} is out of date: run python scripts/config_keys.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    print(f"wrote {OUT.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
