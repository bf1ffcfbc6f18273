"""Nested dataclass configs <-> plain JSON dicts, with errors that name the file and the bad key.

Types are checked, not coerced: a `bool` field takes only a JSON bool (`"online": "false"` is
an error, not True), an `int` field takes an integer (or a float with no fractional part, e.g.
2048.0), a `float` field takes any finite number, a `str` field only a string, a tuple field a
JSON list whose elements are checked one by one (fixed-length tuples also by length), a Literal
field one of its values, and an `X | None` field null or an X. Unknown keys are an error, but
for the keys earlier versions wrote that nothing reads any more (REMOVED_KEYS): one at the value
the method now always uses (or a key whose value never mattered) is dropped with a one-line note
on stderr, so an old run's config.json still loads; one at another value is an error, since the
run it describes can no longer be made. Every error is a `ConfigError` (a ValueError) whose
one-line message names the file and the key.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import sys
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from virus_nerf.errors import ConfigError, one_line

T = TypeVar("T")

ANY = object()  # a removed key whose value never mattered
KEPT_NOT = "measured and not kept, docs/decisions.md D52"


@dataclasses.dataclass(frozen=True)
class Removed:
    """A key earlier versions wrote that nothing reads any more."""

    kept: Any  # the value the method now always uses (ANY: every value loads)
    why: str  # what took its place, or the decision-log entry that measured it


# dotted key -> Removed. Switches measured and not kept (docs/decisions.md D52) load at their
# old default, which is what the method does now
REMOVED_KEYS = {
    "ngp_grid.step_size": Removed(ANY, "the NGP grid's threshold follows the marcher's step, march.step_size"),
    "virus_grid.init_uss_free": Removed(False, KEPT_NOT),
    "virus_grid.init_stereo": Removed("off", KEPT_NOT),
    "virus_grid.warmup_budget_share": Removed(None, KEPT_NOT),
    "virus_grid.threshold_mode": Removed("mean", KEPT_NOT),
    "weights.free_depth": Removed(0.0, KEPT_NOT),
    "field.density_bias": Removed(0.0, KEPT_NOT),
}


# dotted key -> the value a saved config written before the key existed stands for. A run's
# config.json holds every key of the version that wrote it, so a key it lacks was added since, and
# its run was made with this value, whatever today's default is (`load_json_config(saved=True)`).
ADDED_KEYS = {
    "extent.fitted_frame": "box",  # the field spanned the fitted box per axis before (docs/decisions.md D58)
    "weights.free_stereo": 0.0,  # no emptiness before the stereo targets before docs/decisions.md D77
    "virus_grid.stereo_point_increment": 0.0,  # stereo points not grid evidence before docs/decisions.md D84
    # the small room's stereo filters were the others before docs/decisions.md D112
    "stereo.small_room_min_views": 4,
    "stereo.small_room_max_rel_sigma": 0.03,
}


def with_added_keys(data: Any) -> Any:
    """A saved config dict with the keys added since it was written (ADDED_KEYS) set to the values
    its run was made with; a key is set only where its section is there (a complete dump)."""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for dotted, value in ADDED_KEYS.items():
        *parents, leaf = dotted.split(".")
        node = out
        for name in parents:
            if not isinstance(node.get(name), dict):
                break
            node[name] = dict(node[name])  # the caller's dict stays as it was
            node = node[name]
        else:
            node.setdefault(leaf, value)
    return out


def to_dict(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [to_dict(v) for v in obj]
    return obj


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config", *, file: str | Path | None = None) -> T:
    """Build dataclass `cls` from `data`; unknown keys are an error, missing keys keep defaults.

    `file` names the JSON file the dict came from (it goes into every error message); without
    it the messages start with `where` (default "config", e.g. "config.march: unknown key(s)").
    """
    if file is None and where != "config":
        file = where  # older callers passed the file name as `where`
    ctx = _Ctx(file)
    built = _build(cls, data, ctx, "")
    if ctx.dropped:  # only once the config is good: an error stays the one line
        keys = ", ".join(f"'{key}'" for key in ctx.dropped)
        whys = "; ".join(dict.fromkeys(REMOVED_KEYS[key].why for key in ctx.dropped))
        print(f"virus-nerf: note: {file or 'config'}: key{'s' if len(ctx.dropped) > 1 else ''} {keys} ignored "
              f"(no longer read: {whys})", file=sys.stderr)
    return built


@dataclasses.dataclass(frozen=True)
class _Ctx:
    file: str | Path | None
    dropped: list[str] = dataclasses.field(default_factory=list)  # REMOVED_KEYS met

    def error(self, key: str, problem: str) -> ConfigError:
        return ConfigError(problem, file=self.file, key=key)


def _join(key: str, name: str) -> str:
    return f"{key}.{name}" if key else name


def _describe(value: Any) -> str:
    """A short description of a JSON value for error messages: its JSON type and its text."""
    if value is None:
        return "null"
    kind = {bool: "bool", int: "int", float: "float", str: "string", list: "list", dict: "object"}.get(
        type(value), type(value).__name__)
    text = json.dumps(value) if isinstance(value, bool | int | float | str | type(None)) else None
    if text is None:
        try:
            text = json.dumps(value)
        except (TypeError, ValueError):
            text = repr(value)
    return f"{kind} {one_line(text, 60)}"


def _build(cls: type[T], data: Any, ctx: _Ctx, key: str) -> T:
    if not isinstance(data, dict):
        raise ctx.error(key, f"expected a JSON object with the keys of {cls.__name__}, got {_describe(data)}")
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.init]  # type: ignore[arg-type]
    names = [f.name for f in fields]
    removed = [k for k in data if _join(key, str(k)) in REMOVED_KEYS]
    for k in removed:
        gone = REMOVED_KEYS[_join(key, k)]
        if gone.kept is not ANY and data[k] != gone.kept:
            raise ctx.error(_join(key, k), f"{_describe(data[k])}: this switch was removed ({gone.why}); the "
                            f"method now always runs as with {json.dumps(gone.kept)}: drop the key to load it so")
    ctx.dropped.extend(_join(key, k) for k in removed)
    unknown = sorted(set(data) - set(names) - set(removed), key=str)
    if unknown:
        hint = ""
        close = difflib.get_close_matches(str(unknown[0]), names, n=1)
        if close:
            hint = f" (did you mean '{close[0]}'?)"
        raise ctx.error(key, f"unknown key(s) {unknown}{hint}; known: {sorted(names)}")
    kwargs = {name: _convert(hints[name], data[name], ctx, _join(key, name)) for name in names if name in data}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:  # the dataclass's own range checks (__post_init__)
        problem = one_line(exc)
        # "log2_table_size must be in [4, 30], got 40" or "virus_grid.update_interval 0: ...": that key's
        named = problem.split(" ", 1)[0].rsplit(".", 1)[-1]
        raise ctx.error(_join(key, named) if named in names else key, problem) from None


def _expected(tp: Any) -> str:
    """What a type accepts, in JSON words, for error messages."""
    origin = typing.get_origin(tp)
    if tp is bool:
        return "a JSON bool (true or false)"
    if tp is int:
        return "an integer"
    if tp is float:
        return "a number"
    if tp is str:
        return "a string"
    if tp is type(None):
        return "null"
    if tp is Any:
        return "any value"
    if dataclasses.is_dataclass(tp):
        return f"an object ({tp.__name__})"
    if origin is typing.Literal:
        return "one of " + ", ".join(json.dumps(a) for a in typing.get_args(tp))
    if origin in (tuple, list):
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            return f"a list of {len(args)} values"
        return "a list"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_expected(a) for a in typing.get_args(tp))
    return getattr(tp, "__name__", str(tp))


def _convert(tp: Any, value: Any, ctx: _Ctx, key: str) -> Any:
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, ctx, key)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            raise ctx.error(key, f"expected {_expected(tp)}, got null")
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, ctx, key)
            except ConfigError:
                continue
        raise ctx.error(key, f"expected {_expected(tp)}, got {_describe(value)}")
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        for a in allowed:
            if type(a) is type(value) and a == value:
                return value
        raise ctx.error(key, f"expected {_expected(tp)}, got {_describe(value)}")
    if origin in (tuple, list):
        if not isinstance(value, list | tuple):
            raise ctx.error(key, f"expected {_expected(tp)}, got {_describe(value)}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ctx.error(key, f"expected a list of {len(args)} values, got {len(value)}")
            items = [_convert(a, v, ctx, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True))]
        else:
            elem = args[0] if args else Any
            items = [_convert(elem, v, ctx, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ctx.error(key, f"expected {_expected(tp)}, got {_describe(value)}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and math.isfinite(value) and value.is_integer():
            return int(value)
        raise ctx.error(key, f"expected an integer, got {_describe(value)}")
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ctx.error(key, f"expected a finite number, got {value}")
            return float(value)
        raise ctx.error(key, f"expected a number, got {_describe(value)}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ctx.error(key, f"expected a string, got {_describe(value)}")
    return value


def load_json_config(cls: type[T], path: str | Path, saved: bool = False) -> T:
    """Read a JSON config file into dataclass `cls`; every problem is a one-line ConfigError.
    saved: the file is a run's own config.json (every key of its version): a key added since
    loads at the value the run was made with (ADDED_KEYS), not today's default."""
    data = read_json_config(path)
    return from_dict(cls, with_added_keys(data) if saved else data, file=Path(path))


def read_json_config(path: str | Path) -> Any:
    """A JSON config file's parsed content, before any check of its keys (the keys a file sets,
    e.g. whether it gives a time budget); a file that cannot be read or parsed is a one-line
    ConfigError."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError("config file not found", file=path) from None
    except IsADirectoryError:
        raise ConfigError("is a folder; expected a JSON config file", file=path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the config file: {one_line(exc)}", file=path) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}", file=path) from None
    except RecursionError:
        raise ConfigError("not valid JSON: nested too deeply", file=path) from None
    return data
