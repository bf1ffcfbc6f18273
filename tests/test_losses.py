"""Losses (docs/method.md 3.2): known values, masking, NaN safety, gradients only where they belong."""

import math

import pytest
import torch

from virus_nerf.losses import LossTerms, LossWeights, colour_loss, depth_loss, total_loss, uss_loss

NAN = float("nan")


def test_colour_loss_is_zero_for_perfect_prediction():
    rgb = torch.rand(5, 3)
    assert colour_loss(rgb.clone(), rgb).item() == 0.0


def test_colour_loss_known_value_and_mask():
    pred = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
    target = torch.zeros(3, 3)
    # mean over rays and channels: (0 + 1 + 0.25) / 3
    assert colour_loss(pred, target).item() == pytest.approx(1.25 / 3)
    assert colour_loss(pred, target, torch.tensor([True, False, False])).item() == 0.0
    assert colour_loss(pred, target, torch.tensor([False, True, True])).item() == pytest.approx(0.625)


def test_colour_loss_all_masked_is_zero_with_zero_gradient():
    pred = torch.rand(4, 3, requires_grad=True)
    loss = colour_loss(pred, torch.rand(4, 3), torch.zeros(4, dtype=torch.bool))
    loss.backward()
    assert loss.item() == 0.0
    assert torch.equal(pred.grad, torch.zeros(4, 3))


def test_depth_loss_ignores_nan_rays_and_matches_hand_value():
    pred = torch.tensor([1.0, 2.0, 3.0, 4.0], requires_grad=True)
    target = torch.tensor([1.5, NAN, 2.0, NAN])
    loss = depth_loss(pred, target)
    assert loss.item() == pytest.approx((0.25 + 1.0) / 2)  # mean over the 2 valid rays
    loss.backward()
    # d/dD (D - t)^2 / 2 = (D - t): -0.5 and +1.0 on valid rays, exactly 0 on NaN rays
    assert torch.allclose(pred.grad, torch.tensor([-0.5, 0.0, 1.0, 0.0]))


def test_depth_loss_perfect_is_zero():
    d = torch.tensor([0.5, 1.0, NAN])
    assert depth_loss(torch.tensor([0.5, 1.0, 7.0]), d).item() == 0.0


def test_depth_loss_no_valid_ray_is_exactly_zero_and_gradient_is_zero():
    pred = torch.tensor([1.0, 2.0], requires_grad=True)
    loss = depth_loss(pred, torch.tensor([NAN, NAN]))
    loss.backward()
    assert loss.item() == 0.0 and not math.isnan(loss.item())
    assert torch.equal(pred.grad, torch.zeros(2))


def test_uss_loss_zero_when_everything_renders_beyond_or_within_eps():
    echo = torch.tensor([2.0, 2.0, 1.0, NAN])
    pred = torch.tensor([2.5, 1.98, 0.971, 0.1])  # beyond, within eps (0.03), within eps, no echo
    assert uss_loss(pred, echo).item() == 0.0


def test_uss_loss_hand_value_and_gradient_only_on_violating_rays():
    pred = torch.tensor([1.0, 2.0, 0.5, 3.0, 1.9], requires_grad=True)
    echo = torch.tensor([2.0, 2.0, NAN, 3.02, 2.0])
    # valid echoes: rays 0, 1, 3, 4 (4 rays). In front by more than eps: ray 0 (1.0 < 1.97) and
    # ray 4 (1.9 < 1.97). Ray 3 is 2 cm short, inside eps. Loss = (1 + 0.01) / 4.
    loss = uss_loss(pred, echo, eps=0.03)
    assert loss.item() == pytest.approx(1.01 / 4)
    loss.backward()
    expected = torch.tensor([2 * (1.0 - 2.0) / 4, 0.0, 0.0, 0.0, 2 * (1.9 - 2.0) / 4])
    assert torch.allclose(pred.grad, expected)


def test_uss_loss_no_echo_anywhere_is_exactly_zero():
    pred = torch.tensor([0.1, 0.2], requires_grad=True)
    loss = uss_loss(pred, torch.tensor([NAN, NAN]))
    loss.backward()
    assert loss.item() == 0.0
    assert torch.equal(pred.grad, torch.zeros(2))


def test_loss_shape_mismatch_is_a_clear_error():
    with pytest.raises(ValueError, match="depth_loss"):
        depth_loss(torch.zeros(3), torch.zeros(4))
    with pytest.raises(ValueError, match="colour_loss"):
        colour_loss(torch.zeros(3, 3), torch.zeros(3, 4))


def test_total_loss_weights_each_term_and_skips_absent_sensors():
    pred_rgb = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    target_rgb = torch.zeros(2, 3)  # colour loss 0.5
    pred_depth = torch.tensor([1.0, 3.0], requires_grad=True)
    irs = torch.tensor([2.0, NAN])  # 1.0
    uss = torch.tensor([NAN, 4.0])  # (3 - 4)^2 / 1 = 1.0
    rgbd = torch.tensor([1.0, 1.0])  # (0 + 4) / 2 = 2.0
    w = LossWeights(colour=1.0, irs=0.5, uss=0.25, rgbd=2.0)
    terms = total_loss(w, pred_rgb, target_rgb, pred_depth, irs, uss, rgbd)
    assert isinstance(terms, LossTerms)
    assert terms.as_floats() == pytest.approx(
        {"colour": 0.5, "irs": 1.0, "uss": 1.0, "rgbd": 2.0, "stereo": 0.0, "distortion": 0.0, "line_of_sight": 0.0,
         "total": 0.5 + 0.5 + 0.25 + 4.0}
    )
    camera_only = total_loss(w, pred_rgb, target_rgb, pred_depth)
    assert camera_only.total.item() == pytest.approx(0.5)
    assert camera_only.irs.item() == camera_only.uss.item() == camera_only.rgbd.item() == 0.0


def test_distortion_loss_hand_computed_and_gradient_matches_the_double_sum():
    from virus_nerf.losses import distortion_loss

    # ray 0: two samples [1, 2] and [4, 5] with weights 0.5, 0.25; ray 1: none; ray 2: one [2, 2.5]
    t0 = torch.tensor([1.0, 4.0, 2.0])
    t1 = torch.tensor([2.0, 5.0, 2.5])
    offsets = torch.tensor([0, 2, 2, 3])
    w = torch.tensor([0.5, 0.25, 0.8], dtype=torch.float64, requires_grad=True)
    loss = distortion_loss(w, t0, t1, offsets)
    ray0 = 2 * 0.5 * 0.25 * 3.0 + (0.25 * 1.0 + 0.0625 * 1.0) / 3
    ray2 = 0.64 * 0.5 / 3
    assert loss.item() == pytest.approx((ray0 + ray2) / 3)
    loss.backward()
    # reference: the O(n^2) definition, written out
    w2 = w.detach().clone().requires_grad_(True)
    m = (t0 + t1).double() / 2
    d = (t1 - t0).double()
    ref = 0
    for lo, hi in ((0, 2), (2, 2), (2, 3)):
        for i in range(lo, hi):
            for j in range(lo, hi):
                ref = ref + w2[i] * w2[j] * (m[i] - m[j]).abs()
            ref = ref + w2[i] ** 2 * d[i] / 3
    (ref / 3).backward()
    torch.testing.assert_close(w.grad, w2.grad)
