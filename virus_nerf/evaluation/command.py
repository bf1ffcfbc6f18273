"""`virus-nerf sensors`: score the instantaneous LiDAR, USS and IRS scans alone (docs/method.md 6, 7)."""

from __future__ import annotations

from pathlib import Path

from virus_nerf.errors import OutputExistsError
from virus_nerf.evaluation.plots import plots_dir_for, stopped_attempts_plots, write_plots
from virus_nerf.utils.io import remove_stale_partials


def sensors(
    data: Path,
    room: str,
    out: Path,
    n_rays: int = 512,
    odometry_poses: bool = False,
    lidar_angle_range_deg: float = 360.0,
    gt: str = "map",
) -> None:
    """Evaluate the instantaneous LiDAR, USS and IRS scans against the ground truth.

    Writes the metrics (docs/method.md 7 schema) to OUT and the plots to a folder beside it named
    after OUT's stem (results/metrics.json -> results/metrics_plots/), plots first; refuses an
    existing OUT. Plots without OUT are those of a run killed before its end: it is done again
    and they are replaced once the new ones are complete. Prints a compact table of the metrics per sensor and distance zone, per protocol.

    Args:
        data: Dataset folder in the ETHZ format (holds camera_intrinsics.CSV and the room folders).
        room: Room folder name inside DATA, e.g. office.
        out: Path of the metrics.json to write (must not exist).
        n_rays: Number of horizontal rays of the 360-degree ground-truth scan.
        odometry_poses: Use the odometry poses (poses_*_sync*.csv) instead of the optimised ones.
        lidar_angle_range_deg: Horizontal angle range of the LiDAR scan, centred on the robot heading
            (under --gt paper the authors' range of the room is used instead).
        gt: Ground truth, one or more of map (LiDAR map slice as solid 3 cm voxels), exact (the
            simulator's exact scene; simulated recordings only), paper (the authors' raster
            protocol), comma-separated; the first is the document's own, the others go to by_gt.
    """
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.errors import require_int, require_number, require_room_name
    from virus_nerf.evaluation.evaluate import (
        LIDAR_OWN_MAP,
        EvaluationConfig,
        check_ground_truth_inputs,
        evaluate,
        lidar_scored_against_own_map,
        parse_gt_flag,
    )
    from virus_nerf.evaluation.testpoints import recording_warnings, require_test_points

    require_room_name(room)
    require_int("--n-rays", n_rays, 1, 1_000_000)
    require_number("--lidar-angle-range-deg", lidar_angle_range_deg, 0.0, 360.0)
    protocols = parse_gt_flag(gt, scores=True)
    out = Path(out)
    plot_dir = plots_dir_for(out)
    if out.exists():
        raise OutputExistsError(out)
    # plots without metrics.json: a run killed before its end, done again whole (the plots are
    # replaced once the new ones are complete); `.<plots>.partial-<pid>-*` of dead attempts go
    remove_stale_partials(plot_dir)
    redo = stopped_attempts_plots(plot_dir, out)  # a folder holding a user's files: refused
    recording = load_recording(data, room, poses="odometry" if odometry_poses else "optimised")
    require_test_points(recording)  # nothing to score: refused, not an empty table
    check_ground_truth_inputs(recording, protocols)
    config = EvaluationConfig(n_rays=n_rays, lidar_angle_range_deg=lidar_angle_range_deg, gt=protocols)
    result = evaluate(recording, None, config)
    write_plots(result, plot_dir, replace=redo)
    if out.exists():
        raise OutputExistsError(out)
    warnings = [LIDAR_OWN_MAP] if "LiDAR" in config.sensors and protocols and lidar_scored_against_own_map(recording) \
        else []
    warnings += recording_warnings(recording)
    result.write_json(out, warnings=warnings)
    print(f"{result.n_points} test point{'' if result.n_points == 1 else 's'} of {Path(data) / room}")
    print(result.table())
    for w in warnings:
        print(f"warning: {w}")
    print(f"wrote {out} and {plot_dir}/")
