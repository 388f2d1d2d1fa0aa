"""Interactive 3D views for notebooks: plotly figures of meshes and uncertainty-coloured point
clouds. They need no display, GPU or OpenGL (unlike Open3D's own windows), so they work in
headless Jupyter, in CI, and in a notebook viewed on the web after it was executed.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .errors import InputError


def geometry_figure(mesh: o3d.geometry.TriangleMesh | None = None, point_cloud: o3d.geometry.PointCloud | None = None,
                    point_sigma: np.ndarray | None = None, max_triangles: int = 20_000, max_points: int = 8_000,
                    seed: int = 0, title: str | None = None):
    """A ``plotly.graph_objects.Figure`` of a coloured mesh and/or a point cloud.

    mesh: drawn with its vertex colours (decimated to at most `max_triangles`). point_cloud:
    at most `max_points` random points (seeded), coloured by `point_sigma` (M,) metres when
    given (a colour bar in millimetres), else by their own colours. Display it with
    ``fig.show()``, or :func:`notebook_view` for a notebook that is read as HTML.
    """
    try:
        import plotly.graph_objects as go
    except ImportError:  # pragma: no cover - plotly comes with open3d
        raise ImportError("geometry_figure needs plotly: pip install plotly") from None
    if mesh is None and point_cloud is None:
        raise InputError("geometry_figure needs a mesh, a point cloud or both")
    traces = []
    if mesh is not None and not mesh.is_empty():
        if len(mesh.triangles) > max_triangles:
            mesh = mesh.simplify_quadric_decimation(max_triangles)
        v, t = np.asarray(mesh.vertices).round(4), np.asarray(mesh.triangles)  # 0.1 mm: a smaller notebook
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else np.full((len(v), 3), 0.7)
        traces.append(go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=t[:, 0], j=t[:, 1], k=t[:, 2],
                                vertexcolor=[_rgb(c) for c in colors], name="mesh", flatshading=False))
    if point_cloud is not None and not point_cloud.is_empty():
        pts = np.asarray(point_cloud.points).round(4)
        keep = np.random.default_rng(seed).permutation(len(pts))[:max_points]
        if point_sigma is not None:
            point_sigma = np.asarray(point_sigma, np.float64)
            if point_sigma.shape != (len(pts),):
                raise InputError(f"point_sigma must have one value per point ({len(pts)},), got {point_sigma.shape}")
            sigma_mm = (1000 * point_sigma[keep]).round(2)
            marker = dict(size=1.5, color=sigma_mm, colorscale="Viridis", cmin=0,
                          cmax=float(np.percentile(sigma_mm, 95)), colorbar=dict(title="depth sigma (mm)"))
        else:
            colors = np.asarray(point_cloud.colors)[keep] if point_cloud.has_colors() else np.full((len(keep), 3), 0.5)
            marker = dict(size=1.5, color=[_rgb(c) for c in colors])
        traces.append(go.Scatter3d(x=pts[keep, 0], y=pts[keep, 1], z=pts[keep, 2], mode="markers", marker=marker,
                                   name="points"))
    fig = go.Figure(traces)
    fig.update_layout(scene=dict(aspectmode="data"), margin=dict(l=0, r=0, t=30 if title else 0, b=0), title=title,
                      height=500)
    return fig


def notebook_view(figure, plotlyjs: str = "inline"):
    """A plotly `figure` as a notebook output that draws wherever the notebook is opened as HTML
    (nbconvert, nbviewer), where ``figure.show()`` leaves only plotly's JupyterLab mimetype, which
    an exported notebook shows blank: an ``IPython.display.HTML``. plotlyjs: "inline" carries
    plotly.js inside the output (about 5 MB; draws with no network), "cdn" loads it from plotly's
    CDN (a few kB; for notebooks kept in a repository). Make it a cell's value (or ``display`` it)."""
    from IPython.display import HTML

    if plotlyjs not in ("inline", "cdn"):
        raise InputError(f"plotlyjs must be 'inline' or 'cdn', got {plotlyjs!r}")
    return HTML(figure.to_html(include_plotlyjs=True if plotlyjs == "inline" else "cdn", full_html=False))


def _rgb(color) -> str:
    r, g, b = (np.clip(np.asarray(color), 0, 1) * 255).round().astype(int)
    return f"rgb({r},{g},{b})"
