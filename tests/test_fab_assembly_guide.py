"""fab.assembly_guide: renderer visibility and one PDF page per trace after an overview."""
from __future__ import annotations

import re

import numpy as np
import trimesh
from fab_layouts import mesh_from_trimesh, section_layout

from retrotouch.nodes.fab.assembly_guide import Params, assembly_guide, render
from retrotouch.nodes.fab.outline import Params as OutlineParams
from retrotouch.nodes.fab.outline import outline
from retrotouch.nodes.fab.unfold import Params as UnfoldParams
from retrotouch.nodes.fab.unfold import unfold

SPHERE = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=40.0), "icosphere r40")


def test_render_sees_the_near_side_only():
    view = render(SPHERE, np.array([0.0, 0.0, 1.0]), 120)
    points = np.array([[0, 0, 40.0], [0, 0, -40.0], [28.0, 0, 28.0], [28.0, 0, -28.0]])
    np.testing.assert_array_equal(view.visible(points, 0.4), [True, False, True, False])
    px, depth = view.project(points[:1])
    np.testing.assert_allclose(px[0], [60, 60], atol=1.0)  # centred
    covered = np.isfinite(view.depth)
    disc = np.pi * (40.0 * view.scale) ** 2
    assert abs(covered.sum() - disc) < 0.05 * disc  # silhouette of the sphere


def test_guide_has_an_overview_and_one_page_per_trace():
    layout = section_layout(SPHERE, 3, 2)
    outlines = outline(OutlineParams(), unfold(UnfoldParams(), SPHERE, layout))
    files = assembly_guide(Params(image_px=100, views_per_trace=2), SPHERE, layout, outlines)
    pdf = files.contents["assembly_guide.pdf"]
    assert pdf.startswith(b"%PDF")
    assert len(re.findall(rb"/Type\s*/Page\b", pdf)) == 1 + 5
