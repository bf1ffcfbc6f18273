"""An experiment's --out folder (`ablation`, `online`): new, or one the same command left unfinished.

Both commands continue an unfinished experiment where it stopped, so an existing --out is not
refused outright as every other command's is. It is continued only when it is the same command's:
it holds that command's mark (EXPERIMENT_MARK, written when the folder is first taken), or, for a
folder begun before the mark existed, nothing but what the command writes (`data/`, `runs/`).
Anything else (an unrelated folder, a training run, the other experiment's folder) is refused
before anything is written in it, and a finished experiment (its summaries present) too.
"""

from __future__ import annotations

import json
from pathlib import Path

from virus_nerf.errors import OutputExistsError, UsageError

EXPERIMENT_MARK = "experiment.json"  # {"command": "ablation" | "online", "settings": {flag: value}}
EXPERIMENT_ENTRIES = frozenset({"data", "runs", EXPERIMENT_MARK})  # what the commands write besides summaries


class FinishedExperimentError(OutputExistsError):
    """A finished experiment's summary exists: it is not overwritten, and the message says how to
    run the experiment's failed runs (or more seeds) again."""

    def __init__(self, summary: Path, command: str, summaries: list[Path]) -> None:
        names = ", ".join(p.name for p in summaries)
        FileExistsError.__init__(self, f"{summary}: output file already exists: this {command} is finished; to run "
                                 f"its failed runs (or more seeds) again, move {names} away first (the finished "
                                 "runs are reused), or choose a new --out (nothing was overwritten)")
        self.path = Path(summary)


def refuse_existing(paths: list[Path]) -> None:
    """OutputExistsError for the first of `paths` that exists (summary files are never overwritten)."""
    for p in paths:
        if p.exists():
            raise OutputExistsError(p)


def marked_command(out: Path) -> str | None:
    """The command named by OUT's mark; None without one, '?' for a mark that cannot be read."""
    mark = out / EXPERIMENT_MARK
    if not mark.is_file():
        return None
    try:
        command = json.loads(mark.read_text(encoding="utf-8")).get("command")
    except (OSError, ValueError, AttributeError):
        return "?"
    return command if isinstance(command, str) else "?"


def config_setting(config: Path | None) -> str | None:
    """A --config file as an experiment's setting: its path and a digest of its content (the same
    path edited between two runs of the command is another setting)."""
    import hashlib

    if config is None:
        return None
    return f"{config} (sha256 {hashlib.sha256(Path(config).read_bytes()).hexdigest()[:12]})"


def _settings_problem(out: Path, command: str, begun: dict, now: dict) -> str | None:
    """The first setting of `now` that differs from the one the experiment was begun with."""
    for key, value in now.items():
        if key in begun and begun[key] != value:
            shown = {v: "not given" if v is None else str(v) for v in (begun[key], value)}
            return (f"--out {out}: this {command} was begun with {key} {shown[begun[key]]} (now {shown[value]}); "
                    "its runs would mix the two: give the same settings to continue it, or choose a new --out "
                    "(nothing was changed)")
    return None


def take_experiment_folder(out: Path, command: str, summaries: list[Path], settings: dict | None = None) -> None:
    """Create OUT for `command` or check that it holds an unfinished experiment of that command
    begun with the same `settings` (flag -> value: what every run shares, e.g. the budget; more
    seeds or another subset of rooms only add runs), then leave the command's mark and settings
    in it; a one-line error naming OUT before anything is written otherwise (a finished
    experiment: OutputExistsError for its first summary)."""
    from virus_nerf.utils.io import require_makeable, write_json_atomic

    done = next((p for p in summaries if p.exists()), None)
    if done is not None:
        raise FinishedExperimentError(done, command, summaries)
    if out.exists() and not out.is_dir():
        raise OutputExistsError(out)
    require_makeable("--out", out)
    marked = marked_command(out)  # None for a new folder too
    if marked is not None and marked != command:
        raise UsageError(f"--out {out}: holds another experiment ({EXPERIMENT_MARK} says {marked!r}), not an "
                         f"unfinished {command}; choose a new --out (nothing was changed)")
    foreign = sorted(p.name for p in out.iterdir() if p.name not in EXPERIMENT_ENTRIES) if out.is_dir() else []
    if marked is None and foreign:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise UsageError(f"--out {out}: holds {shown}, so it is not an unfinished {command}; choose a new --out "
                         "(nothing was changed)")
    begun = _marked_settings(out) if marked is not None else {}
    settings = settings or {}
    if (problem := _settings_problem(out, command, begun, settings)) is not None:
        raise UsageError(problem)
    out.mkdir(parents=True, exist_ok=True)
    if marked is None or any(key not in begun for key in settings):  # a mark from before settings were kept
        write_json_atomic(out / EXPERIMENT_MARK, {"command": command, "settings": {**settings, **begun}})


def _marked_settings(out: Path) -> dict:
    """The settings OUT's mark keeps ({} for a mark written before they were kept)."""
    try:
        settings = json.loads((out / EXPERIMENT_MARK).read_text(encoding="utf-8")).get("settings", {})
    except (OSError, ValueError, AttributeError):
        return {}
    return settings if isinstance(settings, dict) else {}
