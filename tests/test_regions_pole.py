"""regions.detect's Tx pole choice: the paper's point farthest from the base, or the free region's
geodesic centre (the point whose largest distance to the region is smallest)."""
from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
from curves_fixture import bunny
from touch_fixture import touch_of

from retrotouch.nodes.regions.detect import RegionParams, detect_regions


def test_the_centre_pole_is_nearer_to_the_farthest_point_of_the_region_than_the_far_pole():
    mesh, far_regions, *_ = bunny()
    centre_regions = detect_regions(RegionParams(tx_pole="centre"), mesh, touch_of(mesh))
    assert centre_regions.far_vertex != far_regions.far_vertex
    assert np.array_equal(centre_regions.base_faces, far_regions.base_faces)
    solver = pp3d.MeshHeatMethodDistanceSolver(mesh.vertices, mesh.faces)
    sensing = np.unique(mesh.faces[far_regions.sensing_faces])
    eccentricity = {name: solver.compute_distance(r.far_vertex)[sensing].max()
                    for name, r in (("far", far_regions), ("centre", centre_regions))}
    assert eccentricity["centre"] < 0.8 * eccentricity["far"]
    # the far exclusion moves with the pole and the sensing region keeps its size
    assert centre_regions.exclusion_far[np.any(mesh.faces == centre_regions.far_vertex, axis=1)].all()
    area = lambda r: r.sensing_faces.sum()  # noqa: E731
    assert abs(area(centre_regions) - area(far_regions)) < 0.05 * area(far_regions)
