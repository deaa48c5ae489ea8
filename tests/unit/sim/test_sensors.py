"""Unit tests for the simulated sensors: sim/camera.py, sim/lidar.py, sim/raycast.py and sim/rig.py.

Expected images and scans are computed analytically from the scene's planes
(a wall and a ground slab), independently of the ray caster.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from co3sop_nodes import kernels
from co3sop_nodes.common.classes import LABEL_BY_NAME as L
from co3sop_nodes.common.geometry import carla_pose_to_matrix, carla_to_ros_matrix
from co3sop_nodes.sim import camera, lidar, rig
from co3sop_nodes.sim.raycast import ObjectMeshes, RayScene
from co3sop_nodes.sim.scene import SceneObject
from co3sop_nodes.sim.shapes import Box, Cylinder, Sphere
from co3sop_nodes.sim.town import TownConfig, generate_town
from co3sop_nodes.sim.traffic import Traffic, TrafficConfig

SKY = 13


def pose(yaw: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0, t[0]], [s, c, 0, t[1]], [0, 0, 1, t[2]], [0, 0, 0, 1.0]])


def moved(obj: SceneObject, m: np.ndarray) -> SceneObject:
    return obj.transformed(m)


def scene_of(objects) -> RayScene:
    return RayScene([ObjectMeshes(objects)])


# a road slab (top at z = 0, 200 m square) and a wall whose front face is the plane x = 10,
# spanning y in (-3, 3) and z in (0, 4); both the same plain grey, so shading alone tells them apart
GROUND = SceneObject(1, L["road"], (Box.make([0, 0, -0.15], [200, 200, 0.3]),), (128, 128, 128), "plain")
WALL = SceneObject(2, L["building"], (Box.make([10.5, 0, 2.0], [1.0, 6.0, 4.0]),), (128, 128, 128), "plain")
CAM_HEIGHT = 1.5
W, H = 81, 61  # odd: the centre pixel's ray is exactly the optical axis


def expected_images(k: np.ndarray):
    """(semantic, depth, ambiguous) per pixel from the two planes, for a camera at (0, 0, 1.5) looking along +x."""
    f, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dy, dz = -(u - cx) / f, -(v - cy) / fy  # ray (1, dy, dz): x is the depth along the optical axis
    wall_y, wall_z = 10 * dy, CAM_HEIGHT + 10 * dz
    on_wall = (np.abs(wall_y) < 3) & (wall_z > 0) & (wall_z < 4)
    with np.errstate(divide="ignore"):
        ground_x = np.where(dz < 0, CAM_HEIGHT / -dz, np.inf)
    on_ground = ~on_wall & (ground_x < 100) & (np.abs(np.where(dz < 0, ground_x, 0) * dy) < 100)
    semantic = np.full((H, W), SKY)
    semantic[on_wall], semantic[on_ground] = L["building"], L["road"]
    depth = np.zeros((H, W))
    depth[on_wall], depth[on_ground] = 10.0, ground_x[on_ground]
    # pixels whose ray passes within 1 mm of a silhouette edge are not compared
    ambiguous = (
        (np.abs(np.abs(wall_y) - 3) < 1e-3)
        | (np.abs(wall_z - 4) < 1e-3)
        | (np.abs(wall_z) < 1e-3)
        | (np.abs(ground_x - 100) < 1e-2)
    )
    return semantic, depth, ambiguous


# --- rig ----------------------------------------------------------------------------------------


def test_intrinsics_match_opv2v():
    k = rig.intrinsics(800, 600)
    assert k[0, 0] == pytest.approx(335.639852470912, rel=1e-12)
    assert k[1, 1] == pytest.approx(335.639852470912, rel=1e-12)
    assert (k[0, 2], k[1, 2]) == (400.0, 300.0)
    np.testing.assert_array_equal(k[2], [0, 0, 1])
    assert k[0, 1] == 0 and k[1, 0] == 0
    assert rig.intrinsics(*rig.FULL_RESOLUTION)[0, 0] == pytest.approx(335.639852470912, rel=1e-12)
    assert rig.intrinsics(400, 300)[0, 0] == pytest.approx(335.639852470912 / 2, rel=1e-12)  # scales with the image


# OpenCDA's mounts in CARLA axes (x, y, z, yaw deg; y to the right), as in opv2v-format.md
CARLA_CAMERA_MOUNTS = [(2.5, 0.0, 1.0, 0.0), (0.0, 0.3, 1.8, 100.0), (0.0, -0.3, 1.8, -100.0), (-2.0, 0.0, 1.5, 180.0)]


@pytest.mark.parametrize("index", range(4))
def test_camera_mounts_are_the_carla_mounts_in_rep103(index):
    x, y, z, yaw = CARLA_CAMERA_MOUNTS[index]
    expected = carla_to_ros_matrix(carla_pose_to_matrix([x, y, z, 0.0, yaw, 0.0]))
    np.testing.assert_allclose(rig.vehicle_from_cameras()[index], expected, atol=1e-12)


def test_right_camera_sits_right_and_looks_right():
    assert rig.CAMERA_NAMES[1] == "camera1"
    cams = rig.vehicle_from_cameras()
    right, left, back, front = cams[1], cams[2], cams[3], cams[0]
    assert right[1, 3] < 0 and right[1, 0] < -0.9  # at negative y, optical axis (body x) towards -y
    assert left[1, 3] > 0 and left[1, 0] > 0.9
    assert back[0, 0] == pytest.approx(-1.0) and back[0, 3] < 0
    np.testing.assert_allclose(front[:3, :3], np.eye(3), atol=1e-12)
    for m in cams:
        np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(m[:3, 2], [0, 0, 1], atol=1e-12)  # upright


def test_lidar_mount_and_opv2v_extrinsics():
    np.testing.assert_allclose(rig.vehicle_from_lidar(), pose(0.0, (-0.5, 0.0, 1.9)), atol=0)
    # OPV2V's cameraN.extrinsic (camera <- lidar, CARLA axes), from opv2v-format.md
    extrinsics = [
        [[1, 0, 0, -3.0], [0, 1, 0, 0], [0, 0, 1, 0.9], [0, 0, 0, 1]],
        [[-0.1736, 0.9848, 0, -0.2086], [-0.9848, -0.1736, 0, 0.5445], [0, 0, 1, 0.1], [0, 0, 0, 1]],
        [[-0.1736, -0.9848, 0, -0.2086], [0.9848, -0.1736, 0, -0.5445], [0, 0, 1, 0.1], [0, 0, 0, 1]],
        [[-1, 0, 0, -1.5], [0, -1, 0, 0], [0, 0, 1, 0.4], [0, 0, 0, 1]],
    ]
    for cam, e in zip(rig.vehicle_from_cameras(), extrinsics):
        camera_from_lidar = np.linalg.inv(cam) @ rig.vehicle_from_lidar()
        np.testing.assert_allclose(camera_from_lidar, carla_to_ros_matrix(np.array(e, float)), atol=2e-4)


# --- pixel rays ---------------------------------------------------------------------------------


def test_pixel_rays_centre_and_orientation():
    k = rig.intrinsics(W, H)
    rays = camera.pixel_rays(W, H, k)
    assert rays.shape == (W * H, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    img = rays.reshape(H, W, 3)
    np.testing.assert_allclose(img[H // 2, W // 2], [1, 0, 0], atol=1e-15)
    assert (img[:, 0, 1] > 0).all() and (img[:, -1, 1] < 0).all()  # left of the image is +y
    assert (img[0, :, 2] > 0).all() and (img[-1, :, 2] < 0).all()  # top of the image is up
    # even sizes: the four central rays straddle the axis symmetrically
    rays = camera.pixel_rays(800, 600, rig.intrinsics(800, 600)).reshape(600, 800, 3)
    centre = rays[299:301, 399:401].reshape(-1, 3).sum(axis=0)
    np.testing.assert_allclose(centre / np.linalg.norm(centre), [1, 0, 0], atol=1e-12)
    # the horizontal field of view: pixel edges 0 and 800 are 100 degrees apart
    f = rig.intrinsics(800, 600)[0, 0]
    assert math.degrees(2 * math.atan(400 / f)) == pytest.approx(100.0)
    assert math.degrees(math.atan2(rays[300, 0, 1], rays[300, 0, 0])) == pytest.approx(
        math.degrees(math.atan(399.5 / f))
    )


def test_pixel_rays_invert_a_general_pinhole():
    k = np.array([[120.0, 0, 31.0], [0, 90.0, 17.5], [0, 0, 1]])
    rays = camera.pixel_rays(64, 40, k).reshape(40, 64, 3)
    for u, v in [(0, 0), (63, 39), (10, 30), (31, 17)]:
        optical = np.linalg.inv(k) @ [u + 0.5, v + 0.5, 1.0]  # x right, y down, z forward
        body = np.array([optical[2], -optical[0], -optical[1]])
        np.testing.assert_allclose(rays[v, u], body / np.linalg.norm(body), atol=1e-12)
        # and projecting the ray back gives the pixel centre
        p = k @ np.array([-rays[v, u, 1], -rays[v, u, 2], rays[v, u, 0]])
        np.testing.assert_allclose(p[:2] / p[2], [u + 0.5, v + 0.5], atol=1e-9)


# --- camera.render ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def front_images():
    k = rig.intrinsics(W, H)
    return camera.render(scene_of([GROUND, WALL]), pose(0.0, (0, 0, CAM_HEIGHT)), W, H, k), k


def test_render_depth_and_semantics_match_the_planes(front_images):
    images, k = front_images
    assert images.rgb.shape == (H, W, 3) and images.rgb.dtype == np.uint8
    assert images.depth.shape == (H, W) and images.depth.dtype == np.float32
    assert images.semantic.shape == (H, W) and images.semantic.dtype == np.uint8
    semantic, depth, ambiguous = expected_images(k)
    ok = ~ambiguous
    np.testing.assert_array_equal(images.semantic[ok], semantic[ok])
    np.testing.assert_allclose(images.depth[ok], depth[ok], rtol=1e-4, atol=1e-3)
    # the centre pixel looks straight at the wall: depth 10 m, building
    assert images.semantic[H // 2, W // 2] == L["building"]
    assert images.depth[H // 2, W // 2] == pytest.approx(10.0, abs=1e-3)
    # depth is along the optical axis, not the ray: the whole wall reads 10 m
    assert (images.semantic == L["building"]).sum() > 100
    np.testing.assert_allclose(images.depth[images.semantic == L["building"]], 10.0, atol=1e-3)
    # each class present: wall, ground and sky (depth 0 where nothing was hit)
    assert {L["building"], L["road"], SKY} == set(np.unique(images.semantic).tolist())
    assert (images.depth[images.semantic == SKY] == 0).all()
    assert (images.semantic[0] == SKY).all()


def test_render_is_shaded(front_images):
    images, k = front_images
    rgb = images.rgb.astype(float)
    assert len(np.unique(images.rgb.reshape(-1, 3), axis=0)) > 5
    sky = rgb[images.semantic == SKY]
    assert (sky[:, 2] > sky[:, 0]).all()  # bluish
    # same albedo: ground lit from above is brighter than the wall's face turned away from the sun
    wall = rgb[images.semantic == L["building"]].mean(axis=0)
    ground = rgb[images.semantic == L["road"]].mean(axis=0)
    assert ground.sum() > wall.sum() + 30
    # the wall's shadow: ground 8.5 m ahead (behind the wall as seen from the sun) is darker than at 5.1 m
    f = k[0, 0]
    shadow_row, lit_row = int(round(30.5 + CAM_HEIGHT * f / 8.5 - 0.5)), int(round(30.5 + CAM_HEIGHT * f / 5.1 - 0.5))
    assert images.semantic[shadow_row, W // 2] == images.semantic[lit_row, W // 2] == L["road"]
    assert rgb[shadow_row, W // 2].sum() < rgb[lit_row, W // 2].sum() - 30


def test_render_uses_the_camera_pose(front_images):
    # the same scene turned by 90 degrees about a point, seen by the camera turned with it
    images, k = front_images
    turn = pose(math.pi / 2, (3.0, -7.0, 0.0))
    scene = scene_of([moved(GROUND, turn), moved(WALL, turn)])
    turned = camera.render(scene, turn @ pose(0.0, (0, 0, CAM_HEIGHT)), W, H, k)
    _, _, ambiguous = expected_images(k)
    ok = ~ambiguous
    np.testing.assert_array_equal(turned.semantic[ok], images.semantic[ok])
    np.testing.assert_allclose(turned.depth[ok], images.depth[ok], rtol=1e-4, atol=1e-3)


def test_render_of_an_empty_scene_is_sky():
    k = rig.intrinsics(20, 10)
    images = camera.render(scene_of([SceneObject(1, L["pole"], (Cylinder(0, 50, 0.1, 0, 1),))]), pose(), 20, 10, k)
    assert (images.semantic == SKY).all() and (images.depth == 0).all()


# --- raycast ------------------------------------------------------------------------------------


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "trimesh"])
def test_cast_reports_first_hit_owner_normal_and_range(compiled):
    objs = [
        SceneObject(1, L["pole"], (Cylinder(5, 0, 0.5, -1, 1),)),
        SceneObject(2, L["wall"], (Box.make([8, 0, 0], [1, 4, 4]),)),
        SceneObject(3, L["vegetation"], (Sphere(np.array([0.0, 6.0, 0.0]), 1.0),)),
    ]
    scene = RayScene([ObjectMeshes(objs[:2]), ObjectMeshes(objs[2:])])
    # rays 3 and 4 pass over the pole to the wall's two faces; ray 5 starts inside the wall
    origins = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 1.5], [20, 0, 1.5], [8.0, 0, 1.5]], float)
    directions = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0]])
    hits = scene.cast(origins, directions, compiled=compiled)
    np.testing.assert_array_equal(hits.object_index, [0, 2, -1, 1, 1, 1])
    assert (
        4.5 - 1e-4 < hits.distance[0] < 4.5 + 0.5 * (1 - math.cos(math.pi / 12)) + 1e-4
    )  # the pole's 12-gon, before the wall
    assert hits.distance[1] == pytest.approx(5.0, abs=0.05)  # the icosphere's near side
    assert np.isinf(hits.distance[2])
    np.testing.assert_allclose(hits.distance[3:], [7.5, 11.5, 0.5], atol=1e-4)
    np.testing.assert_allclose(hits.normal[3], [-1, 0, 0], atol=1e-6)  # each facing its ray's origin
    np.testing.assert_allclose(hits.normal[4], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(hits.normal[5], [-1, 0, 0], atol=1e-6)  # the inside of the far face
    np.testing.assert_allclose(hits.point[3:], [[7.5, 0, 1.5], [8.5, 0, 1.5], [8.5, 0, 1.5]], atol=1e-4)
    np.testing.assert_array_equal(hits.normal[2], 0)
    np.testing.assert_array_equal(hits.point[2], 0)
    far = scene.cast(origins, directions, max_distance=4.0, compiled=compiled)
    np.testing.assert_array_equal(far.object_index, [-1, -1, -1, -1, -1, 1])
    assert np.isinf(far.distance[:5]).all()
    assert [scene.objects[i].label for i in (0, 1, 2)] == [L["pole"], L["wall"], L["vegetation"]]


# --- the compiled ray kernel against the reference (trimesh's intersector and NumPy shading) ----------


def random_scene(rng: np.random.Generator) -> RayScene:
    objects = [GROUND]
    for i in range(int(rng.integers(10, 30))):
        c = rng.uniform([-30, -30, 0], [30, 30, 4])
        kind = rng.choice(["box", "cylinder", "sphere"])
        if kind == "box":
            prim = Box.make(c, rng.uniform(0.2, 6, 3), rng.uniform(-np.pi, np.pi))
        elif kind == "cylinder":
            prim = Cylinder(c[0], c[1], rng.uniform(0.1, 2), 0, c[2] + 0.5)
        else:
            prim = Sphere(c, rng.uniform(0.3, 3))
        texture = str(rng.choice(["plain", "bricks", "stripes", "noise"]))
        objects.append(
            SceneObject(i + 3, L["building"], (prim,), tuple(int(v) for v in rng.integers(0, 256, 3)), texture)
        )
    return scene_of(objects)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_cast_is_bit_identical_on_random_rays(seed):
    rng = np.random.default_rng(seed)
    scene = random_scene(rng)
    n = 20000
    directions = rng.normal(size=(n, 3))
    directions[: n // 2] /= np.linalg.norm(directions[: n // 2], axis=1, keepdims=True)  # unit, and not
    shared = np.broadcast_to(rng.uniform(-5, 5, 3), (n, 3))  # one origin (stride 0), as cameras pass it
    each = rng.uniform([-40, -40, -1], [40, 40, 6], (n, 3))
    for origins in (shared, each):
        for max_distance in (np.inf, 25.0):
            ref = scene.cast(origins, directions, max_distance, compiled=False)
            got = scene.cast(origins, directions, max_distance, compiled=True, threads=2)
            assert (ref.object_index >= 0).sum() > n // 10
            for name in ("distance", "object_index", "normal", "point"):
                np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)


@pytest.fixture(scope="module")
def town_scene():
    town = generate_town(TownConfig(), seed=3)
    traffic = Traffic(town, TrafficConfig(cavs=2), seed=4)
    for _ in range(5):
        traffic.step()
    return RayScene([ObjectMeshes(town.objects), ObjectMeshes(traffic.objects())]), traffic


@pytest.mark.parametrize("width, height", [(160, 120), (37, 23)])  # whole blocks and packets of rays, and not
def test_compiled_render_equals_the_reference_in_a_town(town_scene, width, height):
    scene, traffic = town_scene
    k = rig.intrinsics(width, height)
    poses = [cav.pose() @ mount for cav in traffic.cavs for mount in rig.vehicle_from_cameras()]
    ref = [camera.render(scene, p, width, height, k, compiled=False) for p in poses]
    got = camera.render_rig(scene, poses, width, height, k, threads=2, compiled=True)
    for r, g in zip(ref, got):
        np.testing.assert_array_equal(g.rgb, r.rgb)
        np.testing.assert_array_equal(g.depth, r.depth)
        np.testing.assert_array_equal(g.semantic, r.semantic)
    # the images show every texture, sky and shadow
    seen = set()
    for p in poses:
        hits = scene.cast(
            np.broadcast_to(p[:3, 3], (width * height, 3)), camera.pixel_rays(width, height, k) @ p[:3, :3].T
        )
        seen |= {scene.objects[i].texture for i in np.unique(hits.object_index[hits.object_index >= 0])}
    assert seen == {"plain", "bricks", "stripes", "noise"}
    assert any((r.semantic == SKY).any() for r in ref)


def test_single_threaded_blas_keeps_the_products_and_restores_the_threads():
    rng = np.random.default_rng(5)
    body, pose = rng.normal(size=(200_000, 3)), rng.normal(size=(4, 4))
    threaded = body @ pose[:3, :3].T
    setter = kernels._blas_threads_setter()
    if "openblas" in np.show_config(mode="dicts")["Build Dependencies"]["blas"]["name"]:
        assert setter is not None  # numpy's OpenBLAS (0.3.27 on) has per-thread counts
    with kernels.single_threaded_blas():
        alone = body @ pose[:3, :3].T
        if setter is not None:
            assert setter(1) == 1
    np.testing.assert_array_equal(alone, threaded)
    if setter is not None:
        original = setter(3)  # what the block restored
        assert setter(original) == 3
        with kernels.single_threaded_blas():
            pass
        assert setter(original) == original


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "reference"])
def test_render_rig_in_threads_equals_one_by_one(town_scene, compiled):
    scene, traffic = town_scene
    k = rig.intrinsics(64, 48)
    poses = [traffic.cavs[0].pose() @ mount for mount in rig.vehicle_from_cameras()]
    alone = [camera.render(scene, p, 64, 48, k, compiled) for p in poses]
    for a, b in zip(alone, camera.render_rig(scene, poses, 64, 48, k, threads=3, compiled=compiled)):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)


# --- LiDAR --------------------------------------------------------------------------------------


def test_beam_directions():
    cfg = lidar.LidarConfig(channels=16, azimuth_steps=90, upper_fov=3.0, lower_fov=-21.0)
    d = lidar.beam_directions(cfg)
    assert d.shape == (16 * 90, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    el = np.degrees(np.arcsin(d[:, 2])).reshape(16, 90)
    np.testing.assert_allclose(el, np.repeat(np.linspace(3.0, -21.0, 16)[:, None], 90, axis=1), atol=1e-9)
    assert el.max() == pytest.approx(3.0) and el.min() == pytest.approx(-21.0)
    az = np.arctan2(d[:, 1], d[:, 0]).reshape(16, 90) % (2 * np.pi)
    np.testing.assert_allclose(az[0], np.arange(90) * 2 * np.pi / 90, atol=1e-9)
    default = lidar.beam_directions(lidar.LidarConfig())
    assert default.shape == (64 * 1024, 3)


@pytest.mark.parametrize("yaw", [0.0, 0.9])
def test_scan_of_flat_ground(yaw):
    cfg = lidar.LidarConfig(channels=32, azimuth_steps=256, noise_std=0.02)
    height = 1.9
    world_from_lidar = pose(yaw, (5.0, -3.0, height))
    out = lidar.scan(scene_of([GROUND]), world_from_lidar, cfg, np.random.default_rng(0))
    assert out.points.dtype == np.float32 and out.intensity.dtype == np.float32 and out.label.dtype == np.uint8
    n = len(out.points)
    # beams steeper than asin(1.9 / 120) below the horizon reach the ground within range
    el = np.linspace(cfg.upper_fov, cfg.lower_fov, cfg.channels)
    assert n == cfg.azimuth_steps * int((np.sin(np.radians(-el)) * cfg.range > height).sum())
    assert (out.label == L["road"]).all()
    p = out.points.astype(float)
    r = np.linalg.norm(p, axis=1)
    assert np.abs(p[:, 2] + height).max() < 5 * cfg.noise_std
    assert p[:, 2].mean() == pytest.approx(-height, abs=2e-3)
    true_range = height / (-p[:, 2] / r)  # the direction is exact, only the range is noisy
    err = r - true_range
    assert abs(err.mean()) < 2e-3 and 0.017 < err.std() < 0.023
    np.testing.assert_allclose(out.intensity, np.exp(-cfg.attenuation * r), rtol=1e-5)
    assert np.abs(out.intensity - np.exp(-0.004 * true_range)).max() < 0.004 * 5 * cfg.noise_std
    assert r.max() <= cfg.range + 5 * cfg.noise_std


def test_scan_is_in_the_lidar_frame():
    cfg = lidar.LidarConfig(channels=8, azimuth_steps=360, upper_fov=2.0, lower_fov=-2.0, noise_std=0.0)
    wall = SceneObject(5, L["wall"], (Box.make([20.5, 0, 0], [1.0, 40.0, 10.0]),))  # face at world x = 20
    world_from_lidar = pose(math.pi / 2, (10.0, 0.0, 1.0))  # facing world +y: the wall is to its right
    out = lidar.scan(scene_of([wall]), world_from_lidar, cfg, np.random.default_rng(1))
    assert len(out.points) > 50 and (out.label == L["wall"]).all()
    np.testing.assert_allclose(out.points[:, 1], -10.0, atol=1e-3)  # right is -y in REP-103
    assert (out.points[:, 0] ** 2 < 20.0**2).all()
    np.testing.assert_allclose(out.intensity, np.exp(-0.004 * np.linalg.norm(out.points, axis=1)), rtol=1e-5)


def test_scan_noise_is_seeded():
    cfg = lidar.LidarConfig(channels=8, azimuth_steps=64)
    scene = scene_of([GROUND])
    a = lidar.scan(scene, pose(0, (0, 0, 1.9)), cfg, np.random.default_rng(3))
    b = lidar.scan(scene, pose(0, (0, 0, 1.9)), cfg, np.random.default_rng(3))
    c = lidar.scan(scene, pose(0, (0, 0, 1.9)), cfg, np.random.default_rng(4))
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.array_equal(a.points, c.points)
