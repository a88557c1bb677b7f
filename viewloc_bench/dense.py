"""Learning time of a dense mesh: an LM-O part cut into over a million faces.

The bench's own parts have at most 45,666 faces, while a CAD export of an
industrial part often has hundreds of thousands. Midpoint subdivision
(``trimesh.remesh.subdivide``, colours interpolated) multiplies the faces by
four per step without changing the shape, so the figure is the cost of the
faces alone: the LM-O driller's 25,306 faces become 1,619,584 after three
steps, under the upload limit of 2,000,000
(:data:`viewloc_core.mesh.MAX_FACES`). The issue's target is learning from
a mesh within 60 s.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import trimesh

from viewloc_bench.lmo import derived_mesh
from viewloc_bench.sets import BenchObject
from viewloc_core.mesh import mesh_vertex_colours

#: Midpoint subdivisions of the source mesh (each multiplies the faces by 4).
SUBDIVISIONS = 3


def dense_mesh(mesh_path: Path, out_dir: Path, subdivisions: int = SUBDIVISIONS) -> Path:
    """The mesh at ``mesh_path`` subdivided ``subdivisions`` times, as a PLY
    in ``out_dir`` (written once, :func:`viewloc_bench.lmo.derived_mesh`).

    Returns
    -------
    Path
        The dense PLY, vertex colours kept when the source has them.
    """

    def subdivided(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        rgb = mesh_vertex_colours(mesh)
        colours = None if rgb is None else rgb.astype(np.float64)
        for _ in range(subdivisions):
            if colours is None:
                vertices, faces = trimesh.remesh.subdivide(vertices, faces)
            else:
                vertices, faces, attributes = trimesh.remesh.subdivide(
                    vertices, faces, vertex_attributes={"rgb": colours})
                colours = attributes["rgb"]
        return trimesh.Trimesh(vertices, faces, process=False,
                               vertex_colors=None if colours is None
                               else np.round(colours).astype(np.uint8))

    dest = Path(out_dir) / f"{Path(mesh_path).stem}_x{4**subdivisions}.ply"
    return derived_mesh(mesh_path, dest, subdivided)


def dense_object(obj: BenchObject, out_dir: Path,
                 subdivisions: int = SUBDIVISIONS) -> tuple[BenchObject, int]:
    """``obj`` with its mesh replaced by the dense one, and that mesh's faces."""
    path = dense_mesh(obj.mesh_path, out_dir, subdivisions)
    source = trimesh.load(obj.mesh_path, force="mesh", process=False)
    assert isinstance(source, trimesh.Trimesh)
    faces = len(source.faces) * 4**subdivisions
    return dataclasses.replace(obj, name=f"{obj.name}-x{4**subdivisions}", mesh_path=path), faces
