"""Exact scenes from primitives (docs/method.md 5): yawed boxes and vertical cylinders with materials.

A `Scene` is a list of `SceneObject`s (a wall, a table, a chair ...), each made of primitives
and one `Material` (colours, procedural pattern, acoustic smoothness, infrared reflectance).
It casts rays exactly (`cast`, numba kernel, vectorised over rays) and renders camera frames.
`ranges` returns NaN for no hit, so a Scene satisfies the evaluation's RangeModel protocol and
gives exact ground truth. `save`/`load` write/read the exact description as `scene.json`.
World frame: x forward, y left, z up (metres); z = 0 is the LiDAR height at the start.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np

from virus_nerf.errors import DataFormatError
from virus_nerf.sim import kernels
from virus_nerf.utils.io import write_json_atomic

SCENE_FORMAT_VERSION = 1
PatternName = Literal["plain", "stripes", "checker", "noise", "wood"]


@dataclass(frozen=True)
class Box:
    """Box of full `size` (m, local x y z) centred at `center`, rotated by `yaw` (rad) about z."""

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0
    type: Literal["box"] = "box"


@dataclass(frozen=True)
class Cylinder:
    """Vertical cylinder (axis along world z) of `radius` and `height` (m) centred at `center`."""

    center: tuple[float, float, float]
    radius: float
    height: float
    type: Literal["cylinder"] = "cylinder"


Primitive = Box | Cylinder


@dataclass(frozen=True)
class Material:
    """Surface appearance and sensor response.

    colour/colour2: RGB in [0, 1] mixed by the pattern; scale: pattern period (m);
    smooth: acoustically smooth (USS gets no echo at grazing incidence, docs/method.md 5);
    ir_reflectance: in [0, 1], scales the IRS return signal; seed: texture noise seed.
    """

    colour: tuple[float, float, float]
    colour2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pattern: PatternName = "plain"
    scale: float = 0.5
    smooth: bool = True
    ir_reflectance: float = 0.6
    seed: int = 0


@dataclass(frozen=True)
class SceneObject:
    """One piece of the room (wall, floor, table ...) made of primitives sharing a material."""

    name: str
    kind: str
    primitives: tuple[Primitive, ...]
    material: Material


@dataclass(frozen=True)
class CastResult:
    """Result of casting N rays. t (N,) m along the unit direction, inf = no hit;
    normal (N, 3) outward unit normal of the hit face (0 = no hit); object_id (N,) index into
    Scene.objects (-1 = no hit); prim_id (N,) flat primitive index (-1 = no hit)."""

    t: np.ndarray
    normal: np.ndarray
    object_id: np.ndarray
    prim_id: np.ndarray

    def __iter__(self):  # allows `t, normal, object_id = scene.cast(...)`
        return iter((self.t, self.normal, self.object_id))


@dataclass(frozen=True)
class PackedScene:
    """Flat float64/int64 arrays for the kernels (see kernels.py for the layout)."""

    olo: np.ndarray  # (O, 3) object AABB min, m
    ohi: np.ndarray  # (O, 3) object AABB max, m
    ostart: np.ndarray  # (O,) first primitive index
    oend: np.ndarray  # (O,) one past the last primitive index
    ptype: np.ndarray  # (P,) 0 box, 1 cylinder
    pcen: np.ndarray  # (P, 3)
    phalf: np.ndarray  # (P, 3)
    prot: np.ndarray  # (P, 2) cos, sin of yaw
    pobj: np.ndarray  # (P,) object index
    mcol: np.ndarray  # (P, 2, 3) colours
    mpat: np.ndarray  # (P,) pattern code
    mscale: np.ndarray  # (P,) pattern period m
    mseed: np.ndarray  # (P,) texture seed
    msmooth: np.ndarray  # (P,) bool
    mir: np.ndarray  # (P,) IR reflectance


def _prim_aabb(p: Primitive) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(p.center, dtype=np.float64)
    if isinstance(p, Box):
        hx, hy, hz = np.asarray(p.size) / 2
        cs, sn = abs(np.cos(p.yaw)), abs(np.sin(p.yaw))
        ext = np.array([cs * hx + sn * hy, sn * hx + cs * hy, hz])
    else:
        ext = np.array([p.radius, p.radius, p.height / 2])
    return c - ext, c + ext


@dataclass
class Scene:
    """An exact room: objects made of primitives, cast against exactly (docs/method.md 5)."""

    objects: list[SceneObject]
    name: str = "room"
    extent_lo: tuple[float, float, float] = (0.0, 0.0, 0.0)  # room interior AABB, m
    extent_hi: tuple[float, float, float] = (0.0, 0.0, 0.0)
    meta: dict = field(default_factory=dict)  # free-form facts (preset, seed, floor height ...)

    @cached_property
    def packed(self) -> PackedScene:
        ptype, pcen, phalf, prot, pobj = [], [], [], [], []
        mcol, mpat, mscale, mseed, msmooth, mir = [], [], [], [], [], []
        olo, ohi, ostart, oend = [], [], [], []
        for oi, obj in enumerate(self.objects):
            if not obj.primitives:
                raise ValueError(f"object {obj.name!r} has no primitives")
            ostart.append(len(ptype))
            lo_o, hi_o = np.full(3, np.inf), np.full(3, -np.inf)
            m = obj.material
            for p in obj.primitives:
                lo, hi = _prim_aabb(p)
                lo_o, hi_o = np.minimum(lo_o, lo), np.maximum(hi_o, hi)
                pcen.append(p.center)
                if isinstance(p, Box):
                    ptype.append(0)
                    phalf.append(np.asarray(p.size, dtype=np.float64) / 2)
                    prot.append((np.cos(p.yaw), np.sin(p.yaw)))
                else:
                    ptype.append(1)
                    phalf.append((p.radius, p.radius, p.height / 2))
                    prot.append((1.0, 0.0))
                pobj.append(oi)
                mcol.append((m.colour, m.colour2))
                mpat.append(kernels.PATTERN_CODES[m.pattern])
                mscale.append(m.scale)
                mseed.append(m.seed)
                msmooth.append(m.smooth)
                mir.append(m.ir_reflectance)
            oend.append(len(ptype))
            pad = 1e-6
            olo.append(lo_o - pad)
            ohi.append(hi_o + pad)
        f = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.float64))  # noqa: E731
        i = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.int64))  # noqa: E731
        return PackedScene(
            olo=f(olo).reshape(-1, 3), ohi=f(ohi).reshape(-1, 3), ostart=i(ostart), oend=i(oend),
            ptype=i(ptype), pcen=f(pcen).reshape(-1, 3), phalf=f(phalf).reshape(-1, 3),
            prot=f(prot).reshape(-1, 2), pobj=i(pobj), mcol=f(mcol).reshape(-1, 2, 3), mpat=i(mpat),
            mscale=f(mscale), mseed=i(mseed), msmooth=np.asarray(msmooth, dtype=bool), mir=f(mir),
        )

    # ------------------------------------------------------------------ casting
    def cast(
        self, origins: np.ndarray, dirs: np.ndarray, max_range: float | np.ndarray = np.inf,
        chunk: int = 1 << 20,
    ) -> CastResult:
        """First hit of rays origins (N, 3), unit dirs (N, 3) within max_range (m, scalar or (N,)).

        Returns CastResult(t (N,) m, inf = no hit; normal (N, 3); object_id (N,); prim_id (N,)).
        Unpacks as `t, normal, object_id = scene.cast(...)`.
        """
        o = np.ascontiguousarray(np.asarray(origins, dtype=np.float64).reshape(-1, 3))
        d = np.ascontiguousarray(np.asarray(dirs, dtype=np.float64).reshape(-1, 3))
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and dirs {d.shape} differ in shape")
        n = o.shape[0]
        tmax = np.ascontiguousarray(np.broadcast_to(np.asarray(max_range, dtype=np.float64), (n,)))
        t = np.empty(n)
        normal = np.empty((n, 3))
        prim = np.empty(n, dtype=np.int64)
        pk = self.packed
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            kernels.cast_kernel(o[s:e], d[s:e], tmax[s:e], pk.olo, pk.ohi, pk.ostart, pk.oend,
                                pk.ptype, pk.pcen, pk.phalf, pk.prot, t[s:e], normal[s:e], prim[s:e])
        obj = np.where(prim >= 0, pk.pobj[np.maximum(prim, 0)], -1)
        return CastResult(t=t, normal=normal, object_id=obj, prim_id=prim)

    def ranges(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Exact distance (N,) m along unit directions to the first surface, NaN for no hit."""
        t = self.cast(origins, directions).t
        return np.where(np.isfinite(t), t, np.nan)

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict:
        return {
            "format": "virus-nerf-scene",
            "version": SCENE_FORMAT_VERSION,
            "name": self.name,
            "units": "metres, radians; world frame x forward, y left, z up",
            "extent_lo": list(self.extent_lo),
            "extent_hi": list(self.extent_hi),
            "meta": self.meta,
            "objects": [
                {
                    "name": o.name,
                    "kind": o.kind,
                    "material": asdict(o.material),
                    "primitives": [asdict(p) for p in o.primitives],
                }
                for o in self.objects
            ],
        }

    def save(self, path: str | Path) -> None:
        """Write the exact scene as JSON (atomically)."""
        write_json_atomic(path, _jsonable(self.to_dict()))

    @classmethod
    def load(cls, path: str | Path) -> Scene:
        """Read a scene.json written by `save`; errors name the object and field."""
        from virus_nerf.utils.textfile import decode_strict, read_bytes

        path = Path(path)
        try:
            data = json.loads(decode_strict(path, read_bytes(path, "scene file")))
        except json.JSONDecodeError as exc:
            raise DataFormatError(path, f"not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise DataFormatError(path, f"expected a JSON object (a virus-nerf scene), got a {_json_kind(data)}")
        if data.get("format") != "virus-nerf-scene":
            raise DataFormatError(path, "not a virus-nerf scene (field 'format')", field="format")
        extent = {k: _extent(path, data, k, corner) for k, corner in (("extent_lo", "lower"), ("extent_hi", "upper"))}
        if not isinstance(data.get("objects", []), list):
            raise DataFormatError(path, "expected a list of objects", field="objects")
        objects = []
        for i, o in enumerate(data.get("objects", [])):
            where = f"objects[{i}]"
            try:
                m = o["material"]
                mat = Material(
                    colour=tuple(m["colour"]), colour2=tuple(m["colour2"]), pattern=m["pattern"],
                    scale=float(m["scale"]), smooth=bool(m["smooth"]),
                    ir_reflectance=float(m["ir_reflectance"]), seed=int(m["seed"]),
                )
                if mat.pattern not in kernels.PATTERN_CODES:
                    raise ValueError(f"unknown pattern {mat.pattern!r}")
                prims: list[Primitive] = []
                for j, p in enumerate(o["primitives"]):
                    if p["type"] == "box":
                        prims.append(Box(center=tuple(p["center"]), size=tuple(p["size"]), yaw=float(p["yaw"])))
                    elif p["type"] == "cylinder":
                        prims.append(Cylinder(center=tuple(p["center"]), radius=float(p["radius"]),
                                              height=float(p["height"])))
                    else:
                        raise ValueError(f"primitives[{j}] has unknown type {p['type']!r}")
                objects.append(SceneObject(name=o["name"], kind=o["kind"], primitives=tuple(prims), material=mat))
            except (KeyError, TypeError, ValueError) as exc:
                raise DataFormatError(path, f"bad object: {exc}", field=where) from exc
        return cls(objects=objects, name=data.get("name", "room"), extent_lo=extent["extent_lo"],
                   extent_hi=extent["extent_hi"], meta=data.get("meta", {}))


def _json_kind(value) -> str:
    return {list: "list", str: "string", bool: "boolean", type(None): "null"}.get(type(value), "number")


def _extent(path: Path, data: dict, key: str, corner: str) -> tuple[float, float, float]:
    """Field `key` of a scene document: the room's `corner` corner, 3 finite numbers (m)."""
    if key not in data:
        raise DataFormatError(path, f"missing; expected the room's {corner} corner [x, y, z] in metres", field=key)
    value = data[key]
    ok = isinstance(value, list) and len(value) == 3 and all(
        isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v) for v in value)
    if not ok:
        raise DataFormatError(path, f"{value!r} is not 3 finite numbers; expected the room's {corner} corner "
                                    "[x, y, z] in metres", field=key)
    return tuple(value)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float):
        return round(x, 9)
    return x


# ---------------------------------------------------------------------- reference implementation
