"""Rigid bodies: the motion laws of kinematic obstacles and their poses.

An obstacle's signed distance field is sampled once, in its *rest placement*
(the scene's ``scale``, ``rotate``, ``translate``). A moving obstacle is that
rest shape carried by a rigid motion, its *pose* at time t:

    x_world = R(t) · x_rest + T(t)

Particles query the SDF through the inverse, x_rest = Rᵀ (x_world − T). The
laws (``[[obstacle]] motion``):

- ``keyframes``: displacement d and rotation angles θ (about x, then y, then z,
  about ``centre``, default the obstacle's ``translate``) interpolated between
  keys, linearly or ``smooth`` (smoothstep, which eases in and out of every
  key); held before the first and after the last key. R = R(θ), T = c + d − R c.
- ``piston``: T = X(t)·â, X(t) = ramp(t)·(S/2)·sin(2πt/T_p), or X(t)
  interpolated from a CSV of (time, displacement) rows.
- ``flap``: rotation by θ(t) = ramp(t)·A·sin(2πt/T_p) about the hinge axis
  through the hinge point p: R = R(â, θ), T = p − R p.
- ``spin``: θ(t) = 2π·rpm/60·t about the axis through ``centre``.

``ramp(t)`` is 1, or the smoothstep of t/ramp when ``ramp`` > 0, so that a wave
maker starts at rest.

Body velocity: over a step from t₀ to t₁ = t₀ + Δt, the material point of the
body found at x at t₁ was at x₀ = R₀R₁ᵀ(x − T₁) + T₀, so its velocity is
u(x) = (x − x₀)/Δt = A·x + b with A = (I − R₀R₁ᵀ)/Δt and b = (R₀R₁ᵀT₁ − T₀)/Δt:
exactly the displacement the position-based step sees, and exactly zero for a
static body.

Poses are recorded in ``run.json`` as position T and unit quaternion
(w, x, y, z) of R; ``geometry.obstacle_matrix`` composes them with the rest
placement, the one definition every stage places a body with.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..config import BODY_DENSITY, Motion, Obstacle, Scene
from ..errors import InputError, SimulationError
from ..geometry import axis_rotation, euler_rotation, quat_matrix, quat_mul


def smoothstep(u: float) -> float:
    u = min(max(u, 0.0), 1.0)
    return u * u * (3.0 - 2.0 * u)


def read_series(path: Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(times, values) from a two-column CSV; a header line is allowed. InputError names the file and line."""
    if not path.is_file():
        raise InputError(f"{path}: {what}: file not found")
    t: list[float] = []
    x: list[float] = []
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: {what}: not UTF-8 text (offset {exc.start}); save it as UTF-8") from None
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        cells = [c.strip() for c in line.replace(";", ",").split(",")]
        try:
            a, b = float(cells[0]), float(cells[1])
        except (ValueError, IndexError):
            if not t and n == 1:
                continue  # a header
            raise InputError(f"{path}: line {n}: {what}: expected 'time, displacement' numbers, got {line!r}") from None
        if not (math.isfinite(a) and math.isfinite(b)):
            raise InputError(f"{path}: line {n}: values must be finite numbers")
        if t and a <= t[-1]:
            raise InputError(f"{path}: line {n}: times must increase (got {a} after {t[-1]})")
        t.append(a)
        x.append(b)
    if len(t) < 2:
        raise InputError(f"{path}: {what}: needs at least two rows of time, displacement")
    return np.asarray(t), np.asarray(x)


class MotionLaw:
    """The pose (R, T) of one obstacle as a function of time."""

    def __init__(self, o: Obstacle, base_dir: Path | str = ".", index: int = 0):
        self.o = o
        self.m: Motion | None = o.motion
        self.series: tuple[np.ndarray, np.ndarray] | None = None
        m = self.m
        if m is not None and m.kind == "piston" and m.csv is not None:
            p = Path(m.csv)
            self.series = read_series(p if p.is_absolute() else Path(base_dir) / p, f"obstacle[{index}].motion.csv")

    @property
    def moving(self) -> bool:
        return self.m is not None

    @staticmethod
    def _ramp(m: Motion, t: float) -> float:
        return smoothstep(t / m.ramp) if m.ramp > 0 else 1.0

    def piston_displacement(self, t: float) -> float:
        """X(t) [m] along the piston's axis."""
        if self.series is not None:
            ts, xs = self.series
            return float(np.interp(t, ts, xs))
        m = self.m
        # Motion's validator: a piston without a CSV has a stroke and a period.
        assert m is not None and m.stroke is not None and m.period is not None, "a piston's motion"
        return self._ramp(m, t) * 0.5 * m.stroke * math.sin(2.0 * math.pi * t / m.period)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R 3×3, T 3) in float64 at time ``t`` [s]."""
        m = self.m
        if m is None:
            return np.eye(3), np.zeros(3)
        # The fields each law reads below are the ones Motion's validator requires of its kind.
        if m.kind == "piston":
            a = np.asarray(m.axis, np.float64)
            return np.eye(3), self.piston_displacement(t) * a / np.linalg.norm(a)
        if m.kind == "flap":
            assert m.amplitude is not None and m.period is not None
            th = self._ramp(m, t) * math.radians(m.amplitude) * math.sin(2.0 * math.pi * t / m.period)
            R = axis_rotation(m.hinge_axis, th)
            p = np.asarray(m.hinge_point, np.float64)
            return R, p - R @ p
        if m.kind == "spin":
            assert m.rpm is not None
            R = axis_rotation(m.axis, 2.0 * math.pi * m.rpm / 60.0 * t)
            c = np.asarray(m.centre, np.float64)
            return R, c - R @ c
        # keyframes
        keys = m.keyframes
        assert keys
        times = [k.time for k in keys]
        d: list[float]
        ang: list[float]
        if t <= times[0] or len(keys) == 1:
            d, ang = keys[0].translate, keys[0].rotate
        elif t >= times[-1]:
            d, ang = keys[-1].translate, keys[-1].rotate
        else:
            j = int(np.searchsorted(times, t, side="right")) - 1
            u = (t - times[j]) / (times[j + 1] - times[j])
            if m.interpolation == "smooth":
                u = smoothstep(u)
            k0, k1 = keys[j], keys[j + 1]
            d = [(1 - u) * x + u * y for x, y in zip(k0.translate, k1.translate)]
            ang = [(1 - u) * x + u * y for x, y in zip(k0.rotate, k1.rotate)]
        c = np.asarray(m.centre if m.centre is not None else self.o.translate, np.float64)
        R = euler_rotation(ang)
        return R, c + np.asarray(d, np.float64) - R @ c


def step_velocity(R0, T0, R1, T1, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) with u(x) = A·x + b the velocity of the body point at x over a step (see the module doc)."""
    Q = R0 @ R1.T
    return (np.eye(3) - Q) / dt, (Q @ T1 - T0) / dt


def motion_laws(scene: Scene) -> list[MotionLaw]:
    return [MotionLaw(o, scene.base_dir, k) for k, o in enumerate(scene.obstacle)]


# ============================================================================ dynamic bodies
#: Most Gauss–Seidel sweeps over the hull's wall contacts, for the velocity and for the
#: pose (RigidBody.collide_walls); the sweeps stop as soon as they have converged.
WALL_CONTACT_SWEEPS = 8
#: Depth past a wall [m] that the pose correction leaves alone: 10 µm, far below a particle.
#: Without it the last sweeps chase rounding-sized depths on a body resting on a wall
#: (measured: 1.3 against 0.75 ms a step for a slab lying on the floor).
WALL_CONTACT_SLOP = 1e-5
#: A wall contact whose inverse effective mass is below this fraction of 1/M acts only along held
#: DOFs (the body cannot answer it) and is skipped.
WALL_CONTACT_MIN_INV_MASS = 1e-9


def twist_free(q: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The orientation q (w, x, y, z) with its turn about every held world axis removed.

    ``free`` masks the axes x, y, z the body may turn about. Angular velocity on a held axis is
    zero, but turns about two free axes compose into a small turn about the third (the rotations
    do not commute), so the pose is held too, by the swing–twist split q = s ⊗ t with the twist t
    about the held axis ê and the swing s turning nothing about ê:

    - two free axes (ê held): q ← s = q ⊗ t⁻¹, t = normalise(w, (v·ê) ê);
    - one free axis â: q ← its twist about â, normalise(w, (v·â) â);
    - none: q ← 1.

    With z held, a hull's keel heading (the Euler yaw atan2(R₁₀, R₀₀)) then moves only by the
    geometric coupling φθ/2 of roll φ and pitch θ (1° at 12° and 11° at once) and returns with
    them: the twist, not the Euler yaw, is what stays zero, so nothing drifts.
    """
    held = np.flatnonzero(~free)
    if len(held) == 0:
        return q
    if len(held) == 3:
        return np.array([1.0, 0.0, 0.0, 0.0])
    if len(held) == 1:
        t = np.zeros(4)
        t[0], t[1 + held[0]] = q[0], q[1 + held[0]]
        norm = np.linalg.norm(t)
        if norm < 1e-12:  # a half turn about an axis normal to ê: no twist to remove
            return q
        t /= norm
        s = quat_mul(q, t * np.array([1.0, -1.0, -1.0, -1.0]))
        return s / np.linalg.norm(s)
    a = int(np.flatnonzero(free)[0])
    t = np.zeros(4)
    t[0], t[1 + a] = q[0], q[1 + a]
    return t / np.linalg.norm(t)


class RigidBody:
    """A dynamic obstacle: a rigid body moved by gravity and the fluid (two-way coupling).

    Mass properties come from the watertight mesh in its rest placement (trimesh's
    mass properties: volume, centre of mass c₀, inertia tensor I₀ about c₀). State,
    in float64: centre of mass c, orientation quaternion q (w, x, y, z), velocity V,
    angular velocity Ω (world frame). The pose is x = R(q)(x_rest − c₀) + c, so
    T = c − R c₀.

    Integration (semi-implicit Euler, the quaternion renormalised every step):

        V ← V + Δt (F/M + g)
        Ω ← Ω + Δt I⁻¹ (τ − Ω × IΩ),  I = R I₀ Rᵀ
        c ← c + Δt V,  q ← normalise(q + Δt/2 (0, Ω) ⊗ q)

    F and τ are the reaction of the momentum the boundary terms gave the fluid in
    the previous step (explicit coupling, one step behind).

    The domain walls stop the body (:meth:`collide_walls`): frictionless contact
    without bounce at every hull vertex past a wall, solved for the velocity
    and then for the pose by sequential impulses (Catto 2005, "Iterative
    dynamics with temporal coherence"; the pose part as split impulses), so
    that a wall acts on the body's rotation as well as on its centre. A body
    turned against two opposite walls is turned back between them.

    Degrees of freedom (``translation_dof``, ``rotation_dof``: masks P_t, P_r of the world axes):
    a held axis has infinite inertia. The body's inverse mass is P_t/M and its inverse inertia
    K = E (Eᵀ I E)⁻¹ Eᵀ, E the columns of the free axes (the free block of I inverted, so that a
    body free to pitch only turns by τ_y / I_yy), in the integration and at the walls alike:

        V ← V + Δt P_t (F/M + g) + (1 − P_t) U(t),   Ω ← Ω + Δt K (τ − Ω × IΩ)

    with U(t) = ramp(t)·U the ``drive`` velocity (0 without one) at the step's end, and the pose
    kept free of turns about held axes (:func:`twist_free`). The fluid's force along a held axis
    is taken by the constraint (the drive's thrust); along the free ones the body answers it."""

    def __init__(self, mesh, o: Obstacle, gravity, domain_lo, domain_hi, index: int = 0):
        vol = float(mesh.volume)
        self.name = f"obstacle[{index}] ({o.mesh})"
        if vol <= 0:
            raise InputError(f"{o.mesh}: a dynamic obstacle needs a closed mesh with positive volume")
        if o.mass is not None:
            self.mass = float(o.mass)
        else:
            assert o.density is not None  # Obstacle's validator: a dynamic body has a mass or a density
            self.mass = float(o.density) * vol
        rho = self.mass / vol
        if not BODY_DENSITY[0] <= rho <= BODY_DENSITY[1]:  # the density's own range is checked by the scene
            raise InputError(f"{self.name}: mass: {o.mass:g} kg over the mesh's {vol:.4g} m³ is a density of "
                             f"{rho:.4g} kg/m³, outside {BODY_DENSITY[0]:g}..{BODY_DENSITY[1]:g}")
        props = mesh.mass_properties  # for unit density
        self.c0 = np.asarray(props["center_mass"], np.float64)
        self.I0 = np.asarray(props["inertia"], np.float64) * rho
        self.I0_inv = np.linalg.inv(self.I0)
        self.hull = np.asarray(mesh.convex_hull.vertices, np.float64)
        self.g = np.asarray(gravity, np.float64)
        self.lo, self.hi = np.asarray(domain_lo, np.float64), np.asarray(domain_hi, np.float64)
        self.c = self.c0.copy()
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.V = np.zeros(3)
        self.W = np.zeros(3)
        self.F = np.zeros(3)  # reaction force and torque (about c) of the last step
        self.tau = np.zeros(3)
        self.t_free = np.asarray(o.translation_dof, bool)
        self.r_free = np.asarray(o.rotation_dof, bool)
        self.free = bool(self.t_free.all() and self.r_free.all())  # unconstrained: the plain update
        self.drive = o.drive

    def drive_velocity(self, t: float | None) -> np.ndarray:
        """U(t) [m/s]: the drive's velocity eased in by smoothstep(t/ramp); t None: the full speed."""
        d = self.drive
        if d is None:
            return np.zeros(3)
        ease = 1.0 if t is None or d.ramp <= 0 else smoothstep(t / d.ramp)
        return ease * np.asarray(d.velocity, np.float64)

    def inverse_inertia(self, R: np.ndarray) -> np.ndarray:
        """The world-frame inverse inertia at orientation R: I⁻¹ = R I₀⁻¹ Rᵀ when free, else the
        constrained K = E (Eᵀ I E)⁻¹ Eᵀ (zero on held axes)."""
        if self.r_free.all():
            return R @ self.I0_inv @ R.T
        E = np.eye(3)[:, self.r_free]
        if not E.shape[1]:
            return np.zeros((3, 3))
        return E @ np.linalg.inv(E.T @ (R @ self.I0 @ R.T) @ E) @ E.T

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        R = quat_matrix(self.q)
        return R, self.c - R @ self.c0

    def advance(self, dt: float, t: float | None = None) -> None:
        """One step of the body under gravity and the fluid's last reaction, stopped at the walls;
        ``t`` is the time at the step's end (for the drive's ramp; None: the full speed)."""
        if not (np.isfinite(self.F).all() and np.isfinite(self.tau).all()):
            raise SimulationError(f"{self.name}: the fluid's force on it is not finite (the coupling blew up); "
                                  "check its density or mass and the time step")
        R = quat_matrix(self.q)
        I = R @ self.I0 @ R.T
        if self.free:
            self.V = self.V + dt * (self.F / self.mass + self.g)
            self.W = self.W + dt * np.linalg.solve(I, self.tau - np.cross(self.W, I @ self.W))
        else:
            self.V = np.where(self.t_free, self.V + dt * (self.F / self.mass + self.g), self.drive_velocity(t))
            W = self.W + dt * self.inverse_inertia(R) @ (self.tau - np.cross(self.W, I @ self.W))
            self.W = np.where(self.r_free, W, 0.0)
        self.c = self.c + dt * self.V
        q = self.q + 0.5 * dt * quat_mul(np.array([0.0, *self.W]), self.q)
        self.q = q / np.linalg.norm(q)
        self.collide_walls()
        if not self.free:
            self.q = twist_free(self.q, self.r_free)
        if not (np.isfinite(self.c).all() and (self.c >= self.lo).all() and (self.c <= self.hi).all()):
            raise SimulationError(
                f"{self.name}: left the domain (centre of mass at {np.round(self.c, 4).tolist()}, speed "
                f"{np.linalg.norm(self.V):.3g} m/s); check its density or mass and the time step")

    def _contacts(self, slop: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(hull vertices, walls, depths) of every vertex more than ``slop`` past a wall; walls 0–2
        are the lower x, y, z walls (normal +e_a), 3–5 the upper ones (normal −e_a)."""
        verts = (self.hull - self.c0) @ quat_matrix(self.q).T + self.c
        depth = np.concatenate([self.lo - verts, verts - self.hi], axis=1)  # (vertices, 6 walls)
        k, w = np.nonzero(depth > slop)
        return k, w, depth[k, w]

    def _contact_rows(self, k: np.ndarray, w: np.ndarray, depth: np.ndarray) -> list[tuple]:
        """Per contact (hull vertex k, wall w, depth d) at the current pose: (n, r × n, I⁻¹(r × n),
        1/m_eff, d), with n the wall's normal, r the lever arm from the centre of mass and
        1/m_eff = 1/M + (r × n)·I⁻¹(r × n) the inverse effective mass along n."""
        R = quat_matrix(self.q)
        I_inv = self.inverse_inertia(R)
        n = np.zeros((len(k), 3))
        n[np.arange(len(k)), w % 3] = np.where(w < 3, 1.0, -1.0)
        rn = np.cross((self.hull[k] - self.c0) @ R.T, n)
        a = rn @ I_inv.T
        inv_m = self.t_free[w % 3] / self.mass + (rn * a).sum(1)  # n·(P_t n)/M + (r × n)·K(r × n)
        rows = zip(n, rn, a, inv_m.tolist(), depth.tolist())
        # A contact along held DOFs only cannot be answered by the body: skipped, not divided by ~0.
        return [row for row in rows if row[3] > WALL_CONTACT_MIN_INV_MASS / self.mass]

    def collide_walls(self) -> None:
        """Frictionless, inelastic contact of the hull with the domain walls, by sequential impulses:

        1. velocity: at each contact whose point moves into its wall (u_n = n·(V + Ω × r) < 0), an
           impulse j n with j = −u_n·m_eff stops that motion (V += j P_t n/M, Ω += K(r × j n));
        2. pose: each contact still past its wall by d gets the pseudo-impulse p = d·m_eff, which
           moves the centre by p P_t n/M and turns the body by K(r × p n), so that the vertex lands
           on the wall (to first order; the depths are measured again each sweep).

        Both passes sweep the contacts up to WALL_CONTACT_SWEEPS times (Gauss–Seidel), and stop
        early once a sweep changes nothing (the pose: once no vertex is more than
        WALL_CONTACT_SLOP past a wall)."""
        contacts = self._contacts()
        if not len(contacts[0]):
            return
        rows = self._contact_rows(*contacts)
        for _ in range(WALL_CONTACT_SWEEPS):
            moved = False
            for n, rn, a, inv_m, _ in rows:
                un = float(n @ self.V + rn @ self.W)  # n·(V + Ω × r), with n·(Ω × r) = Ω·(r × n)
                if un < 0.0:
                    j = -un / inv_m
                    self.V = self.V + (j / self.mass) * (self.t_free * n)
                    self.W = self.W + j * a
                    moved = True
            if not moved:
                break
        for _ in range(WALL_CONTACT_SWEEPS):
            contacts = self._contacts(WALL_CONTACT_SLOP)
            if not len(contacts[0]):
                break
            dc, dtheta = np.zeros(3), np.zeros(3)
            for n, rn, a, inv_m, depth in self._contact_rows(*contacts):
                d = depth - float(n @ dc + rn @ dtheta)  # what this sweep's corrections left of the depth
                if d > 0.0:
                    p = d / inv_m
                    dc += (p / self.mass) * (self.t_free * n)
                    dtheta += p * a
            self.c = self.c + dc
            q = self.q + 0.5 * quat_mul(np.array([0.0, *dtheta]), self.q)
            self.q = q / np.linalg.norm(q)

    def set_reaction(self, impulse: np.ndarray, moment: np.ndarray, dt: float) -> None:
        """The fluid received ``impulse`` (Σ m Δv) and ``moment`` (Σ x × m Δv, about the origin) from
        this body over a step: the body gets the opposite, F = −J/Δt, τ = −(M − c × J)/Δt."""
        self.F = -impulse / dt
        self.tau = -(moment - np.cross(self.c, impulse)) / dt

    def state(self) -> np.ndarray:
        return np.concatenate([self.c, self.q, self.V, self.W, self.F, self.tau])

    def restore(self, a: np.ndarray) -> None:
        a = np.asarray(a, np.float64)
        self.c, self.q, self.V, self.W, self.F, self.tau = a[0:3], a[3:7], a[7:10], a[10:13], a[13:16], a[16:19]
