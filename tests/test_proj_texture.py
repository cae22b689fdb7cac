"""The projection.textures sink: atlas baking, file names, GLB/OBJ readability."""
from __future__ import annotations

import dataclasses
import io

import cv2
import numpy as np
import pytest
import trimesh

from proj_fixtures import bunny_layout, bunny_mm, bunny_regions, demo_rig
from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.scene import load_scene
from retrotouch.nodes.geometry.triangles import areas, corners
from retrotouch.nodes.projection.depth_frames import demo_trajectory
from retrotouch.nodes.projection.raster import render_textured
from retrotouch.nodes.projection.render import RenderStyle, render_layers
from retrotouch.nodes.projection.atlas import face_uv_pixels
from retrotouch.nodes.projection.textures import TextureParams, layout_atlas, name_from_source, projection_textures


@pytest.fixture(scope="module")
def standing_bunny():
    """The 3000-vertex bunny (mm) and its regions."""
    mesh = bunny_mm(3000)
    return mesh, bunny_regions(mesh)


@pytest.fixture(scope="module")
def regions(standing_bunny):
    return standing_bunny[1]


@pytest.fixture(scope="module")
def baked(tmp_path_factory, standing_bunny):
    mesh, regions = standing_bunny
    layout = bunny_layout(mesh, 8, 6)
    params = TextureParams(texture_px=1024)
    files = projection_textures(params, mesh, regions, layout)
    out = tmp_path_factory.mktemp("run")
    for rel, data in files.contents.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(data)
    return mesh, layout, params, files, out


def test_file_names_do_not_collide(baked):
    *_, files, _ = baked
    assert sorted(files.contents) == [
        "projection/bunny_layout.glb",
        "projection/bunny_layout.mtl",
        "projection/bunny_layout.obj",
        "projection/bunny_scene.npz",
        "projection/bunny_texture.png",
    ]
    obj = files.contents["projection/bunny_layout.obj"].decode()
    assert "mtllib bunny_layout.mtl" in obj
    assert "map_Kd bunny_texture.png" in files.contents["projection/bunny_layout.mtl"].decode()


def test_exports_load_with_the_texture(baked):
    mesh, _, params, files, out = baked
    glb = trimesh.load(io.BytesIO(files.contents["projection/bunny_layout.glb"]), file_type="glb", force="mesh")
    assert glb.visual.material.baseColorTexture.size == (params.texture_px, params.texture_px)
    assert np.isclose(glb.area * 1e6, trimesh.Trimesh(mesh.vertices, mesh.faces).area)  # GLB in metres
    obj = trimesh.load(out / "projection/bunny_layout.obj", force="mesh")
    assert obj.visual.material.image.size == (params.texture_px, params.texture_px)
    assert len(obj.faces) == len(mesh.faces)


def test_crossings_and_curves_are_baked_where_they_map(baked):
    mesh, layout, params, files, _ = baked
    tex = cv2.imdecode(np.frombuffer(files.contents["projection/bunny_texture.png"], np.uint8), cv2.IMREAD_COLOR)
    atlas = layout_atlas(mesh, layout, params)
    px = np.rint(face_uv_pixels(atlas, layout.cells.faces, layout.cells.bary, params.texture_px)).astype(int)
    background = np.array([0xD8, 0xD8, 0xD8])
    at_crossings = tex[px[:, 1], px[:, 0]].astype(int)
    assert (np.abs(at_crossings - background).sum(axis=1) > 60).all()  # something is drawn on every crossing
    pads = tex[px[layout.pad, 1], px[layout.pad, 0]].astype(int)
    assert (np.abs(pads - [0x00, 0xA0, 0xE0]).sum(axis=1) < 60).all()  # pad colour (BGR)
    tx_rows = np.arange(layout.tx.offsets[0], layout.tx.offsets[1] - 1)
    mid = np.rint(face_uv_pixels(atlas, layout.tx.faces[tx_rows], layout.tx.bary[tx_rows], params.texture_px)).astype(int)
    tx_colour = tex[mid[:, 1], mid[:, 0]].astype(int)
    assert (np.abs(tx_colour - [0x20, 0x30, 0xD0]).sum(axis=1) < 90).mean() > 0.8


def test_scene_file_round_trips(baked):
    mesh, layout, _, _, out = baked
    scene = load_scene(out / "projection/bunny_scene.npz")
    assert scene.layer_names == ("tx", "rx")
    np.testing.assert_array_equal(scene.layer_points[0], layout.tx.points)
    np.testing.assert_array_equal(scene.faces, mesh.faces)
    assert np.allclose(np.linalg.norm(scene.layer_normals[1], axis=1), 1.0)


def test_layout_from_another_mesh_is_rejected(baked, regions):
    mesh, layout, *_ = baked
    small = type(mesh)(mesh.vertices, mesh.faces[:100], mesh.source)
    with pytest.raises(UserError, match="faces"):
        projection_textures(TextureParams(texture_px=256), small, regions, layout)


def test_name_from_source():
    assert name_from_source("builtin:bunny sha256:ab12") == "bunny"
    assert name_from_source("/data/my duck.ply sha256:00") == "my_duck"
    assert name_from_source("/data/duck_gao.ply") == "duck_gao"


def test_textured_route_agrees_with_projected_polylines(baked):
    """Both projector routes light the same places: textured-route pixels lie on the polyline route's lines."""
    _, _, _, _, out = baked
    scene = load_scene(out / "projection/bunny_scene.npz")
    assert [t.shape for t in scene.layer_textures] == [(1024, 1024, 3)] * 2
    rig = demo_rig(640, 360)
    T = rig.T_proj_cam @ demo_trajectory(1)[0]
    textured = render_textured(scene, 0, T, rig.projector).max(axis=2) > 128
    lines = render_layers(scene, T, rig.projector, RenderStyle(line_px=1))["tx"].max(axis=2) > 0
    assert textured.sum() > 200
    near_lines = cv2.dilate(lines.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert (textured & near_lines).sum() / textured.sum() > 0.9


def test_layout_without_rx_curves_or_cells(baked, regions, tmp_path):
    """A degenerate layout (no Rx curves, no crossings) still bakes: Tx lines only."""
    mesh, layout, *_ = baked
    empty_rx = dataclasses.replace(
        layout.rx, points=np.zeros((0, 3)), faces=np.zeros(0, np.int64), bary=np.zeros((0, 3)),
        offsets=np.zeros(1, np.int64), lengths_mm=np.zeros(0), end_reason=np.zeros(0, np.int8),
    )
    cells = dataclasses.replace(
        layout.cells, **{f: getattr(layout.cells, f)[:0] for f in
                         ("curve_a", "curve_b", "seg_a", "seg_b", "arc_a", "arc_b", "points", "faces", "bary")}
    )
    bare = dataclasses.replace(layout, rx=empty_rx, cells=cells, pad=np.zeros(0, bool))
    files = projection_textures(TextureParams(texture_px=256), mesh, regions, bare)
    tex = cv2.imdecode(np.frombuffer(files.contents["projection/bunny_texture.png"], np.uint8), cv2.IMREAD_COLOR)
    blue_rx = (tex[..., 0] > 150) & (tex[..., 2] < 100)
    red_tx = (tex[..., 2] > 150) & (tex[..., 0] < 100)
    assert red_tx.sum() > 100 and blue_rx.sum() == 0
    (tmp_path / "scene.npz").write_bytes(files.contents["projection/bunny_scene.npz"])
    assert load_scene(tmp_path / "scene.npz").layer_points[1].shape == (0, 3)


def test_textures_code_version_leaves_out_the_projector_runtime():
    """Editing calibration, rendering or tracking code must not rerun the projection.textures sink."""
    from retrotouch.graph.codeversion import module_hash

    seen, todo = set(), ["retrotouch.nodes.projection.textures"]
    while todo:
        name = todo.pop()
        if name not in seen:
            seen.add(name)
            todo.extend(module_hash(name)[1])
    runtime = {f"retrotouch.nodes.projection.{m}" for m in
               ("calibration", "camera", "cli", "depth_frames", "raster", "render", "smoothing", "structured_light", "tracking")}
    assert seen & runtime == set()
    assert "retrotouch.nodes.data.scene" in seen


def test_only_faces_within_paint_reach_get_charts_the_rest_show_background(baked):
    mesh, layout, params, files, out = baked
    atlas = layout_atlas(mesh, layout, params)
    assert 0.2 < atlas.charted.mean() < 0.95  # the layout's bands, not the whole mesh
    for curves in (layout.tx, layout.rx):
        assert atlas.charted[curves.faces].all()  # every face a curve segment runs through
    centroids = mesh.vertices[mesh.faces].mean(axis=1)
    for point, has_pad in zip(layout.cells.points, layout.pad):
        reach = layout.pad_radius_mm if has_pad else params.crossing_radius_mm
        assert atlas.charted[np.linalg.norm(centroids - point, axis=1) < reach].all()
    rest_uv = atlas.uv[atlas.faces[~atlas.charted]].reshape(-1, 2)
    assert np.ptp(rest_uv, axis=0).max() == 0.0  # one texel for all of them
    px = np.rint([rest_uv[0, 0] * params.texture_px - 0.5, (1 - rest_uv[0, 1]) * params.texture_px - 0.5]).astype(int)
    tex = cv2.imdecode(np.frombuffer(files.contents["projection/bunny_texture.png"], np.uint8), cv2.IMREAD_COLOR)
    window = tex[px[1] - 2 : px[1] + 3, px[0] - 2 : px[0] + 3].reshape(-1, 3)
    assert (window == [0xD8, 0xD8, 0xD8]).all()  # background all around it (bilinear sampling stays clean)
    scene = load_scene(out / "projection/bunny_scene.npz")
    for layer_texture in scene.layer_textures:
        assert (layer_texture[px[1] - 2 : px[1] + 3, px[0] - 2 : px[0] + 3] == 0).all()  # no light there


def test_glb_embeds_the_texture_png_as_written(baked):
    *_, files, _ = baked
    glb = trimesh.load(io.BytesIO(files.contents["projection/bunny_layout.glb"]), file_type="glb", force="mesh")
    embedded = np.asarray(glb.visual.material.baseColorTexture.convert("RGB"))
    png = cv2.imdecode(np.frombuffer(files.contents["projection/bunny_texture.png"], np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(embedded, png[:, :, ::-1])


def test_paint_follows_the_distance_to_the_layout(baked):
    """At random points of the charted faces, the texture (sampled bilinearly at the point's UV)
    shows a layer's colour where the point lies well inside that layer's trace (3D distance to its
    curves), and the background where it is well away from every curve and crossing."""
    from scipy.spatial import cKDTree

    from retrotouch.nodes.projection.atlas import curve_samples, texels_per_mm

    mesh, layout, params, files, _ = baked
    tex = cv2.imdecode(np.frombuffer(files.contents["projection/bunny_texture.png"], np.uint8), cv2.IMREAD_COLOR)
    atlas = layout_atlas(mesh, layout, params)
    rng = np.random.default_rng(7)
    tri = corners(mesh.vertices, mesh.faces)
    weight = areas(tri) * atlas.charted
    faces = rng.choice(len(tri), 100_000, p=weight / weight.sum())
    root, r2 = np.sqrt(rng.random(len(faces))), rng.random(len(faces))
    bary = np.stack([1 - root, root * (1 - r2), root * r2], axis=1)
    points = np.einsum("kj,kjd->kd", bary, tri[faces])
    px = face_uv_pixels(atlas, faces, bary, params.texture_px).astype(np.float32).reshape(-1, 1000, 2)
    colour = cv2.remap(tex, px[..., 0], px[..., 1], cv2.INTER_LINEAR).reshape(-1, 3).astype(int)
    margin = 1.5 / texels_per_mm(mesh, atlas, params.texture_px)
    half = layout.trace_width_mm / 2
    to_tx, to_rx, to_cell = (cKDTree(p).query(points)[0] for p in (curve_samples(layout.tx, 0.02), curve_samples(layout.rx, 0.02), layout.cells.points))
    clear_of_cells = to_cell > max(layout.pad_radius_mm, params.crossing_radius_mm + half) + margin
    for inside, other, bgr in ((to_tx, to_rx, [0x20, 0x30, 0xD0]), (to_rx, to_tx, [0xD0, 0x50, 0x20])):
        painted = (inside < half - margin) & (other > half + margin) & clear_of_cells
        assert painted.sum() > 1000
        assert (np.abs(colour[painted] - bgr).sum(axis=1) < 60).mean() > 0.99
    bare = (np.minimum(to_tx, to_rx) > half + margin) & clear_of_cells
    assert (np.abs(colour[bare] - 0xD8).sum(axis=1) < 60).mean() > 0.97
