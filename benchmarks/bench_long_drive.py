"""Memory and quality against the drive's length (issue 39, item 4): a long drive mapped at x1.

For each drive length (minutes) one simulated drive (half resolution, a room no test uses) is made
once, then `virus-nerf train --online --playback 1` maps it as the robot drives, with the grown box
of mapping while driving, in its own process. Both processes are sampled every 0.5 s from
/proc/PID/status: peak resident memory, split into anonymous (the process's own: tensors, arrays)
and file-backed (mapped files the kernel can drop: the memory-mapped frames, libraries). Reported
per drive: the simulator's seconds and peak memory, the mapper's peak memory, steps,
the final map's accuracy / coverage (zone 3, `map` ground truth) and its safety figures (issue 42:
obstacles within 1 m / 2 m / all marked free, free recall). Real time: an idle machine.

    python benchmarks/bench_long_drive.py --scene office --minutes 1,5 --out benchmarks/results/long_drive.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_out import new_out, write_out

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_time_to_map import DEFAULT_DATA  # noqa: E402

GROWN = '{"extent": {"mode": "grow"}}'


def _status_kb(pid: int) -> dict[str, int]:
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "RssAnon", "RssFile", "RssShmem"):
                out[key] = int(value.split()[0])
    except (OSError, ValueError):
        pass
    return out


def run_sampled(cmd: list[str], every_s: float = 10.0) -> dict:
    """Run `cmd`; its wall seconds and peak VmRSS / RssAnon / RssFile (MB), sampled every 0.5 s,
    and a timeline of [s, RssAnon MB, RssFile MB] every `every_s` (where in the run memory grows)."""
    start = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak: dict[str, int] = {}
    timeline: list[list[float]] = []
    while proc.poll() is None:
        now = _status_kb(proc.pid)
        for k, v in now.items():
            peak[k] = max(peak.get(k, 0), v)
        if now and time.monotonic() - start >= len(timeline) * every_s:
            timeline.append([round(time.monotonic() - start), round(now.get("RssAnon", 0) / 1024),
                             round(now.get("RssFile", 0) / 1024)])
        time.sleep(0.5)
    stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {stderr.strip()[-800:]}")
    return {"wall_s": round(time.monotonic() - start, 1), "stdout": stdout,
            **{f"peak_{k}_mb": round(v / 1024, 1) for k, v in sorted(peak.items())}, "timeline": timeline}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="office")
    ap.add_argument("--sim-seed", type=int, default=91)
    ap.add_argument("--minutes", default="1,5")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    new_out(args.out)  # before the run: a result is never overwritten
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in (float(m) for m in args.minutes.split(",")):
            data = args.data / f"{args.scene}{args.sim_seed}_{minutes:g}min"
            sim = None
            if not data.exists():
                sim = run_sampled([sys.executable, "-m", "virus_nerf.cli", "simulate", "--scene", args.scene, "--out",
                                   str(data), "--seed", str(args.sim_seed), "--duration", str(60 * minutes),
                                   "--resolution-scale", "0.5"])
                sim.pop("stdout")
            cfg = Path(tmp) / "grown.json"
            cfg.write_text(GROWN)
            out = Path(tmp) / f"run{minutes:g}"
            mapped = run_sampled([sys.executable, "-m", "virus_nerf.cli", "train", "--data", str(data), "--room",
                                  args.scene, "--out", str(out), "--online", "--playback", "1", "--gt", "map",
                                  "--config", str(cfg), "--quiet"])
            mapped.pop("stdout")
            doc = json.loads((out / "metrics.json").read_text())
            safety = doc.get("safety") or {}
            zones = safety.get("zones", {})
            nerf = doc.get("sensors", {}).get("NeRF", {}).get("zone3", {})
            row = {"minutes": minutes, "simulate": sim, "train_online": mapped,
                   "steps": doc["train"]["steps"], "train_s": doc["train"]["seconds"],
                   "zone3_accuracy_coverage_m": [round(nerf[k], 3) for k in ("acc_mean", "cov_mean") if k in nerf],
                   "safety_marked_free_1m_2m_all": [zones.get(z, {}).get("free_share") for z in ("1m", "2m", "all")],
                   "free_recall": safety.get("free_recall"),
                   "free_recall_drivable": safety.get("free_recall_drivable")}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        write_out(args.out, json.dumps({"command": "benchmarks/bench_long_drive.py " + " ".join(sys.argv[1:]),
                                        "scene": args.scene, "ground_truth": "map",
                                        "units": {"zone3_accuracy_coverage_m": "m",
                                                  "safety_marked_free_1m_2m_all": "share in [0, 1]",
                                                  "free_recall": "share in [0, 1]"},
                                        "drives": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
