"""`virus-nerf export`: a trained run as map, grid, distance-field, point-cloud and image files.

Every flag, the run folder, the pose file and the output folder are checked before the model
is loaded (--image-scale's pixels, which need the recording's camera, once it is loaded and before
anything is rendered); the output is built in a temporary folder beside OUT and renamed when complete.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError, UsageError

KINDS = ("map", "prob", "grid3d", "esdf", "scans", "cloud", "images")
DEFAULT_KINDS = ("map", "prob", "grid3d", "esdf", "scans")  # cloud and images render many camera rays
NEEDS_VIRUS = ("prob", "grid3d")  # read the Bayesian grid's probabilities
# the scans' defaults (scans/): finer than the map's (maps.occupancy.MAP_RAYS, MAP_POSES), which
# keeps the counts its safety was measured at (D75)
SCAN_RAYS = 720
SCAN_POSES = 60


def parse_what(what: str | None, grid: str) -> tuple[str, ...]:
    """--what 'map,esdf' or 'all' -> the kinds to export, in KINDS order; the default skips
    the VIRUS-grid kinds for an Instant-NGP run, an explicit request for them is an error."""
    if what is None:
        return tuple(k for k in DEFAULT_KINDS if grid == "virus" or k not in NEEDS_VIRUS)
    names = [s.strip() for s in what.split(",")]
    if names == ["all"]:
        names = [k for k in KINDS if grid == "virus" or k not in NEEDS_VIRUS]
    bad = [s for s in names if s not in KINDS]
    if bad or not names:
        problem = f"unknown export {bad[0]!r}" if bad and bad[0] else "an empty name"
        raise UsageError(f"--what {what!r}: {problem}; expected 'all' or a comma-separated subset of {','.join(KINDS)}")
    need = [k for k in names if k in NEEDS_VIRUS]
    if need and grid != "virus":
        raise UsageError(f"--what {what!r}: {need[0]!r} needs the Bayesian VIRUS grid, but the run was trained "
                         f"with grid {grid!r}; leave it out")
    return tuple(k for k in KINDS if k in names)


def export(
    run: Path,
    out: Path,
    what: str | None = None,
    poses: Path | None = None,
    resolution: float = 0.05,
    n_rays: int | None = None,
    max_poses: int | None = None,
    band: float = 0.1,
    cloud_points: int = 200_000,
    image_scale: float | None = None,
) -> None:
    """Export a trained run: ROS map_server maps, the 3D grid, an ESDF, scans, a cloud, images.

    Args:
        run: A run folder written by `virus-nerf train`.
        out: New folder for the files (refused if it exists; docs/usage.md "Exports" lists them).
        what: Comma-separated subset of map,prob,grid3d,esdf,scans,cloud,images, or 'all' (default: map,prob,grid3d,esdf,scans).
        poses: CSV of camera poses time,x,y,z,qx,qy,qz,qw (s, m, camera-to-world, OpenCV axes) for scans and images (default: the recording's test poses).
        resolution: Metres per map pixel (> 0).
        n_rays: Rays per 360 deg scan (default: 360 for map.pgm and the ESDF, as every snapshot's map, whose safety is measured at that count; 720 for scans).
        max_poses: At most this many poses (evenly spread) for the map's scans (default 30, as every snapshot's map), for scans and for images (default 60).
        band: Metres above and below camera height whose grid layers form the probability map.
        cloud_points: At most this many rays (points) for the dense surface cloud.
        image_scale: Rendered image size as a share of the camera's (default: the run's image_scale).
    """
    from virus_nerf.errors import OutputExistsError, require_input_file, require_int, require_number
    from virus_nerf.trainer.run import load_trained
    from virus_nerf.trainer.run_folder import RunLock, open_run, training_finished
    from virus_nerf.utils.io import new_output_dir

    require_number("--resolution", resolution, 0.0)
    if n_rays is not None:
        require_int("--n-rays", n_rays, 1, 1_000_000)
    if max_poses is not None:
        require_int("--max-poses", max_poses, 1)
    require_number("--band", band, 0.0, 10.0, lo_open=False)
    require_int("--cloud-points", cloud_points, 1, 50_000_000)
    if image_scale is not None:
        require_number("--image-scale", image_scale, 0.0, 1.0)
    parse_what(what, "virus")  # the names; whether the run's grid has them is checked below
    pose_set = None
    if poses is not None:
        from virus_nerf.exports.views import read_pose_csv

        require_input_file("--poses", poses, "a CSV with columns time,x,y,z,qx,qy,qz,qw")
        pose_set = read_pose_csv(Path(poses))
    out = Path(out)
    if out.exists():
        raise OutputExistsError(out)  # before any work
    cfg, _ = open_run(run, "--run")
    kinds = parse_what(what, cfg.grid)
    if pose_set is not None and "images" in kinds:  # the scans take the poses' positions alone
        _check_poses_see_the_room(Path(poses), pose_set)
    # not while a `train` works in the run (its checkpoint would be a moment of a moving run);
    # shared with other exports, and nothing written into the run
    with RunLock(Path(run), "--run", shared=True), new_output_dir(out) as tmp:  # OUT made (and checked writable) first
        trainer, cfg, _ = load_trained(run, "--run", poses="odometry" if cfg.odometry_poses else "optimised")
        if pose_set is not None:
            _check_poses_in_box(Path(poses), pose_set, trainer.mapper.box)
        scale = image_scale if image_scale is not None else cfg.image_scale
        if "images" in kinds:  # before anything is rendered
            _image_intrinsics(trainer.recording, scale)
        finished = training_finished(Path(run), trainer.mapper.step)
        written = _export_all(trainer, cfg, tmp, kinds, pose_set, resolution, n_rays, max_poses, band, cloud_points,
                              scale, finished)
    if not finished:
        print(f"note: --run {run}: its training did not finish (no metrics.json of its last step; stopped at step "
              f"{trainer.mapper.step}): exported as it stands (`virus-nerf train --resume --out {run}` continues it)")
    print(f"wrote {out}/: " + ", ".join(written))


def _check_poses_see_the_room(path: Path, pose_set) -> None:
    """--poses for images are cameras in OpenCV axes (z forward): one looking straight up or down
    is a ROS body frame (x forward, z up) or a world that is not z-up, whose images would show the
    ceiling (the Mapper refuses such a SyncFrame alike)."""
    from virus_nerf.data.frame import looks_vertical

    axis_z = pose_set.cam_to_world[:, 2, 2]  # (N,) the optical axis' world z
    for i in np.flatnonzero(looks_vertical(axis_z))[:1]:
        raise DataFormatError(path, f"the camera looks straight {'up' if axis_z[i] > 0 else 'down'}; expected "
                                    "camera-to-world poses in OpenCV camera axes (z forward, y down), not a ROS body "
                                    "frame (x forward, z up), in a world whose z is up", row=int(i) + 2,
                              field="qx/qy/qz/qw")


def _image_intrinsics(recording, image_scale: float):
    """The main stack's camera at `image_scale`, refused in one line below 1x1 px."""
    from virus_nerf.sensors.rig import MAIN_STACK

    stack = recording.stacks.get(MAIN_STACK) or next(iter(recording.stacks.values()))
    intr = stack.intrinsics.scaled(image_scale)
    if intr.width < 1 or intr.height < 1:
        raise UsageError(f"--image-scale {image_scale:g}: CAM{stack.stack_id}'s {stack.intrinsics.width}x"
                         f"{stack.intrinsics.height} px images would be {intr.width}x{intr.height} px; expected a "
                         "scale giving at least 1x1 px")
    return intr


def _check_poses_in_box(path: Path, pose_set, box) -> None:
    """--poses positions lie in the run's scene box, give or take a camera at its edge (the
    Mapper's rule for a fitted box, engine/extent.FITTED_SLACK_M): one far outside is in another
    frame or unit (millimetres), whose scans would be empty."""
    from virus_nerf.engine.extent import FITTED_SLACK_M

    xyz = pose_set.cam_to_world[:, :3, 3]
    for i in np.flatnonzero(~box.padded(FITTED_SLACK_M).contains(xyz))[:1]:
        raise DataFormatError(path, f"camera at ({', '.join(f'{v:.3g}' for v in xyz[i])}) m lies outside the run's "
                                    f"scene box {np.round(box.lo, 2).tolist()}..{np.round(box.hi, 2).tolist()} m; "
                                    "expected poses in the run's world frame, in metres", row=int(i) + 2, field="x/y/z")


# the frame every export is in: the recording's, in which its poses (and LiDAR map) are given
WORLD_FRAME = "world: the recording's pose frame (its LiDAR map's), metres"


def _export_all(trainer, cfg, folder: Path, kinds, pose_set, resolution, n_rays, max_poses, band, cloud_points,
                image_scale, finished: bool = True) -> list[str]:
    """Compute and write every requested kind into `folder`; returns a short line per kind.
    finished: the run's training ended (export.json says so, with the steps it had)."""
    from virus_nerf.exports import clouds, grid3d, views
    from virus_nerf.maps import esdf, observed
    from virus_nerf.maps import occupancy as maps
    from virus_nerf.maps.extract import check_raster
    from virus_nerf.utils.io import write_json_atomic, write_text_atomic

    mapper = trainer.mapper
    box = mapper.box
    lo, hi = np.asarray(box.lo[:2], float), np.asarray(box.hi[:2], float)
    summary: dict = {"kinds": list(kinds), "frame": WORLD_FRAME, "resolution": resolution,
                     "origin": [float(lo[0]), float(lo[1]), 0.0], "steps": mapper.step, "run_finished": finished}
    done = []
    seen = None
    rasters = {"map", "esdf", "prob", "scans"} & set(kinds)
    if rasters:
        check_raster("--resolution", lo, hi, resolution)  # refused before any work if too large
    if rasters or "grid3d" in kinds:
        trainer.prepare()  # the frames the run trained on and its stereo points (cached), as `train` had them
    if rasters:
        seen = mapper.observed(resolution)  # (nx, ny) [ix, iy]: the training frames' view wedges
        summary["observed"] = round(observed.observed_share(seen), 4)
    if "map" in kinds or "esdf" in kinds:
        # the Mapper's own map (engine/views.py): what the run's snapshots wrote and its safety block judged
        rays, poses = maps.MAP_RAYS if n_rays is None else n_rays, maps.MAP_POSES if max_poses is None else max_poses
        m = mapper.map2d(resolution, rays, poses)
        summary["map"] = {"height": mapper.camera_height(), "scans": "360 deg NeRF scans at each position's camera "
                          "height, then the range sensors' hits", "n_rays": rays, "max_poses": poses}
        if "map" in kinds:
            maps.write_map_server(m, folder, "map")
            _write_png(folder / "map.png", m.image)
            done.append(f"map.pgm/.yaml ({m.image.shape[1]}x{m.image.shape[0]} px)")
        if "esdf" in kinds:
            d = esdf.signed_distance(m.image == maps.OCCUPIED, resolution)
            d[m.image == maps.UNKNOWN] = np.nan  # the map claims nothing there (no sensor looked, a shadow)
            esdf.write_esdf(esdf.DistanceField2D(d, resolution, m.origin), folder)
            done.append("esdf.npy/.yaml/.png")
    if "prob" in kinds or "grid3d" in kinds:
        grid = trainer.mapper.grid
        prob3 = grid.probability.detach().cpu().numpy()
        spec = grid.spec
        if "prob" in kinds:
            height = mapper.camera_height()
            maps.write_map_server(mapper.probability_map(resolution, band), folder, "prob")
            summary["prob_map"] = {"height": height, "band": band, "projection": "max over layers in the band"}
            done.append(f"prob.pgm/.yaml (raw: 100 p, unknown where no sensor looked; z {height:.2f} +- {band:g} m)")
        if "grid3d" in kinds:
            info = grid3d.Grid3DInfo(lo=tuple(map(float, spec.box.lo)), hi=tuple(map(float, spec.box.hi)),
                                     resolution=tuple(int(r) for r in spec.resolution),
                                     cell_size=tuple(float(c) for c in spec.cell_size))
            columns = mapper.grid_observed()  # (rx, ry): NaN in grid_probability.npy elsewhere
            grid3d.write_grid3d(prob3, grid.logodds.detach().cpu().numpy(), columns, info, folder)
            summary["grid3d"] = {"observed": round(float(columns.mean()), 4)}
            done.append(f"grid_probability.npy {prob3.shape} (NaN in the {1 - columns.mean():.0%} of the columns "
                        "no sensor looked at)")
    if {"scans", "images"} & set(kinds):
        pose_set = (pose_set or views.recording_test_poses(trainer.recording)).subsample(
            SCAN_POSES if max_poses is None else max_poses)
        write_text_atomic(folder / "poses.csv", pose_set.csv())
        summary["poses"] = {"source": pose_set.source, "count": len(pose_set)}
    if "scans" in kinds:
        (folder / "scans").mkdir()
        n_pts = n_unseen = 0
        for k, pose in enumerate(pose_set.cam_to_world):
            pts = views.scan_points(trainer.mapper.model, pose[:3, 3], SCAN_RAYS if n_rays is None else n_rays)
            keep = views.observed_points(pts, seen, lo, resolution)  # as the maps: none where no sensor looked
            pts, n_unseen = pts[keep], n_unseen + int((~keep).sum())
            clouds.write_pcd(folder / "scans" / f"scan_{k:04d}.pcd", pts)
            clouds.write_ply(folder / "scans" / f"scan_{k:04d}.ply", pts)
            n_pts += len(pts)
        summary["scans"] = {"points": n_pts, "unobserved_left_out": n_unseen}
        done.append(f"scans/ ({len(pose_set)} poses, {n_pts} points; {n_unseen} where no sensor looked left out)")
    if "cloud" in kinds:
        xyz, rgb = views.surface_cloud(trainer.mapper.model, trainer.recording, cloud_points, cfg.image_scale)
        clouds.write_pcd(folder / "cloud.pcd", xyz, rgb)
        clouds.write_ply(folder / "cloud.ply", xyz, rgb)
        summary["cloud_points"] = len(xyz)
        done.append(f"cloud.pcd/.ply ({len(xyz)} points)")
    if "images" in kinds:
        intr = _image_intrinsics(trainer.recording, image_scale)
        (folder / "images").mkdir()
        for k, pose in enumerate(pose_set.cam_to_world):
            rgb, depth_mm = views.render_image(trainer.mapper.model, intr, pose)
            _write_png(folder / "images" / f"color_{k:04d}.png", rgb)
            _write_png(folder / "images" / f"depth_{k:04d}.png", depth_mm)
        summary["images"] = {"width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy,
                             "cx": intr.cx, "cy": intr.cy, "depth": "uint16 z-depth in mm, 0 = no hit"}
        done.append(f"images/ ({len(pose_set)} x {intr.width}x{intr.height} colour + depth)")
    write_json_atomic(folder / "export.json", summary)
    return done


def _write_png(path: Path, image: np.ndarray) -> None:
    """8-bit grey/RGB or 16-bit grey (uint16) PNG, atomically."""
    from virus_nerf.maps.occupancy import write_png

    write_png(path, image)
