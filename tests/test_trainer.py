"""Training end to end on a tiny simulated office: loss falls, resume is exact, runs repeat."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from virus_nerf.data.ethz import load_recording
from virus_nerf.engine.config import MarchConfig
from virus_nerf.errors import OutputExistsError
from virus_nerf.grid.ngp import NgpGridConfig
from virus_nerf.grid.virus import VirusGridConfig
from virus_nerf.trainer.config import TrainConfig
from virus_nerf.trainer.loop import Trainer
from virus_nerf.trainer.run import run_training

METRIC_KEYS = {"acc_mean", "acc_median", "acc_inlier", "acc_too_close", "acc_too_far", "cov_mean", "cov_median",
               "cov_inlier", "cov_too_close", "cov_too_far", "gt_unseen", "n_pred", "n_gt"}


def small_config(**changes) -> TrainConfig:
    base = TrainConfig(
        max_steps=30, max_time=None, batch_size=256, image_scale=1.0, log_every=5, plots=False,
        march=MarchConfig(step_size=0.06, max_samples=64),
        virus_grid=VirusGridConfig(warmup_steps=16, update_interval=4, rays_per_update=128),
        ngp_grid=NgpGridConfig(warmup_steps=16, update_interval=4, max_resolution=64),
    )
    base.evaluation = dataclasses.replace(base.evaluation, n_rays=128)
    return dataclasses.replace(base, **changes)


def params(trainer: Trainer) -> list[torch.Tensor]:
    return [p.detach().clone() for p in trainer.mapper.field.parameters()]


def test_loss_falls(tiny_office, tmp_path):
    rec = load_recording(tiny_office, "office")
    # 128 rays a step (half the CPU time of 256): over seeds 0-2 the last ten steps' colour loss is
    # 0.44-0.46 of the first ten's, the IRS loss 0.03-0.05 (256 rays: 0.44-0.50, 0.03-0.04)
    cfg = small_config(max_steps=60, batch_size=128, virus_grid=VirusGridConfig(warmup_steps=256, update_interval=4))
    trainer = Trainer(rec, cfg, tmp_path, quiet=True)
    terms = [trainer.train_step().as_floats() for _ in range(60)]
    colour = [t["colour"] for t in terms]
    irs = [t["irs"] for t in terms]
    assert np.mean(colour[-10:]) < 0.7 * np.mean(colour[:10])
    assert np.mean(irs[-10:]) < 0.7 * np.mean(irs[:10])


def test_same_seed_same_parameters_and_resume_is_exact(tiny_office, tmp_path):
    rec = load_recording(tiny_office, "office")
    cfg = small_config(max_steps=20, device="cpu")  # the CPU promise; CUDA's atomic adds have no fixed order
    a = Trainer(rec, cfg, tmp_path / "a", quiet=True)
    (tmp_path / "a").mkdir()
    a.fit()
    b = Trainer(rec, cfg, tmp_path / "b", quiet=True)
    (tmp_path / "b").mkdir()
    b.fit()
    for x, y in zip(params(a), params(b), strict=True):
        assert torch.equal(x, y)
    # interrupted after 10 steps, resumed to 20: identical to the uninterrupted run
    c = Trainer(rec, cfg, tmp_path / "c", quiet=True)
    (tmp_path / "c").mkdir()
    for _ in range(10):
        c.train_step()
    c.save_checkpoint()
    del c
    d = Trainer(rec, cfg, tmp_path / "c", quiet=True)
    d.load_checkpoint(tmp_path / "c" / "checkpoint.pt")
    assert d.mapper.step == 10
    d.fit()
    for x, y in zip(params(a), params(d), strict=True):
        assert torch.equal(x, y)
    assert torch.equal(a.mapper.grid.occupied, d.mapper.grid.occupied)


@pytest.mark.parametrize(
    "grid,sensors,odometry",
    [("ngp", ("camera",), False), ("virus", ("camera", "uss"), False), ("virus", ("camera", "irs"), False),
     ("virus", ("camera", "rgbd"), False), ("virus", ("camera", "uss", "irs"), True)],
)
def test_every_table_row_runs(tiny_office, tmp_path, grid, sensors, odometry):
    cfg = small_config(grid=grid, sensors=sensors, odometry_poses=odometry, max_steps=6)
    doc = run_training(tiny_office, "office", tmp_path / "run", cfg, quiet=True)
    assert set(doc["sensors"]) == {"LiDAR", "USS", "IRS", "NeRF"}
    assert doc["train"]["grid"] == grid and doc["train"]["sensors"] == list(sensors)
    assert doc["train"]["steps"] == 6


def test_run_folder_contents_schema_and_no_overwrite(tiny_office, tmp_path):
    out = tmp_path / "run"
    run_training(tiny_office, "office", out, small_config(max_steps=8, plots=True), quiet=True)
    for name in ("config.json", "run.json", "train_log.csv", "checkpoint.pt", "metrics.json"):
        assert (out / name).is_file(), name
    assert (out / "plots" / "metrics_bars.png").is_file()
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["zones"] == {"zone1": [0, 1], "zone2": [0, 2], "zone3": [0, 100]}
    assert doc["gt"] == "map" and "by_gt" not in doc
    for sensor in doc["sensors"].values():
        for zone in ("zone1", "zone2", "zone3"):
            assert set(sensor[zone]) == METRIC_KEYS
    assert {"steps", "seconds", "steps_per_s", "samples_per_s", "grid", "sensors", "seed"} <= set(doc["train"])
    assert doc["train"]["samples_per_s"] > 0
    log = (out / "train_log.csv").read_text().splitlines()
    assert log[0].startswith("step,seconds,loss") and len(log) == 1 + 8 // 5 + 1
    with pytest.raises(OutputExistsError):
        run_training(tiny_office, "office", out, small_config(max_steps=8), quiet=True)


def test_train_and_evaluate_under_several_ground_truths(tiny_office, tmp_path):
    """--gt exact,map: the run's metrics.json is exact's with map in by_gt; `evaluate --gt paper`
    re-scores the checkpoint under another protocol into a new file."""
    import dataclasses

    from virus_nerf.trainer.command import evaluate as evaluate_command

    cfg = small_config(max_steps=4, plots=True)
    cfg = dataclasses.replace(cfg, evaluation=dataclasses.replace(cfg.evaluation, gt=("exact", "map")))
    out = tmp_path / "run"
    doc = run_training(tiny_office, "office", out, cfg, quiet=True)
    assert doc["gt"] == "exact" and list(doc["by_gt"]) == ["exact", "map"]
    assert json.loads((out / "config.json").read_text())["evaluation"]["gt"] == ["exact", "map"]
    assert (out / "plots" / "metrics_bars_gt-map.png").is_file()
    evaluate_command(out, out=tmp_path / "paper.json", gt="paper", plots=False)  # metrics.json alone
    again = json.loads((tmp_path / "paper.json").read_text())
    assert not (tmp_path / "paper_plots").exists()
    assert again["gt"] == "paper" and "by_gt" not in again
    assert again["sensors"]["NeRF"]["zone3"]["n_gt"] != doc["sensors"]["NeRF"]["zone3"]["n_gt"]


def test_online_mode_reveals_frames_with_the_clock(tiny_office, tmp_path):
    """A frame is available once the training clock x playback speed passes its timestamp."""
    rec = load_recording(tiny_office, "office")
    cfg = small_config(online=True, playback_speed=2.0, max_steps=None, max_time=1.0)
    trainer = Trainer(rec, cfg, tmp_path, quiet=True)
    times = np.sort(trainer.store.times)
    assert len(trainer.available_frames()) == 1  # at clock 0 only the first frame
    for k in (1, len(times) // 2, len(times) - 1):
        trainer.mapper.seconds = (times[k] - times[0]) / 2.0 + 1e-6  # just past frame k at playback x2
        assert len(trainer.available_frames()) == k + 1 + int(np.sum(times[k + 1:] == times[k]))
        trainer.mapper.seconds = (times[k] - times[0]) / 2.0 - 1e-6  # just before it
        assert len(trainer.available_frames()) == int(np.sum(times < times[k]))
    assert trainer.max_time == pytest.approx((times[-1] - times[0]) / 2.0)


class _WallField(torch.nn.Module):
    """A field with a known answer: empty up to the plane x = x_wall, opaque behind it."""

    def __init__(self, x_wall: float):
        super().__init__()
        self.x_wall = x_wall
        self.unused = torch.nn.Parameter(torch.zeros(1))  # SceneModel reads the device from it

    def forward(self, positions, dirs, rgb_mask=None):
        sigma = torch.where(positions[:, 0] >= self.x_wall, 1e4, 0.0)
        return sigma, torch.zeros_like(positions)


def test_scene_model_ranges_find_a_known_wall(tiny_office, tmp_path):
    """Rays along +x hit the wall 1 m ahead within one marching step; rays along -x see nothing
    (opacity 0 < min_opacity) and give NaN, never a point at the origin."""
    rec = load_recording(tiny_office, "office")
    cfg = small_config()
    trainer = Trainer(rec, cfg, tmp_path, quiet=True)  # grid before any update: every cell occupied
    origin = rec.stacks[1].cam_to_world[0, :3, 3]
    trainer.mapper.model.field = _WallField(float(origin[0]) + 1.0).to(trainer.mapper.device)
    origins = np.tile(origin, (8, 1))
    dirs = np.array([[1.0, 0.0, 0.0]] * 4 + [[-1.0, 0.0, 0.0]] * 4)
    r = trainer.mapper.model.ranges(origins, dirs)
    assert np.all(np.abs(r[:4] - 1.0) <= cfg.march.step_size)
    assert np.all(np.isnan(r[4:]))


def test_command_line_train_evaluate_export(tiny_office, tmp_path, capsys):
    from virus_nerf.cli import main
    from virus_nerf.config_io import to_dict

    cfg_path = tmp_path / "small.json"
    cfg_path.write_text(json.dumps(to_dict(small_config(max_steps=5))))
    run = tmp_path / "run"
    main(["train", "--data", str(tiny_office), "--room", "office", "--out", str(run), "--config", str(cfg_path),
          "--grid", "ngp", "--sensors", "camera,irs", "--quiet"])
    saved = json.loads((run / "config.json").read_text())
    assert saved["grid"] == "ngp" and saved["sensors"] == ["camera", "irs"] and saved["max_steps"] == 5
    main(["evaluate", "--run", str(run)])
    doc = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert doc["train"]["steps"] == 5 and "NeRF" in doc["sensors"]
    # the run's rate and where it ran (the checkpoint's device; a review: null before)
    trained = json.loads((run / "metrics.json").read_text())["train"]
    assert (doc["train"]["device"], doc["train"]["steps_per_s"]) == (trained["device"], trained["steps_per_s"])
    assert doc["train"]["threads"] == trained["threads"] == torch.get_num_threads()  # a review: null before
    assert doc["train"]["startup_s"] is None and doc["train"]["wall_s"] is None  # no training in evaluate
    assert (run / "evaluation" / "metrics_plots" / "metrics_bars.png").is_file()
    main(["export", "--run", str(run), "--out", str(tmp_path / "map"), "--max-poses", "4"])
    yaml = (tmp_path / "map" / "map.yaml").read_text()
    assert "image: map.pgm" in yaml and (tmp_path / "map" / "map.pgm").read_bytes().startswith(b"P5")
    with pytest.raises(SystemExit) as exc:  # an existing run folder is refused with a clear message
        main(["train", "--data", str(tiny_office), "--room", "office", "--out", str(run), "--max-steps", "1"])
    assert exc.value.code == 2
    assert "already exists" in capsys.readouterr().err


def test_config_round_trips_through_json_and_rejects_unknown_keys():
    from virus_nerf.config_io import from_dict, to_dict

    cfg = small_config(grid="ngp", sensors=("camera", "rgbd"))
    again = from_dict(TrainConfig, json.loads(json.dumps(to_dict(cfg))))
    assert again == cfg
    with pytest.raises(ValueError, match=r"config.march: unknown key\(s\) \['stepsize'\]"):
        from_dict(TrainConfig, {"march": {"stepsize": 0.1}})
    with pytest.raises(ValueError, match="sensors"):
        TrainConfig(sensors=("camera", "lidar"))


def test_trains_and_evaluates_on_the_real_sample(sample_dir, tmp_path):
    """One second of a standing robot: the map will be poor, but the real path must run."""
    doc = run_training(sample_dir, "office", tmp_path / "real", small_config(max_steps=5, image_scale=0.25),
                       quiet=True)
    assert doc["train"]["steps"] == 5
    assert doc["sensors"]["LiDAR"]["zone3"]["n_pred"] > 1000
    assert doc["sensors"]["NeRF"]["zone3"]["n_gt"] > 0


def test_resume_after_a_crash_cuts_the_log_back_to_the_checkpoint(tiny_office, tmp_path):
    rec = load_recording(tiny_office, "office")
    run = tmp_path / "run"
    run.mkdir()
    Trainer(rec, small_config(max_steps=6, log_every=1), run, quiet=True).fit()  # checkpoint at step 6
    with (run / "train_log.csv").open("a") as fh:  # rows a killed process wrote after the checkpoint
        fh.write("7,1.0,0.1,0.1,0,0,0,10,20,0.5,4,0,0,0\n8,1.1,0.1,0.1,0,0,0,10,20,0.5,4,0,0,0\n")
    resumed = Trainer(rec, small_config(max_steps=10, log_every=1), run, quiet=True)
    resumed.load_checkpoint(run / "checkpoint.pt")
    resumed.fit()
    steps = [int(line.split(",")[0]) for line in (run / "train_log.csv").read_text().splitlines()[1:]]
    assert steps == list(range(1, 11))
    assert (run / "train_log.csv").read_text().count("\n7,1.0,") == 0


@pytest.mark.parametrize("twin_device", ["cpu", pytest.param(
    "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"))])
def test_torch_backends_train_like_the_numba_kernels(tiny_office, tmp_path, twin_device):
    """The path a GPU takes (PyTorch marching, compositing and hash encoding) runs the trainer and
    matches the fused numba kernels (CPU) step for step within float rounding, on the CPU and,
    where there is one, on a CUDA GPU."""
    from virus_nerf.field.field import FieldConfig
    from virus_nerf.stereo.depth import StereoConfig

    rec = load_recording(tiny_office, "office")
    # Adam (eps 1e-15) gives a table entry whose gradient is at float-rounding level a full
    # lr-sized step whose sign is the rounding's: such entries may differ by a few lr between the
    # backends; everything else must agree within float rounding.
    runs = {}
    for backend, device in (("numba", "cpu"), ("torch", twin_device)):
        # the stereo targets these shares were measured with: the small room's filters (D112) give
        # the line of sight more targets, and with them more near-zero gradients (3.6e-4 on the CPU)
        cfg = small_config(max_steps=5, march=MarchConfig(step_size=0.06, max_samples=64, backend=backend),
                           field=dataclasses.replace(FieldConfig.cpu_default(), backend=backend), device=device,
                           stereo=StereoConfig(small_room_min_views=4, small_room_max_rel_sigma=0.03))
        trainer = Trainer(rec, cfg, tmp_path / backend, quiet=True)
        losses = [trainer.train_step().as_floats()["total"] for _ in range(5)]
        runs[backend] = (losses, [p.cpu() for p in params(trainer)], trainer.mapper.samples)
    (ln, pn, sn), (lt, pt, st) = runs["numba"], runs["torch"]
    assert sn == st, "both marchers place the same samples"
    np.testing.assert_allclose(lt, ln, rtol=1e-4)
    lr = cfg.optim.lr
    # CUDA's atomic adds sum a gradient in a varying order, so more rounding-level gradients get
    # their sign flipped there: 8.0e-4 of the values measured on an H200 (torch 2.11), 1e-4 on the CPU
    # (a share of all the field's values: an MLP weight whose gradient is near zero, e.g. under
    # the stereo line of sight's gradient in the first steps, is such a value as well)
    share = 1e-4 if twin_device == "cpu" else 2e-3
    off = sum(int((~torch.isclose(b, a, rtol=1e-3, atol=1e-5)).sum()) for a, b in zip(pn, pt, strict=True))
    total = sum(a.numel() for a in pn)
    assert off <= share * total, f"{off} of {total} values differ"
    for a, b in zip(pn, pt, strict=True):
        assert (b - a).abs().max().item() <= 5 * lr * 1.01


def test_density_only_depth_rays_skip_the_colour_network(tiny_office, tmp_path):
    rec = load_recording(tiny_office, "office")
    trainer = Trainer(rec, small_config(density_only_depth_rays=True), tmp_path, quiet=True)
    pts = torch.tensor([[1.0, 1.0, 1.0], [1.5, 1.0, 1.2], [2.0, 2.0, 0.5]]) + torch.tensor(trainer.mapper.box.lo)
    pts, dirs = pts.to(trainer.mapper.device), torch.tensor([[1.0, 0.0, 0.0]] * 3, device=trainer.mapper.device)
    sigma_all, rgb_all = trainer.mapper.field(pts, dirs)
    sigma, rgb = trainer.mapper.field(pts, dirs, torch.tensor([True, False, True], device=trainer.mapper.device))
    assert torch.equal(sigma, sigma_all)
    assert torch.equal(rgb[[0, 2]], rgb_all[[0, 2]]) and torch.all(rgb[1] == 0)
    terms = trainer.train_step()
    assert math.isfinite(terms.total.item())


def test_online_scores_nothing_before_the_first_test_point(tiny_office, tmp_path):
    rec = load_recording(tiny_office, "office")
    trainer = Trainer(rec, small_config(online=True, max_steps=None, max_time=5.0), tmp_path, quiet=True)
    trainer.mapper.seconds = 0.0
    first = min(tp.time for tp in (g.test_point for g in __import__(
        "virus_nerf.evaluation.evaluate", fromlist=["build_ground_truth"]).build_ground_truth(rec)))
    assert first > trainer.t0, "the tiny office must start before its first test point for this test to mean anything"
    assert trainer.evaluate(with_sensors=False) is None
    trainer.mapper.seconds = trainer.duration
    assert trainer.evaluate(with_sensors=False) is not None


def test_grid_prior_uses_only_the_frames_available_at_the_start(tiny_office, tmp_path):
    from virus_nerf.sampler.sensor_rays import irs_zone_rays

    rec = load_recording(tiny_office, "office")
    online = Trainer(rec, small_config(online=True, max_steps=None, max_time=5.0), tmp_path / "a", quiet=True)
    online.prepare()
    offline = Trainer(rec, small_config(), tmp_path / "b", quiet=True)
    offline.prepare()
    first = online.available_frames()
    assert len(first) < len(online.store)
    ref = build_virus_grid_like(offline)
    ref.initialise(irs_zone_rays(online.store, first, ref.config.init_zone_samples).valid())
    assert torch.equal(online.mapper.grid.logodds, ref.logodds)
    assert not torch.equal(offline.mapper.grid.logodds, ref.logodds), "offline uses every training frame"


def build_virus_grid_like(trainer: Trainer):
    from virus_nerf.grid.virus import VirusGrid

    return VirusGrid(trainer.mapper.grid.spec, trainer.mapper.grid.config)


def test_metrics_record_start_up_and_wall_clock(tiny_office, tmp_path):
    doc = run_training(tiny_office, "office", tmp_path / "run", small_config(max_steps=4), quiet=True)
    t = doc["train"]
    assert 0 < t["startup_s"] < t["wall_s"]
    assert t["seconds"] <= t["wall_s"] - t["startup_s"] + 1e-3, "the training clock excludes start-up"
    assert t["device"] == ("cuda" if torch.cuda.is_available() else "cpu"), "where the steps ran (device auto)"


def test_checkpoint_of_another_scene_box_is_refused(tiny_office, tmp_path):
    rec = load_recording(tiny_office, "office")
    a = Trainer(rec, small_config(max_steps=2), tmp_path, quiet=True)
    a.train_step()
    a.save_checkpoint()
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    state["box"]["hi"][0] += 0.5
    torch.save(state, tmp_path / "moved.pt")
    b = Trainer(rec, small_config(max_steps=2), tmp_path, quiet=True)
    b.load_checkpoint(tmp_path / "checkpoint.pt")  # the same box loads
    with pytest.raises(ValueError, match=r"field 'box': lo=.* does not match this mapper's lo=.*\(was the recording or its map changed\?\)") as exc:
        b.load_checkpoint(tmp_path / "moved.pt")
    assert "np.float64" not in str(exc.value), "the boxes are printed as plain numbers"


def test_checkpoints_load_on_the_cpu_whatever_the_trainer_device(tiny_office, tmp_path):
    """Issue 13, item 3: a checkpoint read with map_location=<the trainer's device> put the saved
    CPU generator state on the GPU, and Generator.set_state refused it (--resume, evaluate and
    export crashed on CUDA). Here a trainer that believes it runs on CUDA loads a checkpoint:
    reading it on the CPU works without a GPU; reading it onto the device fails without one."""
    from virus_nerf.trainer.run_folder import read_checkpoint

    rec = load_recording(tiny_office, "office")
    a = Trainer(rec, small_config(max_steps=2), tmp_path, quiet=True)
    a.train_step()
    a.save_checkpoint()
    b = Trainer(rec, small_config(max_steps=2), tmp_path, quiet=True)
    b.mapper.device = torch.device("cuda")  # what a GPU trainer holds; nothing is moved here
    b.load_checkpoint(tmp_path / "checkpoint.pt")
    assert b.mapper.step == 1
    assert torch.equal(b.mapper.generator.get_state(), a.mapper.generator.get_state())
    assert read_checkpoint(tmp_path / "checkpoint.pt", small_config(max_steps=2))["step"] == 1


def test_start_up_is_not_on_the_training_clock(tiny_office, tmp_path, monkeypatch):
    """Issue 13, item 10: frame decoding (and kernel compilation) used to land in the first timed
    step. A decoding that takes 1000 s (by the training clock's own reading: the clock the mapper
    reads jumps while the frames decode) must not appear in the trainer's seconds. No real time
    is measured, so a busy machine cannot fail it."""
    import time
    import types

    import virus_nerf.engine.mapper as mapper_module
    import virus_nerf.trainer.loop as loop

    real, jump = loop.build_frame_store, [0.0]
    clock = types.SimpleNamespace(perf_counter=lambda: time.perf_counter() + jump[0])

    def slow_decoding(*args, **kwargs):
        jump[0] += 1000.0
        return real(*args, **kwargs)

    monkeypatch.setattr(loop, "build_frame_store", slow_decoding)
    monkeypatch.setattr(mapper_module, "time", clock)
    rec = load_recording(tiny_office, "office")
    trainer = Trainer(rec, small_config(max_steps=2), tmp_path, quiet=True)
    summary = trainer.fit()
    assert summary.steps == 2 and jump[0] == 1000.0
    assert summary.seconds < 1000.0, summary


def test_the_offline_stereo_pass_keeps_the_small_rooms_filters_where_the_line_of_sight_term_trains(tiny_office,
                                                                                                  tmp_path,
                                                                                                  monkeypatch):
    """D112: offline in a fitted box up to weights.free_stereo_room_m (the tiny office's), the
    stereo pass keeps tracks of 3 views and points up to 5 % range uncertainty; in a grown box, in
    a room above the limit, without the term or online it keeps the run's own filters (4 views, 3 %)."""
    from virus_nerf.grid.extent import ExtentConfig
    from virus_nerf.losses.weights import LossWeights
    from virus_nerf.stereo.depth import StereoConfig, small_room_config

    assert small_room_config(StereoConfig()) == dataclasses.replace(StereoConfig(), min_views=3, max_rel_sigma=0.05)
    rec = load_recording(tiny_office, "office")

    def pass_config(**changes) -> StereoConfig:
        return Trainer(rec, small_config(**changes), tmp_path, quiet=True).stereo_config()

    small = pass_config()
    assert (small.min_views, small.max_rel_sigma) == (3, 0.05)
    import virus_nerf.stereo.build as build

    asked = []
    real = build.stereo_depth
    monkeypatch.setattr(build, "stereo_depth", lambda rec, frames, cfg, **k: asked.append(cfg) or real(rec, frames, cfg, **k))
    Trainer(rec, small_config(), tmp_path, quiet=True).prepare()  # the pass `train`, `evaluate` and `export` run
    assert asked == [small]
    for changes in ({"extent": ExtentConfig(mode="grow")}, {"weights": LossWeights(free_stereo_room_m=1.0)},
                    {"weights": LossWeights(free_stereo=0.0)}, {"online": True, "max_steps": None, "max_time": 5.0}):
        assert pass_config(**changes) == StereoConfig()


def test_the_logged_terms_add_up_to_the_logged_loss(tiny_office, tmp_path):
    """train_log.csv gives every term of the loss: in each row, loss = the weights' sum of colour,
    irs, uss, rgbd, stereo and distortion, plus line_of_sight (already weighted). Before, the
    stereo, distortion and free-space terms were left out (a default run's loss 11.4 against
    0.94 from its columns)."""
    import csv

    from virus_nerf.losses import LossWeights

    rec = load_recording(tiny_office, "office")
    weights = dataclasses.replace(LossWeights(), distortion=0.01)  # every term on
    cfg = small_config(max_steps=6, log_every=1, weights=weights)
    Trainer(rec, cfg, tmp_path, quiet=True).fit()
    with (tmp_path / "train_log.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6
    w = cfg.weights
    for row in rows:
        v = {k: float(x) for k, x in row.items()}
        parts = (w.colour * v["colour"] + w.irs * v["irs"] + w.uss * v["uss"] + w.rgbd * v["rgbd"]
                 + w.stereo * v["stereo"] + w.distortion * v["distortion"] + v["line_of_sight"])
        assert v["loss"] == pytest.approx(parts, rel=1e-5)
    assert any(float(r["distortion"]) > 0 for r in rows) and any(float(r["line_of_sight"]) > 0 for r in rows)


def test_a_resumed_run_keeps_the_final_evaluation_scored_after_its_last_checkpoint(tiny_office, tmp_path):
    """`train` scores its final evaluation after the last checkpoint, at the checkpoint's step:
    a resume keeps that point on the curve (a review saw it vanish from metrics_vs_time.csv); a
    point of another step (a killed run's, after the checkpoint) is not taken."""
    from virus_nerf.trainer.run_folder import METRICS_VS_TIME, EvalPoint, write_eval_history

    rec = load_recording(tiny_office, "office")
    run = tmp_path / "run"
    run.mkdir()
    Trainer(rec, small_config(max_steps=6), run, quiet=True).fit()  # checkpoint at step 6
    final = EvalPoint(6, 3.0, 0.5, 0.6, 0.2, 0.3, 2, "map")
    write_eval_history(run / METRICS_VS_TIME, [final, EvalPoint(7, 3.5, 0.4, 0.5, 0.2, 0.3, 2, "map")])
    resumed = Trainer(rec, small_config(max_steps=10), run, quiet=True)
    resumed.load_checkpoint(run / "checkpoint.pt")
    assert resumed.eval_history == [final]
