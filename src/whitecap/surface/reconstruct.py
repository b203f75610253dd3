"""Per-frame surface reconstruction with splashsurf (pysplashsurf).

:func:`mesh_frame` is the pure per-frame function: one particle file and a
:class:`MeshParams` in, one mesh file out, a small stats dict back. It runs
unchanged in a worker process (see :mod:`whitecap.surface.driver`).

Radii. whitecap's particle radius r is half the particle spacing, and
splashsurf's particle radius means the same thing (its rest volume is the
cube of twice the radius), so the surface radius is simply
``radius_factor × r``. The smoothing length and the cube size are passed to
pysplashsurf as multiples of that surface radius, which is what it expects.
Our defaults (1.5, 1.2, 0.5) keep the kernel support at 3.6 r, enough
neighbours that thin sheets do not tear, and give a 0.75 r marching-cubes
cell, fine enough that the surface is not faceted: a sphere of particles
comes out watertight within 2 % of its volume.

Walls. The solver keeps particle centres a radius r from the domain walls,
and splashsurf puts the surface about where the particles end, so a fluid
resting against a wall comes out with a gap of about a radius between the
water and the wall: in a glass tank that reads as a film of air. For the walls
that the run says held the fluid (``RunInfo.solid_walls``), the vertices
within :data:`WALL_SNAP` r of a wall plane that face it are moved onto the
plane (:func:`close_wall_gap`), so the water meets the wall.

Threads. splashsurf runs on one thread (:func:`single_threaded_splashsurf`),
so a frame is the same bytes whichever executor meshes it; the mesh stage
runs frames side by side instead (a process pool, or Dask workers).
"""

from __future__ import annotations

import os
import time
import warnings
from numbers import Real
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import ConfigDict, model_validator

from .. import io as wio
from ..config import DEFAULT_UP, Mesh
from ..errors import InputError, WhitecapError
from ..io.mesh import SurfaceMesh, write_mesh
from ..timing import timer


class MeshParams(Mesh):
    """Everything one frame's reconstruction needs: the ``[mesh]`` section (its fields and defaults,
    from :class:`whitecap.config.Mesh`) and the run's own numbers (absolute radius). Frozen and
    picklable, so it travels to worker processes as it is."""

    model_config = ConfigDict(frozen=True)

    particle_radius: float  # simulation particle radius r [m]
    rest_density: float = 1000.0  # [kg/m³]
    up: str = DEFAULT_UP  # the input files' up axis
    #: Solid walls the surface is closed against: (axis 0-2, side -1 lower / +1 upper, plane coordinate [m]).
    walls: tuple = ()

    #: Fields that change the file, not the surface: left out of :meth:`as_dict` (the run's record of
    #: the settings, and the settings key that says whether a mesh is current).
    NOT_RECONSTRUCTION: ClassVar[frozenset[str]] = frozenset({"format"})

    @model_validator(mode="before")
    @classmethod
    def _run_numbers(cls, data: Any) -> Any:
        """The run's radius and density, checked before the section's own checks (one-line InputError)."""
        for name, what in (("particle_radius", "particle radius must be a positive length in metres"),
                           ("rest_density", "rest density must be positive")):
            v = data.get(name) if isinstance(data, dict) else None
            if v is not None and not (isinstance(v, Real) and float(v) > 0 and np.isfinite(float(v))):
                raise InputError(f"mesh: {what} (got {v})")
        return data

    @property
    def surface_radius(self) -> float:
        """Radius handed to splashsurf [m]."""
        return self.radius_factor * self.particle_radius

    def check(self) -> "MeshParams":
        """Warn of settings that make a poor surface (bad ones are refused on construction)."""
        if self.cube_size > 1.0:
            warnings.warn(
                f"mesh: cube_size {self.cube_size} is above 1 surface radius; the surface will look faceted "
                "and thin sheets may tear (splashsurf recommends 0.5-0.75)",
                UserWarning, stacklevel=2,
            )
        return self

    def splashsurf_kwargs(self) -> dict:
        """Keyword arguments of ``pysplashsurf.reconstruction_pipeline`` (not the particles)."""
        return dict(
            particle_radius=self.surface_radius,
            rest_density=self.rest_density,
            smoothing_length=self.smoothing_length,  # multiple of the surface radius
            cube_size=self.cube_size,  # multiple of the surface radius
            iso_surface_threshold=self.iso_surface_threshold,
            multi_threading=False,  # one thread in any case (single_threaded_splashsurf)
            mesh_cleanup=self.mesh_cleanup,
            mesh_smoothing_iters=self.mesh_smoothing_iters or None,
            mesh_smoothing_weights=self.mesh_smoothing_weights,
            mesh_smoothing_weights_normalization=self.mesh_smoothing_weights_normalization,
            normals_smoothing_iters=self.normals_smoothing_iters or None,
            compute_normals=True,
        )

    def as_dict(self) -> dict:
        """The reconstruction's settings, every field but :data:`NOT_RECONSTRUCTION`, in the order run.json
        has always listed them (r first, the rest density after the iso value), so its bytes stay the same."""
        d = self.model_dump(exclude=set(self.NOT_RECONSTRUCTION))
        keys = [k for k in d if k not in ("particle_radius", "rest_density")]
        at = keys.index("iso_surface_threshold") + 1
        return {k: d[k] for k in ["particle_radius", *keys[:at], "rest_density", *keys[at:]]}


def params_from_config(particle_radius: float, config: Mesh | None = None, rest_density: float = 1000.0,
                       **extra) -> MeshParams:
    """MeshParams from a ``[mesh]`` section (every field of it) and the run's particle radius."""
    section = (config or Mesh()).model_dump()
    return MeshParams(**section, particle_radius=float(particle_radius), rest_density=float(rest_density),
                      **extra).check()


#: Environment variable that sizes rayon's global thread pool, which splashsurf's parallel code runs on.
RAYON_THREADS = "RAYON_NUM_THREADS"


def single_threaded_splashsurf() -> None:
    """Give splashsurf one thread, so that its output is the same bytes in every process.

    splashsurf (Rust, on rayon's global thread pool) splits its work between
    threads and adds the pieces in the order they finish: the vertices come out
    in another order, and the sums that follow (mesh smoothing, vertex normals,
    the interpolated velocity) add the same terms in another order. With more
    than one thread the last bits of positions, normals and velocities
    therefore change from run to run, whatever pysplashsurf's
    ``multi_threading`` flag says (its post-processing is parallel regardless).
    :func:`_snap` hides nearly all of that, but a value that lies within that
    noise of a rounding boundary still comes out differently. With one thread
    splashsurf's output is the same, bit for bit, in any process.

    rayon reads the variable once, when the process first uses its pool, so this
    runs before every splashsurf call whitecap makes (a worker process, local or
    Dask, makes its first one here). A process that called pysplashsurf itself
    before whitecap did keeps the pool it started with.
    """
    os.environ[RAYON_THREADS] = "1"


def reconstruct(positions: np.ndarray, velocities: np.ndarray | None, params: MeshParams,
                source: str = "<memory>") -> SurfaceMesh:
    """The surface of one particle cloud. No particles give an empty mesh."""
    single_threaded_splashsurf()
    import pysplashsurf

    pos = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(pos) == 0:
        return SurfaceMesh.empty()
    attrs = None
    if params.interpolate_velocity and velocities is not None:
        attrs = {"velocity": np.ascontiguousarray(velocities, dtype=np.float64).reshape(-1, 3)}
    try:
        with timer("mesh.splashsurf"):
            mesh, _ = pysplashsurf.reconstruction_pipeline(pos, attributes_to_interpolate=attrs,
                                                           **params.splashsurf_kwargs())
    except Exception as exc:  # pysplashsurf raises plain exceptions on failures
        raise WhitecapError(f"{source}: splashsurf reconstruction failed: {exc}") from None
    pa = mesh.point_attributes
    tri = mesh.mesh
    assert isinstance(tri, pysplashsurf.TriMesh3d)  # triangles: no quads are asked for
    verts = _snap(tri.vertices)
    normals = _snap(pa["normals"]) if "normals" in pa else np.zeros_like(verts)
    vel = _snap(pa["velocity"]) if "velocity" in pa else np.zeros_like(verts)
    tie = vel
    if params.walls:
        # Vertices moved onto a wall edge or corner can coincide; where they do,
        # their place before the move still orders them reproducibly.
        tie = np.hstack([vel, verts])
        verts, normals = close_wall_gap(verts, normals, params.walls, params.particle_radius)
        verts, normals = _snap(verts), _snap(normals)
    with timer("mesh.canonical_order"):
        order, faces = canonical_order(verts, normals, np.asarray(tri.triangles, dtype=np.int64), tie)
    return SurfaceMesh(verts[order], faces, normals[order], {"velocity": vel[order]}, source=source)


#: Vertices closer to a solid wall than this many simulation radii r, and facing it, move onto it.
#: Particle centres stay r from a wall and the surface lies up to about another r beyond them
#: (measured: up to 0.55-0.77 r for water at rest in a tank; 1.1 r on the rounded vertical edge
#: where two walls meet), so 1.5 r takes the whole gap and nothing farther.
WALL_SNAP = 1.5
#: A vertex faces a wall when its normal is within about 75 degrees of the wall's outward normal.
WALL_FACING = 0.25


def walls_from_run(info) -> tuple:
    """``MeshParams.walls`` for a run's solid walls (see :meth:`RunInfo.solid_walls`)."""
    lo, hi = info.domain["lower"], info.domain["upper"]
    out = []
    for w in info.solid_walls():
        axis, side = "xyz".index(w[0]), (1 if w[1] == "+" else -1)
        out.append((axis, side, float(hi[axis] if side > 0 else lo[axis])))
    return tuple(out)


def close_wall_gap(verts: np.ndarray, normals: np.ndarray, walls, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Move the vertices that face a solid wall and lie within WALL_SNAP·r of it onto its plane.

    ``walls``: (axis, side, coordinate) triples; ``side`` is the wall's
    outward normal along ``axis`` (+1 for the upper face). Only vertices
    whose normal n has n·side > WALL_FACING move, so the free surface meeting
    the wall stays (its rim triangles stretch down to the wall) and a sheet
    flying past a wall keeps its far side. Facing is judged on the original
    normals, so a vertex on the rounded edge where two walls meet goes onto
    both. Vertices beyond a plane are put on it. A moved vertex's normal takes
    the wall's normal component.
    """
    v = np.array(verts, dtype=np.float64, copy=True)
    n = np.array(normals, dtype=np.float64, copy=True)
    n0 = np.asarray(normals, dtype=np.float64)
    for axis, side, coord in walls:
        d = (coord - v[:, axis]) * side  # distance inside the wall plane [m]
        move = ((d < WALL_SNAP * r) & (n0[:, axis] * side > WALL_FACING)) | (d < 0)
        v[move, axis] = coord
        n[move, axis] = side
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=n, where=length > 0)
    return v, n


#: Vertex positions [m], normals [-] and velocities [m/s] are rounded to multiples of this (~1e-6).
SNAP = 2.0**-20


def _snap(a: np.ndarray) -> np.ndarray:
    """Round to multiples of :data:`SNAP`.

    A guard beside :func:`single_threaded_splashsurf`: should splashsurf's
    last bits ever differ (a pool started with more threads, another build of
    it), a component near zero would round to a different float32. Rounding
    far above that noise keeps the files reproducible in nearly every case; it
    is far below anything a renderer can show.
    """
    return np.round(np.asarray(a, dtype=np.float64) * (1.0 / SNAP)) * SNAP


def canonical_order(vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray,
                    extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A vertex permutation and remapped faces that depend on the geometry only.

    splashsurf with several threads emits the same vertices in a different
    order each time; sorting them by position (normals, then ``extra``, break
    ties) and the faces by their vertex indices makes a mesh file byte-for-byte
    reproducible, whatever the threading or ``--jobs``. Winding is kept: a
    face is only rotated (to its lexicographically smallest rotation).
    """
    # Positions are multiples of SNAP (see _snap), so they are exact integers
    # in SNAP units: one int64 key holds x and y; only the rare runs of equal
    # (x, y) are then re-sorted on the full key. A full lexicographic sort of
    # every vertex costs several times more.
    q = np.rint(vertices * (1.0 / SNAP)).astype(np.int64)
    if len(q) and np.abs(q[:, :2]).max() < 2**31:
        key = ((q[:, 0] + 2**31) << 32) | (q[:, 1] + 2**31)
    else:  # beyond about 2 km from the origin: sort on x alone first
        key = q[:, 0]
    order = np.argsort(key)
    ks = key[order]
    tie = np.flatnonzero(ks[1:] == ks[:-1])
    if tie.size:
        pos = np.union1d(tie, tie + 1)
        sub = order[pos]
        keys = [normals[sub, 2], normals[sub, 1], normals[sub, 0], q[sub, 2], q[sub, 1], q[sub, 0]]
        if extra is not None:
            keys = [extra[sub, k] for k in range(extra.shape[1] - 1, -1, -1)] + keys
        order[pos] = sub[np.lexsort(keys)]
    if len(faces) == 0:
        return order, faces.reshape(0, 3)
    idx_t = np.int32 if len(order) < 2**31 else np.int64  # half the memory traffic of int64
    rank = np.empty(len(order), dtype=idx_t)
    rank[order] = np.arange(len(order), dtype=idx_t)
    f = rank[faces]
    # Rotate each triangle (same winding) so its smallest index leads, ...
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    lead_b = (b < a) & (b < c)
    lead_c = (c < a) & (c < b)
    f = np.stack([np.where(lead_b, b, np.where(lead_c, c, a)),
                  np.where(lead_b, c, np.where(lead_c, a, b)),
                  np.where(lead_b, a, np.where(lead_c, b, c))], axis=1)
    # ... or, for the rare degenerate one with a repeated index, to its
    # lexicographically smallest rotation, which is unambiguous.
    for k in np.flatnonzero((a == b) | (b == c) | (a == c)):
        f[k] = min((tuple(np.roll(f[k], -r)) for r in range(3)))
    nv = len(order)
    if nv < 2**21:  # nv**3 fits an int64: one sort key per triangle
        f64 = f.astype(np.int64)
        f = f[np.argsort((f64[:, 0] * nv + f64[:, 1]) * nv + f64[:, 2])]
    else:
        f = f[np.lexsort((f[:, 2], f[:, 1], f[:, 0]))]
    return order, f


def mesh_frame(in_path: str | Path, out_path: str | Path, params: MeshParams) -> dict:
    """Reconstruct one particle file into one mesh file (format from ``out_path``'s suffix).

    Pure: reads ``in_path``, writes ``out_path`` atomically, returns stats
    (particles, vertices, faces, seconds).
    """
    t0 = time.perf_counter()
    opts: dict[str, Any] = {"up": params.up} if params.up != "z" else {}
    if not params.interpolate_velocity:  # then files without a velocity array are fine
        opts["require_velocity"] = False
    frame = wio.read(in_path, **opts)
    frame.check_finite()
    surface = reconstruct(frame.positions, frame.velocities, params, source=str(in_path))
    with timer("mesh.write"):
        write_mesh(out_path, surface)
    return {
        "in": str(in_path),
        "out": str(out_path),
        "particles": len(frame),
        "vertices": len(surface.vertices),
        "faces": len(surface.faces),
        "seconds": time.perf_counter() - t0,
    }
