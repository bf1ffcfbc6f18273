"""The run folder: one place that knows its file names and reads and writes each file typed.

A run folder (`virus-nerf train --out RUN`) holds:

    config.json          the resolved TrainConfig (pass it back with --config)
    run.json             RunInfo: where the recording is (data folder, room)
    train_log.csv        one LogRow per logged step (trainer/train_log.py)
    checkpoint.pt        field, optimiser, grid, step, clock, RNG states, scene box, config
    metrics_vs_time.csv  one EvalPoint per evaluation during training (and the final one)
    metrics.json         the final evaluation (docs/method.md 7); its presence marks a finished run
    plots/               figures of the final evaluation (none with the config's `plots` off)
    tensorboard/         optional TensorBoard logs
    run.lock             held (fcntl.flock) by the process training in the folder, which writes its
                         pid into it; the system drops the lock when that process dies, however
                         it dies, so a stale lock never needs removing by hand

config.json changes only when a resume with other flags (a larger budget, another batch size)
has made its first step: a resume that fails before (e.g. out of memory) leaves the run as it was.

`open_run` (and `trainer.run.load_trained` on top of it, which also loads the checkpoint into a
Trainer) is the only way the commands (evaluate, export, resume) open an existing run, so every
damaged or foreign folder is refused the same way.
"""

from __future__ import annotations

import dataclasses
import errno
import json
from dataclasses import dataclass
from pathlib import Path

from virus_nerf.errors import DataFormatError, UsageError, one_line
from virus_nerf.utils.io import pid_alive, write_json_atomic, write_text_atomic

CONFIG = "config.json"
RUN_INFO = "run.json"
TRAIN_LOG = "train_log.csv"
CHECKPOINT = "checkpoint.pt"
METRICS = "metrics.json"
METRICS_VS_TIME = "metrics_vs_time.csv"
PLOTS = "plots"
MAP_DIR = "map"  # a run without ground truth: its 2D maps (map.pgm/.yaml/.png, prob.*, snapshot.json)
TENSORBOARD = "tensorboard"
LOCK = "run.lock"


@dataclass(frozen=True)
class RunInfo:
    """Where a run's data came from (run.json), so `evaluate --run` can find it again."""

    data: str  # absolute path of the recording's data folder
    room: str  # room folder inside it

    def write(self, folder: Path) -> None:
        write_json_atomic(Path(folder) / RUN_INFO, dataclasses.asdict(self))

    @staticmethod
    def read(folder: Path) -> RunInfo:
        path = Path(folder) / RUN_INFO
        try:
            info = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise DataFormatError(path, f"not valid JSON: {one_line(exc)}") from None
        if not isinstance(info, dict):
            raise DataFormatError(path, 'expected a JSON object {"data": ..., "room": ...}')
        for key in ("data", "room"):
            if not isinstance(info.get(key), str) or not info[key]:
                raise DataFormatError(path, "expected a non-empty string (where the run's recording is)", field=key)
        return RunInfo(data=info["data"], room=info["room"])


@dataclass(frozen=True)
class EvalPoint:
    """One evaluation of the NeRF's scans during training (zone 3 of the primary ground truth,
    named in `ground_truth`: "map", "scan", ...; None in a file written before it was recorded)."""

    step: int
    seconds: float  # training clock
    acc_mean: float | None  # m
    cov_mean: float | None  # m
    acc_inlier: float | None  # share in [0, 1]
    cov_inlier: float | None
    n_test_points: int  # test points scored (online: those the drive has reached)
    ground_truth: str | None = None  # the protocol the figures are scored against (metrics.json "gt")

    FIELDS = ("step", "seconds", "acc_mean", "cov_mean", "acc_inlier", "cov_inlier", "n_test_points", "ground_truth")


def write_eval_history(path: Path, points: list[EvalPoint]) -> None:
    """metrics_vs_time.csv, atomically; an empty cell is None."""
    if not points:
        return
    lines = [",".join(EvalPoint.FIELDS)]
    for p in points:
        lines.append(",".join("" if getattr(p, k) is None else str(getattr(p, k)) for k in EvalPoint.FIELDS))
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_eval_history(path: Path) -> list[EvalPoint]:
    """metrics_vs_time.csv -> EvalPoints ([] when the file is absent; a file written before the
    `ground_truth` column gives None there)."""
    path = Path(path)
    if not path.is_file():
        return []
    lines = path.read_text().strip().splitlines()
    keys = lines[0].split(",") if lines else []
    if tuple(keys) not in (EvalPoint.FIELDS, EvalPoint.FIELDS[:-1]):
        raise DataFormatError(path, f"header {keys}: expected {list(EvalPoint.FIELDS)}")
    points = []
    for row_no, line in enumerate(lines[1:], start=2):
        cells = dict(zip(keys, line.split(","), strict=False))
        try:
            points.append(EvalPoint(
                step=int(cells["step"]), seconds=float(cells["seconds"]),
                acc_mean=_opt(cells["acc_mean"]), cov_mean=_opt(cells["cov_mean"]),
                acc_inlier=_opt(cells["acc_inlier"]), cov_inlier=_opt(cells["cov_inlier"]),
                n_test_points=int(cells["n_test_points"]), ground_truth=cells.get("ground_truth") or None,
            ))
        except (KeyError, ValueError):
            raise DataFormatError(path, f"expected {len(keys)} values ({', '.join(keys)})", row=row_no) from None
    return points


def _opt(text: str) -> float | None:
    return float(text) if text else None


# ---------------------------------------------------------------------------- metrics.json
def train_summary_block(config, summary) -> dict:
    """The "train" block of metrics.json (docs/method.md 7)."""
    return {
        "steps": summary.steps,
        "seconds": round(summary.seconds, 3),
        "steps_per_s": round(summary.steps_per_s, 4),
        "samples_per_s": round(summary.samples_per_s, 1),
        "startup_s": None if summary.startup_s is None else round(summary.startup_s, 3),
        "wall_s": None if summary.wall_s is None else round(summary.wall_s, 3),
        "device": summary.device,
        "threads": summary.threads,
        "grid": config.grid,
        "sensors": list(config.sensors),
        "seed": config.seed,
        "online": config.online,
        "odometry_poses": config.odometry_poses,
    }


def write_run_metrics(run_dir: Path, result, config, summary, **extra) -> dict:
    """RUN/metrics.json (atomic): the EvaluationResult with the train block of `summary`;
    extra: safety, warnings (evaluation.metrics.metrics_document)."""
    return result.write_json(run_dir / METRICS, train=train_summary_block(config, summary), **extra)


# ---------------------------------------------------------------------------- opening a run
def is_run_config(path: str | Path) -> bool:
    """`path` is a run folder's own config.json (with run.json beside it: every key of the version
    that wrote it), not a file of a few keys: a key it lacks was added since and loads at the value
    the run was made with (config_io.ADDED_KEYS). A copy elsewhere reads as any config file."""
    path = Path(path)
    return path.name == CONFIG and (path.parent / RUN_INFO).is_file()


def load_config_file(path: str | Path):
    """A `--config` file -> TrainConfig: a run's own config.json as that run was made
    (`is_run_config`), any other file over today's defaults. train, map-bag and tune read it alike."""
    from virus_nerf.config_io import load_json_config
    from virus_nerf.trainer.config import TrainConfig

    return load_json_config(TrainConfig, path, saved=is_run_config(path))


def training_finished(run: Path, step: int) -> bool:
    """Whether the run's training finished at `step` (its checkpoint's): `train` writes metrics.json
    when its budget is spent, at that step; a run stopped part-way has none, and one resumed past
    it keeps the earlier one until it ends too."""
    import json

    try:
        steps = json.loads((Path(run) / METRICS).read_text())["train"]["steps"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return isinstance(steps, int) and steps == step


def open_run(run: Path, flag: str):
    """A finished or interrupted run folder -> (TrainConfig, RunInfo); every problem named."""
    from virus_nerf.config_io import load_json_config
    from virus_nerf.trainer.config import TrainConfig

    run = Path(run)
    if not run.exists():
        raise UsageError(f"{flag} {run}: no such run folder; expected a folder written by `virus-nerf train`")
    if not run.is_dir():
        raise UsageError(f"{flag} {run}: is a file; expected a run folder written by `virus-nerf train`")
    for name in (CONFIG, RUN_INFO):
        if not (run / name).is_file():
            raise DataFormatError(run / name, f"missing; {flag} expects a run folder written by `virus-nerf train`")
    cfg = load_json_config(TrainConfig, run / CONFIG, saved=True)
    return cfg, RunInfo.read(run)


def read_checkpoint(path: Path, cfg) -> dict:
    """Read checkpoint.pt on the CPU and check it fits `cfg`; returns its state (step, seconds,
    config, tensors: what `Trainer.load_checkpoint` takes, so the file is read once).

    A missing, truncated or foreign file is a DataFormatError naming it; a checkpoint of another
    grid or field than `cfg` asks for (e.g. `--resume --grid ngp` on a VIRUS run) a UsageError.
    """
    import torch

    from virus_nerf.config_io import to_dict

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "missing: the run has no checkpoint (it stopped before its first one); "
                                    f"continue it with `virus-nerf train --resume --out {path.parent}` "
                                    "(it trains from step 0)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # truncated zip, pickle garbage, not a torch file: torch raises many types
        raise DataFormatError(path, f"not a readable checkpoint ({type(exc).__name__}: {one_line(exc, 160)})") from None
    if not isinstance(state, dict):
        raise DataFormatError(path, f"not a virus-nerf checkpoint (holds a {type(state).__name__}, expected a dict)")
    from virus_nerf.engine.state import STATE_KEYS

    missing = [k for k in STATE_KEYS if k not in state]
    if missing:
        raise DataFormatError(path, f"not a complete virus-nerf checkpoint: lacks {missing}")
    saved = state.get("config")
    if isinstance(saved, dict):
        _check_same_shapes(path, saved, to_dict(cfg))
    check_counters(path, state)
    return state


def check_counters(path: Path, state: dict) -> None:
    """The step, clock and sample count of a checkpoint are numbers and its field and grid dicts
    (a damaged or hand-edited file is named with its field, not a traceback)."""
    from virus_nerf.engine.state import counters_problem

    if (problem := counters_problem(state)) is not None:
        raise DataFormatError(path, problem[1], field=problem[0])


# ---------------------------------------------------------------------------- the run's lock
class RunLock:
    """A lock on a run folder: one process writes in it at a time, and nobody reads it meanwhile.

    `fcntl.flock` on RUN/run.lock; the kernel releases it when the process exits or is killed,
    so there is never a stale lock to remove. A writer (train, evaluate, map-bag) takes it
    exclusively and writes its pid into the file; a reader (`shared`: export) shares it with other
    readers and writes nothing. A process the lock refuses gets a one-line UsageError naming the
    folder, the holder's pid and, where the system tells (Linux), what it does ("the run is still
    training"). A run on read-only media (an archive, a share mounted read-only) has no writer:
    there the lock is a no-op, as it is where flock does not exist (Windows). On a file system
    that keeps no locks (NFS without its lock service) the run is used unlocked, said once.
    """

    def __init__(self, folder: Path, flag: str = "--out", shared: bool = False):
        self.folder = Path(folder)
        self.flag = flag
        self.shared = shared
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        import os

        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX
            return self
        path = self.folder / LOCK
        try:  # a reader makes no lock file: a run without one has no writer at work
            fd = os.open(path, os.O_RDONLY if self.shared else os.O_RDWR | os.O_CREAT, 0o644)
        except FileNotFoundError:
            if self.shared:
                return self
            raise
        except OSError as exc:
            if exc.errno in _UNWRITABLE:  # read-only media or no write permission: nobody trains there
                return self
            raise
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if self.shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in _NO_LOCKS:
                self._refuse(fd)  # held (EWOULDBLOCK)
            # a file system without locks (NFS without its lock service: ENOLCK; some FUSE mounts):
            # the run is used unlocked, as where flock does not exist, and the user is told once
            if self.folder.resolve() not in _TOLD_NO_LOCKS:
                _TOLD_NO_LOCKS.add(self.folder.resolve())
                print(f"warning: {self.flag} {self.folder}: its file system offers no file locks "
                      f"({exc.strerror or exc}); nothing stops another process writing this run at the same time")
        mine = f"{os.getpid()}\n".encode()
        if not self.shared and os.pread(fd, 64, 0) != mine:  # unchanged when this process held it before
            os.ftruncate(fd, 0)
            os.pwrite(fd, mine, 0)
        self._fd = fd
        return self

    def holds(self, folder: Path) -> bool:
        """Whether `folder` is the folder this process locked (its run.lock is the file we hold):
        a folder renamed away meanwhile by another process, and whatever now has its name, are not
        ours to remove. True where flock does not exist (no lock, nothing to compare)."""
        import os

        if self._fd is None:
            try:
                import fcntl  # noqa: F401
            except ImportError:  # pragma: no cover - not POSIX
                return True
            return False
        try:
            here = os.stat(Path(folder) / LOCK)
        except OSError:
            return False
        mine = os.fstat(self._fd)
        return (here.st_dev, here.st_ino) == (mine.st_dev, mine.st_ino)

    def held_by_another(self) -> bool:
        """Whether another process holds the lock now (`probe` would refuse)."""
        try:
            self.probe()
        except UsageError:
            return True
        return False

    def probe(self) -> None:
        """Refuse as `acquire` would while another process holds the lock, but take nothing and
        write nothing (a command checks this before it reads the run for seconds): a writer's
        probe is refused by readers (an export) too, as the kernel lists them; where it cannot
        be told (no /proc/locks), by writers alone."""
        import os

        try:
            import fcntl

            fd = os.open(self.folder / LOCK, os.O_RDONLY)
        except (ImportError, OSError):  # not POSIX, or no lock file: nobody works in the run
            return
        holders = _flock_holders(fd)
        if holders is not None:
            if any(not (self.shared and shared) for _, shared in holders):
                self._refuse(fd)
            os.close(fd)
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            self._refuse(fd)
        os.close(fd)  # drops the shared lock

    def _refuse(self, fd: int):
        """The one-line refusal naming the holder's pid and command (closes `fd`): the holder as
        the kernel lists it (a reader writes no pid), else the pid the last writer wrote while that
        process still runs (a reader's refusal would name a writer long gone)."""
        import os

        pid = next((p for p, _ in _flock_holders(fd) or () if p > 0), None)
        if pid is None:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            pid = int(holder) if holder.isdigit() and pid_alive(int(holder)) else None
        os.close(fd)
        who = f"pid {pid}" if pid else "another process"
        command = _command_of(pid) if pid else None
        doing = _DOING.get(command or "")
        what = f"{doing} (`virus-nerf {command}`, {who})" if doing else f"in use by another virus-nerf process ({who})"
        raise UsageError(f"{self.flag} {self.folder}: the run is {what}; wait for it to end or stop it, "
                         "then run again") from None

    def release(self) -> None:
        import os

        if self._fd is not None:
            os.close(self._fd)  # closing the last descriptor drops the flock
            self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# what a lock holder's command does, for the refusal ("the run is still training (...)")
_DOING = {"train": "still training", "map-bag": "still being mapped", "export": "being exported",
          "evaluate": "being evaluated"}
# the errors of a lock file that cannot be opened for writing: read-only media, no permission
_UNWRITABLE = {errno.EROFS, errno.EACCES, errno.EPERM}
# flock's errors on a file system that keeps no locks (not: EWOULDBLOCK, the lock is held)
_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}
_TOLD_NO_LOCKS: set[Path] = set()  # folders whose missing locks were said (once a process)


def _flock_holders(fd: int) -> list[tuple[int, bool]] | None:
    """(pid, shared) of each flock held on `fd`'s file, from /proc/locks (Linux: "1: FLOCK ADVISORY
    READ PID MAJ:MIN:INODE 0 EOF", device numbers in hex; pid 0: a process this namespace does not
    see); None where it cannot be told (no /proc/locks)."""
    import os

    st = os.fstat(fd)
    try:
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return None
    holders = []
    for line in lines:
        fields = line.split()
        if "FLOCK" not in fields or "->" in fields:  # "->": a process waiting for the lock, not holding it
            continue
        k = fields.index("FLOCK")
        try:
            pid, (major, minor, inode) = int(fields[k + 3]), fields[k + 4].split(":")
            same = (int(major, 16), int(minor, 16), int(inode)) == (os.major(st.st_dev), os.minor(st.st_dev), st.st_ino)
        except (IndexError, ValueError):
            continue
        if same:
            holders.append((pid, fields[k + 2] == "READ"))
    return holders


def _command_of(pid: int) -> str | None:
    """The virus-nerf subcommand process `pid` runs (from /proc/PID/cmdline: the word after
    `virus-nerf` or `-m virus_nerf.cli`); None where it cannot be told (not Linux, another program)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode("utf-8", "replace").split("\0")
    except OSError:
        return None
    for k, arg in enumerate(argv[:-1]):
        if arg == "virus_nerf.cli" or Path(arg).name == "virus-nerf":
            return next((a for a in argv[k + 1:] if a and not a.startswith("-")), None)
    return None


def _check_same_shapes(path: Path, saved: dict, now: dict) -> None:
    """A run keeps its grid kind, network shape and grid resolution (other knobs may change)."""
    if saved.get("grid") != now["grid"]:
        raise UsageError(f"grid {now['grid']!r}: {path} holds a run trained with grid {saved.get('grid')!r}; "
                         "a run keeps its grid (omit --grid, or start a new run)")

    def section(doc: dict, name: str) -> dict:
        return doc[name] if isinstance(doc.get(name), dict) else {}

    grid_key = f"{now['grid']}_grid"
    shape_keys = [("field", k) for k in section(saved, "field") if k not in ("backend", "density_clamp")]
    shape_keys.append((grid_key, "max_resolution"))
    for sec, name in shape_keys:  # keys both versions know (a newer version may add some)
        old, new = section(saved, sec).get(name), section(now, sec).get(name)
        if old is not None and new is not None and old != new:
            key = f"{sec}.{name}"
            raise UsageError(f"{key} {one_line(new, 60)}: {path} was trained with {key} {one_line(old, 60)}; "
                             "a run keeps its network and grid shape")
