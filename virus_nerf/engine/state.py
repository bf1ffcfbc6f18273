"""What a `Mapper.state()` must hold before `Mapper.load_state` touches the mapper.

A state is checked whole first, so that a damaged, edited or foreign one is refused with the key
that is wrong and leaves the mapper as it was (a robot's mapper keeps mapping). The same checks
name the file of a damaged `checkpoint.pt` (trainer/run_folder.py). Each check returns a
(key, problem) pair, or None when the state passes.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping

# the entries every state holds (a state also has optional ones: box, rays, prior_frames, ...)
STATE_KEYS = ("field", "optimizer", "grid", "step", "seconds", "samples", "numpy_rng", "torch_generator")


def counters_problem(state: Mapping) -> tuple[str, str] | None:
    """The step and sample count are integers >= 0, the clock a finite number >= 0, and the field
    and grid dicts."""
    for key, kind in (("step", int), ("samples", int), ("seconds", float)):
        value = state[key]
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        ok = ok and (isinstance(value, int) if kind is int else math.isfinite(value)) and value >= 0
        if not ok:
            expected = "an integer >= 0" if kind is int else "a finite number >= 0"
            return key, f"expected {expected}, got {repr(value)[:60]}"
    for key in ("field", "grid"):
        if not isinstance(state[key], Mapping):
            return key, f"expected a dict of tensors, got {type(state[key]).__name__}"
    return None


# a state's optional counters (written by later releases than the first states): each an integer
# >= 0, or a finite number in a range; frames_at_start is None before the first step
FRAME_COUNTS = ("viewed_frames", "frames_at_start", "prior_frames")  # at most the state's frames
OPTIONAL_COUNTS = ("rays", "stereo_points", *FRAME_COUNTS)
OPTIONAL_NUMBERS = {"last_samples_per_ray": (0.0, math.inf), "visible_share": (0.0, 1.0)}


def optional_counters_problem(state: Mapping) -> tuple[str, str] | None:
    """The optional counters, checked before `load_state` converts them: a bad one was found only
    after the field and Adam had been replaced (a half-loaded mapper); the frame counts are at most
    the state's frames where it lists them."""
    frames = state.get("frames") if isinstance(state.get("frames"), int) else None
    for key in OPTIONAL_COUNTS:
        if key not in state or (state[key] is None and key == "frames_at_start"):
            continue
        value = state[key]
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:  # numpy's too
            return key, f"expected an integer >= 0, got {repr(value)[:60]}"
        if frames is not None and key in FRAME_COUNTS and value > frames:
            return key, f"{value} is more than the state's {frames} frames"
    for key, (lo, hi) in OPTIONAL_NUMBERS.items():
        value = state.get(key, lo)
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not lo <= value <= hi:
            return key, f"expected a number in [{lo:g}, {hi:g}], got {repr(value)[:60]}"
    return None


def tensors_problem(key: str, saved: Mapping, expected: Mapping, *, shapes: bool = True) -> tuple[str, str] | None:
    """Each tensor of entry `key` (field, grid) has the name, type and (with `shapes`) the shape of
    `expected`, the mapper's own state_dict."""
    import torch

    missing = [k for k in expected if k not in saved]
    if missing:
        return key, f"lacks tensor(s) {missing[:4]} of this model's {key}"
    for name, want in expected.items():
        got = saved[name]
        if not isinstance(want, torch.Tensor):
            continue
        if not isinstance(got, torch.Tensor):
            return f"{key}.{name}", f"expected a tensor, got {type(got).__name__}"
        if (shapes and tuple(got.shape) != tuple(want.shape)) or got.ndim != want.ndim \
                or got.dtype.is_floating_point != want.dtype.is_floating_point:
            return f"{key}.{name}", (f"tensor of shape {tuple(got.shape)} ({got.dtype}); this model has "
                                     f"{tuple(want.shape)} ({want.dtype}): damaged or of another model")
    return None


def generators_problem(state: Mapping) -> tuple[str, str] | None:
    """The random generators' states load into generators of the mapper's kinds (tried on new ones)."""
    import numpy as np
    import torch

    try:
        np.random.default_rng().bit_generator.state = state["numpy_rng"]
    except (TypeError, ValueError, KeyError) as exc:
        return "numpy_rng", f"not a numpy PCG64 state ({type(exc).__name__}: {str(exc)[:80]})"
    try:
        torch.Generator(device="cpu").set_state(state["torch_generator"])
    except (TypeError, RuntimeError) as exc:
        return "torch_generator", f"not a torch CPU generator state ({type(exc).__name__}: {str(exc).splitlines()[0][:80]})"
    return None


def expected_frames(state: Mapping):
    """(stack ids (N,) int64, store times (N,) float64 s) of the frames the state was trained on,
    from its "frame_stacks" / "frame_times"; empty arrays for a state written before they were
    kept; a str saying what is wrong with a malformed pair."""
    import numpy as np
    import torch

    stacks, times = state.get("frame_stacks"), state.get("frame_times")
    if stacks is None and times is None:
        return np.zeros(0, np.int64), np.zeros(0, np.float64)
    if not (isinstance(stacks, torch.Tensor) and isinstance(times, torch.Tensor)
            and stacks.dim() == times.dim() == 1 and len(stacks) == len(times)
            and not stacks.is_floating_point() and times.dtype == torch.float64):
        return ("expected frame_stacks (N,) integers and frame_times (N,) float64 seconds, as Mapper.state() "
                "writes them")
    if isinstance(state.get("frames"), int) and len(times) != state["frames"]:
        return f"holds {len(times)} frames, the state's 'frames' says {state['frames']}"
    return stacks.numpy().astype(np.int64), times.numpy().astype(np.float64)


def frames_mismatch(expected, first: int, stack_ids, times) -> str | None:
    """What is wrong when the frames (stack_ids, times (s)) becoming rows first, first+1, .. are
    not the expected frames of those rows (rows beyond the expected list: anything goes); None
    when they are."""
    import numpy as np

    want_stacks, want_times = expected
    n = max(0, min(len(times), len(want_times) - first))
    if n == 0:
        return None
    same = (np.asarray(stack_ids[:n]) == want_stacks[first:first + n]) & (np.asarray(times[:n]) == want_times[first:first + n])
    if same.all():
        return None
    k = int(np.argmin(same))
    row = first + k
    return (f"frame {row} is stack {int(stack_ids[k])} at {float(times[k])!r} s, the loaded state's frame {row} was "
            f"stack {int(want_stacks[row])} at {float(want_times[row])!r} s; expected the frames the state was "
            "trained on, in the same order")
