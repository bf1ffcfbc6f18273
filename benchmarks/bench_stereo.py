"""Camera depth quality: what the stereo stage (virus_nerf/stereo) triangulates, against the truth.

On simulated rooms the truth is exact: each target's ray is cast against the room's scene.json.
On the real sample (../shared/data, when present) the reference is the aligned depth image of the
same RealSense (the D455's own stereo depth, itself ~2 % of the range at 4 m), so there the
figures compare two estimates. Per room: time of the pass, points, targets per frame and share
of training pixels, error percentiles by true range, the share within 3 sigma, gross errors.

    .venv/bin/python benchmarks/bench_stereo.py --rooms common61,common62,common63,office61 \
        --out benchmarks/results/stereo_quality.json

--filters picks the pass's track filters: `defaults` (StereoConfig's own: 4 views, 3 % range
uncertainty; what a drive and an offline run in a room larger than 12 m use), `small-room` (3 views,
5 %: `stereo.depth.small_room_config`) or `offline` (the ones `virus-nerf train` with the defaults
picks for the room offline, trainer/loop.py `stereo_config`, D112).

A room is SCENE+SEED (simulated on first use into benchmarks/.data, as bench_time_to_map does).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np
from bench_out import new_out, write_out

HERE = Path(__file__).resolve().parent
BANDS = ((0, 2), (2, 4), (4, 6), (6, 8), (8, 10), (10, 15))


def _dirs(store, depth) -> np.ndarray:
    """(M, 3) world directions of the targets' rays."""
    from virus_nerf.sensors.camera import pixel_directions

    d = np.zeros((len(depth), 3))
    for s, intr in store.intrinsics.items():
        sel = store.stack_ids[depth.frames] == s
        d[sel] = pixel_directions(intr, depth.uv[sel, 0], depth.uv[sel, 1])
    return d


def _errors(depth, truth: np.ndarray) -> dict:
    ok = np.isfinite(truth)
    err = depth.ranges[ok] - truth[ok]
    z = err / depth.sigmas[ok]
    out = {"compared": int(ok.sum()), "abs_err_median_m": round(float(np.median(np.abs(err))), 4),
           "abs_err_p90_m": round(float(np.percentile(np.abs(err), 90)), 4),
           "signed_err_median_m": round(float(np.median(err)), 4),
           "within_3_sigma": round(float(np.mean(np.abs(z) < 3)), 3),
           "gross_over_0_5m": round(float(np.mean(np.abs(err) > 0.5)), 4),
           "too_close_over_0_5m": round(float(np.mean(err < -0.5)), 4), "by_range": []}
    for lo, hi in BANDS:
        m = (truth[ok] >= lo) & (truth[ok] < hi)
        if m.any():
            out["by_range"].append({"range_m": [lo, hi], "share": round(float(m.mean()), 3),
                                    "abs_err_median_m": round(float(np.median(np.abs(err[m]))), 4),
                                    "sigma_median_m": round(float(np.median(depth.sigmas[ok][m])), 4),
                                    "gross_over_0_5m": round(float(np.mean(np.abs(err[m]) > 0.5)), 4)})
    return out


def filters_for(rec, filters: str):
    """(StereoConfig, its name) for `--filters` and the recording `rec`."""
    from virus_nerf.engine.config import MapperConfig
    from virus_nerf.engine.model import start_box
    from virus_nerf.engine.step_loss import stereo_line_of_sight
    from virus_nerf.stereo.depth import StereoConfig, small_room_config

    cfg = StereoConfig()
    if filters == "offline":
        config = MapperConfig()
        filters = "small-room" if stereo_line_of_sight(config, start_box(rec, config), False, False) else "defaults"
    return (small_room_config(cfg) if filters == "small-room" else cfg), filters


def measure(data: Path, room: str, labels: tuple[str, ...], reference: str, filters: str = "defaults") -> dict:
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.sampler.frames import build_frame_store
    from virus_nerf.stereo.build import stereo_depth

    rec = load_recording(data, room)
    store = build_frame_store(rec, labels, 0.5, with_depth=reference == "depth camera", use_cache=False)
    cfg, used = filters_for(rec, filters)
    t0 = time.perf_counter()
    depth = stereo_depth(rec, store.frame_list(), cfg, use_cache=False)
    seconds = time.perf_counter() - t0
    per_frame = np.bincount(depth.frames, minlength=len(store))
    row = {"filters": used, "min_views": cfg.min_views, "max_rel_sigma": cfg.max_rel_sigma,
           "frames": len(store), "image_size": list(rec.stacks[min(rec.stacks)].image(0).shape[1::-1]),
           "seconds": round(seconds, 2), "points": len(depth.points), "targets": len(depth),
           "targets_per_frame_median": float(np.median(per_frame)),
           "share_of_training_pixels": round(len(depth) / (len(store) * store.width * store.height), 4),
           "range_median_m": round(float(np.median(depth.ranges)), 2) if len(depth) else None,
           "range_p95_m": round(float(np.percentile(depth.ranges, 95)), 2) if len(depth) else None,
           "reference": reference}
    if not len(depth):
        return row
    dirs = _dirs(store, depth)
    if reference == "exact scene":
        from virus_nerf.sim.scene import Scene

        scene = Scene.load(rec.room_dir / "scene.json")
        pose = store.cam_to_world[depth.frames]
        truth = scene.ranges(pose[:, :3, 3], np.einsum("nij,nj->ni", pose[:, :3, :3], dirs))
    else:
        col = np.clip(np.round(depth.uv[:, 0]).astype(int), 0, store.width - 1)
        rowi = np.clip(np.round(depth.uv[:, 1]).astype(int), 0, store.height - 1)
        mm = store.depths_mm[depth.frames, rowi, col].astype(float)
        truth = np.where(mm > 0, mm / 1000.0 / dirs[:, 2], np.nan)
    row.update(_errors(depth, truth))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rooms", default="common61,common62,common63,office61,office62,office63",
                    help="comma-separated SCENE+SEED rooms (office, common or warehouse and a simulation seed)")
    ap.add_argument("--data", type=Path, default=HERE / ".data")
    ap.add_argument("--sample", type=Path, default=HERE.parent.parent / "shared" / "data" / "sample_dataset")
    ap.add_argument("--filters", choices=("defaults", "small-room", "offline"), default="defaults",
                    help="the pass's track filters (the module's docstring)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    for name in args.rooms.split(","):
        if not re.fullmatch(r"(office|common|warehouse)\d+", name):
            ap.error(f"--rooms {args.rooms!r}: {name!r} is no room; expected SCENE+SEED, e.g. office61 (scenes "
                     "office, common, warehouse)")
    new_out(args.out)  # before the run: a result is never overwritten
    sys.path.insert(0, str(HERE))
    from bench_time_to_map import ensure_data

    doc = {"benchmark": "stereo_quality", "settings": f"filters {args.filters}; training image scale 0.5",
           "rooms": {}}
    for name in args.rooms.split(","):
        scene, seed = re.fullmatch(r"([a-z]+)(\d+)", name).groups()
        data = ensure_data(args.data, scene, int(seed))
        doc["rooms"][name] = measure(data, scene, ("train",), "exact scene", args.filters)
        print(name, json.dumps({k: v for k, v in doc["rooms"][name].items() if k != "by_range"}), file=sys.stderr)
    if (args.sample / "office").is_dir():
        doc["rooms"]["real_sample"] = measure(args.sample, "office", ("train", "test"), "depth camera", args.filters)
        print("real_sample", json.dumps({k: v for k, v in doc["rooms"]["real_sample"].items() if k != "by_range"}),
              file=sys.stderr)
    text = json.dumps(doc, indent=2)
    if args.out:
        write_out(args.out, text + "\n")
    else:
        print(text)


if __name__ == "__main__":
    main()
