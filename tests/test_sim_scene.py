"""Exact ray casting of the simulator's primitives (docs/method.md 5) against hand-computed answers."""

from __future__ import annotations

import numpy as np
import pytest
from sim_reference import cast_reference

from virus_nerf.sim.rooms import build_room
from virus_nerf.sim.scene import Box, Cylinder, Material, Scene, SceneObject

GREY = Material((0.5, 0.5, 0.5))


def one(*prims) -> Scene:
    return Scene([SceneObject("o", "test", tuple(prims), GREY)])


def test_axis_aligned_box_distance_and_normal():
    # box spans x in [2, 4]; a ray along +x from the origin enters at x = 2 with normal -x
    s = one(Box((3.0, 0.0, 0.0), (2.0, 1.0, 1.0)))
    t, n, obj = s.cast(np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    assert t[0] == pytest.approx(2.0)
    np.testing.assert_allclose(n[0], [-1, 0, 0])
    assert obj[0] == 0
    # from above along -z: top face at z = 0.5, origin at z = 3 -> t = 2.5, normal +z
    t, n, _ = s.cast(np.array([[3.0, 0.2, 3.0]]), np.array([[0, 0, -1.0]]))
    assert t[0] == pytest.approx(2.5)
    np.testing.assert_allclose(n[0], [0, 0, 1])
    # a diagonal ray: (1, 1, 0)/sqrt2 from (0, -1.5, 0) reaches the face y = -0.5 at x = 1 (misses,
    # x < 2) and the face x = 2 at y = 0.5 (edge) -> hits x = 2 at t = 2 sqrt 2
    d = np.array([[1.0, 1.0, 0.0]]) / np.sqrt(2)
    t, n, _ = s.cast(np.array([[0.0, -1.5, 0.0]]), d)
    assert t[0] == pytest.approx(2 * np.sqrt(2))
    np.testing.assert_allclose(n[0], [-1, 0, 0], atol=1e-12)


def test_yawed_box():
    # a 2 x 2 x 2 cube rotated 45 deg about z, centred at x = 5: its corner points at the origin,
    # so the ray along +x hits the vertical edge at x = 5 - sqrt 2
    s = one(Box((5.0, 0.0, 0.0), (2.0, 2.0, 2.0), np.pi / 4))
    t, n, _ = s.cast(np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    assert t[0] == pytest.approx(5 - np.sqrt(2))
    # slightly above the axis the face normal is (-1, 1)/sqrt2 rotated: the face x' = -1 of the box
    t, n, _ = s.cast(np.array([[0.0, 0.1, 0.0]]), np.array([[1.0, 0, 0]]))
    np.testing.assert_allclose(n[0], [-np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-12)
    # hit point lies on that face: (p - c) . n = 1
    p = np.array([t[0], 0.1, 0.0])
    assert np.dot(p - [5, 0, 0], n[0]) == pytest.approx(1.0)


def test_a_yawed_plank_turns_counter_clockwise():
    """A 4 x 0.2 m plank yawed +30 deg (counter-clockwise from above) about its centre at the origin:
    its upper long face is y = x tan 30 + 0.1 / cos 30, so a ray down -y at x = 1.3 m meets it at
    y = 0.866 m (turned the other way it would be y = -0.635 m), with the face's normal (-sin 30, cos 30)."""
    s = one(Box((0.0, 0.0, 0.0), (4.0, 0.2, 1.0), np.deg2rad(30.0)))
    t, n, _ = s.cast(np.array([[1.3, 3.0, 0.0]]), np.array([[0.0, -1.0, 0.0]]))
    a = np.deg2rad(30.0)
    assert 3.0 - t[0] == pytest.approx(1.3 * np.tan(a) + 0.1 / np.cos(a)) == pytest.approx(0.866, abs=1e-3)
    np.testing.assert_allclose(n[0], [-np.sin(a), np.cos(a), 0.0], atol=1e-12)


def test_vertical_cylinder_side_and_cap():
    s = one(Cylinder((4.0, 0.0, 0.0), 1.0, 2.0))  # x^2 + y^2 <= 1 around (4, 0), z in [-1, 1]
    t, n, _ = s.cast(np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    assert t[0] == pytest.approx(3.0)
    np.testing.assert_allclose(n[0], [-1, 0, 0], atol=1e-12)
    # off-centre at y = 0.6: hits at x = 4 - 0.8 -> t = 3.2, normal (-0.8, 0.6, 0)
    t, n, _ = s.cast(np.array([[0.0, 0.6, 0.0]]), np.array([[1.0, 0, 0]]))
    assert t[0] == pytest.approx(3.2)
    np.testing.assert_allclose(n[0], [-0.8, 0.6, 0], atol=1e-12)
    # top cap from above
    t, n, _ = s.cast(np.array([[4.3, 0.2, 5.0]]), np.array([[0, 0, -1.0]]))
    assert t[0] == pytest.approx(4.0)
    np.testing.assert_allclose(n[0], [0, 0, 1])
    # passing beside it: no hit, inf and NaN in ranges()
    t, n, obj = s.cast(np.array([[0.0, 1.2, 0.0]]), np.array([[1.0, 0, 0]]))
    assert np.isinf(t[0]) and obj[0] == -1
    assert np.isnan(s.ranges(np.array([[0.0, 1.2, 0.0]]), np.array([[1.0, 0, 0]])))[0]


def test_max_range_and_nearest_of_several():
    s = Scene([SceneObject("far", "t", (Box((6.0, 0, 0), (1, 1, 1)),), GREY),
               SceneObject("near", "t", (Cylinder((3.0, 0, 0), 0.5, 1.0),), GREY)])
    t, _, obj = s.cast(np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    assert t[0] == pytest.approx(2.5) and obj[0] == 1
    t, _, obj = s.cast(np.zeros((1, 3)), np.array([[1.0, 0, 0]]), max_range=2.0)
    assert np.isinf(t[0]) and obj[0] == -1


def test_kernel_matches_numpy_reference_in_a_room():
    room = build_room("office", np.random.default_rng(3))
    rng = np.random.default_rng(0)
    lo, hi = np.array(room.scene.extent_lo), np.array(room.scene.extent_hi)
    o = rng.uniform(lo + 0.05, hi - 0.05, (3000, 3))
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    res = room.scene.cast(o, d)
    t_ref, n_ref, k_ref = cast_reference(room.scene, o, d)
    both = np.isfinite(res.t) & np.isfinite(t_ref)
    assert (np.isfinite(res.t) == np.isfinite(t_ref)).all()
    np.testing.assert_allclose(res.t[both], t_ref[both], atol=1e-9)
    same = res.prim_id == k_ref
    assert same.mean() > 0.999  # ties on shared faces may pick either primitive
    np.testing.assert_allclose(res.normal[same], n_ref[same], atol=1e-9)


def test_scene_json_round_trip(tmp_path):
    room = build_room("common", np.random.default_rng(1))
    room.scene.save(tmp_path / "scene.json")
    back = Scene.load(tmp_path / "scene.json")
    assert len(back.objects) == len(room.scene.objects)
    rng = np.random.default_rng(1)
    o = np.broadcast_to([0.0, 0.0, 0.0], (500, 3))
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(back.cast(o, d).t, room.scene.cast(o, d).t, atol=1e-6)


def test_rooms_keep_the_drive_free_and_have_the_preset_size():
    from virus_nerf.sim.trajectory import DrivePath

    for name, area in (("office", 72.0), ("common", 216.0)):
        for seed in (0, 1):
            room = build_room(name, np.random.default_rng(seed))
            lo, hi = np.array(room.scene.extent_lo), np.array(room.scene.extent_hi)
            assert (hi[0] - lo[0]) * (hi[1] - lo[1]) == pytest.approx(area)
            # no primitive may be hit by short horizontal rays from the path at sensor heights
            pts = DrivePath(room.drive).sample(0.25)
            for z in (-0.6, -0.15, 0.0):
                for ang in np.deg2rad([0, 90, 180, 270]):
                    o = np.column_stack([pts, np.full(len(pts), z)])
                    d = np.broadcast_to([np.cos(ang), np.sin(ang), 0.0], o.shape)
                    t = room.scene.cast(o, d, max_range=0.3).t
                    assert np.isinf(t).all(), f"{name} seed {seed}: furniture within 0.3 m of the path"


def test_furniture_varies_with_the_seed():
    a = build_room("office", np.random.default_rng(0)).scene.to_dict()
    b = build_room("office", np.random.default_rng(0)).scene.to_dict()
    c = build_room("office", np.random.default_rng(1)).scene.to_dict()
    assert a == b
    assert a != c


@pytest.mark.parametrize("kind", ["office", "warehouse"])
def test_the_camera_renderer_is_the_scenes_ray_cast_per_pixel(kind):
    """render_camera (the fused, tile-culled kernel) against Scene.cast of every pixel's ray:
    the same primitive, z = t * d_z, the cosine of incidence -normal . d; without noise the colour
    is shade_kernel's (the hit points' albedo lit as the camera lights them) to a rounding step; and the
    tile size is speed only (a tile of 5 px and one of the whole image give the same frame)."""
    import dataclasses

    from virus_nerf.sensors.camera import Intrinsics, pixel_directions
    from virus_nerf.sim import kernels
    from virus_nerf.sim.sensors import CameraModel, render_camera

    room = build_room(kind, np.random.default_rng(5))
    intr = Intrinsics(fx=60.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60)
    pose = np.eye(4)
    yaw = 0.4
    pose[:3, :3] = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]]) @ \
        np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])  # level, looking 0.4 rad left of +x
    pose[:3, 3] = [0.5, 0.2, 0.55]
    model = CameraModel(noise_amp=0.0, tile=5)
    frame = render_camera(room.scene, intr, pose, model, frame_seed=1)
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    d = pixel_directions(intr, u.ravel(), v.ravel()) @ pose[:3, :3].T  # (N, 3) world, unit
    hit = room.scene.cast(np.broadcast_to(pose[:3, 3], d.shape), d, 100.0)
    prim = frame.prim.ravel()
    assert (prim >= 0).mean() > 0.99 and (prim == hit.prim_id).mean() > 0.999  # shared faces may tie
    same = prim == hit.prim_id
    d_z = pixel_directions(intr, u.ravel(), v.ravel())[:, 2]
    np.testing.assert_allclose(frame.z.ravel()[same], (hit.t * d_z)[same], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(frame.cos_incidence.ravel()[same], -np.sum(hit.normal * d, axis=1)[same], atol=1e-9)
    points = pose[:3, 3] + hit.t[:, None] * d
    shaded = np.zeros((len(d), 3))
    pk = room.scene.packed
    kernels.shade_kernel(points, np.ascontiguousarray(hit.normal), hit.prim_id.astype(np.int64), d, pk.pcen, pk.prot,
                         pk.mcol, pk.mpat, pk.mscale, pk.mseed, model.light_array, model.ambient, shaded)
    expected = np.floor(shaded * 255.0 + 0.5)
    assert np.abs(frame.rgb.reshape(-1, 3)[same].astype(float) - expected[same]).max() <= 1
    whole = render_camera(room.scene, intr, pose, dataclasses.replace(model, tile=max(intr.width, intr.height)), 1)
    for a, b in ((frame.rgb, whole.rgb), (frame.z, whole.z), (frame.prim, whole.prim)):
        np.testing.assert_array_equal(a, b)
