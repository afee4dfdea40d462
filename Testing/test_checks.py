"""Tests of the surface validator (BoneWatertightLib/checks.py, SPEC §4)."""

import itertools
import json
import time

import numpy as np
import pytest

from BoneWatertightLib.mesh.checks import check_surface, find_self_intersections, require_valid
from BoneWatertightLib.errors import SurfaceCheckError
from BoneWatertightLib.mesh import Surface


# ---------------------------------------------------------------------------------------------
# Test meshes, built by hand

def icosphere(level=2, radius=1.0, centre=(0.0, 0.0, 0.0)):
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(level):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        ue, inv = np.unique(e, axis=0, return_inverse=True)
        mid = v[ue[:, 0]] + v[ue[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        ab, bc, ca = (inv.reshape(3, -1) + len(v))
        v = np.vstack([v, mid])
        a, b, c = f.T
        f = np.concatenate([np.stack(x, axis=1) for x in
                            ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return v * radius + np.asarray(centre, float), f.astype(np.int64)


def torus(major=3.0, minor=1.0, nu=40, nv=20):
    u, w = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv,
                       indexing="ij")
    r = major + minor * np.cos(w)
    v = np.stack([r * np.cos(u), r * np.sin(u), minor * np.sin(w)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * nv + j
    b = ((i + 1) % nu) * nv + j
    c = ((i + 1) % nu) * nv + (j + 1) % nv
    d = i * nv + (j + 1) % nv
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f.astype(np.int64)


def tetrahedron(offset=(0, 0, 0), scale=1.0):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * scale + offset
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, f


def merge(*meshes):
    vs, fs, n = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(np.asarray(f) + n)
        n += len(v)
    return np.vstack(vs), np.vstack(fs)


def pair_set(pairs):
    return {tuple(p) for p in np.asarray(pairs).tolist()}


# ---------------------------------------------------------------------------------------------
# Clean surfaces

def test_icosphere_is_valid_genus_0():
    v, f = icosphere(3, radius=20.0, centre=(-120.0, 35.0, 400.0))
    r = check_surface(v, f)
    assert r.ok, r.problems
    assert r.problems == []
    assert r.closed and r.edge_manifold and r.vertex_manifold and r.consistent_orientation
    assert r.n_components == 1 and r.genus == 0 and r.outward
    assert r.n_degenerate == 0 and r.n_self_intersections == 0
    assert r.n_vertices == len(v) and r.n_faces == len(f) and r.unreferenced_vertices == 0
    # Inscribed polyhedron: slightly below the sphere's volume.
    assert 0.97 * 4 / 3 * np.pi * 20 ** 3 < r.volume < 4 / 3 * np.pi * 20 ** 3
    json.dumps(r.to_dict())


def test_torus_is_valid_genus_1():
    v, f = torus()
    r = check_surface(v, f)
    assert r.ok, r.problems
    assert r.genus == 1
    assert r.volume == pytest.approx(2 * np.pi ** 2 * 3.0 * 1.0, rel=0.03)


def test_unreferenced_vertices_are_counted_but_not_an_error():
    v, f = icosphere(1)
    v = np.vstack([v, [[5.0, 5.0, 5.0]]])
    r = check_surface(v, f)
    assert r.ok and r.unreferenced_vertices == 1


# ---------------------------------------------------------------------------------------------
# Topological defects

def test_hole_is_not_closed():
    v, f = icosphere(2)
    r = check_surface(v, f[1:])
    assert not r.ok and not r.closed and not r.edge_manifold
    assert r.n_boundary_edges == 3 and r.genus is None
    assert r.vertex_manifold and r.consistent_orientation  # a clean hole, nothing else
    assert any("boundary edges" in p for p in r.problems)


def test_two_spheres_are_two_components():
    mesh = merge(icosphere(2), icosphere(2, centre=(5.0, 0, 0)))
    r = check_surface(*mesh)
    assert not r.ok and r.n_components == 2 and r.genus is None
    assert r.n_self_intersections == 0
    assert any("2 connected components" in p for p in r.problems)
    assert check_surface(*mesh, expect_components=2).ok
    assert check_surface(*mesh, expect_components=None).ok


def test_inverted_faces_are_not_outward():
    v, f = icosphere(2)
    r = check_surface(v, f[:, ::-1])
    assert not r.ok and not r.outward and r.volume < 0 and r.consistent_orientation
    assert any("inward" in p for p in r.problems)


def test_one_flipped_face_is_inconsistent_orientation():
    v, f = icosphere(2)
    f = f.copy()
    f[7] = f[7, ::-1]
    r = check_surface(v, f)
    assert not r.ok and not r.consistent_orientation and r.n_misoriented_edges == 3
    assert r.closed and r.edge_manifold and r.genus is None


def test_bow_tie_vertex_is_not_vertex_manifold():
    # Two tetrahedra sharing only their apex (vertex 3 of the first is vertex 0 of the second).
    v1, f1 = tetrahedron()
    v2, f2 = tetrahedron(offset=(0, 0, 1))
    v = np.vstack([v1, v2[1:]])
    f2 = np.where(f2 == 0, 3, f2 + 3)
    r = check_surface(v, np.vstack([f1, f2]))
    assert r.closed and r.edge_manifold and r.consistent_orientation
    assert not r.vertex_manifold and r.n_nonmanifold_vertices == 1
    assert r.n_components == 1 and not r.ok and r.n_self_intersections == 0


def test_bow_tie_of_two_spheres():
    va, fa = icosphere(2)
    vb, fb = icosphere(2, centre=(2.0, 0, 0))
    # Glue: the vertex of b nearest to a is replaced by a's vertex at (1, 0, 0).
    ia = int(np.argmin(np.linalg.norm(va - [1, 0, 0], axis=1)))
    ib = int(np.argmin(np.linalg.norm(vb - [1, 0, 0], axis=1)))
    fb = np.where(fb == ib, -1, fb + len(va))
    fb[fb == -1] = ia
    r = check_surface(np.vstack([va, vb]), np.vstack([fa, fb]))
    assert not r.vertex_manifold and r.n_nonmanifold_vertices == 1
    assert r.n_components == 1 and r.unreferenced_vertices == 1


def test_edge_with_three_faces_is_not_edge_manifold():
    v, f = icosphere(1)
    a, b = f[0, 0], f[0, 1]
    fin_vertex = (v[a] + v[b]) * 1.5  # outside the sphere
    v = np.vstack([v, fin_vertex])
    r = check_surface(v, np.vstack([f, [[a, b, len(v) - 1]]]))
    assert not r.ok and not r.edge_manifold and r.n_nonmanifold_edges == 1
    assert any("more than 2 faces" in p for p in r.problems)


def test_two_tetrahedra_sharing_an_edge():
    # The second is the first turned 180 degrees about the x axis: both hold edge 0-1.
    v1, f1 = tetrahedron()
    v2 = v1 * [1, -1, -1]
    v = np.vstack([v1, v2[2:]])
    f2 = np.where(f1 >= 2, f1 + 2, f1)
    r = check_surface(v, np.vstack([f1, f2]))
    assert r.closed and not r.edge_manifold and r.n_nonmanifold_edges == 1
    assert r.consistent_orientation and r.outward and r.n_self_intersections == 0
    assert not r.ok and r.genus is None


# ---------------------------------------------------------------------------------------------
# Geometric defects

def test_degenerate_faces_are_counted():
    v, f = icosphere(2)
    a, b, c = f[0]
    v = v.copy()
    v[c] = 0.5 * (v[a] + v[b])  # face 0 becomes a zero-area sliver
    r = check_surface(v, f)
    assert r.n_degenerate >= 1 and not r.ok
    assert any("degenerate" in p for p in r.problems)
    # A repeated index and a duplicated face are degenerate too.
    v, f = icosphere(1)
    r = check_surface(v, np.vstack([f, [[0, 0, 1]]]))
    assert r.n_degenerate == 1 and not r.ok
    r = check_surface(v, np.vstack([f, f[3:4, [1, 2, 0]]]))
    assert r.n_duplicate_faces == 1 and r.n_degenerate == 1 and not r.ok
    assert r.n_self_intersections == 0  # a duplicate is not double-counted as a crossing


def test_vertex_pushed_through_sphere_self_intersects():
    v, f = icosphere(3, radius=10.0)
    v = v.copy()
    v[0] *= -1.5  # through the centre and out of the opposite side
    r = check_surface(v, f)
    assert not r.ok and r.n_self_intersections > 0
    assert r.closed and r.edge_manifold and r.vertex_manifold
    # Every intersecting pair involves a face of the moved vertex.
    moved = set(np.flatnonzero((f == 0).any(axis=1)).tolist())
    pairs = find_self_intersections(v, f)
    assert len(pairs) == r.n_self_intersections
    assert all(a in moved or b in moved for a, b in pairs.tolist())
    assert any("intersecting faces" in p for p in r.problems)
    r = check_surface(v, f, check_self_intersections=False)
    assert r.ok and r.n_self_intersections == 0  # skipped on request


def test_interpenetrating_spheres_self_intersect():
    va, fa = icosphere(3, radius=1.0)
    vb, fb = icosphere(3, radius=1.0, centre=(1.2, 0.1, 0.05))
    v, f = merge((va, fa), (vb, fb))
    r = check_surface(v, f, expect_components=None)
    assert not r.ok and r.n_self_intersections > 20
    pairs = find_self_intersections(v, f)
    # Each pair has one face of each sphere, and the count matches the report.
    assert len(pairs) == r.n_self_intersections
    assert ((pairs[:, 0] < len(fa)) & (pairs[:, 1] >= len(fa))).all()
    assert len(r.self_intersection_pairs) <= 100
    assert len(find_self_intersections(v, f, max_pairs=5)) == 5


def test_touching_is_not_an_intersection():
    # A tetrahedron whose apex touches the middle of another's face, and two tetrahedra
    # touching along an edge: contacts, not crossings.
    v1, f1 = tetrahedron()
    v2, f2 = tetrahedron(offset=(0.2, 0.2, -1.0))  # its apex (0.2,0.2,0) lies on face z=0
    assert len(find_self_intersections(*merge((v1, f1), (v2, f2)))) == 0
    v3 = v1 * [-1, -1, 1]  # turned 180 degrees about z: touches along the z axis only
    assert len(find_self_intersections(*merge((v1, f1), (v3, f1)))) == 0
    # Mirrored in x instead, the two faces x=0 coincide: an overlap of positive area is reported.
    v5 = v1 * [-1, 1, 1]
    assert pair_set(find_self_intersections(*merge((v1, f1), (v5, f1[:, ::-1])))) == {(2, 6)}
    # ... but pushing it a little further in is a crossing.
    v4 = v2 + [0, 0, 0.01]
    assert len(find_self_intersections(*merge((v1, f1), (v4, f2)))) > 0


def test_shared_vertex_and_shared_edge_cases():
    # Shared edge, folded flat onto each other (coplanar, same side).
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.6, 0.8, 0]], float)
    assert pair_set(find_self_intersections(v, [[0, 1, 2], [1, 0, 3]])) == {(0, 1)}
    # Shared edge, coplanar but on opposite sides: a flat hinge, fine.
    v2 = v * [1, 1, 1]
    v2[3] = [0.6, -0.8, 0]
    assert len(find_self_intersections(v2, [[0, 1, 2], [1, 0, 3]])) == 0
    # Shared edge, sharp but non-zero dihedral: fine.
    v3 = v.copy()
    v3[3] = [0.6, 0.8, 0.05]
    assert len(find_self_intersections(v3, [[0, 1, 2], [1, 0, 3]])) == 0
    # Shared vertex, coplanar, overlapping sectors.
    w = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [1, 0.3, 0], [1, 1.5, 0]], float)
    assert pair_set(find_self_intersections(w, [[0, 1, 2], [0, 3, 4]])) == {(0, 1)}
    # Shared vertex, coplanar, disjoint sectors.
    w2 = w.copy()
    w2[3:] = [[-1, -0.3, 0], [-1, -1.5, 0]]
    assert len(find_self_intersections(w2, [[0, 1, 2], [0, 3, 4]])) == 0
    # Shared vertex, not coplanar: the opposite edge pierces the other triangle.
    w3 = w.copy()
    w3[3:] = [[0.5, 0.5, -1.0], [0.5, 0.5, 1.0]]
    assert pair_set(find_self_intersections(w3, [[0, 1, 2], [0, 3, 4]])) == {(0, 1)}
    # ... and the same triangle turned so that it only touches at the shared vertex.
    w4 = w.copy()
    w4[3:] = [[-0.5, -0.5, -1.0], [-0.5, -0.5, 1.0]]
    assert len(find_self_intersections(w4, [[0, 1, 2], [0, 3, 4]])) == 0
    # Disjoint coplanar overlapping triangles.
    u = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0.5, 0.5, 0], [3, 0.5, 0], [0.5, 3, 0]])
    assert pair_set(find_self_intersections(u, [[0, 1, 2], [3, 4, 5]])) == {(0, 1)}


# ---------------------------------------------------------------------------------------------
# Self-intersection finder against a brute-force reference

def _reference_pair(P, Q, n_shared):
    """Independent test: overlap of the two triangles' intervals on the planes' common line.

    For triangles in general position (not coplanar): they share a point other than common
    vertices exactly when the intervals overlap with positive length. Shared edges never count
    (no folds in general position).
    """
    if n_shared >= 2:
        return False
    nP = np.cross(P[1] - P[0], P[2] - P[0])
    nQ = np.cross(Q[1] - Q[0], Q[2] - Q[0])
    u = np.cross(nP, nQ)
    if np.linalg.norm(u) < 1e-12 * np.linalg.norm(nP) * np.linalg.norm(nQ):
        return False  # parallel planes do not occur in the random tests

    def interval(T, n, origin, shared_mask):
        d = (T - origin) @ n
        d[shared_mask] = 0.0
        ts = []
        for a in range(3):
            if d[a] == 0:
                ts.append(T[a] @ u)
            b = (a + 1) % 3
            if d[a] * d[b] < 0:
                x = T[a] + (T[b] - T[a]) * (d[a] / (d[a] - d[b]))
                ts.append(x @ u)
        return (min(ts), max(ts)) if ts else None

    shared_p = np.array([any((P[a] == Q[b]).all() for b in range(3)) for a in range(3)])
    shared_q = np.array([any((Q[a] == P[b]).all() for b in range(3)) for a in range(3)])
    ip = interval(P, nQ, Q[0], shared_p)
    iq = interval(Q, nP, P[0], shared_q)
    if ip is None or iq is None:
        return False
    overlap = min(ip[1], iq[1]) - max(ip[0], iq[0])
    return overlap > 1e-9 * np.linalg.norm(u)


def _brute_force(v, f):
    """Every pair of faces whose bounding boxes touch goes through the reference test."""
    tri = v[f]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    ii, jj = np.triu_indices(len(f), k=1)
    near = ((lo[ii] <= hi[jj]) & (lo[jj] <= hi[ii])).all(axis=1)
    out = set()
    for i, j in zip(ii[near].tolist(), jj[near].tolist()):
        n_shared = len(set(f[i].tolist()) & set(f[j].tolist()))
        if _reference_pair(v[f[i]], v[f[j]], n_shared):
            out.add((i, j))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_random_soup_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 14
    v = rng.random((n, 3)) * 10.0 + [100.0, -50.0, 20.0]
    triples = np.array(list(itertools.combinations(range(n), 3)))
    f = triples[rng.choice(len(triples), 40, replace=False)]
    f = np.array([rng.permutation(t) for t in f])
    mine = pair_set(find_self_intersections(v, f))
    ref = _brute_force(v, f)
    assert mine == ref
    # The soup really is tangled, and pairs with a shared vertex cross too.
    assert len(ref) > 10
    assert any(len(set(f[i].tolist()) & set(f[j].tolist())) == 1 for i, j in ref)


@pytest.mark.parametrize("seed", range(4))
def test_noisy_sphere_matches_brute_force(seed):
    rng = np.random.default_rng(100 + seed)
    v, f = icosphere(2)
    v = v + rng.normal(scale=0.12, size=v.shape)
    mine = pair_set(find_self_intersections(v, f))
    assert mine == _brute_force(v, f)
    print(f"noisy sphere {seed}: {len(mine)} intersecting pairs")
    r = check_surface(v, f)
    assert r.n_self_intersections == len(mine) and r.ok == (len(mine) == 0)


# ---------------------------------------------------------------------------------------------
# require_valid and speed

def test_require_valid():
    v, f = icosphere(2, radius=30.0)
    report = require_valid(Surface(v, f), "bone surface")
    assert report.ok
    with pytest.raises(SurfaceCheckError) as err:
        require_valid(Surface(v, f[2:]), "bone surface")
    msg = str(err.value)
    assert "bone surface" in msg and "boundary edges" in msg and "not closed" in msg
    assert err.value.report is not None and not err.value.report.ok
    with pytest.raises(SurfaceCheckError, match="no faces"):
        require_valid(Surface(v, np.zeros((0, 3), int)))


def test_large_sphere_is_fast():
    vtk = pytest.importorskip("vtk")
    from vtk.util import numpy_support as ns

    src = vtk.vtkSphereSource()
    src.SetRadius(40.0)
    src.SetCenter(10.0, -150.0, 300.0)
    src.SetThetaResolution(320)
    src.SetPhiResolution(320)
    src.Update()
    poly = src.GetOutput()
    v = ns.vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    f = ns.vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    assert len(f) > 200_000
    t0 = time.process_time()
    r = check_surface(v, f)
    seconds = time.process_time() - t0
    print(f"check_surface on {len(f)} faces: {seconds:.2f} s CPU ({r.seconds:.2f} s wall)")
    assert r.ok, r.problems
    assert seconds < 5.0


def _clip_area(P, Q):
    """Area of the intersection of two 2-D triangles (Sutherland-Hodgman clipping)."""
    def signed(poly):
        x, y = np.asarray(poly).T
        return 0.5 * (x @ np.roll(y, -1) - y @ np.roll(x, -1))

    poly = [tuple(p) for p in P]
    q = [tuple(p) for p in Q]
    if signed(q) < 0:
        q = q[::-1]
    for k in range(3):
        a, b = np.array(q[k]), np.array(q[(k + 1) % 3])
        side = [((b - a)[0] * (p[1] - a[1]) - (b - a)[1] * (p[0] - a[0])) for p in poly]
        out = []
        for m in range(len(poly)):
            p1, p2, s1, s2 = poly[m], poly[(m + 1) % len(poly)], side[m], side[(m + 1) % len(poly)]
            if s1 >= 0:
                out.append(p1)
            if s1 * s2 < 0:
                t = s1 / (s1 - s2)
                out.append(tuple(np.array(p1) + t * (np.array(p2) - np.array(p1))))
        poly = out
        if len(poly) < 3:
            return 0.0
    return abs(signed(poly))


@pytest.mark.parametrize("seed", range(4))
def test_coplanar_soup_matches_polygon_clipping(seed):
    # Triangles on a small integer grid in one plane: many shared vertices, shared edges,
    # touching edges and true overlaps. Rotated and moved so that nothing is exact any more.
    rng = np.random.default_rng(seed)
    grid = np.array([(x, y) for x in range(4) for y in range(4)], float)
    triples = np.array([t for t in itertools.combinations(range(len(grid)), 3)
                        if _clip_area(grid[list(t)], grid[list(t)]) > 0])  # not collinear
    f = triples[rng.choice(len(triples), 25, replace=False)]
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    v = np.c_[grid, np.zeros(len(grid))] @ rot.T * 3.7 + [-80.0, 140.0, 260.0]
    mine = pair_set(find_self_intersections(v, f))
    ref = {(i, j) for i, j in itertools.combinations(range(len(f)), 2)
           if _clip_area(grid[f[i]], grid[f[j]]) > 1e-9}
    assert mine == ref
    assert 0 < len(ref) < len(f) * (len(f) - 1) // 2


def test_mirror_symmetric_spheres_that_cross_only_through_edges():
    """Two icospheres offset along a symmetry axis: every intersection segment ends on edges of
    both faces (no edge pierces a face interior), yet the surfaces interpenetrate."""
    va, fa = icosphere(3, radius=8.0)
    vb, fb = icosphere(3, radius=8.0, centre=(0.0, 0.0, 9.6))
    v, f = merge((va, fa), (vb, fb))
    assert len(find_self_intersections(v, f)) > 20
    touching = merge((va, fa), icosphere(3, radius=8.0, centre=(0.0, 0.0, 16.0)))
    assert len(find_self_intersections(*touching)) == 0


@pytest.mark.parametrize("seed", range(6))
def test_only_gives_the_pairs_with_one_of_those_faces(seed):
    """find_self_intersections(only=...) is the full answer filtered to pairs with a face of
    ``only``: on a tangled soup and on a noisy sphere with faces of every size."""
    rng = np.random.default_rng(200 + seed)
    if seed % 2:
        v, f = icosphere(3)
        v = v + rng.normal(scale=0.05, size=v.shape)
        v[rng.choice(len(v), 3)] *= 2.0  # a few long faces
    else:
        n = 14
        v = rng.random((n, 3)) * 10.0
        triples = np.array(list(itertools.combinations(range(n), 3)))
        f = triples[rng.choice(len(triples), 40, replace=False)]
    full = find_self_intersections(v, f)
    assert len(full) > 0
    only = rng.random(len(f)) < (0.1 if seed < 3 else 0.6)  # with and without pruning
    expected = {p for p in pair_set(full) if only[p[0]] or only[p[1]]}
    assert pair_set(find_self_intersections(v, f, only=only)) == expected
    assert len(find_self_intersections(v, f, only=np.zeros(len(f), bool))) == 0


def test_safe_update_backs_off_a_local_step_through_the_surface():
    """A step that pushes one vertex through the far side is backed off (the test looks only
    near the moved faces, and finds the crossing there)."""
    from BoneWatertightLib.mesh.operators import safe_update

    v, f = icosphere(3, radius=10.0)
    new = v.copy()
    new[0] *= -1.5
    out, ok, _ = safe_update(v, new, f, intersections=True)
    assert ok and np.array_equal(out, v)
    small = v.copy()
    small[0] *= 1.05  # a small step outward is kept
    out, ok, _ = safe_update(v, small, f, intersections=True)
    assert ok and np.array_equal(out, small)


def _safe_update_rechecking_everything(old, new, faces, rounds, grow_rounds):
    """safe_update as it was before the incremental test: every round's exact test looks at
    every face that moved from ``old`` (the reference the incremental one must equal)."""
    from BoneWatertightLib.mesh.operators import face_normals

    new = new.copy()
    sub = np.flatnonzero(np.any(new != old, axis=1)[faces].any(axis=1))
    fn_before = face_normals(old, faces[sub])
    ring = 0
    for r in range(rounds + grow_rounds):
        bad = np.zeros(len(faces), bool)
        bad[sub] = np.einsum("ij,ij->i", fn_before, face_normals(new, faces[sub])) < 0.0
        if not bad.any():
            moved = np.any(new != old, axis=1)[faces].any(axis=1)
            pairs = find_self_intersections(new, faces, only=moved)
            if len(pairs) == 0:
                return new, True
            bad[np.unique(pairs)] = True
        back = np.zeros(len(new), bool)
        back[faces[bad]] = True
        if r >= rounds:
            ring += 1
            for _ in range(ring):
                back[faces[back[faces].any(axis=1)]] = True
        new[back] = old[back]
    return new, False


@pytest.mark.parametrize("seed", range(1, 7))
def test_safe_update_tests_only_what_it_put_back_and_still_finds_every_crossing(seed):
    """After the first exact test, safe_update re-tests only the faces of the vertices it put
    back. Patches of a flat ellipsoid's top pushed through its bottom (no flips: only the
    exact test sees them) need several rounds, each putting back vertices whose faces then
    cross: the result equals re-testing every moved face each round, and is clean."""
    from BoneWatertightLib.mesh import operators

    rng = np.random.default_rng(seed)
    v, f = icosphere(4, radius=10.0)
    v = v * np.array([1.0, 1.0, 0.15])
    new = v.copy()
    for _ in range(1 + seed % 3):
        c = rng.normal(scale=3, size=2)
        patch = (np.hypot(v[:, 0] - c[0], v[:, 1] - c[1]) < rng.uniform(2, 4)) & (v[:, 2] > 0)
        new[patch, 2] -= rng.uniform(2.5, 3.5)
    new += rng.normal(scale=0.02, size=new.shape)
    calls = []
    original = operators.find_self_intersections

    def counting(*args, **kwargs):
        calls.append(int(kwargs["only"].sum()))
        return original(*args, **kwargs)

    operators.find_self_intersections = counting
    try:
        out, ok, _ = operators.safe_update(v, new, f, intersections=True)
    finally:
        operators.find_self_intersections = original
    ref, ref_ok = _safe_update_rechecking_everything(v, new, f, operators.BACKOFF_ROUNDS,
                                                     operators.BACKOFF_GROW_ROUNDS)
    assert ok and ref_ok
    assert np.array_equal(out, ref)
    assert len(find_self_intersections(out, f)) == 0
    assert len(calls) >= 2  # crossings were found and put back
    assert max(calls[1:]) < calls[0] / 4  # later rounds test only what was put back


def _inside_cases():
    rng = np.random.default_rng(7)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    v, f = icosphere(4, 6.0)
    yield "ellipsoid", v * np.array([1.0, 0.7, 1.6]) + 12.3, f
    v, f = torus(6, 2, 60, 30)
    yield "torus", v + 10.0, f
    yield "oblique torus", v @ rotation.T + 10.0, f
    v, f = icosphere(2, 5.0)
    # Vertices on the voxel centres' lines and planes: rays through vertices and edges.
    yield "grid vertices", np.round((v + 10.0) * 2) / 2, f


@pytest.mark.parametrize("case", range(4))
def test_inside_mask_counts_ray_crossings_as_the_vtk_stencil_does(case):
    """The ray-parity voxelisation equals VTK's polygon stencil but for voxel centres that lie
    on the surface (a tie either may call inside), rays through vertices and edges included."""
    import vtk
    from BoneWatertightLib.mesh.surface import _ray_parity, _stencil_mask, to_polydata

    name, v, f = list(_inside_cases())[case]
    shape, h = (40, 40, 40), 0.5
    ours = _ray_parity(v, f, shape, h, (0.0, 0.0, 0.0))
    assert ours is not None, name
    ref = _stencil_mask(Surface(v, f), shape, h, (0.0, 0.0, 0.0))
    assert ref.sum() > 1000
    distance = vtk.vtkImplicitPolyDataDistance()
    distance.SetInput(to_polydata(Surface(v, f), normals=False))
    for z, y, x in np.argwhere(ours != ref):
        assert abs(distance.EvaluateFunction(x * h, y * h, z * h)) < 1e-9, name


def test_inside_mask_of_an_open_surface_falls_back_to_the_stencil():
    """A surface with a hole has rays that cross it an odd number of times: the parity is
    not used and VTK's stencil gives the mask."""
    from BoneWatertightLib.mesh.surface import _ray_parity, _stencil_mask, inside_mask

    v, f = icosphere(3, 5.0)
    v = v + 10.2
    pole = np.argmax(v[:, 0])
    opened = f[~np.any(f == pole, axis=1)]  # a hole across the rays along x
    assert _ray_parity(v, opened, (40, 40, 40), 0.5, (0.0, 0.0, 0.0)) is None
    assert np.array_equal(inside_mask(Surface(v, opened), (40, 40, 40), 0.5),
                          _stencil_mask(Surface(v, opened), (40, 40, 40), 0.5, (0.0, 0.0, 0.0)))
    closed = inside_mask(Surface(v, f), (40, 40, 40), 0.5)
    assert 4 / 3 * np.pi * 5.0 ** 3 * 0.97 < closed.sum() * 0.125 < 4 / 3 * np.pi * 5.0 ** 3


@pytest.mark.parametrize("threads", [1, 2])
def test_intersection_batches_tested_on_threads_are_those_of_one_thread(monkeypatch, threads):
    """The narrow phase of the next batches on threads finds the same pairs, also when the
    search stops at ``max_pairs``."""
    from BoneWatertightLib import threads as threads_module
    from BoneWatertightLib.mesh import checks

    monkeypatch.setattr(threads_module.os, "cpu_count", lambda: threads)
    monkeypatch.setattr(checks, "_PAIR_BATCH", 500)  # many batches
    v, f = icosphere(level=4, radius=10.0)
    v = np.asarray(v, np.float64).copy()
    rng = np.random.default_rng(threads)
    spikes = rng.choice(len(v), 80, replace=False)
    v[spikes] += rng.normal(0.0, 3.0, (80, 3))  # pushed through their neighbours
    monkeypatch.setattr(checks, "CHECK_THREADS", 1)
    plain = find_self_intersections(v, f)
    first = find_self_intersections(v, f, max_pairs=5)
    monkeypatch.setattr(checks, "CHECK_THREADS", 2)
    assert len(plain) > 10
    assert np.array_equal(find_self_intersections(v, f), plain)
    assert np.array_equal(find_self_intersections(v, f, max_pairs=5), first)
