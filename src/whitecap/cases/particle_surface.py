"""The surface of a solid drawn as particles: the union of the particles' cells.

A boundary particle of an SPH case stands for the cell of side dp around it
(GenCase fills shapes on a lattice of spacing dp, one particle per cell), so
the solid is the union of those cubes: its faces lie dp/2 outside the outer
particles and dp/2 inside the inner ones, where the fluid's own particles,
dp away from the wall's, meet it. Extracting the exposed cube faces gives:

- the flat faces of boxes exactly (a tank wall, a building), within float
  rounding, where marching cubes or a smoothed level set would bevel every
  edge and corner by about dp;
- a closed (watertight) surface for any set of cells, so a wall one particle
  thick comes out as a closed slab of thickness dp, never a blob or a sheet
  with holes;
- openings where the case has them: nothing is drawn where there are no
  particles (a tank's open top stays open).

Curved shapes come out as steps of dp, the resolution the solver saw them at.
Particles off the lattice (a shape drawn rotated) are snapped to the nearest
cell and the grid is closed (dilated then eroded by one cell), so that a layer
whose particles fall into neighbouring cells has no holes.
"""

from __future__ import annotations

import numpy as np

#: particles farther than this fraction of dp from their lattice cell's centre mean the shape is off the lattice
LATTICE_TOLERANCE = 0.2


def cell_surface(points: np.ndarray, dp: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of the union of the cubes of side ``dp``
    centred on ``points``; faces wind counter-clockwise seen from outside."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    origin = pts[0]  # the lattice through the particles
    f = (pts - origin) / dp
    ijk = np.rint(f).astype(np.int64)
    off_lattice = np.abs(f - ijk).max() > LATTICE_TOLERANCE
    lo = ijk.min(0) - 2
    ijk -= lo
    occ = np.zeros(tuple(ijk.max(0) + 3), bool)
    occ[tuple(ijk.T)] = True
    if off_lattice:
        from scipy import ndimage

        occ = ndimage.binary_closing(occ, structure=np.ones((3, 3, 3), bool))
    quads = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for side in (1, -1):
            nb = np.roll(occ, -side, axis=axis)
            cells = np.argwhere(occ & ~nb)  # the grid has empty cells on every side: roll wraps onto empties
            if not len(cells):
                continue
            base = cells.copy()
            base[:, axis] += 1 if side > 0 else 0  # the face's plane on the corner lattice
            corners = []
            for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                c = base.copy()
                c[:, u] += du
                c[:, v] += dv
                corners.append(c)
            q = np.stack(corners, 1)  # (n, 4, 3) counter-clockwise about +axis
            quads.append(q if side > 0 else q[:, ::-1])
    q = np.concatenate(quads)
    corners, inverse = np.unique(q.reshape(-1, 3), axis=0, return_inverse=True)
    idx = inverse.reshape(-1, 4)
    faces = np.concatenate([idx[:, [0, 1, 2]], idx[:, [0, 2, 3]]])
    vertices = origin + (corners + lo - 0.5) * dp
    return vertices, faces
