"""A dense mesh reduced to a face budget before it is learned.

Learning renders the mesh a few hundred times (training views, contour
views) with Mesa's software rasteriser, whose cost grows with the faces:
the LM-O ape subdivided to 747,392 faces (the same shape) took 103 s to
learn on the 2-core machine, 70 s of it in the renders, against 26 s at its
own 11,678 faces. CAD exports of industrial parts often have hundreds of
thousands of faces, mostly on finely tessellated curves, which the image of
a part a few hundred pixels across cannot show.

Quadric edge collapse (Garland & Heckbert 1997, "Surface simplification
using quadric error metrics", as ``fast_simplification`` implements it
behind ``trimesh.Trimesh.simplify_quadric_decimation``) removes the faces
whose loss changes the surface least, so flat areas lose faces first and
silhouettes keep their shape: the ape reduced from 747,392 to 50,000 faces
kept every vertex within 0.31 mm of an original one (99 % within 0.14 mm;
its diameter is 102 mm).

Colours survive as vertex colours: each kept vertex takes the colour of the
nearest original vertex (a texture is sampled at the original vertices'
UVs first). A mesh within the budget is returned as it is.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from viewloc_core.mesh import mesh_vertex_colours

#: Aggressiveness of the quadric collapse (``fast_simplification``'s
#: ``agg``, 0-10, default 7) tried in turn when the default opens a closed
#: mesh. At 3 it may stop well above the budget (the box's hull: 37,662 of
#: 15,000 faces), so it comes last.
_CLOSED_RETRY_AGGRESSION = (5, 3)


def simplified(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """``mesh`` reduced to ``max_faces`` faces, in the same frame and unit.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Checked mesh in mm (:func:`viewloc_core.mesh.load_mesh`).
    max_faces : int
        Face budget, at least 4.

    Returns
    -------
    trimesh.Trimesh
        ``mesh`` itself when it has at most ``max_faces`` faces; otherwise
        a new mesh of about ``max_faces`` faces (the collapses stop at the
        count, or a little above it where no edge may collapse without
        folding the surface) whose vertices lie on or near the original
        surface, with vertex colours when ``mesh`` has colours; watertight
        when ``mesh`` is, unless no aggressiveness tried keeps it so.
    """
    if max_faces < 4:
        raise ValueError(f"max_faces must be at least 4, got {max_faces}")
    if len(mesh.faces) <= max_faces:
        return mesh
    # fast_simplification takes only writeable arrays, and a mesh's may be
    # read-only views of trimesh's cache (a mesh built from another's
    # ``triangles``): it gets fresh copies.
    source = trimesh.Trimesh(np.array(mesh.vertices, np.float64), np.array(mesh.faces, np.int64),
                             process=False)
    reduced = source.simplify_quadric_decimation(face_count=max_faces)
    # The result's test first: it is the smaller mesh (the input's costs
    # about half a second at 1.6 million faces).
    if not reduced.is_watertight and mesh.is_watertight:
        # At its default aggressiveness (7) the collapse sometimes pinches a
        # closed surface: an edge left with three faces, the part cut in
        # two bodies. The visual hull of a 90 x 39.5 x 107 mm box (145,096
        # faces to 15,000) was; at aggressiveness 5 it stays closed and
        # reaches the budget. A closed mesh stays closed where it can: the
        # collapses are redone less aggressively and the first closed
        # result is kept. Some stay open at every aggressiveness (the LM-O
        # hole puncher, 31,952 faces to 15,576, at 1 to 7): the default
        # result stands.
        for aggression in _CLOSED_RETRY_AGGRESSION:
            retry = source.simplify_quadric_decimation(face_count=max_faces,
                                                       aggression=aggression)
            if retry.is_watertight:
                reduced = retry
                break
    colours = mesh_vertex_colours(mesh)
    out = trimesh.Trimesh(np.asarray(reduced.vertices, np.float64),
                          np.asarray(reduced.faces, np.int64), process=False)
    out.remove_unreferenced_vertices()
    if colours is not None:
        # Each kept vertex lies where the collapse placed it, on or next to
        # the original surface: the nearest original vertex's colour is the
        # surface's colour there.
        _, nearest = cKDTree(np.asarray(mesh.vertices, np.float64)).query(out.vertices)
        rgba = np.full((len(out.vertices), 4), 255, np.uint8)
        rgba[:, :3] = colours[nearest]
        out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=rgba)
    return out
