"""Command-line flags derived from a config dataclass, and the flags given applied on top of a
config (the `train` command's: docs/usage.md).

`flag_tree(TrainConfig)` mirrors the dataclass as a TypedDict with total=False, a nested section
as a nested one. From it tyro makes one flag per field, grouped by section (`--optim.lr`,
`--virus-grid.warmup-steps`; top-level fields have no prefix: `--batch-size`), each with the
field's comment as its help, and what it parses holds only the flags given. So a new knob is one
dataclass field with its comment, and `apply_flags` replaces exactly the fields given: a flag
not given keeps the value of the config file (or of the run being resumed).

The dataclasses check themselves (`__post_init__`, virus_nerf/checks.py); those checks run again
on every section a flag changes and are the only range checks. A value they refuse is one line
naming the flag: `--optim.lr -1.0: expected a finite number > 0`.
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import re
import textwrap
import tokenize
import typing
from typing import Annotated, Any, TypedDict

import tyro

from virus_nerf.errors import UsageError, one_line


@dataclasses.dataclass(frozen=True)
class FlagSpec:
    """A field whose flag is not the derived one."""

    name: str | None = None  # the flag's name without "--" (default: the field's, "_" -> "-")
    type: Any = None  # what the flag parses, converted by the caller (default: the field's type)
    help: str | None = None  # default: the field's comment
    metavar: str | None = None  # default: the type's (INT, FLOAT, ...)


def flag_tree(cls: type, specs: dict[str, FlagSpec | None] | None = None, *, default: Any = None,
              prefix: str = "", only: tuple[str, ...] | None = None) -> type:
    """TypedDict (total=False) with a flag for every field of dataclass `cls`, its help the first
    sentence of the field's comment (the rest, the reasons for the default, stays in the source)
    and its shown default that of `default` (default: `cls()`). `specs` (dotted path -> FlagSpec,
    or None: no flag, e.g. a field only a config file can set) changes single fields. `only`
    (dotted paths): those fields alone, a section only when it keeps one (a help's short list)."""
    specs = specs or {}
    default = cls() if default is None else default
    comments = field_comments(cls)
    hints = typing.get_type_hints(cls)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        path, value = prefix + f.name, getattr(default, f.name)
        spec = specs.get(path, FlagSpec())
        if spec is None:
            continue
        if dataclasses.is_dataclass(hints[f.name]):
            if only is None or any(p.startswith(path + ".") for p in only):
                fields[f.name] = flag_tree(hints[f.name], specs, default=value, prefix=path + ".", only=only)
            continue
        if only is not None and path not in only:
            continue
        # a list shows its default as it is given: values apart, or one comma-separated string
        shown = (" " if spec.type is None else ",").join(map(str, value)) if isinstance(value, tuple) else value
        arg = tyro.conf.arg(name=spec.name, help=spec.help or _first_sentence(comments.get(f.name, "")),
                            metavar=spec.metavar, help_behavior_hint=f"(default: {shown})")
        fields[f.name] = Annotated[spec.type or hints[f.name], arg]
    tree = TypedDict(f"{cls.__name__}Flags", fields, total=False)  # type: ignore[misc]
    doc = inspect.getdoc(cls) or ""
    if not doc.startswith(f"{cls.__name__}("):  # a dataclass without docstring gets its signature
        tree.__doc__ = doc.split("\n\n")[0]  # the section's description in --help
    return tree


def with_annotation(fn: Any, param: str, annotation: Any) -> Any:
    """A copy of function `fn` whose parameter `param` has type `annotation` (what tyro reads):
    the same code, defaults and docstring. A command's `--help` shows a short flag tree this way
    while the command itself parses the whole one."""
    import functools
    import types

    hints = typing.get_type_hints(fn, include_extras=True)
    copy = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    copy = functools.update_wrapper(copy, fn, updated=())
    del copy.__wrapped__  # tyro must read the copy's annotations, not follow the original
    copy.__kwdefaults__ = fn.__kwdefaults__
    copy.__annotations__ = {**hints, param: annotation}
    return copy


def _first_sentence(text: str) -> str:
    """Up to the first ". " before a capital, a digit or "(" ("e.g. office" and "0.15" go on)."""
    return re.split(r"(?<=[^.\s]\.)\s+(?=[A-Z0-9(])", text, maxsplit=1)[0]


def flag_names(given: dict, specs: dict[str, FlagSpec | None] | None = None, prefix: str = "") -> dict[str, str]:
    """Dotted path -> flag (`--virus-grid.warmup-steps`) of every field in `given`."""
    specs = specs or {}
    section = prefix.replace("_", "-")  # "virus_grid." -> "virus-grid."
    names = {}
    for key, value in given.items():
        path = prefix + key
        if isinstance(value, dict):
            names.update(flag_names(value, specs, path + "."))
        else:
            names[path] = "--" + section + ((specs.get(path) or FlagSpec()).name or key.replace("_", "-"))
    return names


def apply_flags(config: Any, given: dict, flags: dict[str, str], prefix: str = "") -> Any:
    """`config` with the fields in `given` (nested dicts for sections) replaced, section by
    section with `dataclasses.replace`, so that every section changed and the whole config
    check themselves again. A value a check refuses is a UsageError naming its flag, from
    `flags` (dotted path -> the flag as the user typed it)."""
    changes = {}
    for key, value in given.items():
        if isinstance(value, dict):
            if value:
                changes[key] = apply_flags(getattr(config, key), value, flags, f"{prefix}{key}.")
        else:
            changes[key] = value
    if not changes:
        return config
    try:
        return dataclasses.replace(config, **changes)
    except UsageError:
        raise
    except ValueError as exc:
        raise UsageError(_name_flags(one_line(exc), flags, prefix)) from None


def _name_flags(message: str, flags: dict[str, str], prefix: str) -> str:
    """A check's message with every key given as a flag written as that flag ("optim.lr -1.0:
    ..." -> "--optim.lr -1.0: ..."); a message that names none (a section's own wording) starts
    with the flags given in that section."""
    named = message
    for path, flag in sorted(flags.items(), key=lambda kv: -len(kv[0])):
        named = re.sub(rf"(?<![\w.-]){re.escape(path)}(?=[\s\[:]|$)", flag, named)
    if named != message:
        return named
    section = [flag for path, flag in flags.items() if path.startswith(prefix)]
    return f"{', '.join(section)}: {message}"


def field_comments(cls: type) -> dict[str, str]:
    """Field name -> its comment in the source of dataclass `cls` (inherited fields included),
    read as tyro reads a dataclass's: the comment at the end of the field's line, else the
    comment lines right above it (or above the fields right before it, which it describes too)."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        own = set(vars(klass).get("__annotations__", {}))
        if not dataclasses.is_dataclass(klass) or not own:
            continue
        try:
            source = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):  # no source (a frozen build): no help text
            continue
        comments, code, strings = {}, set(), set()
        for tok in tokenize.generate_tokens(io.StringIO(source).readline):
            if tok.type == tokenize.COMMENT:
                comments[tok.start[0]] = tok.string.lstrip("#").strip()
            elif tok.type == tokenize.STRING:  # a docstring's lines are no fields
                strings.update(range(tok.start[0] + 1, tok.end[0] + 1))
            if tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
                                tokenize.DEDENT):
                code.add(tok.start[0])
        above: list[str] = []
        after_field = False  # a comment block after a field starts afresh (it describes the next one)
        for number, line in enumerate(source.splitlines(), 1):
            m = re.match(r" {4}(\w+)\s*:", line)
            if m and m.group(1) in own and number not in strings:
                out[m.group(1)] = comments.get(number) or " ".join(above)
                if number in comments:
                    above = []
                after_field = True
            elif number in comments and number not in code:
                if after_field:
                    above, after_field = [], False
                above.append(comments[number])
            else:
                above, after_field = [], False
    return {name: text for name, text in out.items() if text}
