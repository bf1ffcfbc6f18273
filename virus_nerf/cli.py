"""The `virus-nerf` console command (design 7). Each subcommand lives beside its stage."""

from __future__ import annotations

import sys


def _commands() -> dict:
    """Subcommand name -> function; imports are light (torch is imported inside the commands)."""
    from virus_nerf.evaluation.command import sensors
    from virus_nerf.experiments.ablation import ablation
    from virus_nerf.experiments.demo import demo
    from virus_nerf.experiments.export import export
    from virus_nerf.experiments.online import online
    from virus_nerf.sim.command import simulate
    from virus_nerf.trainer.command import evaluate, train

    return {
        "simulate": simulate,
        "sensors": sensors,
        "train": train,
        "evaluate": evaluate,
        "demo": demo,
        "ablation": ablation,
        "online": online,
        "export": export,
    }


def _keep_large_allocations() -> None:
    """Stop glibc returning large tensors to the OS after every step (design 10: ~1.4x faster)."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 1 << 30)
        libc.mallopt(m_trim_threshold, (1 << 31) - 1)
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to tune
        pass


def main(argv: list[str] | None = None) -> None:
    import tyro

    _keep_large_allocations()

    from virus_nerf.errors import DataFormatError, OutputExistsError

    argv = sys.argv[1:] if argv is None else argv
    try:
        tyro.extras.subcommand_cli_from_dict(_commands(), prog="virus-nerf", args=argv)
    except (DataFormatError, OutputExistsError) as exc:
        print(f"virus-nerf: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
