"""The 2D signed Euclidean distance field (ESDF) of a map, for planners.

Signed, in metres, between pixel centres: outside obstacles the distance to the nearest
occupied pixel (> 0), inside obstacles minus the distance to the nearest pixel that is not
occupied (<= -resolution). The distances count unknown pixels as not occupied, and the pixels the
map leaves unknown (no sensor looked there, or the map claims nothing: a shadow behind a low
obstacle, a place no ray reached) are NaN: a planner reading a clearance there would read free
space the map does not claim, as an ESDF over observed space only gives none. Written as
float32 `.npy` in image layout (row 0 = largest y, the map_server raster of `maps`), a map_server
style YAML naming it, and a PNG preview.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.maps.occupancy import yaml_float


@dataclass
class DistanceField2D:
    distance: np.ndarray  # (H, W) float32 metres, row 0 = largest y; +inf where the map has no obstacle; NaN where the map is unknown
    resolution: float  # metres per pixel
    origin: tuple[float, float]  # world (x, y) of the lower-left pixel corner

    def __post_init__(self) -> None:  # Python floats, as OccupancyMap2D's: YAML that reads back as numbers
        self.resolution = float(self.resolution)
        self.origin = (float(self.origin[0]), float(self.origin[1]))


def signed_distance(occupied: np.ndarray, resolution: float) -> np.ndarray:
    """(H, W) bool obstacles -> (H, W) float32 signed distance in metres (see module docstring)."""
    from scipy.ndimage import distance_transform_edt

    occ = np.asarray(occupied, dtype=bool)
    if not occ.any():
        return np.full(occ.shape, np.inf, dtype=np.float32)
    outside = distance_transform_edt(~occ)  # to the nearest occupied pixel; 0 on obstacles
    inside = distance_transform_edt(occ) if not occ.all() else np.full(occ.shape, np.inf)
    return ((outside - inside) * resolution).astype(np.float32)


UNKNOWN_RGB = (70, 110, 200)  # esdf.png: the map's unknown pixels (NaN distance)


def write_esdf(field: DistanceField2D, folder: Path, name: str = "esdf", preview_max: float = 2.0) -> None:
    """esdf.npy + esdf.yaml (origin, resolution, units) + esdf.png (RGB; distance clipped to
    [-preview_max, preview_max] m: black = deep inside obstacles, mid grey = surface, white far,
    blue (UNKNOWN_RGB) = unknown)."""
    from PIL import Image

    from virus_nerf.utils.io import atomic_path, write_text_atomic

    with atomic_path(folder / f"{name}.npy") as tmp, tmp.open("wb") as fh:
        np.save(fh, field.distance.astype(np.float32))
    write_text_atomic(
        folder / f"{name}.yaml",
        f"data: {name}.npy\nunits: metres\nsigned: true  # negative inside obstacles\n"
        f"resolution: {yaml_float(field.resolution)}\norigin: [{yaml_float(field.origin[0])}, "
        f"{yaml_float(field.origin[1])}, 0.0]\n"
        "layout: rows top (largest y) to bottom, columns x increasing, as the map_server image\n",
    )
    d = np.clip(np.nan_to_num(field.distance, nan=0.0, posinf=preview_max), -preview_max, preview_max)
    grey = np.rint((d + preview_max) / (2 * preview_max) * 255).astype(np.uint8)
    rgb = np.repeat(grey[..., None], 3, axis=2)  # (H, W, 3)
    rgb[np.isnan(field.distance)] = UNKNOWN_RGB  # not black: that is deep inside an obstacle
    with atomic_path(folder / f"{name}.png") as tmp:
        Image.fromarray(rgb).save(tmp, format="PNG")
