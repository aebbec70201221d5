"""Bodies from surface meshes and point clouds (issue 29, item 6): ``jm.Mesh`` (a closed triangle
surface read by trimesh: STL, OBJ, PLY), ``jm.Polygon`` (2D loops or a flat mesh's outline) and
``jm.point_cloud``.

The volume checks use the lattice fill's discretisation error.  ``fill`` keeps the lattice points
inside the body, each standing for its lattice cell (a box of side d = h / ppc), so the filled
volume differs from the body's by at most the volume of the cells the surface cuts, which lie
within d sqrt(D) / 2 of the surface: |V_fill - V| <= A d sqrt(D) to first order in d (A the
surface area, the perimeter in 2D).  The body here is the mesh (the icosphere lies inside the
sphere, so its volume is below 4/3 pi r^3 by the faceting error, which is added to the bound
against the sphere)."""

import numpy as np
import pytest

import jaxmpm as jm

trimesh = pytest.importorskip("trimesh")

CENTER = (0.5, 0.5, 0.5)


def icosphere(radius=0.3, subdivisions=3):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    mesh.apply_translation(CENTER)
    return mesh


def volume(particles) -> float:
    return float(np.sum(np.asarray(particles.volume)))


def positions(particles) -> set:
    return {tuple(p) for p in np.round(np.asarray(particles.x), 12).tolist()}


def winding_number(x, tri):
    """The generalised winding number of the triangles about each point (Van Oosterom and
    Strackee's solid angle, brute force): 1 inside a closed outward-oriented surface, 0 outside."""
    a, b, c = (tri[None, :, k] - x[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
    num = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("ptk,ptk->pt", a, b) * lc + np.einsum("ptk,ptk->pt", b, c) * la
           + np.einsum("ptk,ptk->pt", c, a) * lb)
    return np.sum(2 * np.arctan2(num, den), axis=1) / (4 * np.pi)


# --------------------------------------------------------------------------- 3D: a sphere and boxes
def test_meshed_sphere_from_stl_fills_its_volume(tmp_path):
    mesh = icosphere()
    path = tmp_path / "sphere.stl"
    mesh.export(path)
    region = jm.Mesh(path)
    assert region.volume == pytest.approx(mesh.volume, rel=1e-6)  # STL stores float32 vertices
    sphere = 4 / 3 * np.pi * 0.3**3
    assert mesh.volume < sphere
    for cells, ppc in ((16, 2), (24, 2)):
        grid = jm.Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (cells,) * 3)
        particles = jm.fill(grid, region, ppc=ppc)
        d = 1.0 / cells / ppc
        bound = mesh.area * d * np.sqrt(3)
        assert abs(volume(particles) - mesh.volume) <= bound
        assert abs(volume(particles) - sphere) <= bound + (sphere - mesh.volume)
        # measured: 16 cells 8.0e-4, 24 cells 1.6e-7 against bounds of 6.1e-2 and 4.1e-2
        assert abs(volume(particles) - mesh.volume) <= 0.02 * bound


def test_inside_test_agrees_with_the_winding_number():
    mesh = icosphere(subdivisions=2)
    grid = jm.Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (12, 12, 12))
    lattice = np.asarray(jm.fill(grid, jm.Box((0.15,) * 3, (0.85,) * 3), ppc=2).x)
    inside = jm.Mesh(mesh).contains(lattice)
    w = winding_number(lattice, np.asarray(mesh.vertices)[np.asarray(mesh.faces)])
    assert np.all(np.isclose(w, 0.0, atol=1e-6) | np.isclose(w, 1.0, atol=1e-6))
    assert np.array_equal(inside, w > 0.5)
    assert 0 < inside.sum() < inside.size


@pytest.mark.parametrize("lower, upper", [
    ((0.25, 0.25, 0.25), (0.75, 0.75, 0.75)),                  # faces on lattice cell faces: exact
    ((17 / 64, 0.25, 0.3), (33 / 64, 41 / 64, 0.7)),           # faces through lattice points
])
def test_meshed_box_fills_what_box_fills(lower, upper):
    """Columns through the box's edges and corners, points on its faces: the mesh's tie rules
    are Box's (lower <= x < upper), so the particles are the same."""
    grid = jm.Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (16, 16, 16))
    mesh = trimesh.creation.box(bounds=np.array([lower, upper]))
    from_mesh = jm.fill(grid, jm.Mesh(mesh), ppc=2)
    from_box = jm.fill(grid, jm.Box(lower, upper), ppc=2)
    assert positions(from_mesh) == positions(from_box)
    if lower[0] == 0.25:
        assert volume(from_mesh) == pytest.approx(0.125, rel=1e-14)


def test_rotated_box_and_orientation():
    rotation = trimesh.transformations.rotation_matrix(0.3, [1.0, 2.0, 3.0])[:3, :3]
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    region = jm.Mesh(box, rotate=rotation, translate=CENTER)
    assert region.volume == pytest.approx(0.024, rel=1e-12)
    grid = jm.Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (32, 32, 32))
    particles = jm.fill(grid, region, ppc=2)
    bound = box.area * (1 / 64) * np.sqrt(3)
    assert abs(volume(particles) - 0.024) <= 0.02 * bound  # measured 1.3e-5 against a bound of 1.4e-2
    # the inside is by parity: inverted or mixed triangle orientation changes nothing
    faces = np.array(box.faces)
    faces[::2] = faces[::2, ::-1]
    mixed = jm.Mesh((np.array(box.vertices), faces), rotate=rotation, translate=CENTER)
    assert positions(jm.fill(grid, mixed, ppc=2)) == positions(particles)


def test_obj_ply_round_trip_and_transformations(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=300.0)  # millimetres, about the origin
    grid = jm.Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (12, 12, 12))
    filled = {}
    for suffix in ("stl", "obj", "ply"):
        path = tmp_path / f"sphere.{suffix}"
        mesh.export(path)
        region = jm.Mesh(path, scale=1e-3, translate=CENTER)
        assert np.allclose(region.bounds(), ((0.2, 0.2, 0.2), (0.8, 0.8, 0.8)), atol=1e-6)
        filled[suffix] = positions(jm.fill(grid, region, ppc=2))
    direct = icosphere(subdivisions=2)
    assert filled["stl"] == filled["obj"] == filled["ply"] == positions(jm.fill(grid, jm.Mesh(direct), ppc=2))
    # per-axis scale: an ellipsoid, volume scaled by the product of the factors
    region = jm.Mesh(mesh, scale=(1e-3, 5e-4, 1e-3), translate=CENTER)
    assert region.volume == pytest.approx(mesh.volume * 0.5e-9, rel=1e-12)


# --------------------------------------------------------------------------- 2D
def test_polygon_circle_and_hole():
    theta = np.linspace(0.0, 2 * np.pi, 128, endpoint=False)
    circle = np.stack([0.5 + 0.3 * np.cos(theta), 0.5 + 0.3 * np.sin(theta)], axis=1)
    area = 0.5 * 128 * 0.3**2 * np.sin(2 * np.pi / 128)  # the 128-gon's
    perimeter = 128 * 2 * 0.3 * np.sin(np.pi / 128)
    for cells in (32, 64):
        grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (cells, cells))
        particles = jm.fill(grid, jm.Polygon(circle), ppc=2)
        bound = perimeter * (1 / cells / 2) * np.sqrt(2)
        assert abs(volume(particles) - area) <= 0.05 * bound  # measured 5.7e-4, 1.6e-4 against 4.2e-2, 2.1e-2
    # a loop inside another is a hole; vertex lattice-aligned squares are exact
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (16, 16))
    outer = [(0.25, 0.25), (0.75, 0.25), (0.75, 0.75), (0.25, 0.75)]
    hole = [(0.375, 0.375), (0.625, 0.375), (0.625, 0.625), (0.375, 0.625), (0.375, 0.375)]  # closed explicitly
    particles = jm.fill(grid, jm.Polygon([outer, hole]), ppc=2)
    assert volume(particles) == pytest.approx(0.25 - 0.0625, rel=1e-14)
    assert positions(jm.fill(grid, jm.Polygon(outer), ppc=2)) == positions(jm.fill(grid, jm.Box(*outer[::2]), ppc=2))


def test_polygon_from_a_flat_mesh_file(tmp_path):
    """A flat annulus of triangles written as PLY: its outline (outer and inner circles) bounds the region."""
    n = 48
    theta = 2 * np.pi * np.arange(n) / n
    outer = np.stack([0.5 + 0.35 * np.cos(theta), 0.5 + 0.35 * np.sin(theta)], axis=1)
    inner = np.stack([0.5 + 0.15 * np.cos(theta), 0.5 + 0.15 * np.sin(theta)], axis=1)
    vertices = np.concatenate([outer, inner])
    i, j = np.arange(n), (np.arange(n) + 1) % n
    faces = np.concatenate([np.stack([i, j, n + j], axis=1), np.stack([i, n + j, n + i], axis=1)])
    flat = trimesh.Trimesh(np.concatenate([vertices, np.zeros((2 * n, 1))], axis=1), faces, process=False)
    path = tmp_path / "annulus.ply"
    flat.export(path)
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (32, 32))
    from_file = jm.fill(grid, jm.Polygon(path), ppc=2)
    from_loops = jm.fill(grid, jm.Polygon([outer, inner]), ppc=2)
    assert positions(from_file) == positions(from_loops)
    area = 0.5 * n * (0.35**2 - 0.15**2) * np.sin(2 * np.pi / n)
    bound = n * 2 * (0.35 + 0.15) * np.sin(np.pi / n) * (1 / 64) * np.sqrt(2)
    assert abs(volume(from_file) - area) <= bound


# --------------------------------------------------------------------------- point clouds
def test_point_cloud_from_arrays_and_csv(tmp_path):
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))
    x = np.array([[0.2, 0.3], [0.5, 0.5], [0.7, 0.6]])
    vol = np.array([1e-3, 2e-3, 3e-3])
    particles = jm.point_cloud(x, vol, velocity=(1.0, 0.0), density=2.0, grid=grid)
    assert np.allclose(particles.x, x) and np.allclose(particles.volume, vol)
    assert np.allclose(particles.mass, 2.0 * vol) and np.allclose(particles.v, [[1.0, 0.0]] * 3)
    path = tmp_path / "cloud.csv"
    np.savetxt(path, np.column_stack([x, vol, np.ones(3), -np.ones(3)]), delimiter=",",
               header="x,y,volume,vx,vy", comments="")
    read = jm.point_cloud(path, grid=grid)
    assert np.allclose(read.x, x) and np.allclose(read.volume, vol) and np.allclose(read.v, [[1.0, -1.0]] * 3)
    assert read.mass is None
    with pytest.raises(jm.InputError, match="off the grid"):
        jm.point_cloud(x + 1.0, vol, grid=grid)
    with pytest.raises(jm.InputError, match="volume"):
        jm.point_cloud(x, -vol)
    with pytest.raises(jm.InputError, match="volume is missing"):
        jm.point_cloud(x)
    with pytest.raises(jm.InputError, match="both a column of the file and an argument"):
        jm.point_cloud(path, vol)


# --------------------------------------------------------------------------- errors
def test_errors_name_the_problem_and_the_fix(tmp_path):
    grid3 = jm.Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (8, 8, 8))
    grid2 = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))
    with pytest.raises(jm.InputError, match="no such file.*check the path"):
        jm.Mesh(tmp_path / "missing.stl")
    (tmp_path / "body.step").write_text("ISO-10303-21;")
    with pytest.raises(jm.InputError, match="STL, OBJ or PLY"):
        jm.Mesh(tmp_path / "body.step")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat garbage\n")
    with pytest.raises(jm.InputError, match="cannot read it as PLY"):
        jm.Mesh(tmp_path / "bad.ply")
    (tmp_path / "empty.stl").write_text("hello world")
    with pytest.raises(jm.InputError, match="no triangles"):
        jm.Mesh(tmp_path / "empty.stl")
    open_mesh = icosphere(subdivisions=1)
    open_mesh.update_faces(np.arange(len(open_mesh.faces)) != 0)  # a hole: one triangle gone
    path = tmp_path / "open.stl"
    open_mesh.export(path)
    with pytest.raises(jm.InputError, match=r"not closed \(watertight\): 3 of its .*fill_holes"):
        jm.Mesh(path)
    with pytest.raises(jm.InputError, match="grid covers.*scale=1e-3"):
        jm.fill(grid3, jm.Mesh(icosphere(), scale=1000.0), ppc=2)
    with pytest.raises(jm.InputError, match="Mesh is 3D but the grid is 2D.*jm.Polygon"):
        jm.fill(grid2, jm.Mesh(icosphere()), ppc=2)
    with pytest.raises(jm.InputError, match="Polygon is 2D but the grid is 3D.*jm.Mesh"):
        jm.fill(grid3, jm.Polygon([(0.1, 0.1), (0.5, 0.1), (0.3, 0.4)]), ppc=2)
    with pytest.raises(jm.InputError, match="not a rotation"):
        jm.Mesh(icosphere(), rotate=np.diag([1.0, 2.0, 1.0]))
    with pytest.raises(jm.InputError, match="scale"):
        jm.Mesh(icosphere(), scale=0.0)
    with pytest.raises(jm.InputError, match="not flat"):
        jm.Polygon(icosphere())
    with pytest.raises(jm.InputError, match="enclosing no area"):
        jm.Polygon([(0.1, 0.1), (0.5, 0.1), (0.9, 0.1)])


# --------------------------------------------------------------------------- into a simulation
def test_a_meshed_body_runs():
    shape = jm.Linear()
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    region = jm.Mesh(mesh)
    grid = jm.Grid.covering(*region.bounds(), 0.1, shape=shape, pad=0.1)
    particles = jm.fill(grid, region, ppc=2, velocity=(0.0, 0.0, -1.0))
    sim = jm.Simulation(grid=grid, shape=shape, material=jm.NeoHookean(E=1e4, nu=0.3, density=1e3),
                        scheme=jm.FLIP(), gravity=(0.0, 0.0, -9.8))
    state = sim.init(particles)
    final, history = sim.run(state, dt=1e-3, steps=4, save_every=2)
    mass = float(np.sum(np.asarray(state.mass)))
    assert mass == pytest.approx(1e3 * volume(particles))
    # free fall of the whole body: momentum m (v0 - g t) after 4 steps
    assert np.asarray(history.momentum)[-1] == pytest.approx([0.0, 0.0, -mass * (1.0 + 9.8 * 4e-3)], abs=1e-9 * mass)
    assert np.all(np.isfinite(np.asarray(final.x)))
