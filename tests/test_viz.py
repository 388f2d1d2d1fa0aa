"""open3d_pnerf.viz: interactive plotly views that need no display."""

import re

import numpy as np
import open3d as o3d
import pytest

from open3d_pnerf.errors import InputError
from open3d_pnerf.viz import geometry_figure, notebook_view


def test_geometry_figure_draws_a_coloured_mesh_and_points_coloured_by_sigma():
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=20)
    mesh.paint_uniform_color([1.0, 0.5, 0.0])
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random((500, 3))))
    sigma = np.linspace(0.001, 0.05, 500)
    fig = geometry_figure(mesh, cloud, sigma, max_points=100, max_triangles=200)
    surface, points = fig.data
    assert surface.type == "mesh3d" and len(surface.i) <= 200 and surface.vertexcolor[0] == "rgb(255,128,0)"
    assert points.type == "scatter3d" and len(points.x) == 100
    assert points.marker.colorbar.title.text == "depth sigma (mm)" and max(points.marker.color) <= 50.0
    assert "plotly" in fig.to_html(include_plotlyjs=False)  # renders without a display
    with pytest.raises(InputError, match="one value per point"):
        geometry_figure(point_cloud=cloud, point_sigma=sigma[:10])
    with pytest.raises(InputError):
        geometry_figure()


def test_notebook_view_carries_plotly_js_for_a_reader_without_network():
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(1).random((50, 3))))
    html = notebook_view(geometry_figure(point_cloud=cloud)).data
    assert "Plotly.newPlot" in html and "scatter3d" in html
    assert len(html) > 1_000_000 and not re.search(r"<script[^>]+src=", html)  # plotly.js inline, nothing to download
    lean = notebook_view(geometry_figure(point_cloud=cloud), plotlyjs="cdn").data
    assert "Plotly.newPlot" in lean and len(lean) < 100_000
    assert re.search(r'<script[^>]+src="https://cdn\.plot\.ly/plotly-[\d.]+\.min\.js"', lean)
    with pytest.raises(InputError, match="plotlyjs must be"):
        notebook_view(geometry_figure(point_cloud=cloud), plotlyjs=True)
