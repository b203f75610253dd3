"""The scene model: one typed, validated description of a whole run.

A scene is a TOML file. Units are SI (metres, seconds, kilograms, kg/m³) and
**z is up**, as in Blender and DualSPHysics. Every field documents its unit;
every field has a default that works, so a scene only names what differs.

    from whitecap.config import load_scene
    scene = load_scene("scenes/dam_break.toml")

Errors are raised as :class:`whitecap.errors.InputError` with one line naming
the file, the dotted key and what was expected, plus a did-you-mean for
unknown keys.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal, TypeVar, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import ErrorDetails

from .errors import InputError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

Job = TypeVar("Job", bound="DataclassInstance")

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
#: Per world axis x, y, z: a degree of freedom that is free (true) or held (false).
Dof3 = Annotated[list[bool], Field(min_length=3, max_length=3)]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    @field_validator("*", mode="after")
    @classmethod
    def _finite(cls, v: Any) -> Any:
        vals = v if isinstance(v, list) else [v]
        for x in vals:
            if isinstance(x, float) and not math.isfinite(x):
                raise ValueError("must be a finite number")
        return v


# --------------------------------------------------------------------------- domain
class Domain(_Section):
    """The simulation box. Particles are kept inside it by the walls."""

    lower: Vec3 = Field([0.0, 0.0, 0.0], description="lower corner of the box [m]")
    upper: Vec3 = Field([1.0, 0.5, 0.8], description="upper corner of the box [m]")
    gravity: Vec3 = Field([0.0, 0.0, -9.81], description="gravitational acceleration [m/s²], z up")

    @model_validator(mode="after")
    def _ordered(self) -> "Domain":
        if any(u <= lo for lo, u in zip(self.lower, self.upper)):
            raise ValueError("domain.upper must be greater than domain.lower on every axis")
        return self


# --------------------------------------------------------------------------- solver
class Solver(_Section):
    """Position Based Fluids (Macklin & Müller 2013) parameters."""

    particle_radius: float = Field(0.01, gt=0, description="particle radius r [m]; spacing is 2r")
    rest_density: float = Field(1000.0, gt=0, description="rest density ρ0 [kg/m³]")
    kernel_support: float = Field(4.0, ge=2.5, le=6.0, description="kernel support h as a multiple of r [-]")
    frame_rate: float = Field(30.0, gt=0, description="output frames per second [1/s]")
    substeps: int | None = Field(
        None, ge=1, le=1000, description="fixed substeps per frame; unset = CFL-limited dt [-]"
    )
    cfl: float = Field(0.4, gt=0, le=1.0, description="CFL number: dt ≤ cfl·2r/v_max [-]")
    gravity_dt_limit: float = Field(
        0.005, gt=0, description="also bound dt so that |g|·dt² ≤ this × spacing 2r (limits compression per step) [-]"
    )
    max_substeps: int = Field(60, ge=1, le=10000, description="upper bound on CFL substeps per frame [-]")
    min_substeps: int = Field(2, ge=1, le=10000, description="lower bound on CFL substeps per frame [-]")
    iterations: int = Field(4, ge=1, le=100, description="density-constraint iterations per step [-]")
    relaxation: float = Field(
        1e-4, gt=0, description="constraint-force mixing ε, relative to Σ|∇C|² of a full neighbourhood [-]"
    )
    xsph_c: float = Field(0.05, ge=0, le=1, description="XSPH viscosity c [-]")
    vorticity_epsilon: float = Field(0.05, ge=0, description="vorticity confinement ε in f = ε (N × ω) [m/s]")
    scorr_k: float = Field(
        1e-4, ge=0, description="artificial pressure strength k, relative to λ of a full neighbourhood [-]"
    )
    scorr_n: int = Field(4, ge=1, le=8, description="artificial pressure exponent n [-]")
    scorr_dq: float = Field(0.2, ge=0, lt=1, description="artificial pressure Δq as a fraction of h [-]")
    max_neighbors: int = Field(64, ge=16, le=512, description="fixed neighbour-list capacity per particle [-]")
    reorder_interval: int = Field(
        8, ge=0,
        description="steps between cell reorders of particle data; 0 = never [-] "
        "(8: 2-6 % faster steps than 32 at 120k-1M, measured interleaved in one process)",
    )
    wall_friction: float = Field(0.0, ge=0, le=1, description="tangential velocity damping at domain walls [-]")
    max_speed: float = Field(
        100.0, gt=0, description="a particle faster than this is a blow-up and stops the run [m/s]"
    )
    max_particles: int | None = Field(
        None, ge=1, description="particle capacity with [[emitter]]s; unset = the initial fluid plus all that the "
        "emitters add over the run [-]")


# --------------------------------------------------------------------------- fluid blocks
def _check_box(lower, upper, what: str) -> None:
    """The one check of a box's corners (fluid blocks, emitters, sinks): both given, upper above lower."""
    if lower is None or upper is None:
        raise ValueError(f"{what} needs 'lower' and 'upper'")
    if any(u <= lo for lo, u in zip(lower, upper)):
        raise ValueError("box upper must be greater than lower on every axis")


def _shape_bounds(sec) -> tuple[list[float], list[float]]:
    """(lower, upper) of a fluid block's or an emitter's shape: a box's corners, else the box round its
    ``center`` ± ``radius`` (a sphere's, or a disk's whatever its direction)."""
    if sec.shape == "box":
        return list(sec.lower), list(sec.upper)
    c, r = sec.center, sec.radius
    return [c[i] - r for i in range(3)], [c[i] + r for i in range(3)]


class FluidBlock(_Section):
    """An initial block of fluid, filled with a cubic lattice of spacing 2r."""

    shape: Literal["box", "sphere"] = Field("box", description="box or sphere")
    lower: Vec3 | None = Field(None, description="box lower corner [m]")
    upper: Vec3 | None = Field(None, description="box upper corner [m]")
    center: Vec3 | None = Field(None, description="sphere centre [m]")
    radius: float | None = Field(None, gt=0, description="sphere radius [m]")
    velocity: Vec3 = Field([0.0, 0.0, 0.0], description="initial velocity [m/s]")

    @model_validator(mode="after")
    def _shape_fields(self) -> "FluidBlock":
        if self.shape == "box":
            _check_box(self.lower, self.upper, "a box")
        elif self.center is None or self.radius is None:
            raise ValueError("a sphere needs 'center' and 'radius'")
        return self

    def bounds(self) -> tuple[list[float], list[float]]:
        return _shape_bounds(self)

    def lattice_count(self, r: float) -> int:
        """About how many particles the block holds at spacing 2r (a sphere: by its volume share)."""
        lo, hi = self.bounds()
        cnt = 1.0
        for a in range(3):
            cnt *= max(0.0, math.floor((hi[a] - lo[a] - 2 * r) / (2 * r) + 1e-6) + 1)
        return int(cnt * (math.pi / 6.0 if self.shape == "sphere" else 1.0))


# --------------------------------------------------------------------------- obstacles
# (placement and pose matrices: whitecap.geometry)


class Keyframe(_Section):
    """One keyframe of a prescribed motion: the body's offset from its rest placement."""

    time: float = Field(..., ge=0, description="time of the keyframe [s]")
    translate: Vec3 = Field([0.0, 0.0, 0.0], description="displacement from the rest placement [m]")
    rotate: Vec3 = Field(
        [0.0, 0.0, 0.0], description="rotation about x, y, z (in that order) about the motion centre [deg]"
    )


class Motion(_Section):
    """Prescribed (kinematic) motion of an obstacle, relative to its rest placement.

    ``kind`` picks the law: ``keyframes``, ``piston``, ``flap`` or ``spin``; only the
    fields of that law may be set (sim/bodies.py evaluates them)."""

    kind: Literal["keyframes", "piston", "flap", "spin"] = Field(..., description="motion law")
    # keyframes
    keyframes: list[Keyframe] | None = Field(None, description="keyframes: times, displacements, rotations")
    interpolation: Literal["linear", "smooth"] = Field(
        "linear", description="keyframes: linear, or smooth (C1 cubic Hermite with zero end slopes)")
    centre: Vec3 | None = Field(
        None, description="keyframes/spin: rotation centre [m]; default: the obstacle's translate")
    # piston
    axis: Vec3 | None = Field(None, description="piston: direction of the stroke; spin: rotation axis [-]")
    stroke: float | None = Field(None, gt=0, description="piston: peak-to-peak displacement S [m]")
    period: float | None = Field(None, gt=0, description="piston/flap: period T [s]")
    csv: str | None = Field(
        None, description="piston: CSV file of time [s], displacement [m] rows, instead of stroke/period"
    )
    ramp: float = Field(0.0, ge=0, description="piston/flap: the amplitude ramps up smoothly over this time [s]")
    # flap
    hinge_axis: Vec3 | None = Field(None, description="flap: hinge direction [-]")
    hinge_point: Vec3 | None = Field(None, description="flap: a point on the hinge [m]")
    amplitude: float | None = Field(None, gt=0, description="flap: angular amplitude [deg]")
    # spin
    rpm: float | None = Field(None, description="spin: revolutions per minute (sign: right-hand rule) [1/min]")

    _FIELDS: ClassVar[dict] = {
        "keyframes": ({"keyframes"}, {"interpolation", "centre"}),
        "piston": ({"axis"}, {"stroke", "period", "csv", "ramp"}),
        "flap": ({"hinge_axis", "hinge_point", "amplitude", "period"}, {"ramp"}),
        "spin": ({"axis", "centre", "rpm"}, set()),
    }

    @model_validator(mode="after")
    def _fields_of_kind(self) -> "Motion":
        need, may = self._FIELDS[self.kind]
        missing = sorted(k for k in need if getattr(self, k) is None)
        if missing:
            raise ValueError(f"motion kind '{self.kind}' needs '{missing[0]}'")
        # Fields away from their defaults (a resolved scene.toml spells the defaults out).
        given = {k for k, f in type(self).model_fields.items() if k != "kind" and getattr(self, k) != f.default}
        extra = sorted(given - need - may)
        if extra:
            raise ValueError(f"'{extra[0]}' does not apply to motion kind '{self.kind}'")
        for k in ("axis", "hinge_axis"):
            v = getattr(self, k)
            if v is not None and math.sqrt(sum(x * x for x in v)) < 1e-9:
                raise ValueError(f"'{k}' must not be the zero vector")
        if self.kind == "piston" and (self.csv is None) == (self.stroke is None or self.period is None):
            raise ValueError("a piston needs either 'stroke' and 'period' or 'csv'")
        if self.kind == "piston" and self.csv is not None and (self.stroke is not None or self.period is not None):
            raise ValueError("a piston takes 'csv' or 'stroke' and 'period', not both")
        if self.kind == "keyframes":
            times = [k.time for k in self.keyframes]  # type: ignore[union-attr]
            if not times or any(b <= a for a, b in zip(times, times[1:])):
                raise ValueError("keyframes need at least one entry, with strictly increasing times")
        return self


class Drive(_Section):
    """A prescribed speed for a dynamic body (propulsion): its centre of mass moves at ``velocity``
    along the translation DOFs it holds (``translation_dof`` false), in the world frame, while the
    free DOFs stay two-way coupled (sim/bodies.RigidBody). The water's resistance along a driven
    DOF is taken by the drive, as a towing carriage takes a model's."""

    velocity: Vec3 = Field(..., description="velocity of the centre of mass along x, y, z, world frame [m/s]; "
                           "non-zero only on held translation DOFs")
    ramp: float = Field(0.0, ge=0, description="the speed eases in (smoothstep) from rest over this time [s]")


#: Densities a dynamic obstacle may have [kg/m³]: from light foams (expanded polystyrene is 10–30) to
#: the densest metals (osmium, 22 590). Far below, the fluid's smallest push throws the body out of
#: the tank within a step; far above, the wall contacts no longer hold it.
BODY_DENSITY = (1.0, 25_000.0)


class Obstacle(_Section):
    """A rigid obstacle from a watertight triangle mesh (OBJ/STL/PLY); static unless it has a motion."""

    mesh: str = Field(..., description="collision mesh file, relative to the scene file")
    render_mesh: str | None = Field(None, description="high-poly mesh for rendering; default: the collision mesh")
    translate: Vec3 = Field([0.0, 0.0, 0.0], description="translation [m]")
    rotate: Vec3 = Field([0.0, 0.0, 0.0], description="rotation about x, y, z, applied in that order [deg]")
    scale: float = Field(1.0, gt=0, description="uniform scale [-]")
    friction: float = Field(0.1, ge=0, le=1, description="Coulomb-like tangential damping at contact [-]")
    repair: bool = Field(False, description="try to repair a mesh that is not watertight")
    stiffness: float = Field(5.0e4, ge=0, description="penalty stiffness k in F = k·n·(−sdf) [1/s²]")
    sdf_resolution: float = Field(1.0, gt=0, le=4.0, description="SDF grid spacing as a multiple of r [-]")
    material: str = Field("stone", description="render material preset: stone, clay, metal, plastic, glass "
                          "(a thin pane: seen through without refraction, as a closed tank's walls), or a terrain "
                          "preset: concrete, rock, sand, grass (procedural, wet below [terrain] water_level)")
    color: Vec3 = Field([0.8, 0.78, 0.72], description="render base colour, linear RGB [0-1]")
    texture: str | None = Field(
        None, description="image texture (PNG, JPEG...) mapped by the render mesh's UVs, relative to the scene file; "
        "replaces the base colour"
    )
    motion: Motion | None = Field(None, description="prescribed motion; unset = static")
    dynamic: bool = Field(False, description="a rigid body moved by the fluid and gravity (two-way coupling)")
    density: float | None = Field(None, ge=BODY_DENSITY[0], le=BODY_DENSITY[1],
                                  description="dynamic: the body's density [kg/m³]")
    mass: float | None = Field(None, gt=0, description="dynamic: the body's mass, instead of density [kg]")
    translation_dof: Dof3 = Field(
        [True, True, True], description="dynamic: may the centre of mass move along world x, y, z? false holds "
        "it (or lets drive move it), as DualSPHysics' translationDOF [-]")
    rotation_dof: Dof3 = Field(
        [True, True, True], description="dynamic: may the body turn about world x, y, z (roll, pitch, yaw of a "
        "hull along x)? false holds it, as DualSPHysics' rotationDOF [-]")
    drive: Drive | None = Field(None, description="dynamic: a prescribed speed along the held translation DOFs")

    @model_validator(mode="after")
    def _dynamic_fields(self) -> "Obstacle":
        if self.dynamic:
            if (self.density is None) == (self.mass is None):
                raise ValueError("a dynamic obstacle needs exactly one of 'density' and 'mass'")
            if self.motion is not None:
                raise ValueError("an obstacle is either dynamic or has a prescribed motion, not both")
            if self.drive is not None:
                free = [a for a, v, f in zip("xyz", self.drive.velocity, self.translation_dof) if v != 0 and f]
                if free:
                    raise ValueError(f"drive.velocity moves the body along {free[0]}, a free DOF: hold it "
                                     f"(translation_dof false on {free[0]}) or set that component to 0")
        else:
            given = [k for k in ("density", "mass", "drive") if getattr(self, k) is not None] + [
                k for k in ("translation_dof", "rotation_dof") if not all(getattr(self, k))]
            if given:
                raise ValueError(f"'{given[0]}' applies only with dynamic = true")
        return self


# --------------------------------------------------------------------------- terrain
class Terrain(_Section):
    """Ground that is part of the scene: a heightfield from a 16-bit heightmap or a surface mesh.

    It collides as a static obstacle (whitecap/terrain.py turns it into a watertight solid that
    is appended to ``obstacle`` with material "terrain") and renders finer, with a procedural
    material (render/terrain.py)."""

    heightmap: str | None = Field(
        None, description="16-bit grayscale PNG, relative to the scene file; 0 = height[0], 65535 = height[1]; "
        "the top row is the +y edge")
    mesh: str | None = Field(None, description="a terrain surface mesh (OBJ/STL/PLY), open or closed, in world "
                             "coordinates, instead of a heightmap: its highest surface is the ground")
    lower: list[float] | None = Field(None, min_length=2, max_length=2,
                                      description="heightmap: x, y of its lower corner [m]; unset = domain.lower")
    size: list[float] | None = Field(None, min_length=2, max_length=2,
                                     description="heightmap: extent in x, y [m]; unset = the domain's")
    height: list[float] | None = Field(None, min_length=2, max_length=2, description="heightmap: heights of "
                                       "pixel values 0 and 65535 [m]; unset = the domain floor to a quarter up")
    resolution: float | None = Field(None, gt=0, description="collision mesh spacing [m]; unset = 2 particle radii")
    render_resolution: float | None = Field(None, gt=0, description="render mesh spacing [m] (finer); "
                                            "unset = resolution / 4")
    base: float | None = Field(None, description="z of the collision solid's flat bottom [m]; unset = below the "
                               "domain floor")
    friction: float = Field(0.2, ge=0, le=1, description="tangential damping at contact, as obstacle.friction [-]")
    sdf_resolution: float = Field(1.0, gt=0, le=4.0, description="SDF grid spacing as a multiple of r [-]")
    material: Literal["sand", "rock", "grass", "concrete"] = Field(
        "sand", description="render: the ground's procedural material; rock shows on steep slopes of any")
    water_level: float | None = Field(None, description="render: the still water line [m]: below it (and a wet "
                                      "band above) the ground is wet, darker and glossier; unset = the top of the "
                                      "highest fluid block")
    wet_band: float | None = Field(None, ge=0, description="render: height of wet ground above water_level [m]; "
                                   "unset = a tenth of the terrain's relief")
    rock_slope: float = Field(40.0, ge=0, le=90, description="render: slopes steeper than this are rock [deg]; "
                              "90 = none")
    grass_above: float | None = Field(None, description="render: grass grows above this height [m]; unset = none")
    texture_scale: float | None = Field(None, gt=0, description="render: size of the texture's larger features [m]; "
                                        "unset = from the terrain's size")

    @model_validator(mode="after")
    def _one_source(self) -> "Terrain":
        if (self.heightmap is None) == (self.mesh is None):
            raise ValueError("give exactly one of 'heightmap' and 'mesh'")
        if self.size is not None and min(self.size) <= 0:
            raise ValueError("terrain.size must be positive in x and y")
        if self.height is not None and self.height[1] < self.height[0]:
            raise ValueError("terrain.height must be [low, high] with low <= high")
        return self


# --------------------------------------------------------------------------- inflow and outflow
class Emitter(_Section):
    """An inflow: particles enter on a lattice of spacing 2r across a face, moving with ``velocity``.

    ``box``: the face is the box's upstream side across the axis of the velocity's largest
    component; ``disk``: a disk of ``radius`` about ``center``, facing the velocity. The rate is
    ``rate`` (a volume flux, each particle standing for (2r)³ of water) or ``particles_per_second``."""

    shape: Literal["box", "disk"] = Field("box", description="box or disk")
    lower: Vec3 | None = Field(None, description="box: lower corner [m]")
    upper: Vec3 | None = Field(None, description="box: upper corner [m]")
    center: Vec3 | None = Field(None, description="disk: centre [m]")
    radius: float | None = Field(None, gt=0, description="disk: radius [m]")
    velocity: Vec3 = Field(..., description="velocity of the entering water [m/s]; not zero")
    rate: float | None = Field(None, gt=0, description="volume flux [m³/s]")
    particles_per_second: float | None = Field(None, gt=0, description="particles entering per second, "
                                               "instead of rate [1/s]")
    start: float = Field(0.0, ge=0, description="time the inflow starts [s]")
    stop: float | None = Field(None, gt=0, description="time the inflow stops [s]; unset = never")

    @model_validator(mode="after")
    def _shape_fields(self) -> "Emitter":
        if self.shape == "box":
            _check_box(self.lower, self.upper, "a box emitter")
        elif self.center is None or self.radius is None:
            raise ValueError("a disk emitter needs 'center' and 'radius'")
        if math.sqrt(sum(x * x for x in self.velocity)) < 1e-9:
            raise ValueError("'velocity' must not be zero: the water enters with it")
        if (self.rate is None) == (self.particles_per_second is None):
            raise ValueError("give exactly one of 'rate' [m³/s] and 'particles_per_second'")
        if self.stop is not None and self.stop <= self.start:
            raise ValueError("'stop' must be after 'start'")
        return self

    def bounds(self) -> tuple[list[float], list[float]]:
        return _shape_bounds(self)

    def sites(self, r: float):
        """(sites, direction, speed): the face's lattice sites (N×3 float64, spacing 2r, where the
        particles appear), the unit direction they advance in through the face, and the speed
        across the face [m/s] (the velocity's component along that direction). A box's face is its
        upstream side across the axis of the velocity's largest component, one radius in."""
        import numpy as np

        v = np.asarray(self.velocity, np.float64)
        if self.shape == "box":
            lo, hi = np.asarray(self.lower, np.float64), np.asarray(self.upper, np.float64)
            a = int(np.argmax(np.abs(v)))
            axes = [np.arange(lo[b] + r, hi[b] - r + 1e-6 * r, 2 * r) for b in range(3)]
            axes[a] = np.array([lo[a] + r if v[a] > 0 else hi[a] - r])
            g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
            d = np.zeros(3)
            d[a] = np.sign(v[a])
            return g, d, float(abs(v[a]))
        d = v / np.linalg.norm(v)
        u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        w = np.cross(d, u)
        m = int(self.radius / (2 * r)) + 1  # type: ignore[operator]
        ij = np.stack(np.meshgrid(np.arange(-m, m + 1), np.arange(-m, m + 1), indexing="ij"), -1).reshape(-1, 2)
        off = 2 * r * ij.astype(np.float64)
        off = off[np.hypot(off[:, 0], off[:, 1]) <= self.radius - r + 1e-6 * r]  # type: ignore[operator]
        g = np.asarray(self.center, np.float64) + off[:, :1] * u + off[:, 1:] * w
        return g, d, float(np.linalg.norm(v))

    def per_second(self, r: float) -> float:
        """Particles entering per second: ``particles_per_second``, or ``rate`` / (2r)³."""
        if self.rate is not None:
            return self.rate / (2 * r) ** 3
        assert self.particles_per_second is not None  # the validator asks for exactly one of the two
        return float(self.particles_per_second)

    def emitted_by(self, r: float, t: float) -> int:
        """How many particles the emitter has added by time ``t`` (those due at or before t)."""
        end = t if self.stop is None else min(t, self.stop)
        return 0 if end < self.start else math.floor(self.per_second(r) * (end - self.start) + 1e-9) + 1


class Sink(_Section):
    """An outflow: every particle that enters the region is removed at the end of the step.

    ``box``: the box from ``lower`` to ``upper``; ``plane``: the half space beyond the plane
    through ``point`` on the side ``normal`` points to."""

    shape: Literal["box", "plane"] = Field("box", description="box or plane (a half space)")
    lower: Vec3 | None = Field(None, description="box: lower corner [m]")
    upper: Vec3 | None = Field(None, description="box: upper corner [m]")
    point: Vec3 | None = Field(None, description="plane: a point on it [m]")
    normal: Vec3 | None = Field(None, description="plane: its normal, pointing into the removed side [-]")

    @model_validator(mode="after")
    def _shape_fields(self) -> "Sink":
        if self.shape == "box":
            _check_box(self.lower, self.upper, "a box sink")
        else:
            if self.point is None or self.normal is None:
                raise ValueError("a plane sink needs 'point' and 'normal'")
            if math.sqrt(sum(x * x for x in self.normal)) < 1e-9:
                raise ValueError("'normal' must not be the zero vector")
        return self

    def contains(self, p: list[float]) -> bool:
        """Whether the point ``p`` is in the removed region."""
        if self.shape == "box":
            assert self.lower is not None and self.upper is not None  # the validator's box check
            return all(lo <= x <= hi for lo, x, hi in zip(self.lower, p, self.upper))
        assert self.point is not None and self.normal is not None  # the validator's plane check
        return sum((x - q) * n for x, q, n in zip(p, self.point, self.normal)) >= 0


# --------------------------------------------------------------------------- foam
class Foam(_Section):
    """Diffuse particles (spray, foam, bubbles) after Ihmsen et al. 2012."""

    enabled: bool = Field(True, description="generate diffuse particles during `simulate`")
    preset: Literal[
        "ihmsen2012", "dualsphysics", "splishsplash", "splishsplash-box", "splishsplash-manual", "auto"
    ] = Field(
        "auto",
        description="parameter preset; every value set below overrides it. 'auto' sets the clamping "
        "thresholds from percentiles of each potential over frames sampled across the run (in the "
        "simulation: a running estimate that only rises) and the multipliers from the budget",
    )
    budget: float = Field(
        3.0, gt=0, le=50,
        description="'auto': diffuse particles per fluid particle at the peak, all types together; it sets "
        "k_ta, k_wc, k_vo for it [-]",
    )
    shares: list[float] = Field(
        [1.0, 1.0, 1.0], min_length=3, max_length=3,
        description="'auto': how the budget splits into spray, foam, bubbles (relative; each type peaks at "
        "budget × its share / the sum) [-]",
    )
    # Clamping thresholds φ(I, τmin, τmax) of the potentials. Unset = from the preset.
    ta_min: float | None = Field(None, ge=0, description="trapped-air τmin [m/s]")
    ta_max: float | None = Field(None, gt=0, description="trapped-air τmax [m/s]")
    wc_min: float | None = Field(None, ge=0, description="wave-crest τmin [-]")
    wc_max: float | None = Field(None, gt=0, description="wave-crest τmax [-]")
    ke_min: float | None = Field(None, ge=0, description="kinetic-energy τmin, per unit mass [J/kg]")
    ke_max: float | None = Field(None, gt=0, description="kinetic-energy τmax, per unit mass [J/kg]")
    vo_min: float | None = Field(None, ge=0, description="vorticity τmin [1/s]")
    vo_max: float | None = Field(None, gt=0, description="vorticity τmax [1/s]")
    k_ta: float | None = Field(None, ge=0, description="trapped-air multiplier k_ta [1/s]")
    k_wc: float | None = Field(None, ge=0, description="wave-crest multiplier k_wc [1/s]")
    k_vo: float | None = Field(None, ge=0, description="vorticity multiplier k_vo [1/s]")
    spray_below: int | None = Field(None, ge=0, description="spray when a particle has fewer fluid neighbours [-]")
    bubble_above: int | None = Field(None, ge=0, description="bubble when a particle has more fluid neighbours [-]")
    lifetime_min: float | None = Field(None, ge=0, description="foam lifetime lower bound (counts down while foam) [s]")
    lifetime_max: float | None = Field(None, ge=0, description="foam lifetime upper bound [s]")
    lifetime_multiplier: float | None = Field(
        None, ge=0, description="if > 0: lifetime = multiplier × I_k × frame time (DualSPHysics style) [-]"
    )
    buoyancy: float | None = Field(None, ge=0, description="bubble buoyancy k_b [-]")
    drag: float | None = Field(None, ge=0, le=1, description="bubble drag k_d [-]")
    spray_multiplier: float = Field(1.0, ge=0, le=100, description="generation of spray, relative to the rest [-]")
    foam_multiplier: float = Field(1.0, ge=0, le=100, description="generation of foam, relative to the rest [-]")
    bubble_multiplier: float = Field(1.0, ge=0, le=100, description="generation of bubbles, relative to the rest [-]")
    spray_lifetime: list[float] | None = Field(
        None, min_length=2, max_length=2,
        description="spray lifetime range [min, max], counting down while spray; "
        "unset = spray lives until it lands [s]",
    )
    bubble_lifetime: list[float] | None = Field(
        None, min_length=2, max_length=2,
        description="bubble lifetime range [min, max], counting down while a bubble; unset = until it surfaces [s]",
    )
    foam_dissipation: float | None = Field(
        None, ge=0, le=100,
        description="foam thins out: each foam particle vanishes at this rate besides its lifetime; "
        "unset = the preset's (0.5, none for the FoamGenerator presets) [1/s]",
    )
    wall_correction: bool | None = Field(
        None,
        description="FoamGenerator presets: its count correction for foam near the domain's faces "
        "(what its --bbsize turns on; foam there becomes bubbles); unset = off, as FoamGenerator without a box",
    )
    slots_per_particle: int | None = Field(
        None, ge=1, le=64,
        description="at most this many new particles per fluid particle and frame; unset = no limit [-]",
    )
    max_particles: int | None = Field(
        None, ge=1, description="capacity of diffuse particles; unset = 3 × budget × fluid particles [-]"
    )
    radius: float = Field(0.5, gt=0, description="diffuse particle radius as a multiple of the fluid radius [-]")
    support: float = Field(
        4.0, ge=2.0, le=8.0, description="neighbourhood radius h as a multiple of the fluid radius [-]"
    )

    @model_validator(mode="after")
    def _ranges(self) -> "Foam":
        for name in ("spray_lifetime", "bubble_lifetime"):
            r = getattr(self, name)
            if r is not None and not 0 < r[0] <= r[1]:
                raise ValueError(f"foam.{name} must be [min, max] with 0 < min <= max, got {r}")
        if min(self.shares) < 0 or sum(self.shares) <= 0:
            raise ValueError(f"foam.shares must be [spray, foam, bubbles] >= 0 with a positive sum, got {self.shares}")
        return self


# --------------------------------------------------------------------------- mesh
#: splashsurf's own smoothing-weight normalization (its CLI's and pysplashsurf's default; Löschner et al. 2023).
SPLASHSURF_WEIGHTS_NORMALIZATION = 13.0


class Mesh(_Section):
    """Surface reconstruction with splashsurf (``whitecap mesh``).

    Lengths are multiples of a radius, as pysplashsurf takes them: the surface
    radius is ``radius_factor`` × the simulation's particle radius r (r is half
    the particle spacing), and ``smoothing_length`` and ``cube_size`` are
    multiples of that surface radius.
    """

    radius_factor: float = Field(
        1.5, gt=0, le=4.0,
        description="surface particle radius as a multiple of the simulation radius r [-] (splashsurf: 1.4-1.6)",
    )
    smoothing_length: float = Field(
        1.2, gt=0, le=10.0,
        description="SPH smoothing length as a multiple of the surface radius [-]; kernel support is twice it",
    )
    cube_size: float = Field(
        0.5, gt=0, le=4.0,
        description="marching-cubes cell edge as a multiple of the surface radius [-] (0.5-0.75; above 1 warns)",
    )
    iso_surface_threshold: float = Field(0.6, gt=0, description="iso value of the SPH colour field [-]")
    mesh_cleanup: bool = Field(True, description="Moore-Warren cleanup of marching-cubes slivers")
    mesh_smoothing_iters: int = Field(15, ge=0, le=1000, description="Laplacian smoothing passes on vertices [-]")
    mesh_smoothing_weights: bool = Field(
        True, description="weight the smoothing so it acts at the surface, not inside thin sheets (Löschner 2023)"
    )
    mesh_smoothing_weights_normalization: float = Field(
        SPLASHSURF_WEIGHTS_NORMALIZATION, gt=0, le=1000.0,
        description="distance-weighted neighbour count Σ(1 − d²/h_c²) at which a vertex is smoothed fully [-] "
        "(splashsurf's default 13); fewer neighbours smooth less, so lower it to smooth films a particle or two thick",
    )
    normals_smoothing_iters: int = Field(10, ge=0, le=1000, description="smoothing passes on vertex normals [-]")
    interpolate_velocity: bool = Field(True, description="interpolate particle velocity onto vertices (motion blur)")
    format: Literal["ply", "obj"] = Field("ply", description="mesh file format (obj carries no velocity)")


# --------------------------------------------------------------------------- view
class View(_Section):
    """Real-time GGUI viewer (`whitecap view`). Camera fields left out are framed on the domain."""

    camera_position: Vec3 | None = Field(None, description="camera eye position [m]; default: in front of the domain")
    lookat: Vec3 | None = Field(None, description="point the camera looks at [m]; default: the domain centre")
    fov: float = Field(45.0, gt=1.0, lt=170.0, description="vertical field of view [deg]")
    window_size: list[int] = Field([1280, 720], min_length=2, max_length=2, description="window width, height [px]")
    color_mode: Literal["speed", "density"] = Field("speed", description="what colours the fluid particles")
    color_range: list[float] | None = Field(
        None, min_length=2, max_length=2,
        description="colour-map range [m/s] or [kg/m³]; default: fitted to the first frame shown",
    )
    point_scale: float = Field(1.0, gt=0, le=10.0, description="drawn fluid sphere radius as a multiple of r [-]")
    background: Vec3 = Field([0.13, 0.14, 0.17], description="background colour, RGB [0-1]")
    move_speed: float = Field(1.0, gt=0, description="WASD/QE camera speed [domain diagonals per second]")
    fps_limit: int = Field(60, ge=1, le=1000, description="frame rate cap of the interactive window [1/s]")
    steps_per_draw: int | None = Field(
        None, ge=1, le=10000,
        description="live mode: solver steps between redraws; unset = a whole output frame per redraw [-]",
    )
    web_points: Literal["auto", "browser", "server"] = Field(
        "auto", description="browser viewer (--web): where particles are drawn: the page's WebGL, pictures drawn "
        "on the server, or auto = on the server above 30,000 particles (view/web.py SERVER_POINTS_ABOVE)",
    )


# --------------------------------------------------------------------------- render
class Render(_Section):
    """Offline rendering in Blender (Cycles). Unset camera keys frame the fluid automatically."""

    resolution: list[int] = Field([1920, 1080], min_length=2, max_length=2, description="final image size [px]")
    samples: int = Field(128, ge=1, le=65536, description="final Cycles samples per pixel [-]")
    device: Literal["auto", "cpu", "gpu"] = Field(
        "auto",
        description="Cycles device: auto = a GPU (OptiX, CUDA, HIP, oneAPI) where Blender finds one, else the CPU",
    )
    preview_resolution: list[int] = Field([320, 240], min_length=2, max_length=2, description="preview size [px]")
    preview_samples: int = Field(
        8, ge=1, le=4096,
        description="preview samples per pixel [-] "
        "(8: the denoiser gives the same picture as 16 at about 60 % of the CPU time)",
    )
    camera_start: Vec3 | None = Field(None, description="camera position at the first frame [m]")
    camera_end: Vec3 | None = Field(None, description="camera position at the last frame; unset = camera_start [m]")
    camera_target: Vec3 | None = Field(
        None, description="point the camera looks at; unset = centre of the fluid's bounds over the run [m]"
    )
    camera_orbit: float = Field(0.0, ge=-360, le=360, description="orbit about the target over the run [deg]")
    lens: float = Field(32.0, gt=1, le=500, description="camera focal length [mm]")
    water_color: Vec3 = Field([0.55, 0.8, 0.9], description="volume absorption tint of the water, linear RGB [0-1]")
    water_absorption: float = Field(3.0, ge=0, description="volume absorption density [1/m]")
    water_roughness: float = Field(0.02, ge=0, le=1, description="surface roughness of the water [-]")
    spray_radius: list[float] | None = Field(
        None, min_length=2, max_length=2,
        description="spray droplet radius range [m]; unset = 0.1–0.25 × particle radius",
    )
    foam_radius: list[float] | None = Field(
        None, min_length=2, max_length=2,
        description="foam bubble radius range [m]; unset = 0.15–0.35 × particle radius",
    )
    bubble_radius: list[float] | None = Field(
        None, min_length=2, max_length=2, description="air bubble radius range [m]; unset = 0.1–0.3 × particle radius"
    )
    diffuse_copies: int = Field(
        1, ge=1, le=16,
        description="render-time multiplier: jittered copies of each diffuse particle (seeded by its id, so they "
        "keep their place from frame to frame); thickens foam without re-simulating [-]",
    )
    droplet_particles: float = Field(
        0.0, ge=0,
        description="fluid-mesh pieces holding fewer particles than this (by their volume) are drawn with the spray's "
        "material: in a scale model a lone particle's blob is a centimetre bead of clear water where the prototype "
        "throws white spray; 0 = off [-]",
    )
    motion_blur: bool = Field(True, description="motion blur from vertex velocities and object motion")
    shutter: float = Field(0.5, gt=0, le=2, description="shutter open time [frames]")
    denoise: bool = Field(True, description="OpenImageDenoise on the final image when available")
    glare: float = Field(0.15, ge=0, le=1, description="strength of the compositor glare (0 = off) [-]")
    sun_strength: float = Field(3.0, ge=0, description="sun irradiance [W/m²] (Blender units); with the sky only")
    sun_angle: Vec3 = Field(
        [50.0, 10.0, 30.0],
        description="sun lamp rotation about x, y, z [deg]; the sky's sun is put where it points from",
    )
    world_strength: float = Field(1.0, ge=0, description="strength of the sky or of the environment image [-]")
    environment: str | None = Field(
        None, description="an HDRI (.hdr or .exr) lighting the scene, relative to the scene file; unset = physical sky"
    )
    sky_type: Literal["MULTIPLE_SCATTERING", "SINGLE_SCATTERING", "PREETHAM", "HOSEK_WILKIE"] = Field(
        "MULTIPLE_SCATTERING", description="Blender's physical sky model when no environment image is set"
    )
    exposure: float = Field(0.0, ge=-10, le=10, description="exposure of the AgX view transform [stops]")
    focus_target: Vec3 | None = Field(None, description="depth of field: the point in focus; unset = camera target [m]")
    fstop: float | None = Field(
        None, gt=0, le=1024, description="depth of field: aperture f-number; unset = no depth of field [-]"
    )
    container: Literal["glass", "basin", "none"] | None = Field(
        None,
        description="the domain's solid walls drawn as a glass tank with an open top, an opaque tiled basin, or "
        "nothing; unset = glass where the run's walls held the fluid, else none",
    )
    wall_thickness: float | None = Field(
        None, gt=0, description="container wall thickness [m]; unset = 2.5 particle radii"
    )
    ground: bool = Field(True, description="a textured ground plane under the domain box")
    ground_texture: Literal["tiles", "checker", "concrete"] = Field(
        "tiles", description="the ground's procedural texture"
    )
    # open sea around the domain and a camera that follows (render/sea.py, render/camera_follow.py)
    sea: bool = Field(False, description="a sea surface around the domain to the horizon, blended into the simulated "
                      "water at the domain's edge (the container is then none)")
    sea_level: float | None = Field(None, description="the sea's still-water level [m]; unset = the level the first "
                                    "frame's water would settle at over the domain's floor")
    sea_wave_height: float | None = Field(None, ge=0, description="crest-to-trough height of the sea's waves [m]; "
                                          "unset = 2.5 % of the domain's longer horizontal side")
    sea_wave_length: float | None = Field(None, gt=0, description="length of the sea's longest waves [m]; unset = "
                                          "20 % of the domain's longer horizontal side")
    sea_wave_direction: float = Field(0.0, ge=-360, le=360, description="direction the sea's waves travel, from +x "
                                      "toward +y [deg]")
    sea_blend: float | None = Field(None, gt=0, description="distance from the domain's edge over which the sea goes "
                                    "from the simulated water's height to its own level and waves [m]; unset = 25 % "
                                    "of the domain's longer horizontal side")
    camera_follow: str | Vec3 | None = Field(None, description='"body:K": the camera follows obstacle K (its '
                                             "recorded poses); [x, y, z]: it looks at that point; unset = no follow")
    camera_smoothing: float = Field(0.5, ge=0, description="time constant of the follow camera's critically damped "
                                    "smoothing [s] (0 = rigidly attached)")
    camera_offset: Vec3 | None = Field(None, description="follow camera: its position relative to the followed point "
                                       "[m]; unset = the default framing's (or the preset's)")
    camera_preset: Literal["over_water"] | None = Field(None, description='"over_water": a low camera just above the '
                                                        "sea level looking across the water")
    camera_height: float | None = Field(None, gt=0, description="over_water: the camera's height above the sea level "
                                        "[m]; unset = 4 % of the framed width")

    @model_validator(mode="after")
    def _radius_ranges(self) -> "Render":
        for name in ("spray_radius", "foam_radius", "bubble_radius"):
            r = getattr(self, name)
            if r is not None and not 0 < r[0] <= r[1]:
                raise ValueError(f"render.{name} must be [min, max] in metres with 0 < min <= max, got {r}")
        if self.sea and self.container not in (None, "none"):
            raise ValueError(f"render.sea needs container = 'none' (the sea replaces the tank), got '{self.container}'")
        f = self.camera_follow
        if isinstance(f, str) and not (f.startswith("body:") and f[5:].isdigit()):
            raise ValueError(f"render.camera_follow must be 'body:K' (K an obstacle's index) or [x, y, z], got '{f}'")
        return self


# --------------------------------------------------------------------------- cluster
class Cluster(_Section):
    """Per-frame stages on a Dask cluster (``--cluster slurm|pbs|local|ADDRESS``); see the README.

    ``cores``, ``memory``, ``walltime``, ``queue`` and ``account`` describe one
    batch job (dask-jobqueue); ``jobs`` is how many such jobs to start.
    """

    jobs: int = Field(1, ge=1, le=100_000, description="batch jobs to start (slurm, pbs) or local workers (local) [-]")
    cores: int = Field(4, ge=1, le=4096, description="cores per batch job [-]")
    processes: int = Field(1, ge=1, le=4096, description="Dask worker processes per batch job (one Blender each) [-]")
    memory: str = Field("16GB", pattern=r"^\d+(\.\d+)?\s*[KMGT]i?B$", description="memory per batch job, e.g. 16GB")
    walltime: str = Field(
        "01:00:00", pattern=r"^(\d+-)?\d{1,3}:\d{2}(:\d{2})?$", description="time limit per batch job, HH:MM:SS"
    )
    queue: str | None = Field(None, description="partition (Slurm) or queue (PBS); unset = the site's default")
    account: str | None = Field(None, description="account or project to charge; unset = the user's default")
    interface: str | None = Field(
        None, description="network interface the workers talk on (e.g. ib0); unset = the default"
    )
    job_extra: list[str] = Field(default_factory=list, description="extra #SBATCH/#PBS options, e.g. ['--gres=gpu:1']")
    setup: list[str] = Field(
        default_factory=list, description="shell lines run in each job before the worker starts (module load, venv)"
    )
    local_directory: str | None = Field(None, description="worker scratch directory on each node; unset = Dask's")
    connect_timeout: float = Field(
        10.0, gt=0, le=3600, description="seconds to wait for the scheduler to answer before failing [s]"
    )


# --------------------------------------------------------------------------- output
class Output(_Section):
    """What `simulate` writes."""

    frames: int = Field(60, ge=1, le=1_000_000, description="number of frames after frame 0 [-]")
    formats: list[Literal["ply", "npz"]] = Field(["ply"], description="particle file formats to write")
    checkpoint_interval: int = Field(
        0, ge=0, description="frames between resume checkpoints (and one at the last frame); 0: automatic, "
        "every frame on the CPU and every 20 frames on a GPU, which keeps checkpoints under 5% of the run "
        "(a resume recomputes the frames after the last checkpoint, byte for byte) [-]")


# --------------------------------------------------------------------------- scene
class Scene(_Section):
    """A whole run. Sections: domain, solver, fluid, obstacle, foam, mesh, view, render, cluster, output."""

    name: str = Field("scene", description="a label for the run, and the run directory's name under out/")
    seed: int = Field(0, ge=0, lt=2**32, description="random seed for everything stochastic")
    domain: Domain = Field(default_factory=Domain)
    solver: Solver = Field(default_factory=Solver)
    fluid: list[FluidBlock] = Field(default_factory=list, description="initial fluid blocks")
    obstacle: list[Obstacle] = Field(default_factory=list, description="obstacles, static or moving")
    terrain: Terrain | None = Field(None, description="the ground as a heightmap or mesh; collides as an obstacle")
    emitter: list[Emitter] = Field(default_factory=list, description="inflows: particles enter during the run")
    sink: list[Sink] = Field(default_factory=list, description="outflows: particles entering them are removed")
    foam: Foam = Field(default_factory=Foam)
    mesh: Mesh = Field(default_factory=Mesh)
    view: View = Field(default_factory=View)
    render: Render = Field(default_factory=Render)
    cluster: Cluster = Field(default_factory=Cluster)
    output: Output = Field(default_factory=Output)

    # Where relative paths in the scene (meshes) are resolved; not part of the TOML.
    base_dir: str = Field(".", exclude=True, description="directory of the scene file (internal)")
    source: str = Field("<scene>", exclude=True, description="the scene file, for messages (internal)")

    @field_validator("name")
    @classmethod
    def _one_path_component(cls, v: str) -> str:
        # The default run directory is out/NAME: a name with a separator, '..' or nothing at all
        # would put the run (and a --force deletion) outside out/ or into out/ itself.
        if not v.strip() or v in (".", "..") or any(c in v for c in "/\\\0:") or v != v.strip():
            raise ValueError("must be one folder name, not empty, without '/', '\\', ':' or '..' "
                             "(the run goes to out/NAME)")
        return v

    @model_validator(mode="after")
    def _blocks_inside(self) -> "Scene":
        lo, hi = self.domain.lower, self.domain.upper
        for k, b in enumerate(self.fluid):
            blo, bhi = b.bounds()
            if any(blo[i] < lo[i] - 1e-9 or bhi[i] > hi[i] + 1e-9 for i in range(3)):
                raise ValueError(
                    f"fluid[{k}]: the block spans {blo}..{bhi}, outside the domain {lo}..{hi} "
                    "(domain.lower, domain.upper)"
                )
        self._check_inflow()
        return self

    def _check_inflow(self) -> None:
        """Emitters inside the domain, each within what its face carries, within the capacity; no
        initial fluid block wholly inside a sink. (Emitters inside obstacles: sim/emitters.py.)"""
        lo, hi = self.domain.lower, self.domain.upper
        r = self.solver.particle_radius
        total = 0.0
        for k, e in enumerate(self.emitter):
            elo, ehi = e.bounds()
            if any(elo[i] < lo[i] - 1e-9 or ehi[i] > hi[i] + 1e-9 for i in range(3)):
                raise ValueError(f"emitter[{k}]: spans {[round(v, 6) for v in elo]}..{[round(v, 6) for v in ehi]}, "
                                 f"outside the domain {lo}..{hi} (emitter[{k}].lower/upper/center)")
            sites, _, speed = e.sites(r)
            if len(sites) == 0:
                raise ValueError(f"emitter[{k}]: its face holds no particle at spacing 2r = {2 * r:g} m; "
                                 "enlarge it or lower solver.particle_radius")
            pps, most = e.per_second(r), len(sites) * speed / (2 * r)
            if pps > most * (1 + 1e-9):
                field = "rate" if e.rate is not None else "particles_per_second"
                raise ValueError(f"emitter[{k}].{field}: {pps:.4g} particles/s is more than its face carries at "
                                 f"this speed without overlap ({most:.4g}/s = {len(sites)} sites x {speed:.3g} m/s "
                                 f"/ 2r); raise the velocity or enlarge the emitter")
            total += e.emitted_by(r, self.output.frames / self.solver.frame_rate)
        cap = self.solver.max_particles
        if cap is not None and self.emitter and not self.sink:
            n0 = sum(b.lattice_count(r) for b in self.fluid)
            if n0 + total > cap:
                raise ValueError(f"emitter[*].rate: the emitters add {total:,.0f} particles over the run, "
                                 f"{n0:,} are there at the start: more than solver.max_particles = {cap:,} "
                                 "and no [[sink]] removes any; lower the rates or raise solver.max_particles")
        for k, b in enumerate(self.fluid):
            blo, bhi = b.bounds()
            corners = [[(blo, bhi)[(c >> a) & 1][a] for a in range(3)] for c in range(8)]
            for j, s in enumerate(self.sink):
                if all(s.contains(c) for c in corners):
                    raise ValueError(f"sink[{j}]: covers the whole of fluid[{k}], which would be removed at the "
                                     "first step; move the sink or the block")

    def resolve(self, path: str) -> Path:
        """A path from the scene file, resolved against the scene's directory."""
        p = Path(path)
        return p if p.is_absolute() else Path(self.base_dir) / p

    def to_toml(self) -> str:
        import tomli_w

        return tomli_w.dumps(_drop_none(self.model_dump(exclude={"base_dir", "source"})))


#: Taichi backends a command may ask for (:func:`whitecap.sim.runtime.init`): ``auto`` is CUDA when
#: present, else the CPU; and the one every command and stage defaults to.
ARCHES = ("cpu", "cuda", "auto")
DEFAULT_ARCH = "cpu"
#: Up axes of particle files read from other solvers (``y``: converted to whitecap's z up on
#: reading), and the default: whitecap's own.
UP_AXES = ("z", "y")
DEFAULT_UP = "z"


def choices(model: type[BaseModel], name: str) -> tuple[str, ...]:
    """The allowed values of a Literal field, e.g. ``choices(Foam, "preset")``: the CLI's
    choices come from here, so the scene model stays their one definition."""
    return get_args(model.model_fields[name].annotation)


def with_options(cls: type[Job], job: Job | None, options: dict[str, Any]) -> Job:
    """A stage's options object (a frozen dataclass next to its driver: SimulateJob, RenderJob,
    ExportJob...): ``job`` with ``options`` (its field names) replacing its fields, or a new one
    built from them when ``job`` is None. Anything else in place of ``job`` is a TypeError (so a
    path passed where the job goes does not pass silently)."""
    if job is not None and not isinstance(job, cls):
        raise TypeError(f"expected a {cls.__qualname__} (or keyword options), got {type(job).__qualname__}")
    return cls(**options) if job is None else dataclasses.replace(job, **options)


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_drop_none(v) for v in d]
    return d


# --------------------------------------------------------------------------- loading
def _model_at(loc: tuple, model: type[BaseModel] = Scene) -> type[BaseModel] | None:
    """Walk a validation-error location to the model class that owns it."""
    m: Any = model
    for part in loc:
        if isinstance(part, int):
            continue
        fld = m.model_fields.get(part) if hasattr(m, "model_fields") else None
        if fld is None:
            return m
        ann = fld.annotation
        inner = getattr(ann, "__args__", None)
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            m = ann
        elif inner:
            sub = [a for a in inner if isinstance(a, type) and issubclass(a, BaseModel)]
            if not sub:
                return m
            m = sub[0]
        else:
            return m
    return m


def _format_error(err: ErrorDetails, source: str) -> str:
    loc = tuple(err["loc"])
    key = ".".join(str(p) if not isinstance(p, int) else f"[{p}]" for p in loc).replace(".[", "[")
    if err["type"] == "extra_forbidden":
        owner = _model_at(loc[:-1])
        hint = ""
        if owner is not None:
            close = difflib.get_close_matches(str(loc[-1]), list(owner.model_fields), n=1)
            if close:
                hint = f"; did you mean '{close[0]}'?"
        return f"{source}: {key}: unknown key{hint}"
    msg = err["msg"].removeprefix("Value error, ")
    got = err.get("input")
    got_s = "" if isinstance(got, dict) or got is None else f" (got {got!r})"
    if not key:  # a whole-scene check: its message names the fields
        return f"{source}: {msg}{got_s}"
    return f"{source}: {key}: {msg}{got_s}"


def scene_from_dict(data: dict, source: str = "<scene>", base_dir: str | Path = ".") -> Scene:
    """Validate a parsed TOML table into a :class:`Scene`."""
    try:
        scene = Scene.model_validate(data)
    except ValidationError as exc:
        raise InputError(_format_error(exc.errors()[0], source)) from None
    scene.base_dir = str(base_dir)
    scene.source = source
    if scene.terrain is not None:  # the terrain joins the obstacles (whitecap/terrain.py)
        from .terrain import expand

        expand(scene, source)
    return scene


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file. Raises InputError with file and key."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a directory, not a scene file (give the .toml file)")
    if not p.is_file():
        raise InputError(f"{p}: scene file not found")
    try:
        data = tomllib.loads(p.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset {exc.start}); "
                         "save the scene file as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{p}: malformed TOML: {exc}") from None
    return scene_from_dict(data, str(p), p.parent.resolve())


def default_scene() -> Scene:
    """The fully defaulted scene: a small dam break."""
    return Scene(fluid=[FluidBlock(lower=[0.02, 0.02, 0.02], upper=[0.32, 0.48, 0.5])])
