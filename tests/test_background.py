"""The learned colour beyond the box (field/background.py): values by hand, the azimuth seam,
and a ray through empty space that renders the background and trains it."""

import math

import pytest
import torch

from virus_nerf.field.background import DirectionalBackground
from virus_nerf.render.compositing import composite
from virus_nerf.render.samples import PackedSamples


def _direction(azimuth_deg: float, elevation_deg: float) -> torch.Tensor:
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return torch.tensor([[math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]])


def test_bin_centres_and_the_azimuth_seam():
    bg = DirectionalBackground(n_azimuth=4, n_elevation=2)  # 90 deg x 90 deg bins
    with torch.no_grad():
        bg.logits.zero_()
        bg.logits[0, :, 1, 0] = torch.tensor([2.0, 0.0, -2.0])  # elevation 0..90, azimuth -180..-90
        bg.logits[0, :, 1, 3] = torch.tensor([-2.0, 0.0, 2.0])  # elevation 0..90, azimuth 90..180
        bg.logits[0, :, 1, 1:3] = 1.0  # elevation 0..90, azimuth -90..90
    # the centre of bin (1, 0): azimuth -135 deg, elevation 45 deg -> exactly its colour
    centre = bg(_direction(-135.0, 45.0))[0]
    torch.testing.assert_close(centre, torch.sigmoid(torch.tensor([2.0, 0.0, -2.0])))
    # azimuth 180 deg lies halfway between the last column's centre (135) and the first's (-135)
    seam = bg(_direction(180.0, 45.0))[0]
    torch.testing.assert_close(seam, torch.full((3,), 0.5))  # mean of the logits (+-2): 0
    # a quarter of the way from column 3's centre (135 deg) to column 0's (225 deg): 3/4 of one, 1/4 of the other
    quarter = bg(_direction(157.5, 45.0))[0]
    torch.testing.assert_close(quarter, torch.sigmoid(torch.tensor([-1.0, 0.0, 1.0])), atol=1e-6, rtol=0)
    # straight up (azimuth 0, between columns 1 and 2) reads the top row alone (border), not row 0
    up = bg(torch.tensor([[1e-9, 0.0, 1.0]]))[0]
    torch.testing.assert_close(up, torch.sigmoid(torch.ones(3)), atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_an_empty_ray_renders_and_trains_the_background(backend):
    """One ray with no samples (it leaves the box at once) and one ray with an opaque sample:
    the first's colour is the background's, the second's the sample's; the colour loss's
    gradient reaches the background's table through the empty ray only."""
    bg = DirectionalBackground(n_azimuth=8, n_elevation=4)
    dirs = torch.cat([_direction(22.5, 22.5), _direction(-157.5, -22.5)])  # two bin centres
    samples = PackedSamples(ray_indices=torch.tensor([1]), t_starts=torch.tensor([1.0]), t_ends=torch.tensor([2.0]),
                            ray_offsets=torch.tensor([0, 0, 1]))
    sigma = torch.tensor([50.0])  # opacity 1 - e^-50
    rgb = torch.tensor([[0.2, 0.4, 0.6]])
    out = composite(sigma, rgb, samples, n_rays=2, background=bg(dirs), backend=backend)
    torch.testing.assert_close(out.rgb[0], torch.full((3,), 0.5))  # logits 0: grey
    torch.testing.assert_close(out.rgb[1], rgb[0], atol=1e-6, rtol=0)
    loss = ((out.rgb - torch.tensor([[1.0, 0.0, 0.0], [0.2, 0.4, 0.6]])) ** 2).sum()
    loss.backward()
    grad = bg.logits.grad[0]  # (3, 4, 8)
    # d loss / d logit at the empty ray's bin (row 2, column 4): 2 (0.5 - target) * sigmoid' (0.25)
    torch.testing.assert_close(grad[:, 2, 4], torch.tensor([-0.25, 0.25, 0.25]))
    assert grad.abs().sum() == pytest.approx(0.75, abs=1e-4)  # nowhere else (the opaque ray: e^-50)
