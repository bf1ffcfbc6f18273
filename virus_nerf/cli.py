"""The `virus-nerf` console command (docs/method.md 7). Each subcommand lives beside its stage."""

from __future__ import annotations

import contextlib
import functools
import io
import re
import sys
from typing import NoReturn

from virus_nerf.errors import one_line

# subcommand name -> "module:function". Only the chosen command's module is imported: a mistake in
# its flags, `virus-nerf --help` or `simulate` do not wait for torch, matplotlib and numba, which the
# other commands' modules load (every module at once: 6 s on a 2-core machine before any output)
COMMANDS = {
    "simulate": "virus_nerf.sim.command:simulate",
    "sensors": "virus_nerf.evaluation.command:sensors",
    "train": "virus_nerf.trainer.command:train",
    "evaluate": "virus_nerf.trainer.command:evaluate",
    "demo": "virus_nerf.experiments.demo:demo",
    "ablation": "virus_nerf.experiments.ablation:ablation",
    "online": "virus_nerf.experiments.online:online",
    "tune": "virus_nerf.experiments.tune:tune",
    "export": "virus_nerf.exports.command:export",
    "import-bag": "virus_nerf.data.bags.command:import_bag",
    "map-bag": "virus_nerf.mapping.command:map_bag",
    "ros2": "virus_nerf.ros2.command:ros2",
    "ros2-play": "virus_nerf.ros2.command:ros2_play",
}


def _command(name: str):
    """The function of subcommand `name` (its module imported)."""
    import importlib

    module, function = COMMANDS[name].split(":")
    return getattr(importlib.import_module(module), function)


def _commands() -> dict:
    """Subcommand name -> function, every module imported."""
    return {name: _command(name) for name in COMMANDS}


def _listed_summary(name: str) -> str:
    """A command's one-line description (`_summary`) read from its module's source, not imported
    (an installation without the sources imports it)."""
    import ast
    import importlib.util

    module, function = COMMANDS[name].split(":")
    try:
        origin = importlib.util.find_spec(module).origin
        with open(origin, encoding="utf-8") as f:
            tree = ast.parse(f.read(), filename=origin)
        node = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == function)
    except (AttributeError, OSError, SyntaxError, TypeError, ValueError, StopIteration):  # no source beside it
        return _summary(_command(name))
    return _first_paragraph(ast.get_docstring(node))


def _not_chosen() -> None:
    """A command listed but not chosen on this command line (never parsed or run)."""
    raise RuntimeError("virus-nerf: a command that was not imported was chosen (a bug in cli._parse)")


def _train_short_help():
    """What `train --help` shows: the product knobs (`--help-all`: the command's every flag)."""
    from virus_nerf.trainer.command import train_short_help

    return train_short_help()


# subcommand name -> the function its `--help` shows, where that is not the command itself
_SHORT_HELP = {"train": _train_short_help}


def _summary(fn) -> str:
    """A command's one-line description: the first paragraph of its docstring."""
    return _first_paragraph(fn.__doc__)


def _first_paragraph(doc: str | None) -> str:
    """The first paragraph of a docstring on one line."""
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def _keep_large_allocations() -> None:
    """Stop glibc returning large tensors to the OS after every step (docs/method.md 10: ~1.4x faster)."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 1 << 30)
        libc.mallopt(m_trim_threshold, (1 << 31) - 1)
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to tune
        pass


def _deferred(commands: dict) -> dict:
    """The same commands, but calling one only returns what to run (parsing and running apart)."""

    def defer(fn):
        @functools.wraps(fn)
        def parsed(*args, **kwargs):
            return functools.partial(fn, *args, **kwargs)

        return parsed

    return {name: defer(fn) for name, fn in commands.items()}


_METAVAR_WORDS = {"INT": "an integer", "FLOAT": "a number", "STR": "a string", "PATH": "a path"}
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
_BOX = "\u256d\u256e\u2570\u256f\u2502"  # rounded corners and the vertical bar


def tyro_error_line(text: str, command: str | None = None) -> str:
    """tyro's boxed parse-error report as one line naming the argument and what was expected;
    `command` (the subcommand given) makes the help pointer `virus-nerf COMMAND --help`."""
    lines = [_ANSI.sub("", ln) for ln in text.splitlines()]
    title, sections, current = "", [], []
    for ln in lines:
        raw = ln.strip()
        if raw.startswith("\u256d"):  # top border: "╭─ Title ───╮"
            title = raw.strip(_BOX + "\u2500 ")
            continue
        if raw.startswith("\u2570"):
            continue
        body = raw.strip(_BOX).strip()
        if len(body) >= 3 and set(body) <= {"\u2500", "-"}:  # a rule between sections
            sections.append(current)
            current = []
        elif body:
            current.append(body)
    sections.append(current)
    if not title and len(sections) > 1 and len(sections[0]) == 1:  # ASCII form: title, rule, body
        title = sections.pop(0)[0]
    helpref = ""
    keep = []
    for sec in sections:
        joined = " ".join(sec)
        if joined.startswith("For full helptext"):
            ref = re.sub(r"^(run:?|see)\s+", "", joined.split(",", 1)[-1].strip())
            helpref = ref if ref.endswith("--help") else ""
            continue
        if sec:
            keep.append(sec)
    if not keep:
        return one_line(text) or "invalid command line"
    first = " ".join(keep[0])
    m = re.match(r"Error parsing (\S+): no type matching (.+?) could be instantiated from \[(.*?)\]\.?", first)
    m2 = re.match(r"Error parsing (\S+): (?:could not convert string to (float)|invalid literal for (int)\(\) "
                  r"with base 10): (.*)", first)
    if m:
        flag, types_, value = m.groups()
        expected = [t for t in types_.split("|") if t != "{None}"]
        msg = f"{flag} {value}: expected " + " or ".join(_METAVAR_WORDS.get(t, t) for t in expected or [types_])
    elif m2:
        flag, is_float, _, value = m2.groups()
        msg = f"{flag} {value}: expected {'a number' if is_float else 'an integer'}"
    elif first.startswith("Error parsing "):
        msg = first.removeprefix("Error parsing ").split(" Got errors:")[0]
    elif title == "Required options":
        body = [ln for sec in keep for ln in sec]
        missing = [ln for ln in body if ln.startswith("-")]
        for k, ln in enumerate(body):  # a positional shows as its metavar alone, its help on the next line
            if re.fullmatch(r"[A-Z][A-Z_]*", ln):
                words = []
                for nxt in body[k + 1:]:  # its help, wrapped over lines up to "(required)"
                    if nxt.startswith("-") or re.fullmatch(r"[A-Z][A-Z_]*", nxt):
                        break
                    words.append(nxt)
                    if nxt.endswith("(required)"):
                        break
                what = " ".join(words).removesuffix("(required)").strip().rstrip(".")
                missing.append(f"{ln} (the positional argument: {what})" if what else f"{ln} (positional)")
        who = keep[0][0].removeprefix("Missing from ").rstrip(":")
        msg = f"{who}: missing required argument(s) {', '.join(missing)}"
    elif title == "Missing subcommand":
        msg = "missing command: " + first[0].lower() + first[1:]
    else:
        msg = "; ".join(" ".join(sec) for sec in keep)
    if helpref and command and helpref == "virus-nerf --help":
        helpref = f"virus-nerf {command} --help"  # tyro names the top-level help for a subcommand's flag
    if helpref:
        msg += f" (see {helpref})"
    return one_line(msg)


def _parse(argv: list[str]):
    """Parse the command line; a mistake ends here with one line on stderr and exit code 2."""
    from typing import Annotated, Any, Union

    import tyro

    captured = io.StringIO()
    command = next((a for a in argv if not a.startswith("-")), None)
    if command not in COMMANDS and command is not None and command.replace("_", "-") in COMMANDS:
        command = command.replace("_", "-")  # tyro takes `map_bag` for `map-bag`
    commands = {command: _command(command)} if command in COMMANDS else {}
    if any(a.startswith("--tyro-") for a in argv):  # tyro's own options (shell completion): every command
        commands = _commands()
    if command in commands and "--help-all" in argv:  # the command's every flag
        argv = ["--help" if a == "--help-all" else a for a in argv]
    elif command in _SHORT_HELP and ("--help" in argv or "-h" in argv):
        commands = {command: _SHORT_HELP[command]()}
    # `virus-nerf --help` lists one line per command; a command's own --help shows its whole docstring
    summaries = command not in commands
    chosen = _deferred(commands)
    union = Union[tuple(  # type: ignore[misc]  # noqa: UP007  (a Union of a tuple, as tyro.extras.subcommand_cli_from_dict)
        Annotated[Any, tyro.conf.subcommand(name=name, constructor=chosen.get(name, _not_chosen),
                                            description=_listed_summary(name) if summaries else None)]
        for name in COMMANDS) + (Annotated[None, tyro.conf.Suppress],)]
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(union, prog="virus-nerf", args=argv)
    except SystemExit as exc:
        if exc.code in (0, None):  # --help (printed to stdout)
            sys.stderr.write(captured.getvalue())
            raise
        line = tyro_error_line(captured.getvalue(), command if command in commands else None)
        _fail(_help_all_for_hidden_flags(line, command))


def _help_all_for_hidden_flags(line: str, command: str | None) -> str:
    """tyro's "Perhaps you meant: --X ... in virus-nerf train --help" for a flag that only
    `train --help-all` lists (the short help shows the product knobs alone): the help named is the
    one that shows it."""
    if command != "train" or "Perhaps you meant" not in line:
        return line
    from virus_nerf.trainer.config import PRODUCT_KNOBS

    shown = {"--" + k.replace("_", "-") for k in PRODUCT_KNOBS}
    suggested = set(re.findall(r"--[\w.-]+", line.split("Perhaps you meant", 1)[1])) - {"--help", "--help-all"}
    if suggested and not suggested & shown:
        line = line.replace("virus-nerf train --help", "virus-nerf train --help-all")
    return line


def _fail(message: str) -> NoReturn:
    print(f"virus-nerf: error: {one_line(message, limit=1000)}", file=sys.stderr)
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> None:
    """Run one subcommand. Every user mistake (bad argument, bad config, bad input file,
    existing output, missing run) exits 2 with one line `virus-nerf: error: ...`; tracebacks
    are left for bugs. A reader of stdout that goes away (`virus-nerf train --help | head`)
    ends the command quietly with 141, as SIGPIPE ends a Unix tool."""
    try:
        _main(argv)
    except KeyboardInterrupt:  # Ctrl-C in the first tenth of a second, before _main's own handling
        print("virus-nerf: interrupted (Ctrl-C)", file=sys.stderr)
        raise SystemExit(130) from None
    except BrokenPipeError:
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        raise SystemExit(141) from None


def _main(argv: list[str] | None) -> None:
    _keep_large_allocations()

    from virus_nerf.errors import (
        DISK_FULL_ERRNOS,
        PENDING_NOTES,
        DataFormatError,
        NotWrittenError,
        OutputExistsError,
        OutputGoneError,
        UsageError,
        say_notes,
    )
    from virus_nerf.utils.stop import stop_on_signals

    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        # SIGTERM as Ctrl-C: temporary outputs removed, one line, exit 143; from the start, so a
        # stop while the command's modules load (torch: a second or two) is one line as well
        with stop_on_signals():
            run = _parse(argv)
            _one_line_thread_errors()
            run()
        say_notes()  # a command that did not say them where its work began
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGINT/SIGTERM of a command that stops cleanly
        _interrupted(exc)
    except (UsageError, DataFormatError, OutputExistsError, NotWrittenError, OutputGoneError) as exc:
        PENDING_NOTES.clear()  # the error line alone
        _fail(str(exc))
    except OSError as exc:
        if exc.filename is None:
            raise
        # a path the user named cannot be read or written (permissions, a file where a folder
        # belongs, ...): the system's reason and the path, not a traceback
        import os

        where = os.fsdecode(exc.filename) + (f" -> {os.fsdecode(exc.filename2)}" if exc.filename2 else "")
        if exc.errno in DISK_FULL_ERRNOS:
            # every output is written to a temporary name and renamed whole: what was there is intact
            _fail(f"{where}: could not be written ({exc.strerror or 'no space left on device'}); nothing was lost "
                  "(outputs are written whole under a temporary name, so every file written before is intact); "
                  "free some space and run the command again"
                  + (" (a training continues from its last checkpoint with --resume)" if argv[:1] == ["train"] else ""))
        _fail(f"{where}: {exc.strerror or exc}")


def _one_line_thread_errors() -> None:
    """A helper thread (TensorBoard's event writer) that cannot write its file says so in one line,
    not a traceback: the command itself names what it could not write. Other errors keep Python's
    report (they are bugs)."""
    import os
    import threading

    default = threading.excepthook
    if getattr(default, "one_line", False):  # set by an earlier command of this process
        return

    def hook(args) -> None:
        exc = args.exc_value
        if isinstance(exc, OSError) and exc.filename is not None:
            name = args.thread.name if args.thread is not None else "a thread"
            print(f"virus-nerf: warning: {name}: {os.fsdecode(exc.filename)}: {exc.strerror or exc}", file=sys.stderr)
            return
        default(args)

    hook.one_line = True
    threading.excepthook = hook


def _interrupted(exc: KeyboardInterrupt) -> NoReturn:
    """A stop asked for by a signal: exit 128 + the signal (130 Ctrl-C, 143 SIGTERM) with no
    traceback; one line unless the command already said where its outputs are (utils/stop.py)."""
    from virus_nerf.utils.stop import Stopped, exit_code_of, quiet_after_stop

    quiet_after_stop()  # what the stop cut half-built may report at exit: not after the one line
    if not (isinstance(exc, Stopped) and exc.reported):
        what = exc.name if isinstance(exc, Stopped) else "Ctrl-C"
        print(f"virus-nerf: interrupted ({what})", file=sys.stderr)
    raise SystemExit(exit_code_of(exc))


if __name__ == "__main__":
    main()
