"""Unit tests for co3sop_nodes.sim.shapes: exact, strict voxel overlap; vertical ray entry; meshes.

References are independent of the module: an exact linear program solved by
vertex enumeration (boxes), nearest-point geometry (cylinders, spheres), dense
point sampling inside each cube, and Embree ray casts of the primitives' own
meshes (trimesh's RayMeshIntersector).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from co3sop_nodes.sim.shapes import EPS, Box, Cylinder, Sphere, rotation
from co3sop_nodes.sim.town import TownConfig, generate_town

BAND = 1e-5  # m: configurations this close to touching are left to the strictness tests


# --- independent references ---------------------------------------------------------------------


def rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


_SUBSETS = np.array(list(itertools.combinations(range(12), 4)))  # (495, 4)


def common_margin(box: Box, centers: np.ndarray, half: float) -> np.ndarray:
    """max t such that some point lies at least t inside every face of both the cube and the box.

    The exact optimum of a small LP (variables p, t), found by enumerating its
    vertices: t > 0 iff the interiors intersect, t < 0 iff the closed solids are
    disjoint, and when t > 0 the intersection holds a ball of radius t.
    """
    axes = box.rot.T  # (3, 3) rows: the box's unit face normals
    a = np.concatenate([np.eye(3), -np.eye(3), axes, -axes])  # (12, 3) unit rows
    m = np.concatenate([a[_SUBSETS], np.ones((len(_SUBSETS), 4, 1))], axis=2)  # (495, 4, 4): [a_i, 1] (p, t) = b_i
    ok = np.abs(np.linalg.det(m)) > 1e-9
    inv, subsets = np.linalg.inv(m[ok]), _SUBSETS[ok]
    box_b = np.concatenate([axes @ box.center + box.half, -(axes @ box.center) + box.half])
    out = []
    for chunk in np.array_split(np.atleast_2d(centers), max(1, len(centers) // 256)):
        b = np.concatenate([chunk + half, -chunk + half, np.broadcast_to(box_b, (len(chunk), 6))], axis=1)  # (N, 12)
        sol = np.einsum("kij,nkj->nki", inv, b[:, subsets])  # (N, K, 4) vertices: p, t
        feasible = (sol[..., :3] @ a.T + sol[..., 3:] <= b[:, None, :] + 1e-9).all(axis=2)
        out.append(np.where(feasible, sol[..., 3], -np.inf).max(axis=1))
    return np.concatenate(out)


def face_axes_only_overlap(box: Box, centers: np.ndarray, half: float) -> np.ndarray:
    """A deliberately incomplete SAT (faces only, no edge crossings), to show the random cases are hard."""
    axes = np.concatenate([np.eye(3), box.rot.T])
    reach = half * np.abs(axes).sum(axis=1) + np.abs(axes @ box.rot) @ box.half
    return (np.abs((box.center - centers) @ axes.T) < reach).all(axis=1)


def cube_points(center: np.ndarray, half: float, n: int = 7, margin: float = 1e-4) -> np.ndarray:
    """A lattice of n^3 points strictly inside a cube."""
    s = np.linspace(-half + margin, half - margin, n)
    return center + np.stack(np.meshgrid(s, s, s, indexing="ij"), axis=-1).reshape(-1, 3)


def inside_box(box: Box, p: np.ndarray, margin: float) -> np.ndarray:
    return (np.abs((p - box.center) @ box.rot) < box.half - margin).all(axis=1)


def random_box(rng) -> Box:
    size = np.exp(rng.uniform(np.log(0.02), np.log(4.0), 3))
    return Box.make(rng.uniform(-3, 3, 3), size, *rng.uniform(-np.pi, np.pi, 3))


def centres_around(rng, lo, hi, half, n) -> np.ndarray:
    return rng.uniform(lo - half - 0.3, hi + half + 0.3, (n, 3))


def centres_near_box(rng, box: Box, half, n) -> np.ndarray:
    """Cube centres spread over the box's own frame, grown by the cube's circumradius: near its faces, edges, corners."""
    reach = box.half + half * math.sqrt(3) + 0.05
    return box.center + rng.uniform(-reach, reach, (n, 3)) @ box.rot.T


# --- rotation -----------------------------------------------------------------------------------


def test_rotation_is_rz_ry_rx_and_proper():
    rng = np.random.default_rng(1)
    for yaw, pitch, roll in rng.uniform(-np.pi, np.pi, (50, 3)):
        r = rotation(yaw, pitch, roll)
        np.testing.assert_allclose(r, rz(yaw) @ ry(pitch) @ rx(roll), atol=1e-12)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation(np.pi / 2)[:, 0], [0, 1, 0], atol=1e-15)  # yaw turns x to +y


def test_box_make_half_sizes_and_axes():
    b = Box.make([1, 2, 3], [4, 2, 1], yaw=0.3)
    np.testing.assert_array_equal(b.half, [2, 1, 0.5])
    np.testing.assert_allclose(b.rot, rz(0.3), atol=1e-15)
    assert b.mesh().volume == pytest.approx(8.0)


# --- Box.overlaps -------------------------------------------------------------------------------


def test_axis_aligned_box_overlap_equals_interval_test():
    rng = np.random.default_rng(2)
    checked = {True: 0, False: 0}
    for _ in range(200):
        lo = rng.uniform(-2, 2, 3)
        hi = lo + np.exp(rng.uniform(np.log(0.01), np.log(3), 3))
        yaw = rng.choice([0.0, np.pi, -np.pi / 2]) if rng.random() < 0.3 else 0.0
        size = hi - lo if abs(yaw) != np.pi / 2 else (hi - lo)[[1, 0, 2]]
        box = Box.make((lo + hi) / 2, size, yaw)
        for half in (0.05, 0.1, 0.25):
            c = centres_around(rng, lo, hi, half, 40)
            pen = np.minimum(c + half, hi) - np.maximum(c - half, lo)  # overlap of the intervals per axis
            clear = (np.abs(pen) > BAND).all(axis=1)
            expected = (pen > 0).all(axis=1)
            got = box.overlaps(c, half)
            np.testing.assert_array_equal(got[clear], expected[clear])
            for v in (True, False):
                checked[v] += int((expected[clear] == v).sum())
    assert min(checked.values()) > 1000  # both outcomes well exercised


def test_rotated_box_overlap_equals_exact_lp():
    rng = np.random.default_rng(3)
    agree = {True: 0, False: 0}
    faces_only_wrong = 0
    for _ in range(250):
        box = random_box(rng)
        lo, hi = box.aabb()
        half = float(rng.choice([0.05, 0.1, 0.2]))
        c = np.concatenate([centres_around(rng, lo, hi, half, 12), centres_near_box(rng, box, half, 12)])
        t = common_margin(box, c, half)
        got = box.overlaps(c, half)
        clear = np.abs(t) > BAND
        np.testing.assert_array_equal(got[clear], (t > 0)[clear], err_msg=f"box {box}, half {half}, centres {c[clear]}")
        for v in (True, False):
            agree[v] += int(((t > 0) == v)[clear].sum())
        faces_only_wrong += int((face_axes_only_overlap(box, c, half) != (t > 0))[clear].sum())
    assert min(agree.values()) > 1000
    assert faces_only_wrong > 10  # the sample includes edge-edge cases that need the cross-product axes


def test_rotated_box_edge_edge_separation():
    # a box turned 45 deg about z and 45 deg about x: its edge passes near the cube's edge
    box = Box.make([0, 0, 0], [2, 2, 2], yaw=np.pi / 4, roll=np.pi / 4)
    half = 0.5
    # move the cube along a direction where only an edge-cross axis separates the two
    rng = np.random.default_rng(4)
    c = rng.uniform(-2.5, 2.5, (4000, 3))
    t = common_margin(box, c, half)
    clear = np.abs(t) > BAND
    np.testing.assert_array_equal(box.overlaps(c, half)[clear], (t > 0)[clear])
    assert (face_axes_only_overlap(box, c, half) != (t > 0))[clear].sum() > 10


def test_overlap_when_some_cube_point_is_strictly_inside_box():
    rng = np.random.default_rng(5)
    hits = 0
    for _ in range(150):
        box = random_box(rng)
        half = float(rng.choice([0.05, 0.1, 0.2]))
        c = centres_near_box(rng, box, half, 10)
        got = box.overlaps(c, half)
        for centre, g in zip(c, got):
            if inside_box(box, cube_points(centre, half), 1e-4).any():
                assert g, (box, centre, half)
                hits += 1
    assert hits > 300


def test_no_overlap_for_clearly_separated_cubes():
    rng = np.random.default_rng(6)
    for _ in range(100):
        # boxes larger than the cubes, so a cube pushed into a face's centre meets the face
        box = Box.make(rng.uniform(-3, 3, 3), rng.uniform(0.5, 4.0, 3), *rng.uniform(-np.pi, np.pi, 3))
        half = float(rng.choice([0.05, 0.1, 0.2]))
        n = box.rot[:, int(rng.integers(0, 3))] * rng.choice([-1, 1])  # a face normal
        reach = box.half @ np.abs(box.rot.T @ n) + half * np.abs(n).sum()
        lateral = rng.normal(size=(20, 3))
        lateral -= np.outer(lateral @ n, n)
        c = box.center + n * (reach + rng.uniform(1e-3, 1.0, (20, 1))) + lateral
        assert not box.overlaps(c, half).any()
        # and moved inwards along the same normal, through the face's centre, it overlaps
        c_in = box.center + n * (reach - 1e-3)
        assert box.overlaps(c_in[None], half).all()


def test_box_touching_faces_edges_corners_do_not_overlap():
    box = Box.make([0, 0, 0], [2, 2, 2])  # faces at +-1
    h = 0.25
    touching = [(1.25, 0, 0), (-1.25, 0, 0), (0, 1.25, 0), (0, 0, -1.25), (1.25, 1.25, 0), (1.25, -1.25, 1.25)]
    assert not box.overlaps(np.array(touching, float), h).any()
    assert box.overlaps(np.array(touching, float) * (1 - 1e-3), h).all()
    # penetration must exceed EPS
    assert not box.overlaps(np.array([[1.25 - EPS / 10, 0, 0]]), h).any()
    assert box.overlaps(np.array([[1.25 - 10 * EPS, 0, 0]]), h).all()


def test_rotated_box_touching_face_does_not_overlap():
    box = Box.make([0.3, -0.2, 0.1], [2.0, 3.0, 1.5], yaw=0.5, pitch=0.3, roll=-0.2)
    h = 0.1
    for j in range(3):
        for sign in (-1, 1):
            n = sign * box.rot[:, j]
            reach = box.half[j] + h * np.abs(n).sum()
            c = box.center + n * reach
            assert not box.overlaps(c[None], h).any()
            assert box.overlaps((box.center + n * (reach - 1e-4))[None], h).all()


def test_thin_box_and_wire():
    # a 2 cm thick sheet and a 2 cm wire still overlap the cubes they pass through
    sheet = Box.make([0.0, 0.0, 0.0], [4, 4, 0.02], pitch=0.2)
    wire = Box.make([0.0, 0.03, 0.0], [4, 0.02, 0.02], yaw=0.1)
    rng = np.random.default_rng(7)
    for prim in (sheet, wire):
        lo, hi = prim.aabb()
        c = centres_around(rng, lo, hi, 0.1, 3000)
        t = common_margin(prim, c, 0.1)
        clear = np.abs(t) > BAND
        assert (t[clear] > 0).sum() > 20
        np.testing.assert_array_equal(prim.overlaps(c, 0.1)[clear], (t > 0)[clear])


# --- Cylinder and Sphere overlaps ---------------------------------------------------------------


def cube_gap_xy(c: np.ndarray, half: float, x: float, y: float) -> np.ndarray:
    """Distance in x-y from (x, y) to the nearest point of each cube's square footprint."""
    nearest = np.clip(np.array([x, y]), c[:, :2] - half, c[:, :2] + half)
    return np.hypot(nearest[:, 0] - x, nearest[:, 1] - y)


def test_cylinder_overlap_equals_nearest_point_reference():
    rng = np.random.default_rng(8)
    counts = {True: 0, False: 0}
    for _ in range(200):
        cyl = Cylinder(
            *rng.uniform(-3, 3, 2),
            float(np.exp(rng.uniform(np.log(0.01), np.log(2.0)))),
            *sorted(rng.uniform(-2, 3, 2)),
        )
        half = float(rng.choice([0.05, 0.1, 0.2]))
        lo, hi = cyl.aabb()
        c = centres_around(rng, lo, hi, half, 50)
        radial = cyl.radius - cube_gap_xy(c, half, cyl.x, cyl.y)  # > 0: the footprints' interiors meet
        vertical = np.minimum(c[:, 2] + half, cyl.z1) - np.maximum(c[:, 2] - half, cyl.z0)
        clear = (np.abs(radial) > BAND) & (np.abs(vertical) > BAND)
        expected = (radial > 0) & (vertical > 0)
        got = cyl.overlaps(c, half)
        np.testing.assert_array_equal(got[clear], expected[clear])
        for v in (True, False):
            counts[v] += int((expected[clear] == v).sum())
        # sampling: a cube point strictly inside the cylinder means overlap
        for centre, g in zip(c, got):
            p = cube_points(centre, half, 5)
            inside = (
                (np.hypot(p[:, 0] - cyl.x, p[:, 1] - cyl.y) < cyl.radius - 1e-4)
                & (p[:, 2] > cyl.z0 + 1e-4)
                & (p[:, 2] < cyl.z1 - 1e-4)
            )
            if inside.any():
                assert g
    assert min(counts.values()) > 1000


def test_cylinder_touching_does_not_overlap():
    cyl = Cylinder(0.0, 0.0, 1.0, 0.0, 2.0)
    h = 0.25
    touching = np.array([[1.25, 0, 1], [0, -1.25, 1], [0, 0, -0.25], [0, 0, 2.25]])
    assert not cyl.overlaps(touching, h).any()
    inward = touching.copy()
    inward[:2, :2] *= 1 - 1e-3
    inward[2, 2] += 1e-3
    inward[3, 2] -= 1e-3
    assert cyl.overlaps(inward, h).all()
    # the cube's corner nearest the axis exactly on the circle
    d = 1 / math.sqrt(2) + h
    assert not cyl.overlaps(np.array([[d, d, 1.0]]), h).any()
    assert cyl.overlaps(np.array([[d - 1e-4, d - 1e-4, 1.0]]), h).all()
    # a thin pole between column centres is still found by the cubes it passes through
    pole = Cylinder(0.1, 0.1, 0.01, 0.0, 2.0)
    assert pole.overlaps(np.array([[0.05, 0.05, 1.0], [0.15, 0.15, 1.0]]), 0.05).all()
    assert not pole.overlaps(np.array([[0.25, 0.1, 1.0]]), 0.05).any()


def test_sphere_overlap_equals_nearest_point_reference():
    rng = np.random.default_rng(9)
    counts = {True: 0, False: 0}
    for _ in range(200):
        sph = Sphere(rng.uniform(-3, 3, 3), float(np.exp(rng.uniform(np.log(0.01), np.log(2.0)))))
        half = float(rng.choice([0.05, 0.1, 0.2]))
        lo, hi = sph.aabb()
        c = centres_around(rng, lo, hi, half, 50)
        nearest = np.clip(sph.center, c - half, c + half)
        margin = sph.radius - np.linalg.norm(nearest - sph.center, axis=1)
        clear = np.abs(margin) > BAND
        got = sph.overlaps(c, half)
        np.testing.assert_array_equal(got[clear], (margin > 0)[clear])
        for v in (True, False):
            counts[v] += int(((margin > 0) == v)[clear].sum())
        for centre, g in zip(c, got):
            if (np.linalg.norm(cube_points(centre, half, 5) - sph.center, axis=1) < sph.radius - 1e-4).any():
                assert g
    assert min(counts.values()) > 1000


def test_sphere_touching_does_not_overlap():
    sph = Sphere(np.array([1.0, 2.0, 3.0]), 0.5)
    h = 0.25
    touching = sph.center + np.array([[0.75, 0, 0], [0, -0.75, 0], [0, 0, 0.75]])
    assert not sph.overlaps(touching, h).any()
    assert sph.overlaps(sph.center + (touching - sph.center) * (1 - 1e-3), h).all()
    corner = sph.center + (0.5 / math.sqrt(3) + h)  # nearest cube corner exactly on the sphere
    assert not sph.overlaps(corner[None], h).any()
    assert sph.overlaps((corner - 1e-4)[None], h).all()


# --- vertical_entry against ray casts of the primitive's own mesh ----------------------------------


def mesh_top(prim, xy: np.ndarray) -> np.ndarray:
    """z of the first hit of downward rays at xy on prim.mesh() (Embree); NaN where they miss."""
    top = prim.aabb()[1][2] + 5.0
    origins = np.column_stack([xy, np.full(len(xy), top)])
    directions = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    loc, ray, _ = RayMeshIntersector(prim.mesh()).intersects_location(origins, directions, multiple_hits=False)
    out = np.full(len(xy), np.nan)
    out[ray] = loc[:, 2]
    return out


def near_silhouette(prim, xy: np.ndarray, r: float = 1e-4) -> np.ndarray:
    """Whether the analytic hit/miss changes within r of each xy (the ray grazes an edge)."""
    hit = np.isfinite(prim.vertical_entry(xy))
    out = np.zeros(len(xy), bool)
    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        out |= np.isfinite(prim.vertical_entry(xy + r * np.array([np.cos(a), np.sin(a)]))) != hit
    return out


def test_box_vertical_entry_matches_mesh_ray_cast():
    rng = np.random.default_rng(10)
    hit_count = miss_count = 0
    for n in range(60):
        box = (
            random_box(rng)
            if n % 3
            else Box.make(rng.uniform(-3, 3, 3), rng.uniform(0.05, 3, 3), rng.uniform(-np.pi, np.pi))
        )
        lo, hi = box.aabb()
        xy = rng.uniform(lo[:2] - 0.3, hi[:2] + 0.3, (300, 2))
        analytic, meshed = box.vertical_entry(xy), mesh_top(box, xy)
        ok = ~near_silhouette(box, xy)
        np.testing.assert_array_equal(np.isfinite(analytic[ok]), np.isfinite(meshed[ok]))
        both = ok & np.isfinite(analytic)
        np.testing.assert_allclose(analytic[both], meshed[both], atol=1e-4)
        hit_count += int(both.sum())
        miss_count += int((ok & ~np.isfinite(analytic)).sum())
    assert hit_count > 3000 and miss_count > 1000


def test_box_vertical_entry_exact_values():
    box = Box.make([1.0, 2.0, -0.15], [4.0, 2.0, 0.3])  # a road slab, top at z = 0
    xy = np.array([[1.0, 2.0], [-0.9, 1.1], [3.1, 2.0], [1.0, 3.0001]])
    got = box.vertical_entry(xy)
    np.testing.assert_allclose(got[:2], [0.0, 0.0], atol=1e-12)
    assert np.isnan(got[2:]).all()
    tilted = Box.make([0, 0, 0], [2, 2, 2], pitch=np.pi / 4)  # a ridge along y at z = sqrt 2
    np.testing.assert_allclose(
        tilted.vertical_entry(np.array([[0.0, 0.5], [0.5, 0.0]])), [math.sqrt(2), math.sqrt(2) - 0.5], atol=1e-12
    )


def test_cylinder_vertical_entry_matches_mesh_ray_cast():
    rng = np.random.default_rng(11)
    compared = 0
    for _ in range(40):
        cyl = Cylinder(*rng.uniform(-3, 3, 2), float(rng.uniform(0.05, 2)), *sorted(rng.uniform(-2, 3, 2)))
        xy = np.array([cyl.x, cyl.y]) + rng.uniform(-1.3, 1.3, (400, 2)) * cyl.radius
        d = np.hypot(xy[:, 0] - cyl.x, xy[:, 1] - cyl.y)
        analytic, meshed = cyl.vertical_entry(xy), mesh_top(cyl, xy)
        inner = d < cyl.radius * math.cos(math.pi / 12) - 1e-4  # inside the 12-gon inscribed in the circle
        outer = d > cyl.radius + 1e-4
        np.testing.assert_allclose(analytic[inner], cyl.z1, atol=0)
        np.testing.assert_allclose(meshed[inner], cyl.z1, atol=1e-4)
        assert np.isnan(analytic[outer]).all() and np.isnan(meshed[outer]).all()
        ring = ~inner & ~outer & (d < cyl.radius - 1e-9)
        np.testing.assert_allclose(analytic[ring], cyl.z1, atol=0)  # the analytic circle covers the ring
        compared += int(inner.sum() + outer.sum())
    assert compared > 10000


def test_sphere_vertical_entry_matches_mesh_ray_cast():
    rng = np.random.default_rng(12)
    for _ in range(40):
        sph = Sphere(rng.uniform(-3, 3, 3), float(rng.uniform(0.05, 3)))
        xy = sph.center[:2] + rng.uniform(-1.3, 1.3, (400, 2)) * sph.radius
        d = np.hypot(*(xy - sph.center[:2]).T)
        analytic, meshed = sph.vertical_entry(xy), mesh_top(sph, xy)
        np.testing.assert_allclose(
            analytic[d < sph.radius], sph.center[2] + np.sqrt(sph.radius**2 - d[d < sph.radius] ** 2), atol=1e-12
        )
        assert np.isnan(analytic[d > sph.radius]).all()
        assert np.isnan(meshed[d > sph.radius + 1e-4]).all()
        core = d < 0.8 * sph.radius
        assert np.isfinite(meshed[core]).all()
        # the icosphere is inscribed: its top is below the sphere's, by at most a few percent of r here
        assert (meshed[core] <= analytic[core] + 1e-4).all()
        np.testing.assert_allclose(meshed[core], analytic[core], atol=0.03 * sph.radius)


# --- aabb ---------------------------------------------------------------------------------------


def test_aabb_contains_mesh_vertices():
    rng = np.random.default_rng(13)
    for _ in range(50):
        for prim in (
            random_box(rng),
            Cylinder(*rng.uniform(-3, 3, 2), float(rng.uniform(0.01, 2)), *sorted(rng.uniform(-2, 3, 2))),
            Sphere(rng.uniform(-3, 3, 3), float(rng.uniform(0.01, 3))),
        ):
            lo, hi = prim.aabb()
            v = prim.mesh().vertices
            assert (v >= lo - 1e-9).all() and (v <= hi + 1e-9).all()
            if isinstance(prim, Box):  # a box's aabb is tight: its corners are mesh vertices
                np.testing.assert_allclose(v.min(axis=0), lo, atol=1e-9)
                np.testing.assert_allclose(v.max(axis=0), hi, atol=1e-9)
            if isinstance(prim, Cylinder):
                np.testing.assert_allclose([v[:, 2].min(), v[:, 2].max()], [prim.z0, prim.z1], atol=1e-9)


def test_aabb_contains_every_overlapping_cube_centre_within_half():
    # conservative culling relies on this: nothing overlaps a cube outside the aabb grown by half
    rng = np.random.default_rng(14)
    for _ in range(60):
        for prim in (
            random_box(rng),
            Sphere(rng.uniform(-3, 3, 3), float(rng.uniform(0.01, 2))),
            Cylinder(*rng.uniform(-3, 3, 2), float(rng.uniform(0.01, 2)), *sorted(rng.uniform(-2, 3, 2))),
        ):
            lo, hi = prim.aabb()
            c = centres_around(rng, lo, hi, 0.1, 300)
            hit = prim.overlaps(c, 0.1)
            assert ((c[hit] > lo - 0.1) & (c[hit] < hi + 0.1)).all()


def _trimesh_reference(prim) -> tuple[np.ndarray, np.ndarray]:
    """The meshes as trimesh.creation builds and places them (what the cameras ray-cast before `triangles`)."""
    if isinstance(prim, Box):
        transform = np.eye(4)
        transform[:3, :3], transform[:3, 3] = prim.rot, prim.center
        m = trimesh.creation.box(extents=2 * prim.half, transform=transform)
    elif isinstance(prim, Cylinder):
        m = trimesh.creation.cylinder(radius=prim.radius, height=prim.z1 - prim.z0, sections=12)
        m.apply_translation([prim.x, prim.y, (prim.z0 + prim.z1) / 2])
    else:
        m = trimesh.creation.icosphere(subdivisions=2, radius=prim.radius)
        m.apply_translation(prim.center)
    return m.vertices, m.faces


def test_triangles_are_bit_identical_to_trimesh_creation():
    rng = np.random.default_rng(5)
    prims = [
        Box.make([0, 0, 0], [1, 2, 3]),
        Box.make([1e-9, 0, 0], [1, 1, 1]),
        Sphere(np.zeros(3), 1.0),
        Cylinder(0.0, 0.0, 0.5, -1.0, 1.0),
    ]  # identity and near-identity placements: trimesh skips them
    for _ in range(200):
        prims.append(Box.make(rng.normal(size=3) * 50, rng.uniform(0.05, 20, 3), *rng.uniform(-np.pi, np.pi, 3)))
        prims.append(Cylinder(*rng.normal(size=2) * 50, rng.uniform(0.05, 3), *np.sort(rng.uniform(-2, 10, 2))))
        prims.append(Sphere(rng.normal(size=3) * 50, rng.uniform(0.1, 5)))
    town = generate_town(TownConfig(), seed=3)
    prims += [p for o in town.objects for p in o.primitives]
    for prim in prims:
        vertices, faces = prim.triangles()
        ref_vertices, ref_faces = _trimesh_reference(prim)
        np.testing.assert_array_equal(vertices, ref_vertices)
        np.testing.assert_array_equal(faces, ref_faces)
