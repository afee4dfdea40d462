"""Exact point-to-triangle distances and surface-distance statistics."""

import numpy as np
import pytest

from BoneWatertightLib.mesh import Surface
from metrics import (TriangleLocator, closest_point_on_triangles, sample_surface,
                     surface_distance, vertex_distances)


def icosphere(radius, subdivisions, centre=(0.0, 0.0, 0.0)):
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.ravel().reshape(3, -1).T + len(v)
        v = np.vstack([v, mid])
        a, b, c = f.T
        ab, bc, ca = m.T
        f = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                            np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
    return Surface(v * radius + np.asarray(centre), f)


TRI = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]])


@pytest.mark.parametrize("p, dist, feature", [
    ((0.2, 0.2, 1.0), 1.0, 0),              # above the face
    ((0.5, 0.5, 0.0), 0.0, 3),              # on edge bc
    ((0.1, 0.1, 0.0), 0.0, 0),              # inside, in plane
    ((2.0, 0.0, 0.0), 1.0, 5),              # beyond vertex b
    ((0.0, 3.0, 4.0), (4.0 ** 2 + 2.0 ** 2) ** 0.5, 6),  # beyond vertex c, off-plane
    ((-1.0, -1.0, 0.0), 2 ** 0.5, 4),       # behind vertex a
    ((0.5, -1.0, 0.0), 1.0, 1),             # outside edge ab
    ((-2.0, 0.5, 1.0), 5 ** 0.5, 2),        # outside edge ac
    ((1.0, 1.0, 0.0), 0.5 ** 0.5, 3),       # outside edge bc
])
def test_point_triangle_hand_cases(p, dist, feature):
    a, b, c = (np.repeat(TRI[k][None], 1, 0) for k in range(3))
    cp, feat = closest_point_on_triangles(np.array([p], float), a, b, c)
    assert np.linalg.norm(cp[0] - p) == pytest.approx(dist, abs=1e-12)
    assert int(feat[0]) == feature


def test_degenerate_triangle():
    a = np.array([[0.0, 0, 0]])
    b = np.array([[1.0, 0, 0]])
    c = np.array([[2.0, 0, 0]])  # collinear
    cp, _ = closest_point_on_triangles(np.array([[1.5, 1.0, 0.0]]), a, b, c)
    assert np.linalg.norm(cp[0] - [1.5, 1.0, 0.0]) == pytest.approx(1.0)


def test_locator_matches_brute_force():
    rng = np.random.default_rng(3)
    s = icosphere(3.0, 2, centre=(250.0, -180.0, 400.0))  # far from the origin: float32 care
    s.vertices += rng.normal(scale=0.2, size=s.vertices.shape)
    p = rng.normal(size=(1500, 3)) * 5 + [250.0, -180.0, 400.0]
    brute = np.full(len(p), np.inf)
    for t in s.faces:
        a, b, c = (np.repeat(s.vertices[t[k]][None], len(p), 0) for k in range(3))
        cp, _ = closest_point_on_triangles(p, a, b, c)
        brute = np.minimum(brute, np.linalg.norm(cp - p, axis=1))
    for use_o3d in (True, False):
        d = TriangleLocator(s, use_open3d=use_o3d).query(p)[0]
        np.testing.assert_allclose(d, brute, atol=1e-9 if not use_o3d else 1e-5)


def test_signed_vertex_distances():
    s = icosphere(10.0, 4)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(2000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d_out = vertex_distances(u * 11.0, s)
    d_in = vertex_distances(u * 9.0, s)
    assert (d_out > 0).all() and (d_in < 0).all()
    # The mesh is inscribed in the sphere: distances within the chord error of +-1.
    assert np.abs(d_out - 1.0).max() < 0.05 and np.abs(d_in + 1.0).max() < 0.05
    # Exactly on vertices: zero.
    assert np.abs(vertex_distances(s.vertices[:100], s, signed=False)).max() < 1e-5


def test_sphere_to_larger_sphere():
    a = icosphere(10.0, 5)
    b = icosphere(10.5, 5)
    r = surface_distance(a, b, n_samples=20000)
    # Both are inscribed polyhedra; the chord error (< 0.01 mm here) is the only deviation.
    assert r["mean"] == pytest.approx(0.5, abs=0.01)
    assert r["max"] == pytest.approx(0.5, abs=0.02)
    assert r["frac_under_1"] == 1.0
    assert surface_distance(a, icosphere(10.6, 5), n_samples=5000)["frac_under_0_5"] == 0.0
    assert r["a_to_b"]["mean"] == pytest.approx(0.5, abs=0.01)
    assert r["b_to_a"]["p95"] == pytest.approx(0.5, abs=0.02)
    # Identical meshes: zero.
    assert surface_distance(a, a, n_samples=5000)["max"] < 1e-5


def test_samples_are_uniform_by_area():
    s = icosphere(1.0, 3)
    s.vertices[:, 0] *= 4.0  # stretch: areas differ strongly between triangles
    p = sample_surface(s, 40000, seed=1)
    # Fraction of samples with x > 0 = half of the area by symmetry.
    assert abs((p[:, 0] > 0).mean() - 0.5) < 0.02
