"""Rigid bodies as triangle meshes for pictures: the zero isosurface of each body's SDF grid, posed.

The isosurface is what the MPM's contact sees of a body (primitive, mesh file or URDF link
alike), so the picture shows the contact shape, not a nicer one. Contouring uses VTK's
flying-edges marching cubes (VTK is the 3D renderer's library already).
"""

from __future__ import annotations

import numpy as np

from cosim.render.frame import Mesh


def sdf_surface(grid) -> Mesh:
    """Body-frame triangle mesh (vertices (V, 3) [m], faces (F, 3)) of an ``SDFGrid``'s zero level."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

    values = np.asarray(grid.values, dtype=np.float64)
    image = vtkImageData()
    image.SetDimensions(*values.shape)
    image.SetOrigin(*np.asarray(grid.origin, dtype=np.float64))
    image.SetSpacing(grid.spacing, grid.spacing, grid.spacing)
    image.GetPointData().SetScalars(numpy_to_vtk(values.ravel(order="F"), deep=True))  # VTK: x fastest
    contour = vtkFlyingEdges3D()
    contour.SetInputData(image)
    contour.SetValue(0, 0.0)
    contour.ComputeNormalsOff()
    contour.Update()
    poly = contour.GetOutput()
    if poly.GetNumberOfPoints() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    vertices = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    faces = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    return vertices, faces


def posed(mesh: Mesh, position: np.ndarray, rotation: np.ndarray) -> Mesh:
    """``mesh`` moved from its body frame to the world: x_world = R x_body + p."""
    vertices, faces = mesh
    return vertices @ np.asarray(rotation).T + np.asarray(position), faces


def rigid_geometry(grids: list, poses: list[list[tuple[np.ndarray, np.ndarray]]], dim: int) -> list[list]:
    """Per saved frame, each rigid body as ``Frame.rigid`` wants it: posed isosurface meshes in 3D,
    posed surface points (the SDF nodes within half a spacing of the surface) in 2D.

    ``poses``: per frame, (position, rotation) of each body, in the order of ``grids``.
    """
    if dim == 3:
        local = [sdf_surface(g) for g in grids]
        return [[posed(m, p, R) for m, (p, R) in zip(local, frame)] for frame in poses]
    from cosim.couplers.sdf import surface_points

    local = [surface_points(g) for g in grids]
    return [[p + pts @ R.T for pts, (p, R) in zip(local, frame)] for frame in poses]
