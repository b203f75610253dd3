"""Rigid obstacles from watertight triangle meshes, static or moving.

Loading (host side): trimesh reads OBJ/STL/PLY; the mesh is checked for
watertightness (or repaired on request), transformed (scale, then rotations
about x, y, z in that order, then translation) and sampled into a signed
distance field on a regular grid with spacing ``sdf_resolution × r``, padded
by the kernel support. Distances (negative inside) come from libigl. The grid is cached on disk,
keyed by the mesh file's content, the transform and the resolution, so a second run starts at once.

Collision (Taichi, per particle and obstacle):

- broad phase: one AABB per obstacle, grown by the kernel support h; only
  particles inside it go further;
- narrow phase: trilinear interpolation of the SDF, whose gradient is the
  normal n;
- response: a penalty acceleration F = k·n·(−φ) for particles within the
  contact band (φ = sdf − r < 0, the particle's surface inside), a
  position projection after every constraint iteration so that sdf ≥ r
  (no particle inside), and a velocity response that removes the inward
  normal velocity and damps the tangential part by ``friction``.

Moving obstacles (sim/bodies.py): the SDF stays in the rest placement; each
step uploads every obstacle's pose (R, T) and step velocity u(x) = A·x + b, and
every kernel reads a particle at x_rest = Rᵀ(x − T) and turns the SDF gradient
back with R. The velocity response, friction included, acts on the velocity
relative to the body, v − u; the penalty and the projection use the body's pose
at the end of the step, so a pushing body moves the water with it; the density
map is read at the moved body. A static obstacle has R = I, T = 0, u = 0: the
same contact as before bodies could move (its runs match earlier versions'
frames for the first steps, then differ in the last bits, as the kernels
compile to different instruction orders).

Boundary density: like the domain walls, an obstacle adds ρ0·ψ(sdf) to a
nearby particle's density (the planar density map of Bender et al. 2019,
using the half-space kernel integral ψ) and ψ'(sdf)·n to the constraint
gradient. We chose this over boundary particles (Akinci et al. 2012)
because the SDF is needed for collisions anyway, it costs one lookup per
particle instead of thousands of extra neighbours, and it does not depend on
how well a surface is sampled; its error is the planar approximation on
strongly curved parts, smaller than a particle for shapes larger than h.
A dynamic body has none: with it a floating body rode a particle radius too
high (docs/obstacles.md, Floating bodies); the fluid meets it by contact alone, whose
momentum (projection, penalty, velocity response) the body takes back.
"""

import contextlib
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import taichi as ti

from ..config import Obstacle, Scene
from ..errors import InputError
from ..geometry import obstacle_transform, pose_matrix, pose_record
from ..io.atomic import write_arrays
from ..io.record import Pose
from ..resources import cache_dir
from ..timing import timer
from .grid import F1, F3, I1, ivec3, vec3
from .launch import TEMPLATE

# ndarrays of bodies' integer vectors and matrices (typed Any: Taichi's annotations are not Python types)
IV: Any = ti.types.ndarray(dtype=ivec3, ndim=1)
M3: Any = ti.types.ndarray(dtype=ti.math.mat3, ndim=1)
SDF_CACHE_VERSION = 2  # 2: meshes with inconsistent winding are refused or repaired
FAR = 1e6  # SDF value outside an obstacle's grid [m]
# Width of the contact band of the velocity response, × r: a particle counts as touching
# while sdf < r + CONTACT_BAND·r. The position projection leaves particles at sdf = r
# exactly; the band keeps them in contact despite the trilinear SDF's interpolation
# error and float rounding, and is thin enough (a twentieth of r) not to slow particles
# that merely pass close by.
CONTACT_BAND = 0.05
# Initial fluid particles keep this distance (× r) from a dynamic body: the lattice puts some
# exactly at r, where the trilinear SDF's error (up to ~0.1 r) has the first projection kick
# them, and through the coupling the body, sideways (measured: 0.3 m/s on a free 8 cm cube).
DYNAMIC_START_GAP = 1.25


# ============================================================================ host side
def load_mesh(path: Path, repair: bool = False):
    """A watertight trimesh from OBJ/STL/PLY, or InputError naming the file."""
    import trimesh

    if not path.is_file():
        raise InputError(f"{path}: obstacle mesh file not found")
    try:
        m = trimesh.load_mesh(str(path), process=False)
    except Exception as exc:
        raise InputError(f"{path}: not a readable mesh ({exc})") from None
    if m is None or len(m.faces) == 0:
        raise InputError(f"{path}: the mesh is empty (no triangles)")
    bad = ~np.isfinite(np.asarray(m.vertices)).all(axis=1)
    if bad.any():  # processing would drop them and report the hole they leave
        raise InputError(f"{path}: {int(bad.sum())} vertices are NaN or infinite (the first is vertex "
                         f"{int(np.argmax(bad)) + 1})")
    m.process()  # merge duplicate vertices, as a loader with process=True does
    if not m.is_watertight:
        if repair:
            trimesh.repair.fill_holes(m)
            trimesh.repair.fix_normals(m)
            m.merge_vertices()
        if not m.is_watertight:
            open_edges = len(trimesh.grouping.group_rows(m.edges_sorted, require_count=1))
            hint = "" if repair else "; set repair = true to try to close it"
            raise InputError(f"{path}: mesh is not watertight: {open_edges} open edges{hint}")
    if not m.is_winding_consistent:
        # Faces wound against their neighbours make the signed distance flip sign across
        # them: the obstacle would hold water inside and push it away outside.
        fixed = m.copy()
        trimesh.repair.fix_normals(fixed)  # consistent winding, outward (positive volume)
        flipped = int((np.asarray(fixed.faces) != np.asarray(m.faces)).any(axis=1).sum())
        if not repair:
            raise InputError(f"{path}: inconsistent winding: {flipped} of {len(m.faces)} faces are wound "
                             "against their neighbours; set repair = true to reorient them")
        m = fixed
    if m.volume < 0:  # consistently inside out: turn it outward
        m.invert()
    return m


def compute_sdf(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Signed distances (negative inside) of points to a watertight mesh, with libigl.

    libigl is exact (pseudo-normal sign, exact point-triangle distances). We
    measured point-cloud-utils to be faster but to return wrong magnitudes
    for some queries on large triangles (a box's faces), so we do not use it."""
    import igl

    s = igl.signed_distance(
        np.ascontiguousarray(points, np.float64), np.ascontiguousarray(vertices, np.float64),
        np.ascontiguousarray(faces, np.int64),
    )
    return np.asarray(s[0])


@dataclass
class SDFGrid:
    origin: np.ndarray  # world position of sample (0, 0, 0) [m]
    spacing: float  # [m]
    values: np.ndarray  # (nx, ny, nz) float32 [m]
    aabb_lo: np.ndarray  # mesh bounds [m]
    aabb_hi: np.ndarray
    beyond: float = FAR  # value outside the grid: FAR (free space); −FAR for an inverted wall

    def sample(self, pts: np.ndarray) -> np.ndarray:
        """Trilinear SDF at points (host side; ``beyond`` outside the grid)."""
        from scipy.ndimage import map_coordinates

        c = ((pts - self.origin) / self.spacing).T
        return map_coordinates(self.values, c, order=1, mode="constant", cval=self.beyond)

    def inverted(self) -> "SDFGrid":
        """The same surface with inside and outside swapped: a closed wall that holds the fluid
        inside it (the space within is free, everything beyond the surface, the grid's far
        field included, is wall). Host side only (the kernels read ``values`` with FAR outside)."""
        return SDFGrid(self.origin, self.spacing, -self.values, self.aabb_lo, self.aabb_hi, -self.beyond)

    def normal(self, pts: np.ndarray) -> np.ndarray:
        """Unit outward normals ∇sdf/|∇sdf| at points (host side; central differences of half a cell)."""
        pts = np.asarray(pts, np.float64)
        e = 0.5 * self.spacing
        g = np.stack([self.sample(pts + e * a) - self.sample(pts - e * a) for a in np.eye(3)], axis=1)
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)


def build_sdf(o: Obstacle, path: Path, r: float, pad: float) -> SDFGrid:
    M = obstacle_transform(o)
    dx = o.sdf_resolution * r
    raw = path.read_bytes() if path.is_file() else b""
    key = hashlib.sha256(
        raw + json.dumps([M.round(12).tolist(), dx, pad, o.repair, SDF_CACHE_VERSION]).encode()
    ).hexdigest()[:32]
    cached = cache_dir("sdf") / f"{key}.npz"
    if cached.is_file():
        try:
            z = np.load(cached)
            return SDFGrid(z["origin"], float(z["spacing"]), z["values"], z["aabb_lo"], z["aabb_hi"])
        except Exception:
            pass  # a damaged cache entry is recomputed
    m = load_mesh(path, o.repair)
    m.apply_transform(M)
    lo, hi = m.bounds[0] - pad, m.bounds[1] + pad
    dims = np.maximum(np.ceil((hi - lo) / dx).astype(int) + 1, 2)
    axes = [lo[a] + dx * np.arange(dims[a]) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    with timer("obstacles.sdf"):
        vals = compute_sdf(m.vertices, m.faces, pts).astype(np.float32).reshape(tuple(dims))
    grid = SDFGrid(lo.astype(np.float32), float(dx), vals,
                   m.bounds[0].astype(np.float32), m.bounds[1].astype(np.float32))
    with contextlib.suppress(OSError):  # a cache: a full or read-only disk only costs the next run the SDF
        write_arrays(cached, dict(origin=grid.origin, spacing=grid.spacing, values=vals, aabb_lo=grid.aabb_lo,
                                  aabb_hi=grid.aabb_hi))
    return grid


class PosedSDF:
    """An obstacle's SDF for host-side users such as the diffuse particles, at the obstacle's pose of
    a frame and of the frame before (for the body's velocity over the frame). Set them per frame
    with :meth:`at_frame`: run.json's records of the two poses (obstacle ``index``) where there are
    some, else its motion law's poses at those times. A static obstacle stays at rest."""

    def __init__(self, grid: SDFGrid, law, index: int):
        self.grid, self.law, self.index = grid, law, index
        self.R0 = self.R1 = np.eye(3)
        self.T0 = self.T1 = np.zeros(3)
        self.dt = 0.0

    def _pose(self, time: float, body: Pose | None) -> tuple[np.ndarray, np.ndarray]:
        if body is not None:
            M = pose_matrix(body)
            return M[:3, :3], M[:3, 3]
        return self.law.pose(time)

    def at_frame(self, time: float, body: Pose | None, dt: float = 0.0, prev: Pose | None = None) -> None:
        """The pose at ``time`` (record ``body``) and at ``time − dt`` (record ``prev``; without one,
        the pose this was last set to, or with dt = 0 the same pose: at rest over the frame)."""
        R1, T1 = self._pose(time, body)
        if dt <= 0:
            self.R0, self.T0 = R1, T1
        elif prev is not None or body is None:
            self.R0, self.T0 = self._pose(time - dt, prev)
        else:
            self.R0, self.T0 = self.R1, self.T1
        self.R1, self.T1, self.dt = R1, T1, float(dt)

    @property
    def moved(self) -> bool:
        return not (np.array_equal(self.R0, self.R1) and np.array_equal(self.T0, self.T1))

    def sample(self, pts: np.ndarray, before: bool = False) -> np.ndarray:
        """Signed distance at world points, the body at this frame's pose (or the last frame's)."""
        R, T = (self.R0, self.T0) if before else (self.R1, self.T1)
        return self.grid.sample((np.asarray(pts, np.float64) - T) @ R)  # x_rest = Rᵀ(x − T)

    def normal(self, pts: np.ndarray) -> np.ndarray:
        """Unit outward normals at world points, this frame's pose: R·n_rest."""
        return self.grid.normal((np.asarray(pts, np.float64) - self.T1) @ self.R1) @ self.R1.T

    def carry(self, pts: np.ndarray) -> np.ndarray:
        """Where the body takes points attached to it over the frame: R1 R0ᵀ (x − T0) + T1."""
        return ((np.asarray(pts, np.float64) - self.T0) @ self.R0) @ self.R1.T + self.T1

    def velocity(self, pts: np.ndarray) -> np.ndarray:
        """The body's velocity over the frame at world points (sim.bodies.step_velocity; 0 at rest)."""
        if self.dt <= 0:
            return np.zeros((len(pts), 3))
        from .bodies import step_velocity

        A, b = step_velocity(self.R0, self.T0, self.R1, self.T1, self.dt)
        return np.asarray(pts, np.float64) @ A.T + b


class Obstacles:
    """All obstacles of a scene: SDF grids on the host, packed for the kernels."""

    def __init__(self, scene: Scene, grids: list[SDFGrid], bodies: dict | None = None):
        self.scene = scene
        self.grids = grids
        self.bodies = bodies or {}  # {obstacle index: sim.bodies.RigidBody}
        self.entries = scene.obstacle
        from .bodies import motion_laws

        self.laws = motion_laws(scene)

    def __len__(self) -> int:
        return len(self.grids)

    def outside_mask(self, pos: np.ndarray) -> np.ndarray:
        """Initial fluid particles to keep: those at least one radius outside every obstacle."""
        r = self.scene.solver.particle_radius
        keep = np.ones(len(pos), bool)
        for k, (g, law) in enumerate(zip(self.grids, self.laws)):
            R, T = law.pose(0.0)
            gap = DYNAMIC_START_GAP * r if k in self.bodies else r
            keep &= g.sample((np.asarray(pos, np.float64) - T) @ R) >= gap  # x_rest = Rᵀ(x − T)
        return keep

    def posed_grids(self) -> list:
        """The SDFs for host-side users (the diffuse particles), each as a :class:`PosedSDF`."""
        return [PosedSDF(g, law, k) for k, (g, law) in enumerate(zip(self.grids, self.laws))]

    def collider(self, solver) -> "ObstacleCollider":
        return ObstacleCollider(self, solver)


def load_obstacles(scene: Scene) -> Obstacles | None:
    if not scene.obstacle:
        return None
    r = scene.solver.particle_radius
    h = scene.solver.kernel_support * r
    lo, hi = np.array(scene.domain.lower), np.array(scene.domain.upper)
    grids = []
    for k, o in enumerate(scene.obstacle):
        path = scene.resolve(o.mesh)
        g = build_sdf(o, path, r, pad=h + 2 * o.sdf_resolution * r)
        if (g.aabb_hi < lo).any() or (g.aabb_lo > hi).any():
            raise InputError(f"{path}: obstacle[{k}] lies outside the domain {lo.tolist()}..{hi.tolist()} "
                             "after its transform")
        grids.append(g)
    bodies = {}
    for k, o in enumerate(scene.obstacle):
        if o.dynamic:
            from .bodies import RigidBody

            m = load_mesh(scene.resolve(o.mesh), o.repair)
            m.apply_transform(obstacle_transform(o))
            bodies[k] = RigidBody(m, o, scene.domain.gravity, lo, hi, index=k)
    return Obstacles(scene, grids, bodies)


# ============================================================================ obstacles of run.json
#: A container whose closed mesh holds more than this fraction of the first frame's fluid is a
#: wall around the fluid (SPlisHSPlasH's isWall box), not a solid: its SDF is inverted.
FLUID_INSIDE_FRACTION = 0.5


def run_obstacle_grids(info, run_dir: Path, fluid: np.ndarray | None = None) -> list:
    """SDFs of the obstacles listed in run.json (``info.obstacles``: an imported case's tank,
    obstacles and bodies, cases/run_dir.py) for host-side users, each as a :class:`PosedSDF`
    whose pose comes per frame from run.json's ``bodies``. Meshes are found by
    ``io.run.obstacle_path`` and placed by ``geometry.obstacle_transform``; the grid spacing is the
    entry's ``sdf_resolution`` × r (default 1).

    A ``container`` that holds most of ``fluid`` (the first frame's positions) inside its closed
    mesh is a wall around the fluid: its SDF is inverted, so the particles stay inside it. A mesh
    that is not closed cannot bound a volume: it is left out, with a warning."""
    from pydantic import ValidationError

    from ..config import Solver
    from ..io.run import obstacle_path
    from ..progress import console
    from .bodies import MotionLaw

    r = float(info.particle_radius)
    h = float(info.extra.get("kernel_support") or Solver.model_fields["kernel_support"].default * r)
    where = Path(run_dir) / "run.json"
    out = []
    for k, e in enumerate(info.obstacles):
        if not e.mesh:
            raise InputError(f"{where}: field 'obstacles[{k}].mesh': expected a mesh file path")
        path = obstacle_path(e.mesh, info, run_dir)
        if path is None:
            raise InputError(f"{where}: field 'obstacles[{k}].mesh': {e.mesh} not found")
        keys = ("translate", "rotate", "scale", "sdf_resolution", "repair")
        given = e.model_dump()
        try:
            o = Obstacle(mesh=str(path), **{key: given[key] for key in keys if key in given})
        except ValidationError as exc:
            err = exc.errors()[0]
            field = ".".join(str(x) for x in err["loc"])
            raise InputError(f"{where}: field 'obstacles[{k}].{field}': {err['msg']}") from None
        try:
            g = build_sdf(o, path, r, pad=h + 2 * o.sdf_resolution * r)
        except InputError as exc:  # an open wall (or one wound both ways): no volume to keep particles out of
            console.print(f"[yellow]warning:[/] {exc}: obstacle[{k}] ({e.name or path.name}) is left out of "
                          "the diffuse particles' collisions", soft_wrap=True)
            continue
        if e.role == "container" and fluid is not None and len(fluid):
            if float((g.sample(np.asarray(fluid, np.float64)) < 0).mean()) > FLUID_INSIDE_FRACTION:
                g = g.inverted()
        out.append(PosedSDF(g, MotionLaw(o, run_dir, k), k))
    return out


# ============================================================================ kernels
@ti.func
def sdf_sample(values: F1, off: ti.i32, origin: vec3, inv_dx: ti.f32, dims: ivec3, p: vec3):
    """Trilinear SDF value and its gradient (the analytic gradient of the trilinear cell)."""
    u = (p - origin) * inv_dx
    d = FAR
    grad = vec3(0.0, 0.0, 1.0)
    if u.x >= 0 and u.y >= 0 and u.z >= 0 and u.x < dims.x - 1 and u.y < dims.y - 1 and u.z < dims.z - 1:
        c = ti.cast(ti.floor(u), ti.i32)
        f = u - c
        base = off + (c.x * dims.y + c.y) * dims.z + c.z
        sy, sx = dims.z, dims.y * dims.z
        v000 = values[base]
        v001 = values[base + 1]
        v010 = values[base + sy]
        v011 = values[base + sy + 1]
        v100 = values[base + sx]
        v101 = values[base + sx + 1]
        v110 = values[base + sx + sy]
        v111 = values[base + sx + sy + 1]
        c00 = v000 * (1 - f.z) + v001 * f.z
        c01 = v010 * (1 - f.z) + v011 * f.z
        c10 = v100 * (1 - f.z) + v101 * f.z
        c11 = v110 * (1 - f.z) + v111 * f.z
        c0 = c00 * (1 - f.y) + c01 * f.y
        c1 = c10 * (1 - f.y) + c11 * f.y
        d = c0 * (1 - f.x) + c1 * f.x
        gx = c1 - c0
        gy = (c01 - c00) * (1 - f.x) + (c11 - c10) * f.x
        gz = ((v001 - v000) * (1 - f.y) + (v011 - v010) * f.y) * (1 - f.x) + (
            (v101 - v100) * (1 - f.y) + (v111 - v110) * f.y
        ) * f.x
        grad = vec3(gx, gy, gz) * inv_dx
    return d, grad


@ti.func
def in_box(p: vec3, lo: vec3, hi: vec3) -> ti.i32:
    return p.x >= lo.x and p.y >= lo.y and p.z >= lo.z and p.x <= hi.x and p.y <= hi.y and p.z <= hi.z


@ti.func
def to_rest(rot: TEMPLATE, trans: TEMPLATE, o: ti.i32, x: vec3) -> vec3:
    """x_rest = Rᵀ(x − T): a world point in the obstacle's rest placement, where its SDF lives."""
    return rot[o].transpose() @ (x - trans[o])


@ti.func
def give(imp: TEMPLATE, mom: TEMPLATE, body_of: TEMPLATE, i: ti.i32, o: ti.i32, x: vec3, dmv: vec3):
    """Momentum m·Δv that dynamic body o gave particle i (and its moment x × m·Δv about the origin);
    the body takes the opposite (sim/bodies.RigidBody.set_reaction)."""
    imp[i] += dmv
    mom[i] += x.cross(dmv)
    body_of[i] = o


@ti.kernel
def obstacle_penalty(
    n: ti.i32, x: F3, v: F3, values: F1, off: I1, origin: F3, inv_dx: F1, dims: IV, box_lo: F3, box_hi: F3,
    rot: M3, trans: F3, stiffness: F1, r: ti.f32, dt: ti.f32,
    dyn: I1, imp: F3, mom: F3, body_of: I1, m: ti.f32,
):
    """v ← v + Δt·k·n·(−φ) for φ = sdf − r < 0 (penalty force per unit mass), n = R∇sdf."""
    for i in range(n):
        for o in range(off.shape[0]):
            xl = to_rest(rot, trans, o, x[i])
            if in_box(xl, box_lo[o], box_hi[o]):
                d, g = sdf_sample(values, off[o], origin[o], inv_dx[o], dims[o], xl)
                phi = d - r
                if phi < 0.0 and g.norm() > 1e-9:
                    dv = dt * stiffness[o] * (-phi) * (rot[o] @ g.normalized())
                    v[i] += dv
                    if dyn[o] == 1:
                        give(imp, mom, body_of, i, o, x[i], m * dv)


@ti.kernel
def obstacle_project_and_density_map(
    n: ti.i32, p: F3, values: F1, off: I1, origin: F3, inv_dx: F1, dims: IV, box_lo: F3, box_hi: F3,
    rot: M3, trans: F3, r: ti.f32, h: ti.f32, psi_table: F1, dpsi_table: F1, psi: F1, grad_psi: F3,
    dyn: I1, imp: F3, mom: F3, body_of: I1, m_inv_dt: ti.f32,
):
    """Fused at the start of each constraint iteration (one SDF lookup serves both):
    x* ← x* + (r − sdf)·n where sdf < r (the projection that ends the previous
    iteration, or follows the prediction), then ψ_i += ψ(sdf), ∇ψ_i += ψ'(sdf)·∇sdf,
    the obstacle's share of ρ_i/ρ0 (static and kinematic obstacles only: a dynamic body
    has no density map, see the module doc)."""
    for i in range(n):
        for o in range(off.shape[0]):
            xl = to_rest(rot, trans, o, p[i])
            if in_box(xl, box_lo[o], box_hi[o]):
                d, g = sdf_sample(values, off[o], origin[o], inv_dx[o], dims[o], xl)
                if d < r and g.norm() > 1e-9:
                    dp = (r - d) * (rot[o] @ g.normalized())
                    p[i] += dp
                    if dyn[o] == 1:
                        give(imp, mom, body_of, i, o, p[i], m_inv_dt * dp)
                    xl = to_rest(rot, trans, o, p[i])
                    d, g = sdf_sample(values, off[o], origin[o], inv_dx[o], dims[o], xl)
                if d < h and dyn[o] == 0:
                    gn = rot[o] @ g.normalized() if g.norm() > 1e-9 else vec3(0.0)
                    # pbf.lookup's interpolation, kept inline on purpose: calling lookup (whose
                    # table size is a compile-time constant) rounds differently, and runs with
                    # obstacles would no longer give the bytes they gave before.
                    dd = ti.max(d, 0.0)
                    t = ti.math.clamp(dd / h, 0.0, 1.0) * (psi_table.shape[0] - 1)
                    k = ti.min(ti.cast(ti.floor(t), ti.i32), psi_table.shape[0] - 2)
                    f = t - k
                    psi[i] += (1.0 - f) * psi_table[k] + f * psi_table[k + 1]
                    gp = ((1.0 - f) * dpsi_table[k] + f * dpsi_table[k + 1]) * gn
                    grad_psi[i] += gp


@ti.kernel
def obstacle_project(
    n: ti.i32, p: F3, values: F1, off: I1, origin: F3, inv_dx: F1, dims: IV, box_lo: F3, box_hi: F3,
    rot: M3, trans: F3, r: ti.f32, dyn: I1, imp: F3, mom: F3, body_of: I1, m_inv_dt: ti.f32,
):
    """x* ← x* + (r − sdf)·n where sdf < r: no particle inside, none closer than its radius."""
    for i in range(n):
        for o in range(off.shape[0]):
            if in_box(to_rest(rot, trans, o, p[i]), box_lo[o], box_hi[o]):
                for _ in range(2):  # a second pass settles particles pushed into a crease
                    d, g = sdf_sample(values, off[o], origin[o], inv_dx[o], dims[o], to_rest(rot, trans, o, p[i]))
                    if d < r and g.norm() > 1e-9:
                        dp = (r - d) * (rot[o] @ g.normalized())
                        p[i] += dp
                        if dyn[o] == 1:
                            give(imp, mom, body_of, i, o, p[i], m_inv_dt * dp)


@ti.kernel
def obstacle_response(
    n: ti.i32, p: F3, v: F3, values: F1, off: I1, origin: F3, inv_dx: F1, dims: IV, box_lo: F3, box_hi: F3,
    rot: M3, trans: F3, vel_a: M3, vel_b: F3, friction: F1, r: ti.f32, band: ti.f32,
    dyn: I1, imp: F3, mom: F3, body_of: I1, m: ti.f32,
):
    """For particles in contact, relative to the body's velocity u = A·x + b: drop the
    inward normal part of v − u, damp its tangential part (friction relative to the body)."""
    for i in range(n):
        for o in range(off.shape[0]):
            xl = to_rest(rot, trans, o, p[i])
            if in_box(xl, box_lo[o], box_hi[o]):
                d, g = sdf_sample(values, off[o], origin[o], inv_dx[o], dims[o], xl)
                if d < r + band and g.norm() > 1e-9:
                    nrm = rot[o] @ g.normalized()
                    u = vel_a[o] @ p[i] + vel_b[o]
                    vr = v[i] - u
                    vn = vr.dot(nrm)
                    vt = vr - vn * nrm
                    v_new = u + ti.max(vn, 0.0) * nrm + (1.0 - friction[o]) * vt
                    if dyn[o] == 1:
                        give(imp, mom, body_of, i, o, p[i], m * (v_new - v[i]))
                    v[i] = v_new


# ============================================================================ collider
class ObstacleCollider:
    """Plugs the obstacles into PBFSolver.colliders."""

    def __init__(self, obst: Obstacles, solver):
        grids = obst.grids
        sizes = [g.values.size for g in grids]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32)
        k = len(grids)
        self.values = ti.ndarray(ti.f32, int(sum(sizes)))
        self.values.from_numpy(np.concatenate([g.values.ravel() for g in grids]).astype(np.float32))

        def arr(data, kind):
            a = ti.Vector.ndarray(3, ti.f32, k) if kind == "v" else (
                ti.Vector.ndarray(3, ti.i32, k) if kind == "iv" else ti.ndarray(ti.i32 if kind == "i" else ti.f32, k))
            a.from_numpy(np.asarray(data, np.int32 if kind in ("i", "iv") else np.float32))
            return a

        h = solver.h
        self.off = arr(offsets, "i")
        self.origin = arr([g.origin for g in grids], "v")
        self.inv_dx = arr([1.0 / g.spacing for g in grids], "f")
        self.dims = arr([g.values.shape for g in grids], "iv")
        # Broad phase: the mesh AABB grown by the kernel support.
        self.box_lo = arr([g.aabb_lo - h for g in grids], "v")
        self.box_hi = arr([g.aabb_hi + h for g in grids], "v")
        self.stiffness = arr([o.stiffness for o in obst.entries], "f")
        self.friction = arr([o.friction for o in obst.entries], "f")
        self.band = CONTACT_BAND * solver.r
        # Poses and step velocities, uploaded each step (sim/bodies.py); identity for static ones.
        self.laws = obst.laws
        self.bodies = obst.bodies  # {obstacle index: RigidBody} of the dynamic ones
        self.moving = any(law.moving for law in self.laws) or bool(self.bodies)
        # Two-way coupling: per particle, the momentum the dynamic bodies gave it this step, its
        # moment and which body (size 1 when there is no dynamic body).
        nb = getattr(solver, "capacity", solver.n) if self.bodies else 1
        self.dyn = arr([1 if j in self.bodies else 0 for j in range(k)], "i")
        self.imp = ti.Vector.ndarray(3, ti.f32, nb)
        self.mom = ti.Vector.ndarray(3, ti.f32, nb)
        self.body_of = ti.ndarray(ti.i32, nb)
        self.m = float(solver.mass)
        self.inv_dt = 0.0
        self.in_step = False
        self.grids = obst.grids
        self.overlaps: set = set()  # (dynamic body, obstacle) pairs already warned about
        self.rot = ti.Matrix.ndarray(3, 3, ti.f32, k)
        self.trans = ti.Vector.ndarray(3, ti.f32, k)
        self.vel_a = ti.Matrix.ndarray(3, 3, ti.f32, k)
        self.vel_b = ti.Vector.ndarray(3, ti.f32, k)
        self.set_poses(solver.time, solver.time)

    def set_poses(self, t0: float, t1: float, dt: float = 0.0) -> None:
        """Upload every obstacle's pose at t1 and its velocity over the step t0 → t1: kinematic ones
        from their motion law, dynamic ones advanced by one step ``dt`` (when dt > 0)."""
        from .bodies import step_velocity

        R, T, A, B = [], [], [], []
        for j, law in enumerate(self.laws):
            body = self.bodies.get(j)
            if body is not None:
                R0, T0 = body.pose()
                if dt > 0:
                    body.advance(dt, t1)
                R1, T1 = body.pose()
            else:
                R0, T0 = law.pose(t0)
                R1, T1 = law.pose(t1)
            a, b = step_velocity(R0, T0, R1, T1, t1 - t0) if t1 > t0 else (np.zeros((3, 3)), np.zeros(3))
            R.append(R1)
            T.append(T1)
            A.append(a)
            B.append(b)
        self.upload(R, T, A, B)

    def upload(self, R, T, A, B) -> None:
        """The poses (R, T), float64 on the host (``self.poses``), and step velocities for the kernels."""
        self.poses = list(zip(R, T))
        self.rot.from_numpy(np.asarray(R, np.float32))
        self.trans.from_numpy(np.asarray(T, np.float32))
        self.vel_a.from_numpy(np.asarray(A, np.float32))
        self.vel_b.from_numpy(np.asarray(B, np.float32))

    # Recorded launches (sim/launch.py): the solver's step records these into its phases.
    def bindings(self, pre: str) -> dict:
        """This collider's arrays and constants, by the names its recorded launches use."""
        return {
            pre + "values": self.values, pre + "off": self.off, pre + "origin": self.origin,
            pre + "inv_dx": self.inv_dx, pre + "dims": self.dims, pre + "box_lo": self.box_lo,
            pre + "box_hi": self.box_hi, pre + "rot": self.rot, pre + "trans": self.trans,
            pre + "stiffness": self.stiffness, pre + "friction": self.friction, pre + "band": self.band,
            pre + "vel_a": self.vel_a, pre + "vel_b": self.vel_b, pre + "dyn": self.dyn, pre + "imp": self.imp,
            pre + "mom": self.mom, pre + "body_of": self.body_of, pre + "m": self.m,
            pre + "m_inv_dt": self.m * self.inv_dt,
        }

    @staticmethod
    def _geo(rec, pre: str) -> list:
        return [rec[pre + k] for k in ("values", "off", "origin", "inv_dx", "dims", "box_lo", "box_hi", "rot", "trans")]

    @staticmethod
    def _coupling(rec, pre: str) -> list:
        return [rec[pre + k] for k in ("dyn", "imp", "mom", "body_of")]

    def prepare(self, s, dt: float) -> None:
        """Host work before a step's launches: move the bodies to their pose at its end,
        and clear the momentum the dynamic ones will collect."""
        if self.moving:
            self.set_poses(s.time, s.time + dt, dt)
        if self.bodies:
            self.in_step, self.inv_dt = True, 1.0 / dt
            for a in (self.imp, self.mom):
                a.fill(0.0)
            self.body_of.fill(-1)

    def record_forces(self, rec, pre: str) -> None:
        """The penalty, before the prediction."""
        r = rec
        rec(obstacle_penalty, r["n"], r["x"], r["v"], *self._geo(r, pre), r[pre + "stiffness"], r["r"], r["dt"],
            *self._coupling(r, pre), r[pre + "m"])

    def body_records(self) -> list[Pose]:
        """Every obstacle's current pose as run.json records it (sim.bodies.pose_record)."""

        return [pose_record(R, T) for R, T in self.poses]

    def poses_at(self, t: float) -> None:
        """Bodies at their pose at ``t`` with zero step velocity (after a restore, for output)."""
        if self.moving:
            self.set_poses(t, t)

    def record_density_map(self, rec, pre: str) -> None:
        r = rec
        rec(obstacle_project_and_density_map, r["n"], r["p"], *self._geo(r, pre), r["r"], r["h"], r["psi_table"],
            r["dpsi_table"], r["psi"], r["grad_psi"], *self._coupling(r, pre), r[pre + "m_inv_dt"])

    def record_project(self, rec, pre: str) -> None:
        r = rec
        rec(obstacle_project, r["n"], r["p"], *self._geo(r, pre), r["r"], *self._coupling(r, pre),
            r[pre + "m_inv_dt"])

    def record_respond(self, rec, pre: str) -> None:
        r = rec
        rec(obstacle_response, r["n"], r["p"], r["v"], *self._geo(r, pre), r[pre + "vel_a"], r[pre + "vel_b"],
            r[pre + "friction"], r["r"], r[pre + "band"], *self._coupling(r, pre), r[pre + "m"])

    def finish_step(self, s) -> None:
        """Host work after a step's launches: the dynamic bodies take the particles' reaction."""
        if self.bodies and self.in_step:
            self.in_step = False
            imp = self.imp.to_numpy().astype(np.float64)
            mom = self.mom.to_numpy().astype(np.float64)
            which = self.body_of.to_numpy()
            for j, body in self.bodies.items():
                sel = which == j
                body.set_reaction(imp[sel].sum(0), mom[sel].sum(0), 1.0 / self.inv_dt)
            self.check_overlaps(s.time + 1.0 / self.inv_dt)

    def check_overlaps(self, t: float) -> None:
        """Bodies do not collide with each other or with static obstacles: warn (once per pair)
        when a hull vertex of a dynamic body is inside another obstacle."""
        for j, body in self.bodies.items():
            R, T = self.poses[j]
            verts = (body.hull @ R.T + T)
            for k, (Rk, Tk) in enumerate(self.poses):
                if k == j or (j, k) in self.overlaps:
                    continue
                if (self.grids[k].sample((verts - Tk) @ Rk) < 0).any():
                    self.overlaps.add((j, k))
                    from ..progress import console

                    console.print(f"[yellow]warning:[/] obstacle[{j}] passes into obstacle[{k}] at t={t:.3f} s: "
                                  "contact between bodies is not modelled")

    # ------------------------------------------------------------ checkpoint
    def checkpoint(self) -> dict[str, np.ndarray]:
        if not self.bodies:
            return {}
        return {"bodies": np.stack([self.bodies[j].state() for j in sorted(self.bodies)])}

    def restore(self, data: dict) -> None:
        if self.bodies and "bodies" in data:
            for row, j in zip(np.asarray(data["bodies"]), sorted(self.bodies)):
                self.bodies[j].restore(row)
