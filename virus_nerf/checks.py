"""Type and range checks of config knobs, for the dataclasses' own `__post_init__`: the one
place a knob's range is written, whether the value came from a config file, a command-line
flag or Python. A bad value is a ValueError "NAME VALUE: expected WHAT", NAME the knob's dotted
path in config.json (`virus_grid.warmup_steps`), which the command line turns into one line
naming the file and key, or the flag (virus_nerf/config_flags.py)."""

from __future__ import annotations

import math
import numbers


class Checks:
    """Checks of the knobs of `config`; `prefix` is the section's path in config.json
    ("virus_grid.") for a section that checks itself."""

    def __init__(self, config, prefix: str = "") -> None:
        self.config = config
        self.prefix = prefix

    def get(self, dotted: str):
        obj = self.config
        for part in dotted.split("."):
            obj = getattr(obj, part)
        return obj

    def bad(self, name: str, value, expected: str) -> ValueError:
        return ValueError(f"{self.prefix}{name} {value!r}: expected {expected}")

    def integer(self, name: str, lo: int, hi: int | None = None, optional: bool = False) -> None:
        v = self.get(name)
        if v is None and optional:
            return
        ok = isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= lo and (hi is None or v <= hi)
        if not ok:
            rng = f"an integer >= {lo}" if hi is None else f"an integer in [{lo}, {hi}]"
            raise self.bad(name, v, rng + (" or None" if optional else ""))

    def number(self, name: str, lo: float, hi: float | None = None, *, lo_open: bool = True,
               hi_open: bool = False, optional: bool = False) -> None:
        v = self.get(name)
        if v is None and optional:
            return
        ok = isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)
        ok = ok and (v > lo if lo_open else v >= lo) and (hi is None or (v < hi if hi_open else v <= hi))
        if not ok:
            rng = f"{'>' if lo_open else '>='} {lo:g}" if hi is None else \
                f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
            raise self.bad(name, v, f"a finite number {rng}" + (" or None" if optional else ""))

    def flag(self, name: str) -> None:
        if not isinstance(self.get(name), bool):
            raise self.bad(name, self.get(name), "a bool (true or false)")

    def choice(self, name: str, allowed: tuple[str, ...]) -> None:
        if self.get(name) not in allowed:
            raise self.bad(name, self.get(name), "one of " + ", ".join(repr(a) for a in allowed))
