"""The weights of the training loss (`LossWeights`), apart from the terms so that a config, a
flag or `--help` reads them without loading torch."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LossWeights:
    """Weights of L_tot (docs/method.md 3.2). Depth terms are in m^2, colour in [0,1]^2 units.

    colour, irs, uss: from the 20-trial Optuna study on a simulated office (`virus-nerf tune`,
    docs/results/tune_office41), checked on held-out offices and the common area (README, time
    to map): the colour term down-weighted 3x and the one-sided USS term 10x against the
    authors' weights converted to metres (IRS/USS 50, RGB-D 100 on depths normalised by roughly a
    10 m room: 0.5, 0.5, 1.0 with colour 1.0; configs/paper.json restores them).
    """

    colour: float = 0.3189  # photometric term
    irs: float = 1.0379  # IRS depth term
    uss: float = 0.0505  # one-sided USS depth term
    rgbd: float = 1.0  # RGB-D depth term
    # triangulated camera depth (the stereo sensor), per ray down-weighted by its noise against
    # stereo_sigma_ref (weighted_depth_loss)
    stereo: float = 1.0
    stereo_sigma_ref: float = 0.1  # m
    # line-of-sight emptiness before each USS echo over the cone (free_space_loss, docs/decisions.md
    # D32), free_margin m short of the echo
    free_uss: float = 0.5
    free_margin: float = 0.1
    # line-of-sight emptiness before each stereo target (free_space_loss), ending free_stereo_short
    # of the target's range and at least max(free_margin, 2 sigma) before it (`stereo_free_until`),
    # on only offline in a fitted box whose longest horizontal side is at most free_stereo_room_m:
    # it clears the office's density sheets beside the path; in the larger rooms it cuts real
    # surfaces (far targets graze or see past what their rays cross), and while driving it marked
    # more obstacles near the path free (docs/decisions.md D77)
    free_stereo: float = 40.0
    free_stereo_short: float = 0.1
    free_stereo_room_m: float = 12.0
    # interval distortion (m) on every ray against haze along rays; the paper has none; off (D21)
    distortion: float = 0.0
