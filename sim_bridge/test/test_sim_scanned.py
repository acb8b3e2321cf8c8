"""Scanned objects: the vendored files are read and attributed, stand where they are placed, and
render with their textures in the bundled scene and the generated hold-out kind."""

import re

import mujoco
import numpy as np
import pytest
import trimesh

from area3d_eval.open3d_loader import import_open3d
from area3d_msgs_py.backproject import backproject
from sim_bridge.geoms import geom_meshes
from sim_bridge.holdout_scenes import write_holdout_scene
from sim_bridge.mjcf import Mjcf
from sim_bridge.render import RgbdRenderer
from sim_bridge.scanned_objects import (
    SCANNED_DIR,
    SCANNED_OBJECTS,
    add_scanned,
    footprint,
    place_scanned,
    read_msh,
)
from sim_bridge.scenes import load_scene


def test_every_vendored_file_is_attributed_with_its_licence():
    notice = (SCANNED_DIR / "NOTICE.md").read_text()
    assert "Apache License" in (SCANNED_DIR / "LICENSE").read_text()
    assert "CC BY 4.0" in notice and "Calli" in notice and "myosuite" in notice
    stems = {p.stem for p in SCANNED_DIR.iterdir() if p.suffix in (".msh", ".png")}
    assert stems == set(SCANNED_OBJECTS)
    for stem in stems:
        assert f"`{stem}`" in notice
        assert (SCANNED_DIR / f"{stem}.msh").is_file() and (SCANNED_DIR / f"{stem}.png").is_file()


@pytest.mark.parametrize("name", SCANNED_OBJECTS)
def test_read_msh_agrees_with_mujoco(name):
    vertices, faces = read_msh(SCANNED_DIR / f"{name}.msh")
    spec = f'<mujoco><asset><mesh name="m" file="{SCANNED_DIR / name}.msh"/></asset><worldbody><geom type="mesh" mesh="m"/></worldbody></mujoco>'
    model = mujoco.MjModel.from_xml_string(spec)
    assert model.mesh_facenum[0] == len(faces) and faces.min() >= 0
    assert faces.max() < len(vertices)
    # MuJoCo moves and turns the vertices into the mesh's principal frame: compare what that
    # keeps, the surface area of the triangles
    theirs = trimesh.Trimesh(
        model.mesh_vert[: model.mesh_vertnum[0]],
        model.mesh_face[: model.mesh_facenum[0]],
        process=False,
    )
    assert trimesh.Trimesh(vertices, faces, process=False).area == pytest.approx(
        theirs.area, rel=1e-4
    )


def test_read_msh_rejects_a_truncated_or_foreign_file(tmp_path):
    good = (SCANNED_DIR / f"{SCANNED_OBJECTS[0]}.msh").read_bytes()
    (tmp_path / "cut.msh").write_bytes(good[:-12])
    with pytest.raises(ValueError, match=r"cut\.msh.*got \d+ bytes for counts.*expected \d+ bytes"):
        read_msh(tmp_path / "cut.msh")
    (tmp_path / "tiny.msh").write_bytes(b"abc")
    with pytest.raises(ValueError, match=r"tiny\.msh.*got 3 bytes, expected a \.msh header"):
        read_msh(tmp_path / "tiny.msh")
    with pytest.raises(ValueError, match="scanned object: got 'banana'.*003_cracker_box"):
        footprint("banana")


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.4])
def test_a_placed_scan_stands_on_the_surface_centred_where_asked(tmp_path, yaw):
    doc = Mjcf("one")
    name = add_scanned(doc, tmp_path, "035_power_drill")
    assert add_scanned(doc, tmp_path, "035_power_drill") == name  # assets added once
    assert sum("035_power_drill.msh" in a for a in doc.assets) == 1
    place_scanned(doc, "drill", name, (0.3, -0.2), 0.9, yaw)
    (tmp_path / "one.xml").write_text(doc.xml([]))
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "one.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    (mesh,) = geom_meshes(model, data)
    lo, hi = mesh.bounds
    assert lo[2] == pytest.approx(0.9, abs=1e-5)  # the lowest point on the surface
    fp = footprint(name)
    assert hi[2] - lo[2] == pytest.approx(fp.z_max - fp.z_min, abs=1e-5)
    # every point within the footprint's disc around the asked centre
    assert np.linalg.norm(mesh.vertices[:, :2] - [0.3, -0.2], axis=1).max() <= fp.radius + 1e-5


def _chroma_spread(scene, T):
    """Spread of the chromaticity (r, g, b over their sum; mean per-channel standard deviation)
    of the pixels of a 320 x 240 view at `T` whose depth lands on a scan's surface (within 2 mm),
    and how many there are. Shading scales a plain colour's channels alike: its spread stays
    below 0.01; printed labels spread it over 0.1."""
    model, data = scene.model()
    ids = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]
    scans = trimesh.util.concatenate(geom_meshes(model, data, ids))
    o3d = import_open3d()
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(scans.vertices.astype(np.float32), scans.faces.astype(np.uint32))
    with RgbdRenderer(scene, width=320, height=240) as renderer:
        rgb, depth = renderer.render(T)
    points, pixels = backproject(depth, renderer.K, T)
    on = surface.compute_distance(points.astype(np.float32)).numpy() < 0.002
    colours = rgb.reshape(-1, 3)[pixels[on]].astype(float) + 1.0
    return float((colours / colours.sum(axis=1, keepdims=True)).std(axis=0).mean()), int(on.sum())


@pytest.fixture(scope="module")
def counter(tmp_path_factory):
    root = tmp_path_factory.mktemp("scanned")
    return [load_scene(write_holdout_scene("scanned_counter", root / f"s{s}", s)) for s in (0, 1)]


@pytest.mark.parametrize("which", ["bundled", "holdout0", "holdout1"])
def test_scans_stand_in_the_roi_and_render_with_their_textures(counter, which):
    scene = load_scene("scanned_objects") if which == "bundled" else counter[int(which[-1])]
    model, _ = scene.model()
    scans = [model.mesh(i).name for i in range(model.nmesh)]
    assert len(scans) >= 4 and set(scans) <= set(SCANNED_OBJECTS)
    assert scene.level == "object"
    model, data = scene.model()
    ids = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]
    for mesh in geom_meshes(model, data, ids):
        lo, hi = mesh.bounds
        assert np.all(lo >= scene.roi_min - 1e-6) and np.all(hi <= scene.roi_max + 1e-6)
    gt = scene.ground_truth_mesh()
    spread, count = _chroma_spread(scene, scene.eval_views[0])
    assert count > 1000  # the scans are in view ...
    assert spread > 0.05  # ... and show their printed labels, not one flat colour
    assert len(gt.faces) > len(scans) * 16384  # every scan's whole surface is ground truth


def test_the_holdout_kind_is_seeded_and_self_contained(counter, tmp_path):
    again = load_scene(write_holdout_scene("scanned_counter", tmp_path / "again", 0))
    assert again.mjcf_path.read_text() == counter[0].mjcf_path.read_text()
    assert counter[0].mjcf_path.read_text() != counter[1].mjcf_path.read_text()
    # the scans' files lie in the scene's folder: the folder can be moved as a whole
    files = re.findall(r'file="([^"]+)"', counter[0].mjcf_path.read_text())
    assert any(f.endswith(".msh") for f in files)
    assert all("/" not in f and (counter[0].mjcf_path.parent / f).is_file() for f in files)
