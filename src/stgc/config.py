"""Config dataclasses <-> command line and JSON.

Every package owns its config as a dataclass whose fields carry a default and `metadata={"help": ...}`.
This module turns such a dataclass into argparse options (`--section.field VALUE`), applies dotted
`key=value` overrides (`--set train.iterations=5000`) with the field's own type, and round-trips configs
through JSON, so the CLI and the saved `config.json` never drift from the code.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import json
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

from stgc.errors import StgcError


# Options that change how a run executes or what it logs, not what it trains: a run made with other values of
# these is still the same run (a model trained with 2 threads serves a plan run at 1 thread).
EXECUTION_OPTIONS = frozenset({"train.threads", "train.backend", "train.eval_every", "train.eval_at_end",
                               "train.log_every", "train.checkpoint_every", "train.save_iterations", "train.progress",
                               "train.tensorboard", "train.stop_after", "data.image_cache_mb"})


# Options that name a file or folder: two configs agree on one when they name the same place (`same_place`).
PATH_OPTIONS = frozenset({"data.path", "compaction.loss_reference"})


def same_option_value(name: str, first: Any, second: Any) -> bool:
    """Whether the option `name` (dotted, with its section: "compaction.loss_reference") has one value in two
    configs."""
    if name in PATH_OPTIONS and first and second:
        return same_place(first, second)
    return bool(first == second)


def same_place(first: str | Path, second: str | Path) -> bool:
    """Whether two paths name one dataset or run: one path however spelled (relative or absolute), or a folder and
    a file in it (DATA may name a dataset's metadata file, a loss reference a file of its run). Two files are two
    places even in one folder (one MIV sequence of several)."""
    a, b = Path(str(first)).resolve(), Path(str(second)).resolve()
    if a == b:
        return True
    if a.is_file() and b.is_file():
        return False
    return (a.parent if a.is_file() else a) == (b.parent if b.is_file() else b)


class ConfigError(StgcError, ValueError):
    """An override names an unknown field or gives a value of the wrong type."""


@dataclasses.dataclass(frozen=True)
class FieldSpec:
    dotted: str  # e.g. "densify.grad_threshold" relative to the section
    type: Any
    default: Any
    help: str


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(get_args(tp)) == 2:
            return args[0], True
    return tp, False


def iter_fields(obj_or_cls: Any, prefix: str = "") -> Iterator[FieldSpec]:
    """All leaf fields of a (nested) config dataclass, with dotted names."""
    cls = obj_or_cls if isinstance(obj_or_cls, type) else type(obj_or_cls)
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        if not f.init or f.name.startswith("_"):
            continue
        tp = hints[f.name]
        if isinstance(obj_or_cls, type):
            if f.default is not dataclasses.MISSING:
                default = f.default
            elif f.default_factory is not dataclasses.MISSING:
                default = f.default_factory()
            else:
                default = None
        else:
            default = getattr(obj_or_cls, f.name)
        name = f"{prefix}{f.name}"
        inner, _ = _unwrap_optional(tp)
        if dataclasses.is_dataclass(inner) and isinstance(inner, type):
            yield from iter_fields(default if default is not None else inner, prefix=f"{name}.")
        else:
            yield FieldSpec(name, tp, default, f.metadata.get("help", ""))


def _type_name(tp: Any) -> str:
    inner, optional = _unwrap_optional(tp)
    if get_origin(inner) is Literal:
        s = "|".join(str(a) for a in get_args(inner))
    elif isinstance(inner, type):
        s = inner.__name__
    else:
        s = str(inner).replace("typing.", "")
    return f"{s}|{_unset_word(inner)}" if optional else s


def _unset_word(inner: Any) -> str:
    """How an optional option is left unset on the command line: 'none', or 'null' where 'none' is one of its values
    (model.decoder_activation)."""
    return "null" if get_origin(inner) is Literal and "none" in get_args(inner) else "none"


def coerce(value: Any, tp: Any, name: str) -> Any:
    """Convert a command-line string (or a JSON value) to the field type `tp`."""
    inner, optional = _unwrap_optional(tp)
    unset = ("null", "") if _unset_word(inner) == "null" else ("none", "null", "")
    if isinstance(value, str) and optional and value.lower() in unset:  # a value named 'none' stays that value
        return None
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{name}: None is not allowed (expected {_type_name(tp)})")
    origin = get_origin(inner)
    try:
        if origin is Literal:
            choices = get_args(inner)
            for c in choices:
                if value == c or (isinstance(value, str) and str(c) == value):
                    return c
            raise ConfigError(_not_a_choice(name, value, choices))
        if inner is bool:
            if isinstance(value, bool):
                return value
            s = str(value).lower()
            if s in ("1", "true", "yes", "on"):
                return True
            if s in ("0", "false", "no", "off"):
                return False
            raise ConfigError(f"{name}: {value!r} is not a boolean (true/false)")
        if inner is int:
            if isinstance(value, float) and not value.is_integer():
                raise ConfigError(f"{name}: {value!r} is not an integer")
            if isinstance(value, str) and "e" in value.lower():  # 3e4 = 30000, but 1e-4 is no integer
                number = float(value)
                if not number.is_integer():
                    raise ConfigError(f"{name}: {value!r} is not an integer")
                return int(number)
            return int(value)
        if inner is float:
            return float(value)
        if inner is str:
            return str(value)
        if origin in (list, tuple) or inner in (list, tuple):
            items = json.loads(value) if isinstance(value, str) and value.strip().startswith("[") else value
            if isinstance(items, str):
                items = [s for s in items.split(",") if s.strip()]
            args = get_args(inner)
            elem = args[0] if args else str
            out = [coerce(v, elem, name) for v in items]
            return tuple(out) if (origin is tuple or inner is tuple) else out
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: cannot read {value!r} as {_type_name(tp)} ({exc})") from None
    return value


def apply_overrides(obj: Any, overrides: dict[str, Any], section: str = "") -> Any:
    """Return a copy of the config dataclass `obj` with dotted-name overrides applied."""
    if not overrides:
        return obj
    specs = {s.dotted: s for s in iter_fields(obj)}
    grouped: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in specs:
            where = f"{section}." if section else ""
            close = difflib.get_close_matches(key, list(specs), n=1)
            hint = f" (did you mean {where}{close[0]}?)" if close else ""
            raise ConfigError(f"unknown option {where}{key}{hint}")
        grouped[key] = coerce(value, specs[key].type, f"{section}.{key}" if section else key)
    return _replace_nested(obj, grouped)


def _replace_nested(obj: Any, values: dict[str, Any]) -> Any:
    direct = {k: v for k, v in values.items() if "." not in k}
    nested: dict[str, dict[str, Any]] = {}
    for k, v in values.items():
        if "." in k:
            head, rest = k.split(".", 1)
            nested.setdefault(head, {})[rest] = v
    for head, sub in nested.items():
        direct[head] = _replace_nested(getattr(obj, head), sub)
    return dataclasses.replace(obj, **direct)


def check(condition: bool, name: str, value: Any, expected: str) -> None:
    """Raise a ConfigError naming the field unless `condition` holds (what every config's `validate` uses)."""
    if not condition:
        raise ConfigError(f"{name}: {value!r} is not allowed ({expected})")


def _not_a_choice(name: str, value: Any, choices: tuple[Any, ...]) -> str:
    """The message for a value that is none of a fixed-choice option's values (parser and `validate_config` alike)."""
    return f"{name}: {value!r} is not one of {', '.join(map(str, choices))}"


def literal_choices(tp: Any) -> tuple[tuple[Any, ...], bool] | None:
    """(the values, whether None is allowed too) of a fixed-choice field type: `Literal[...]`, `Optional[Literal[...]]`
    or `Literal[...] | None`; None for any other type."""
    inner, optional = _unwrap_optional(tp)
    return (get_args(inner), optional) if get_origin(inner) is Literal else None


def _is_choice(value: Any, choices: tuple[Any, ...]) -> bool:
    """Whether `value` is one of `choices` as its own type: "last", not 1 for True nor "1" for 1 (the run compares
    values with `==`, and config.json must read back as it trained)."""
    return any(value == c and isinstance(value, type(c)) and isinstance(value, bool) == isinstance(c, bool)
               for c in choices)


def check_choices(obj: Any, section: str = "") -> None:
    """Raise ConfigError, as the command line's parser does, when a fixed-choice (Literal-typed) option of the config
    dataclass `obj` or of a config nested in it holds none of its values (`section` prefixes the names errors give;
    anything but a dataclass instance, None included, passes). A config built in Python is checked by nothing else,
    and code that tests `== "last"` takes a typo for the other choice, then config.json cannot be read back."""
    if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        return
    prefix = f"{section}." if section else ""
    hints = _hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_choices(value, f"{prefix}{f.name}")
            continue
        kind = literal_choices(hints.get(f.name))
        if kind is None:
            continue
        choices, optional = kind
        if not ((value is None and optional) or _is_choice(value, choices)):
            raise ConfigError(_not_a_choice(f"{prefix}{f.name}", value, choices))


def validate_config(obj: Any, section: str = "") -> Any:
    """Check every fixed-choice (Literal-typed) option of `obj` and of its nested config dataclasses against its
    values (`check_choices`), then call `validate(prefix)` on each of them that defines it; returns `obj`."""
    check_choices(obj, section)
    _call_validators(obj, section)
    return obj


def _call_validators(obj: Any, section: str) -> None:
    """`validate(prefix)` of `obj` and of every nested config dataclass that defines it, the nested ones first."""
    if not dataclasses.is_dataclass(obj):
        return
    prefix = f"{section}." if section else ""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            _call_validators(value, f"{prefix}{f.name}")
    validator = getattr(obj, "validate", None)
    if callable(validator):
        validator(prefix)


def to_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)


def from_dict(cls: type, data: dict[str, Any], section: str = "") -> Any:
    """Rebuild a config dataclass from `to_dict` output; unknown keys are an error, missing keys take defaults.
    `section` ("train") prefixes the option names errors give."""
    where = f"{section}." if section else ""
    if not isinstance(data, dict):
        raise ConfigError(f"{section or cls.__name__}: {data!r} is not an object of options")
    # Groups of options ("densify" of train.densify.*) hold objects and options hold values: the other way round is
    # a damaged file (a group read as one unknown option, or an object's keys read as a string's).
    specs = list(iter_fields(cls))
    leaves = {spec.dotted for spec in specs}
    groups = {spec.dotted.rsplit(".", k)[0] for spec in specs for k in range(1, spec.dotted.count(".") + 1)}
    flat: dict[str, Any] = {}

    def walk(d: dict[str, Any], prefix: str) -> None:
        for k, v in d.items():
            name = f"{prefix}{k}"
            if name in groups:
                if not isinstance(v, dict):
                    raise ConfigError(f"{where}{name}: {v!r} is not an object (it holds the options {where}{name}.*)")
                walk(v, f"{name}.")
            elif isinstance(v, dict) and name in leaves:
                raise ConfigError(f"{where}{name}: {v!r} is an object, not a value")
            else:
                flat[name] = v

    walk(data, "")
    return apply_overrides(cls(), flat, section)


def from_saved(cls: type, data: dict[str, Any], section: str = "") -> Any:
    """`from_dict` for a config saved by an earlier version of stgc: a key it lacks takes the value in
    `cls.SAVED_BEFORE` (dotted names), the option's behaviour before it existed, so a saved run is read as it
    trained; the current default applies to new configs only. `section` prefixes the option names errors give."""
    if not isinstance(data, dict):
        raise ConfigError(f"{section or cls.__name__}: {data!r} is not an object of options")
    data = json.loads(json.dumps(data))  # a deep copy of plain JSON values
    for dotted, value in getattr(cls, "SAVED_BEFORE", {}).items():
        target = data
        *parents, key = dotted.split(".")
        for parent in parents:
            target = target.setdefault(parent, {})
            if not isinstance(target, dict):  # a damaged group: from_dict names it
                break
        else:
            target.setdefault(key, value)
    return from_dict(cls, data, section)


def parse_set_arguments(items: list[str] | None) -> dict[str, str]:
    """`["train.iterations=5000", ...]` -> {"train.iterations": "5000"}."""
    out: dict[str, str] = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        out[key.strip()] = value.strip()
    return out


def add_config_arguments(parser: argparse.ArgumentParser, section: str, cls_or_obj: Any, title: str) -> None:
    """Add one `--section.field` option per leaf field; given values are collected by `collect_overrides`."""
    group = parser.add_argument_group(title)
    for spec in iter_fields(cls_or_obj):
        default = spec.default
        shown = "none" if default is None else (str(default).lower() if isinstance(default, bool) else default)
        # Where the help says what the default is (an unset option that something else decides), it is not repeated.
        says_default = "default" in spec.help.lower() and default is None
        group.add_argument(
            f"--{section}.{spec.dotted}",
            dest=f"cfg:{section}:{spec.dotted}",
            metavar=_type_name(spec.type).upper() if get_origin(_unwrap_optional(spec.type)[0]) is not Literal
            else "{" + _type_name(spec.type) + "}",
            default=argparse.SUPPRESS,
            help=spec.help if says_default else f"{spec.help} (default: {shown})".strip(),
        )


def collect_overrides(namespace: argparse.Namespace) -> dict[str, dict[str, str]]:
    """{section: {dotted: raw_value}} for every `--section.field` given on the command line."""
    out: dict[str, dict[str, str]] = {}
    for key, value in vars(namespace).items():
        if key.startswith("cfg:"):
            _, section, dotted = key.split(":", 2)
            out.setdefault(section, {})[dotted] = value
    return out


def split_sections(flat: dict[str, str], sections: set[str]) -> dict[str, dict[str, str]]:
    """Group `--set` overrides `section.field=value` by their leading section name."""
    out: dict[str, dict[str, str]] = {}
    for key, value in flat.items():
        head, _, rest = key.partition(".")
        if head not in sections or not rest:
            raise ConfigError(f"--set {key}: keys start with one of {', '.join(sorted(sections))}")
        out.setdefault(head, {})[rest] = value
    return out
