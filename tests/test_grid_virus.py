"""The Bayesian VIRUS grid (docs/method.md 3.4): sensor model, traversal, eq. 9, warm-up, resume."""

import math

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from virus_nerf.grid.base import GridSpec, GridUpdateBatch, cell_index
from virus_nerf.grid.sensor_model import cells_along_ray, depth_log_odds, nerf_log_odds
from virus_nerf.grid.virus import VirusGrid, VirusGridConfig
from virus_nerf.scene_box import SceneBox

L_INIT = math.log(0.55 / 0.45)
L_PRIOR = math.log(0.49 / 0.51)


def _phi(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


def _reference_increment(a, b, m, cfg: VirusGridConfig) -> float:
    """The sensor-model formula written out independently of the numba kernel."""
    sigma = cfg.std_per_m * m + cfg.std_floor
    s, d = b - a, 0.5 * (a + b)
    p_det = cfg.hit_probability * (1.0 - math.exp(-s / cfg.stop_length))
    n_bar = (_phi((b - m) / sigma) - _phi((a - m) / sigma)) / s
    lam = cfg.false_rate
    ratio = 1.0 - p_det * _phi((m - d) / sigma) + p_det * math.exp(lam * (m - d)) * n_bar / lam
    return max(-cfg.max_increment, min(cfg.max_increment, math.log(ratio)))


def _batch(depth=None, nerf=None) -> GridUpdateBatch:
    """depth = (origins, directions, ranges), nerf = (origins, directions, far); None = no rays."""
    e3, e = torch.zeros(0, 3), torch.zeros(0)
    do, dd, dr = depth if depth is not None else (e3, e3, e)
    no, nd, nf = nerf if nerf is not None else (e3, e3, e)
    return GridUpdateBatch(do, dd, dr, no, nd, nf)


def _config(**changes) -> VirusGridConfig:
    """The grid parameters the hand-computed cases below are laid out for (the values before the
    tuning study: 3 cm/m range noise, 0.3 false detections/m, zeta 0.25, Instant-NGP's alpha 0.01)."""
    earlier = dict(std_per_m=0.03, false_rate=0.3, zeta=0.25, threshold_alpha=0.01, warmup_steps=128,
                   update_interval=16, rays_per_update=1024)
    return VirusGridConfig(**{**earlier, **changes})


def _unit(v) -> torch.Tensor:
    t = torch.tensor(v, dtype=torch.float32)
    return t / t.norm(dim=-1, keepdim=True)


# ---------------------------------------------------------------- Depth-Update
BAR = SceneBox((0.0, 0.0, 0.0), (4.0, 1.0, 1.0))  # 40 x 10 x 10 cells of 0.1 m


def test_depth_update_profile_along_one_ray():
    cfg = _config(max_resolution=40)
    grid = VirusGrid(BAR, cfg)
    assert grid.spec.resolution == (40, 10, 10)
    m = 2.0
    sigma = cfg.std_per_m * m + cfg.std_floor  # 0.08 m: visit up to 2.24 m
    before = grid.logodds.clone()
    grid.depth_update(torch.tensor([[0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([m]))
    change = grid.logodds - before
    row = change[:, 5, 5].double()
    # every cell up to m + 3 sigma, each against the formula; the last one only up to 2.24 m
    for i in range(23):
        a, b = 0.1 * i, min(0.1 * (i + 1), m + 3 * sigma)
        assert row[i].item() == pytest.approx(_reference_increment(a, b, m, cfg), abs=1e-5)
    assert torch.all(row[:17] < 0), "free before the range"
    assert row[0].item() == pytest.approx(math.log(1 - cfg.hit_probability * (1 - math.exp(-5))), abs=1e-5)
    assert row[19].item() > 0 and row[20].item() > 0, "occupied on both sides of m = 2.0 m"
    assert torch.all(row[23:] == 0), "untouched beyond m + 3 sigma"
    assert int(torch.argmax(row)) in (19, 20)
    change[:, 5, 5] = 0
    assert torch.all(change == 0), "no other cell touched"


def test_depth_update_convergence_to_the_clamps():
    cfg = _config(max_resolution=40)
    grid = VirusGrid(BAR, cfg)
    o, d, m = torch.tensor([[0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([2.05])
    for _ in range(30):
        grid.depth_update(o, d, m)
    row = grid.logodds[:, 5, 5]
    assert row[20].item() == 4.0  # the cell holding the hit, [2.0, 2.1]
    assert torch.all(row[:17] == -4.0)  # well before the hit
    assert torch.all(row[24:] == torch.tensor(L_INIT, dtype=torch.float32))  # beyond 2.05 + 3 * 0.0815


def test_depth_update_with_tiny_noise_still_hits_the_peak_cell():
    # sigma far below the cell size: the segment-averaged Gaussian still finds the peak (docs/method.md 9.4)
    cfg = _config(max_resolution=40, std_per_m=0.0, std_floor=0.002)
    grid = VirusGrid(BAR, cfg)
    before = grid.logodds.clone()
    grid.depth_update(torch.tensor([[0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([1.234]))
    row = (grid.logodds - before)[:, 5, 5]
    assert row[12].item() == pytest.approx(cfg.max_increment)
    assert torch.all(row[:12] < 0) and torch.all(row[13:] == 0)


def test_depth_log_odds_is_unimodal_in_distance():
    cfg = _config()
    for m in (0.3, 1.0, 2.5, 4.0):
        starts = np.arange(0.0, m + 0.3, 0.01)
        inc = [depth_log_odds(a, a + 0.05, m, cfg.std_per_m * m + cfg.std_floor, cfg.false_rate,
                              cfg.hit_probability, cfg.stop_length, 50.0) for a in starts]
        k = int(np.argmax(inc))
        assert abs(starts[k] + 0.025 - m) < 0.03
        assert np.all(np.diff(inc[: k + 1]) >= -1e-12) and np.all(np.diff(inc[k:]) <= 1e-12)
        assert min(inc) >= math.log(1 - cfg.hit_probability) - 1e-12


def test_traversal_visits_a_gapless_chain_of_every_crossed_cell():
    grid = VirusGrid(SceneBox((0.0, 0.0, 0.0), (2.0, 1.5, 1.0)), _config(max_resolution=20))
    spec = grid.spec  # 20 x 15 x 10 cells of 0.1 m
    o = np.array([0.03, 0.07, 0.11])
    d = np.array([1.0, 0.73, 0.41])
    d /= np.linalg.norm(d)
    cells, a, b = cells_along_ray(spec, o, d, t_end=10.0)
    t_exit = min((np.array([2.0, 1.5, 1.0]) - o) / d)
    assert a[0] == 0.0 and b[-1] == pytest.approx(t_exit)
    assert np.array_equal(a[1:], b[:-1]), "segments tile the ray"
    res = np.array(spec.resolution)
    ijk = np.stack(np.unravel_index(cells, res), axis=-1)
    steps = np.abs(np.diff(ijk, axis=0)).sum(axis=-1)
    assert np.all(steps == 1), "consecutive cells share a face"
    u0 = np.floor(o / 0.1)
    u1 = np.floor((o + d * (t_exit - 1e-9)) / 0.1)
    assert len(cells) == 1 + int(np.abs(u1 - u0).sum()) == len(set(cells.tolist()))
    mids = torch.from_numpy(o + d * ((a + b) / 2)[:, None])
    assert torch.equal(cell_index(mids, spec), torch.from_numpy(cells)), "the marcher's formula"


def test_traversal_of_a_ray_from_outside_starts_at_the_box():
    spec = VirusGrid(SceneBox((0.0, 0.0, 0.0), (2.0, 1.5, 1.0)), _config(max_resolution=20)).spec
    cells, a, b = cells_along_ray(spec, [-1.0, 0.52, 0.47], [1.0, 0.1, 0.0], t_end=100.0)
    assert a[0] == pytest.approx(math.sqrt(1.01))
    assert len(cells) == 20 + 1  # x crosses 20 cells, y one boundary (0.52 -> 0.72)
    assert len(cells_along_ray(spec, [-1.0, 0.5, 0.5], [-1.0, 0.0, 0.0], t_end=100.0)[0]) == 0


@settings(max_examples=150, deadline=None, derandomize=True)  # the same rays on every machine
@given(origin=st.tuples(*[st.floats(-1.0, 3.0) for _ in range(3)]),
       direction=st.tuples(*[st.sampled_from([0.0, 1.0, -1.0]) | st.floats(-1.0, 1.0) for _ in range(3)]),
       t_start=st.floats(0.0, 1.0), length=st.floats(0.0, 4.0))
@example(origin=(0.0, 0.0, 1.0), direction=(0.0, 0.0, -1.0), t_start=1.0, length=1.0)  # touches a corner at t_start
def test_traversal_against_dense_sampling_of_random_rays(origin, direction, t_start, length):
    """Random rays (inside or outside the box, negative, axis-parallel, grazing) against a dense
    reference: the ray's points from t_start to t_end sampled every 0.1 mm and named by the
    marcher's cell formula. The segments tile the part of [t_start, t_end] inside the box, each
    cell once and named by the formula at every sample strictly inside its segment, and every
    sampled cell is among them (a cell crossed for less than a sample step may be missed by the
    samples, not by the traversal)."""
    d = np.array(direction)
    if np.linalg.norm(d) < 1e-3:
        return
    d /= np.linalg.norm(d)
    o, box_hi = np.array(origin), np.array([2.0, 1.5, 1.0])
    spec = VirusGrid(SceneBox((0.0, 0.0, 0.0), tuple(box_hi)), _config(max_resolution=20)).spec
    t_end = t_start + length
    cells, a, b = cells_along_ray(spec, o, d, t_end=t_end, t_start=t_start)
    t = np.arange(t_start, t_end, 1e-4)
    p = o + t[:, None] * d
    named = cell_index(torch.from_numpy(p), spec).numpy()  # -1 outside (a face at lo is inside)
    inside = named >= 0
    sampled = named[inside]
    assert len(set(cells.tolist())) == len(cells) and np.all(cells >= 0)
    if len(cells):
        assert set(sampled.tolist()) <= set(cells.tolist())
        assert np.array_equal(a[1:], b[:-1]) and np.all(b > a), "contiguous, non-empty segments"
        assert a[0] >= t_start - 1e-12 and b[-1] <= t_end + 1e-12
        assert a[0] == pytest.approx(t[inside][0], abs=2e-4) and b[-1] == pytest.approx(t[inside][-1], abs=2e-4)
        for cell, lo_t, hi_t in zip(cells, a, b, strict=True):
            ts = t[(t > lo_t + 1e-9) & (t < hi_t - 1e-9)]
            if len(ts):
                assert np.all(cell_index(torch.from_numpy(o + ts[:, None] * d), spec).numpy() == cell)
    else:
        assert inside.sum() <= 2, "no segment: the ray misses the box (or touches it for a sample: zero length)"


@settings(max_examples=60, deadline=None, derandomize=True)
@given(origin=st.tuples(st.floats(0.05, 1.95), st.floats(0.05, 1.45), st.floats(0.05, 0.95)),
       direction=st.tuples(*[st.sampled_from([0.0, 1.0, -1.0]) | st.floats(-1.0, 1.0) for _ in range(3)]),
       measured=st.floats(0.05, 2.5))
def test_depth_update_of_a_random_ray_is_the_formula_in_each_crossed_cell(origin, direction, measured):
    """The numba Depth-Update of one ray (any direction, from anywhere in the box) against the
    sensor-model formula written out here (`_reference_increment`), cell by cell along the ray's
    traversal up to m + 3 sigma, clamped to the log-odds bounds; no other cell changes."""
    d = np.array(direction)
    if np.linalg.norm(d) < 1e-3:
        return
    d /= np.linalg.norm(d)
    cfg = _config(max_resolution=20)
    grid = VirusGrid(SceneBox((0.0, 0.0, 0.0), (2.0, 1.5, 1.0)), cfg)
    before = grid.logodds.clone().double()
    grid.depth_update(torch.tensor([origin]), torch.from_numpy(d[None]).float(), torch.tensor([measured]))
    change = (grid.logodds.double() - before).reshape(-1)
    sigma = cfg.std_per_m * measured + cfg.std_floor
    o32, d32 = np.float32(origin).astype(np.float64), torch.from_numpy(d[None]).float()[0].double().numpy()
    d32 /= np.linalg.norm(d32)
    cells, a, b = cells_along_ray(grid.spec, o32, d32, t_end=measured + 3 * sigma)
    expected = torch.zeros_like(change)
    for cell, lo_t, hi_t in zip(cells, a, b, strict=True):
        if hi_t - lo_t > 1e-9:
            inc = _reference_increment(lo_t, hi_t, measured, cfg)
            after = min(cfg.logodds_max, max(cfg.logodds_min, before.reshape(-1)[cell].item() + inc))
            expected[cell] = after - before.reshape(-1)[cell].item()
    np.testing.assert_allclose(change.numpy(), expected.numpy(), atol=2e-5)


def test_marcher_reads_the_cell_the_depth_update_writes():
    cfg = _config()
    grid = VirusGrid(SceneBox((0.0, 0.0, 0.0), (9.0, 8.0, 2.6)), cfg)  # 128 x 114 x 37
    o = torch.tensor([[1.0, 1.2, 0.9]])
    d = _unit([[0.83, 0.51, 0.13]])
    m = 3.1
    g = torch.Generator().manual_seed(0)
    for k in range(4):
        grid.update(cfg.warmup_steps + 16 * k, None, _batch(depth=(o, d, torch.tensor([m]))), g)
    occ = grid.occupied.reshape(-1)
    hit = cell_index(o + d * m, grid.spec)
    assert occ[hit].item(), "the cell the marcher looks up at the measured point is occupied"
    assert not occ[cell_index(o + d * (m / 2), grid.spec)].item()
    centres = grid.spec.cell_centers()[occ]
    dist = (centres - (o + d * m)).norm(dim=-1)
    sigma = cfg.std_per_m * m + cfg.std_floor
    assert 1 <= occ.sum() <= 20 and torch.all(dist < 3 * sigma + 0.07 * math.sqrt(3))


# ----------------------------------------------------------------- NeRF-Update
CUBE = SceneBox((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))  # 10^3 cells of 0.1 m


def test_eq9_increment_sign_and_value():
    s = np.array([2.0, 2.0 * math.e, 2.0 / math.e, 0.0])
    inc = nerf_log_odds(s, 2.0, zeta=0.5, max_increment=10.0, sigma_floor=1e-6)
    assert inc[0] == 0.0
    assert inc[1] == pytest.approx(0.5)
    assert inc[2] == pytest.approx(-0.5)
    assert inc[3] == pytest.approx(max(-10.0, 0.5 * math.log(1e-6 / 2.0)))


def test_nerf_update_hand_computed_bayes_step_then_clamp():
    cfg = _config(max_resolution=10, pos_noise_per_m=0.0)
    grid = VirusGrid(CUBE, cfg)
    rays = (torch.tensor([[0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([1.0]))
    g = torch.Generator().manual_seed(1)
    grid.nerf_update(lambda p: torch.full((p.shape[0],), 10.0), *rays, g)
    # sigma_T = min(sigma_T_max, mean = 10) = -ln(0.99) / 0.01 = 1.005 /m
    sigma_t = -math.log(0.99) / 0.01
    expected = L_INIT + 0.25 * math.log(10.0 / sigma_t)
    touched = grid.logodds != torch.tensor(L_INIT, dtype=torch.float32)
    assert touched[:, 5, 5].sum() >= 5 and touched.sum() == touched[:, 5, 5].sum()
    assert torch.allclose(grid.logodds[touched], torch.tensor(expected, dtype=torch.float32))
    for _ in range(30):
        grid.nerf_update(lambda p: torch.full((p.shape[0],), 10.0), *rays, g)
    assert torch.all(grid.logodds[:, 5, 5] == 4.0), "l + increment is clamped at the upper bound"


def test_nerf_update_at_threshold_changes_nothing_and_splits_above_below():
    cfg = _config(max_resolution=10, pos_noise_per_m=0.0, nerf_points_per_ray=64)
    o = torch.tensor([[0.0, y, z] for y in (0.15, 0.55, 0.85) for z in (0.25, 0.65)])
    rays = (o, torch.tensor([[1.0, 0.0, 0.0]]).expand(6, 3), torch.full((6,), 1.0))
    g = torch.Generator().manual_seed(2)
    grid = VirusGrid(CUBE, cfg)
    grid.nerf_update(lambda p: torch.full((p.shape[0],), 0.5), *rays, g)  # sigma_T = mean = 0.5
    assert torch.all(grid.logodds == torch.tensor(L_INIT, dtype=torch.float32))
    # dense for x > 0.5, thin before: sigma_T = sigma_T_max; raised behind, lowered in front
    grid.nerf_update(lambda p: torch.where(p[:, 0] > 0.5, 50.0, 0.02), *rays, g)
    assert grid.last_nerf_update.sigma_threshold == pytest.approx(-math.log(0.99) / 0.01)
    rows = grid.logodds[:, [1, 5, 8]][:, :, [2, 6]]
    assert torch.all(rows[5:] > L_INIT) and torch.all(rows[:5] < L_INIT)


# --------------------------------------------------------------------- warm-up
def test_untouched_cells_empty_after_warmup_counted_in_steps():
    cfg = _config(max_resolution=8, update_interval=16, warmup_steps=256)
    g = torch.Generator().manual_seed(0)
    every = VirusGrid(CUBE, cfg)
    for step in range(0, 257, 16):
        every.update(step, None, None, g)
        if step == 128:
            assert every.occupied.all(), "still marched in the middle of the warm-up"
    once = VirusGrid(CUBE, cfg)
    once.update(256, None, None, g)
    for grid in (every, once):
        assert not grid.occupied.any()
        assert torch.allclose(grid.logodds, torch.tensor(L_PRIOR, dtype=torch.float32), atol=1e-6)


def test_the_warmup_lasts_warmup_steps_driving_while_frames_keep_arriving():
    # 0.55 -> 0.49 over 100 steps offline, over 300 while driving; untouched cells only
    cfg = _config(max_resolution=8, update_interval=10, warmup_steps=100, warmup_steps_driving=300)
    g = torch.Generator().manual_seed(0)
    l_init, l_prior = math.log(0.55 / 0.45), math.log(0.49 / 0.51)
    offline, driving = VirusGrid(CUBE, cfg), VirusGrid(CUBE, cfg)
    offline.update(60, None, None, g)
    driving.update(60, None, None, g, driving=True)
    assert torch.allclose(offline.logodds, torch.tensor(l_init + 0.6 * (l_prior - l_init)), atol=1e-6)
    assert torch.allclose(driving.logodds, torch.tensor(l_init + 0.2 * (l_prior - l_init)), atol=1e-6)
    driving.update(150, None, None, g, driving=True)
    assert driving.occupied.all(), "still marched halfway through the driving warm-up"
    driving.update(150, None, None, g, driving=False)  # the switch moves every cell to the offline offset
    assert torch.allclose(driving.logodds, torch.tensor(l_prior), atol=1e-6)


def test_a_column_first_seen_while_driving_restarts_its_warmup_from_p_init():
    # warm-up 100 steps while driving; column (2, 3) is first looked at at step 100, when every
    # cell is already at the prior: it goes back to p_init and decays again over the next 100
    # steps, evidence kept; a column in view at step 0 follows the run's clock; hand-computed
    cfg = _config(max_resolution=8, update_interval=10, warmup_steps_driving=100, warmup_restart="view")
    g = torch.Generator().manual_seed(0)
    grid = VirusGrid(CUBE, cfg)
    seen_at_start = np.zeros((8, 8), dtype=bool)
    seen_at_start[0, 0] = True
    assert grid.restart_warmup_in_view(seen_at_start, 0) == 0  # frames there from the start: the run's clock
    grid.update(100, None, None, g, driving=True)
    assert torch.allclose(grid.logodds, torch.tensor(L_PRIOR), atol=1e-6)
    with torch.no_grad():
        grid.logodds[2, 3, 5] += 1.0  # evidence in the column, kept through the restart
    late = np.zeros((8, 8), dtype=bool)
    late[2, 3] = late[0, 0] = True
    assert grid.restart_warmup_in_view(late, 100) == 1  # (0, 0) was seen before: not restarted
    grid.update(100, None, None, g, driving=True)
    col = grid.logodds[2, 3].clone()
    assert torch.allclose(col[[0, 1, 2, 3, 4, 6, 7]], torch.tensor(L_INIT), atol=1e-6)
    assert col[5] == pytest.approx(L_INIT + 1.0, abs=1e-6)
    assert torch.allclose(grid.logodds[0, 0], torch.tensor(L_PRIOR), atol=1e-6)
    assert grid.occupied[2, 3].all() and grid.warmup_done  # the run's clock is done; the column runs its own
    grid.update(150, None, None, g, driving=True)  # half of its own warm-up
    assert grid.logodds[2, 3, 0] == pytest.approx(L_INIT + 0.5 * (L_PRIOR - L_INIT), abs=1e-6)
    assert grid.logodds[4, 4, 4] == pytest.approx(L_PRIOR, abs=1e-6)
    state = grid.state_dict()
    again = VirusGrid(CUBE, cfg)
    again.load_state_dict(state)
    for g_ in (grid, again):
        g_.update(200, None, None, g, driving=True)
        assert g_.logodds[2, 3, 0] == pytest.approx(L_PRIOR, abs=1e-6)
        assert g_.logodds[2, 3, 5] == pytest.approx(L_PRIOR + 1.0, abs=1e-6)
        assert g_.warmup_done


def test_grown_columns_start_unseen_and_restart_when_looked_at():
    cfg = _config(max_resolution=8, warmup_steps_driving=100, warmup_restart="view")
    g = torch.Generator().manual_seed(0)
    grid = VirusGrid(GridSpec.from_cell(SceneBox((0, 0, 0), (0.8, 0.8, 0.8)), 0.1), cfg)
    grid.restart_warmup_in_view(np.ones((8, 8), dtype=bool), 0)
    grid.update(100, None, None, g, driving=True)
    grid.grow(SceneBox((0, 0, 0), (1.2, 0.8, 0.8)))  # four new columns of x
    assert grid.logodds.shape == (12, 8, 8)
    assert torch.allclose(grid.logodds, torch.tensor(L_PRIOR), atol=1e-6), "new cells: the run's clock"
    view = np.zeros((12, 8), dtype=bool)
    view[5:, :] = True  # the old columns 5..7 were seen; 8..11 are new
    assert grid.restart_warmup_in_view(view, 120) == 4 * 8
    grid.update(120, None, None, g, driving=True)
    assert torch.allclose(grid.logodds[8:], torch.tensor(L_INIT), atol=1e-6)
    assert torch.allclose(grid.logodds[:8], torch.tensor(L_PRIOR), atol=1e-6)


def test_evidence_holds_a_cell_up_through_the_warmup():
    cfg = _config(max_resolution=40, warmup_steps=256)
    grid = VirusGrid(BAR, cfg)
    g = torch.Generator().manual_seed(0)
    depth = (torch.tensor([[0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([2.05]))
    grid.update(16, None, _batch(depth=depth), g)
    grid.update(400, None, None, g)
    occ = grid.occupied
    assert occ[20, 5, 5], "the hit cell stays occupied"
    assert occ.sum() == occ[17:24, 5, 5].sum() >= 2, "only cells around the hit survive"
    assert not occ[:17].any(), "free and untouched cells end empty"


# ------------------------------------------------------ sensor sets and resume
def _mixed_batch(gen: torch.Generator) -> GridUpdateBatch:
    n = 40
    o = torch.rand(n, 3, generator=gen) * 0.5 + 0.25
    d = _unit(torch.randn(n, 3, generator=gen).tolist())
    return GridUpdateBatch(o, d, 0.1 + torch.rand(n, generator=gen) * 0.5, o.clone(), d.clone(), torch.full((n,), 1.5))


def _density(p: torch.Tensor) -> torch.Tensor:
    return torch.exp(4.0 * (p[:, 0] - 0.5))


def test_camera_only_and_depth_only_batches_run():
    cfg = _config(max_resolution=10, rays_per_update=32)
    b = _mixed_batch(torch.Generator().manual_seed(3))
    camera_only = _batch(nerf=(b.nerf_origins, b.nerf_directions, b.nerf_far))
    depth_only = _batch(depth=(b.depth_origins, b.depth_directions, b.depth_ranges))
    g = torch.Generator().manual_seed(0)
    for batch, fn in ((camera_only, _density), (depth_only, _density), (depth_only, None), (None, _density), (_batch(), _density)):
        grid = VirusGrid(CUBE, cfg)
        grid.update(0, fn, batch, g)
        assert torch.isfinite(grid.logodds).all()
    grid = VirusGrid(CUBE, cfg)
    grid.update(0, _density, camera_only, g)
    assert grid.last_nerf_update.n_drawn == 32 * cfg.nerf_points_per_ray, "whole budget to NeRF-Update"


def test_state_round_trip_and_resume_are_exact():
    cfg = _config(max_resolution=12, rays_per_update=32)
    data = _mixed_batch(torch.Generator().manual_seed(4))
    a = VirusGrid(CUBE, cfg)
    ga = torch.Generator().manual_seed(5)
    for step in (0, 16, 32):
        a.update(step, _density, data, ga)
    b = VirusGrid(CUBE, cfg)
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.logodds, b.logodds)
    gb = torch.Generator()
    gb.set_state(ga.get_state())
    for step in (48, 64, 300):
        a.update(step, _density, data, ga)
        b.update(step, _density, data, gb)
    assert torch.equal(a.logodds, b.logodds)
    assert a.state_dict()["decay_applied"] == b.state_dict()["decay_applied"]
    with pytest.raises(ValueError, match="logodds"):
        VirusGrid(CUBE, _config(max_resolution=8)).load_state_dict(a.state_dict())


def test_bad_config_and_bad_rays_are_clear_errors():
    with pytest.raises(ValueError, match="hit_probability"):
        _config(hit_probability=1.0)
    grid = VirusGrid(CUBE, _config(max_resolution=4))
    with pytest.raises(ValueError, match="depth rays"):
        grid.depth_update(torch.zeros(2, 3), torch.ones(3, 3), torch.ones(2))


def test_grid_over_a_given_spec_matches_the_box_constructor():
    cfg = _config(max_resolution=16)
    a = VirusGrid(BAR, cfg)
    b = VirusGrid(GridSpec.from_box(BAR, 16), cfg, device="cpu")
    assert a.spec == b.spec and b.occupied.device == torch.device("cpu")
    assert b.occupied.shape == (16, 4, 4) and b.occupied.all()


# ------------------------------------------------- start-up prior, NaN guard, forward source
def test_initialise_from_sensor_rays_is_one_depth_update_per_ray():
    from virus_nerf.grid.base import SensorRays

    cfg = _config(max_resolution=40)
    rays = SensorRays(torch.tensor([[0.0, 0.55, 0.55], [0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]] * 2),
                      torch.tensor([2.05, float("nan")]))
    grid = VirusGrid(BAR, cfg)
    assert grid.initialise(rays.valid()) > 0
    ref = VirusGrid(BAR, cfg)
    ref.depth_update(rays.origins[:1], rays.directions[:1], rays.ranges[:1])
    assert torch.equal(grid.logodds, ref.logodds)
    # the hand-computed profile: free in front (one pass ln(1 - p_det)), occupied at the return
    assert grid.logodds[5, 5, 5] == pytest.approx(L_INIT + _reference_increment(0.5, 0.6, 2.05, cfg), abs=1e-6)
    assert grid.logodds[20, 5, 5] > L_INIT > grid.logodds[10, 5, 5]
    # the paper's plain warm-up ignores the prior
    plain = VirusGrid(BAR, _config(max_resolution=40, init="none"))
    assert plain.initialise(rays.valid()) == 0
    assert torch.all(plain.logodds == torch.tensor(L_INIT, dtype=torch.float32))


def test_nan_densities_never_reach_a_cell():
    cfg = _config(max_resolution=10, pos_noise_per_m=0.0)
    rays = (torch.tensor([[0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([1.0]))
    grid = VirusGrid(CUBE, cfg)
    # NaN in the first half of the ray, 10 /m behind: only the dense half moves, by eq. 9 exactly
    grid.nerf_update(lambda p: torch.where(p[:, 0] < 0.5, float("nan"), 10.0), *rays, torch.Generator().manual_seed(1))
    assert torch.isfinite(grid.logodds).all()
    assert torch.all(grid.logodds[:5] == torch.tensor(L_INIT, dtype=torch.float32))
    sigma_t = -math.log(0.99) / 0.01  # min(sigma_T_max, mean of the finite densities = 10)
    moved = grid.logodds[5:, 5, 5]
    assert torch.allclose(moved, torch.tensor(L_INIT + 0.25 * math.log(10.0 / sigma_t), dtype=torch.float32))
    # all NaN: nothing changes at all
    before = grid.logodds.clone()
    grid.nerf_update(lambda p: torch.full((p.shape[0],), float("nan")), *rays, torch.Generator().manual_seed(2))
    assert torch.equal(grid.logodds, before)


def test_forward_samples_update_the_cells_they_lie_in():
    cfg = _config(max_resolution=10, nerf_update_source="forward")
    grid = VirusGrid(CUBE, cfg)
    pts = torch.tensor([[0.15, 0.15, 0.15], [0.16, 0.12, 0.18], [0.85, 0.85, 0.85], [2.0, 0.5, 0.5]])
    sigma = torch.tensor([100.0, 1.0, 0.001, 50.0])  # the last point is outside the box
    batch = GridUpdateBatch(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0), torch.zeros(1, 3),
                            torch.tensor([[1.0, 0.0, 0.0]]), torch.ones(1), forward_points=pts, forward_sigma=sigma)
    grid.update(0, None, batch, torch.Generator().manual_seed(0))
    sigma_t = min(-math.log(0.99) / 0.01, (100.0 + 1.0 + 0.001) / 3)
    inc = [max(-2.0, min(2.0, 0.25 * math.log(s / sigma_t))) for s in (100.0, 1.0, 0.001)]
    assert grid.logodds[1, 1, 1].item() == pytest.approx(L_INIT + (inc[0] + inc[1]) / 2, abs=1e-6)
    assert grid.logodds[8, 8, 8].item() == pytest.approx(L_INIT + inc[2], abs=1e-6)
    assert (grid.logodds != torch.tensor(L_INIT, dtype=torch.float32)).sum() == 2


def test_nan_forward_densities_never_reach_a_cell():
    """Issue 13, item 4, on the default path (NeRF-Update from the forward pass's densities): a
    NaN density is dropped, it neither poisons its cell nor drags the mean threshold."""
    grid = VirusGrid(CUBE, _config(max_resolution=10, nerf_update_source="forward"))
    pts = torch.tensor([[0.15, 0.15, 0.15], [0.16, 0.12, 0.18], [0.85, 0.85, 0.85]])
    info = grid.nerf_update_from_samples(pts, torch.tensor([float("nan"), 100.0, float("nan")]))
    assert torch.isfinite(grid.logodds).all()
    assert info.n_points == 1
    sigma_t = min(-math.log(0.99) / 0.01, 100.0)
    assert grid.logodds[1, 1, 1].item() == pytest.approx(L_INIT + 0.25 * math.log(100.0 / sigma_t), abs=1e-6)
    assert grid.logodds[8, 8, 8].item() == pytest.approx(L_INIT)  # only NaN there: untouched


def test_surface_points_raise_their_cells_once_by_the_increment_and_clamp():
    """D84: the stereo's triangulated points are surfaces for the grid. CUBE's 0.1 m cells: three
    points in cell (2, 3, 4), one in (7, 7, 7), one outside the box and a NaN; two cells raised
    by stereo_point_increment (1.5) once each, the rest at l_init; a second call adds again and
    clamps at logodds_max; increment 0 raises nothing."""
    grid = VirusGrid(CUBE, _config(max_resolution=10, stereo_point_increment=1.5))
    points = np.array([[0.21, 0.31, 0.41], [0.25, 0.35, 0.45], [0.29, 0.39, 0.49], [0.75, 0.75, 0.75],
                       [1.5, 0.5, 0.5], [np.nan, 0.5, 0.5]])
    assert grid.surface_points(points) == 2
    raised = torch.full(grid.logodds.shape, L_INIT, dtype=torch.float32)
    raised[2, 3, 4] = raised[7, 7, 7] = L_INIT + 1.5
    assert torch.allclose(grid.logodds, raised)
    assert bool(grid.occupied[2, 3, 4]) and bool(grid.occupied[0, 0, 0])  # p_init is marched too
    for _ in range(3):
        grid.surface_points(points[:1])
    assert grid.logodds[2, 3, 4] == pytest.approx(4.0) and grid.logodds[7, 7, 7] == pytest.approx(L_INIT + 1.5)
    none = VirusGrid(CUBE, _config(max_resolution=10, stereo_point_increment=0.0))
    assert none.surface_points(points) == 0 and torch.all(none.logodds == torch.tensor(L_INIT, dtype=torch.float32))
