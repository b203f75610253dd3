"""Open water to the horizon: a sea surface around the domain box (``[render] sea = true``).

The sea is one mesh of rings around the domain's footprint: ring 0 lies on
the domain's side walls, later rings are offset outward with a spacing that
grows with the distance, out to :data:`EXTENT` domain sizes, far past the
horizon at any camera height the renderer picks. Per frame
(:func:`sea_heights`) each vertex's height blends, over ``sea_blend`` metres
from the wall, from the simulated water's height at that point of the wall
to the still-water level plus small waves (a few deep-water sine waves, so the
frame is a pure function of its time). At the wall the blend is flat
(smoothstep), so the sea meets the simulated surface at its height and
without a kink.

The simulated water's mesh is closed: its faces on the side walls and the
floor would stand inside the sea's water as a glass-like wall. With the sea
those faces are dropped (:func:`open_walls`), so the fluid mesh and the sea
together are one open sheet over one body of water (Cycles follows the
volume across them; the ground is its bottom). The sea uses the water's own
material; its ripples are a bump weighted by the mesh attribute
:data:`RIPPLE_ATTR`, which only the sea carries, so the simulated water
stays as it was.

The geometry is pure numpy (tested without Blender); :func:`add_sea` and
:func:`update_sea` are the bpy steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Render
from ..io.run import RunInfo

#: The sea reaches this many times the domain's longer horizontal side from its edge.
EXTENT = 500.0
#: Ring spacing grows by this share of the distance from the wall.
GROWTH = 0.08
#: Samples on each quarter circle around a corner of the domain.
CORNER_SAMPLES = 8
#: Around-the-domain samples at most (their spacing is at least the perimeter over this).
MAX_AROUND = 2000
#: Defaults as shares of the domain's longer horizontal side (see config.Render).
WAVE_HEIGHT_SHARE, WAVE_LENGTH_SHARE, BLEND_SHARE = 0.025, 0.2, 0.25
#: The deep-water sine waves: (direction offset [deg], wavelength share, phase [rad]); amplitude ∝ wavelength.
WAVES = ((0.0, 1.0, 0.0), (25.0, 0.73, 1.7), (-35.0, 0.52, 4.1), (60.0, 0.37, 2.9))
#: A wave is drawn in the geometry only where the mesh spacing is below its length over this.
WAVE_SAMPLES = 6.0
#: Water at the domain's edge is the sea's when its top is within this share of the domain's height of the level.
SEA_WATER = 0.25
#: The edge's detail fades outward, and its profile is smoothed along the outline, over this share of the blend.
EDGE_DETAIL = 0.1
#: The edge's profile carried out across the blend stays within this many sea wave heights of the level.
EDGE_PROFILE = 2.0
#: Near a side wall the fluid mesh's normals lose their part along the wall's normal over this many particle
#: radii (a little more than the surface kernel's support, 2 × smoothing_length 1.2-1.6 × radius_factor 1.5 r).
WALL_NORMAL_REACH = 5.0
#: Point attribute of the sea mesh: 0 at the domain's edge, 1 past the blend; weights the ripple bump.
RIPPLE_ATTR = "sea_ripple"
#: Ripple bump: noise feature size as a share of the wave length, and the bump's strength.
RIPPLE_SIZE, RIPPLE_STRENGTH = 0.15, 0.6


# ============================================================================ pure geometry
@dataclass
class SeaLayout:
    """The fixed topology of the sea: vertex (ring k, sample j) at base[j] + d[k]·normal[j]."""

    lo: np.ndarray  # domain lower corner (3,)
    hi: np.ndarray  # domain upper corner (3,)
    base: np.ndarray  # (n, 2) points on the domain's footprint outline (corners repeated)
    normal: np.ndarray  # (n, 2) outward unit normals
    wall: np.ndarray  # (n,) which wall a sample lies on: 0 y-, 1 x+, 2 y+, 3 x-; -1 a corner sample
    d: np.ndarray  # (m,) ring distances from the wall [m], d[0] = 0
    spacing: np.ndarray  # (m,) mesh spacing at each ring [m]
    faces: np.ndarray  # (f, 3) triangles, counter-clockwise seen from above

    def xy(self) -> np.ndarray:
        """(m·n, 2) vertex positions, ring by ring."""
        return (self.base[None, :, :] + self.d[:, None, None] * self.normal[None, :, :]).reshape(-1, 2)


def horizontal_size(info: RunInfo) -> float:
    lo, hi = np.array(info.domain["lower"], float), np.array(info.domain["upper"], float)
    return float(max(hi[0] - lo[0], hi[1] - lo[1]))


def wave_height(cfg: Render, info: RunInfo) -> float:
    return cfg.sea_wave_height if cfg.sea_wave_height is not None else WAVE_HEIGHT_SHARE * horizontal_size(info)


def wave_length(cfg: Render, info: RunInfo) -> float:
    return cfg.sea_wave_length if cfg.sea_wave_length is not None else WAVE_LENGTH_SHARE * horizontal_size(info)


def blend_distance(cfg: Render, info: RunInfo) -> float:
    return cfg.sea_blend if cfg.sea_blend is not None else BLEND_SHARE * horizontal_size(info)


def sea_layout(lo, hi, step: float, extent: float, fine: float | None = None, fine_until: float = 0.0) -> SeaLayout:
    """Rings around the footprint of the box [lo, hi]: samples about ``step`` apart along the
    walls (CORNER_SAMPLES on each corner's quarter circle), rings from the walls out to ``extent``:
    ``step`` apart at the wall, at most ``fine`` apart out to ``fine_until`` (the waves' region),
    then further apart with the distance."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    x0, y0, x1, y1 = lo[0], lo[1], hi[0], hi[1]
    perimeter = 2 * (x1 - x0 + y1 - y0)
    step = max(step, perimeter / MAX_AROUND)
    # walls counter-clockwise seen from above: (start, end, outward normal); a corner follows each
    walls = [((x0, y0), (x1, y0), (0.0, -1.0)), ((x1, y0), (x1, y1), (1.0, 0.0)),
             ((x1, y1), (x0, y1), (0.0, 1.0)), ((x0, y1), (x0, y0), (-1.0, 0.0))]
    base, normal, wall = [], [], []
    for w, (start, end, out) in enumerate(walls):
        a, b = np.array(start), np.array(end)
        k = max(2, int(math.ceil(np.linalg.norm(b - a) / step)))
        t = np.arange(1, k) / k
        base += list(a + t[:, None] * (b - a))
        normal += [out] * (k - 1)
        wall += [w] * (k - 1)
        a0 = math.atan2(out[1], out[0])
        for s in np.linspace(0.0, math.pi / 2, CORNER_SAMPLES + 1):
            base.append(b)
            normal.append((math.cos(a0 + s), math.sin(a0 + s)))
            wall.append(-1)
    fine = max(fine or step, step)

    def gap(x):
        if x < fine_until:
            return max(step, min(fine, step + GROWTH * x))
        return fine + GROWTH * (x - fine_until)

    rings = [0.0]
    while rings[-1] < extent:
        rings.append(rings[-1] + gap(rings[-1]))
    d = np.array(rings)
    spacing = np.array([gap(x) for x in d])
    n, m = len(base), len(d)
    j = np.arange(n)
    jn = (j + 1) % n
    faces = []
    for k in range(m - 1):
        a, b, c, e = k * n + j, k * n + jn, (k + 1) * n + jn, (k + 1) * n + j
        # the outline runs counter-clockwise and the rings go outward: (a, c, b) and (a, e, c) face up
        faces.append(np.stack([a, c, b], 1))
        faces.append(np.stack([a, e, c], 1))
    return SeaLayout(lo, hi, np.array(base, float), np.array(normal, float), np.array(wall), d, spacing,
                     np.concatenate(faces).astype(np.int32))


def wall_tolerance(r: float) -> float:
    """How close to a wall plane a mesh vertex counts as on it [m] (meshing snaps them to ~1e-6 m)."""
    return max(1e-3 * r, 4e-6)


def open_walls(verts: np.ndarray, faces: np.ndarray, lo, hi, r: float) -> np.ndarray:
    """The fluid mesh's faces less those on the domain's side walls and floor: faces whose
    three vertices lie on those planes and that do not face up (a surface triangle in a
    corner, between two walls, stays)."""
    if len(faces) == 0:
        return faces
    v = np.asarray(verts, float)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    eps = wall_tolerance(r)
    on = ((np.abs(v[:, 0] - lo[0]) < eps) | (np.abs(v[:, 0] - hi[0]) < eps) | (np.abs(v[:, 1] - lo[1]) < eps)
          | (np.abs(v[:, 1] - hi[1]) < eps) | (np.abs(v[:, 2] - lo[2]) < eps))
    f = np.asarray(faces)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    up = n[:, 2] > 0.5 * np.linalg.norm(n, axis=1)
    drop = on[f].all(1) & ~up
    return f[~drop]


def wall_normals(verts: np.ndarray, normals: np.ndarray, lo, hi, reach: float) -> np.ndarray:
    """The fluid mesh's vertex normals made level with the sea at the side walls: each normal's
    component along a side wall's normal is scaled by smoothstep(distance to that wall / ``reach``),
    then the normal is renormalised. The surface reconstruction sees no particles beyond a wall, so
    the water's top rounds off toward it and its smoothed normals lean out over the last few radii;
    the sea continues the water there as the mirror of the inside, whose slope across the wall is
    zero, so the leaning normals shaded a crease along every wall. A normal that would vanish (one
    facing the wall, on a face open_walls drops) points up."""
    v = np.asarray(verts, float)
    n = np.array(normals, float, copy=True)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    for axis in (0, 1):
        n[:, axis] *= smoothstep(np.minimum(v[:, axis] - lo[axis], hi[axis] - v[:, axis]) / reach)
    norm = np.linalg.norm(n, axis=1)
    flat = norm < 1e-6
    n[flat] = (0.0, 0.0, 1.0)
    norm[flat] = 1.0
    return n / norm[:, None]


def edge_heights(layout: SeaLayout, verts: np.ndarray, r: float, level: float | None = None,
                 reach: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(height, inset) of the sea's inner edge at each outline sample [m].

    Where the simulated water touches the wall: the highest fluid-mesh vertex on that wall
    within a sample spacing (at least r) of the sample, inset 0. A wall the water touches
    nowhere (a wave maker or an inflow stands between it and the water) is met where the water
    is: the edge moves ``inset`` inward, up to ``reach``, to the water's nearest vertices in the
    sample's strip, at the top of the water there (:func:`sea_xy` spreads the move over the
    blend), where the water there is the sea's (its top within SEA_WATER × the domain's height
    of ``level``; not a dam-break column standing in a dry domain). Where the water does not
    reach a wall (a beach, a breakwater standing on it), a gap of up to three samples is bridged
    by a straight line between the samples on either side, and so is a longer one next to the
    sea's water (a step there would run out across the sea as a slab); a longer one between
    water that is not the sea's is the floor (a terrain above it hides the sea there, as the
    ground of a dry domain). Without any water the edge is at ``level`` (the floor without one).
    Corner samples take the higher of their two walls' nearest heights."""
    lo, hi = layout.lo, layout.hi
    v = np.asarray(verts, float).reshape(-1, 3)
    eps = wall_tolerance(r)
    n = len(layout.base)
    h = np.full(n, np.nan)
    inset = np.zeros(n)
    tol = SEA_WATER * (hi[2] - lo[2])
    planes = [(1, lo[1], 0), (0, hi[0], 1), (1, hi[1], 0), (0, lo[0], 1)]  # (normal axis, plane, along axis)
    for w, (axis, plane, along) in enumerate(planes):
        sel = np.flatnonzero(layout.wall == w)
        if len(sel) == 0 or len(v) == 0:
            continue
        s = layout.base[sel, along]
        half = max(np.abs(np.diff(s)).max() if len(s) > 1 else r, r)
        inward = (plane - v[:, axis]) * layout.normal[sel[0], axis]  # distance from the wall into the domain
        touching = np.abs(inward) < eps
        near = touching if touching.any() else (inward > 0) & (inward <= reach)
        if not near.any():
            continue
        order = np.argsort(v[near, along])
        u, z, d = v[near, along][order], v[near, 2][order], np.maximum(inward[near][order], 0.0)
        a, b = np.searchsorted(u, s - half), np.searchsorted(u, s + half)
        for i, (ia, ib) in enumerate(zip(a, b)):
            if ib > ia:
                d0 = d[ia:ib].min()
                top = z[ia:ib][d[ia:ib] <= d0 + 2 * r].max()
                if d0 > eps and level is not None and abs(top - level) > tol:
                    continue  # water standing off this wall that is not the sea's: no inset
                h[sel[i]], inset[sel[i]] = top, d0
    edge = layout.wall >= 0
    known = np.flatnonzero(edge & np.isfinite(h))
    fill = lo[2] if level is None else level
    if len(known) == 0:
        return np.full(n, fill), inset
    # bridge the gaps along the loop (edge samples only): a straight line between the known samples
    # on either side, so the sea's edge has no step where a beach or an obstacle keeps the water off
    sea_water = np.ones(n, bool) if level is None else np.abs(np.nan_to_num(h, nan=np.inf) - level) <= tol
    idx = np.flatnonzero(edge)
    pos = np.searchsorted(known, idx)
    prev = known[(pos - 1) % len(known)]
    nxt = known[pos % len(known)]
    for i, p, q in zip(idx, prev, nxt):
        if np.isfinite(h[i]):
            continue
        gp, gq = (i - p) % n, (q - i) % n
        edges_between = (layout.wall[np.arange(p, p + gp + gq + 1) % n] >= 0).sum() - 2
        if edges_between > 3 and not (sea_water[p] or sea_water[q]):
            h[i] = lo[2]
            continue
        t = gp / max(gp + gq, 1)
        h[i] = (1 - t) * h[p] + t * h[q]
        inset[i] = (1 - t) * inset[p] + t * inset[q]
    # corners: the higher of the nearest wall samples on either side
    for i in np.flatnonzero(~edge):
        a = i
        while layout.wall[a] < 0:
            a = (a - 1) % n
        b = i
        while layout.wall[b] < 0:
            b = (b + 1) % n
        h[i] = max(h[a], h[b])
    return h, inset


def sea_xy(layout: SeaLayout, inset: np.ndarray, blend: float) -> np.ndarray:
    """(m·n, 2) vertex positions with each sample's edge moved ``inset`` inward: ring k of sample
    j at d[k] − inset[j]·(1 − smoothstep(d[k]/blend)) along its normal (still in order outward,
    since that grows with d)."""
    d = layout.d[:, None] - inset[None, :] * (1 - smoothstep(layout.d / blend))[:, None]
    return (layout.base[None, :, :] + d[:, :, None] * layout.normal[None, :, :]).reshape(-1, 2)


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def waves(xy: np.ndarray, spacing: np.ndarray, t: float, height: float, length: float, direction_deg: float,
          g: float) -> np.ndarray:
    """Sea surface elevation at points ``xy`` (n, 2) at time ``t``: the sum of the WAVES sines
    (deep-water dispersion ω = √(g k)), crest-to-trough ``height`` where all are drawn. A wave
    shorter than WAVE_SAMPLES × the local mesh ``spacing`` (n,) fades out (the ripple bump
    stands for it there)."""
    total = sum(share for _, share, _ in WAVES)
    z = np.zeros(len(xy))
    for off, share, phase in WAVES:
        lam = length * share
        amp = 0.5 * height * share / total
        k = 2 * math.pi / lam
        ang = math.radians(direction_deg + off)
        kvec = k * np.array([math.cos(ang), math.sin(ang)])
        fade = np.clip(2.0 - spacing * WAVE_SAMPLES / lam, 0.0, 1.0)
        z += amp * fade * np.sin(xy @ kvec - math.sqrt(g * k) * t + phase)
    return z


def outline_smooth(layout: SeaLayout, h: np.ndarray, width: float) -> np.ndarray:
    """``h`` (n,) smoothed along the closed outline: a Gaussian of standard deviation ``width`` [m]
    in the distance along it (corner samples, at one point, are a distance 0 apart)."""
    if width <= 0 or len(h) < 2:
        return h.copy()
    step = np.linalg.norm(np.diff(layout.base, axis=0, append=layout.base[:1]), axis=1)
    u = np.concatenate([[0.0], np.cumsum(step)[:-1]])
    perimeter = step.sum()
    gap = np.abs(u[:, None] - u[None, :])
    gap = np.minimum(gap, perimeter - gap)
    w = np.exp(-0.5 * (gap / width) ** 2)
    return (w @ h) / w.sum(1)


def sea_heights(layout: SeaLayout, edge: np.ndarray, level: float, blend: float, t: float, height: float,
                length: float, direction_deg: float, g: float) -> tuple[np.ndarray, np.ndarray]:
    """(z of every vertex, ripple weight of every vertex), ring by ring: from the simulated
    water's ``edge`` heights at the wall to ``level`` plus :func:`waves` past ``blend``. Outward
    from the wall the edge's detail (sample-to-sample jitter, a splash at the wall) fades over
    EDGE_DETAIL × blend and only its profile, smoothed along the outline over that width and
    held within EDGE_PROFILE × ``height`` of the level (a splash on an obstacle at the wall is
    no swell), carries on, so no ridge or hump runs out from the wall across the blend."""
    m, n = len(layout.d), len(layout.base)
    s = smoothstep(layout.d / blend)[:, None] * np.ones((1, n))
    xy = layout.xy()
    corner = np.where(layout.wall < 0, (math.pi / 2) / CORNER_SAMPLES, 0.0)
    sp = np.maximum(layout.spacing[:, None], layout.d[:, None] * corner[None, :]).ravel()
    w = waves(xy, sp, t, height, length, direction_deg, g)
    cap = EDGE_PROFILE * height
    profile = level + np.clip(outline_smooth(layout, edge, EDGE_DETAIL * blend) - level, -cap, cap)
    keep = np.exp(-layout.d / (EDGE_DETAIL * blend))[:, None]
    inner = profile[None, :] + keep * (edge - profile)[None, :]
    z = (1 - s) * inner + s * level + s * w.reshape(m, n)
    return z.ravel(), s.ravel()


def still_level(cfg: Render, info: RunInfo, run_dir: Path | None) -> float:
    """``[render].sea_level``, else the level the first frame's water would settle at over the
    domain's floor: its volume (particles × mass / rest density, or the closed mesh's volume)
    over the floor's area. The domain's floor where the run has neither."""
    if cfg.sea_level is not None:
        return float(cfg.sea_level)
    lo, hi = np.array(info.domain["lower"], float), np.array(info.domain["upper"], float)
    area = (hi[0] - lo[0]) * (hi[1] - lo[1])
    volume = None
    if run_dir is not None:
        from ..io import read, read_mesh

        fluid, mesh = info.files("fluid"), info.files("mesh")
        if fluid:
            n = len(read(Path(run_dir) / fluid[0][1]))
            volume = n * info.particle_mass / info.rest_density
        elif mesh:
            m = read_mesh(Path(run_dir) / mesh[0][1])
            tri = np.asarray(m.vertices, float)[np.asarray(m.faces)]
            volume = abs(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()) / 6
    if volume is None:
        return float(lo[2])
    return float(min(lo[2] + volume / area, hi[2]))


# ============================================================================ bpy steps
@dataclass
class Sea:
    obj: Any  # the sea's Blender object
    layout: SeaLayout
    level: float
    blend: float
    height: float
    length: float
    direction: float
    g: float
    r: float
    ripple_w: Any  # the noise node whose W the frame time drives


def add_ripples(mat, length: float):
    """A bump on the water material weighted by the RIPPLE_ATTR attribute (0 where a mesh lacks
    it: the simulated water is untouched). Returns the 4D noise node; its W is the time."""
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    coord = nt.nodes.new("ShaderNodeTexCoord")
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.noise_dimensions = "4D"
    noise.inputs["Scale"].default_value = 1.0 / (RIPPLE_SIZE * length)
    noise.inputs["Detail"].default_value = 3.0
    nt.links.new(coord.outputs["Object"], noise.inputs["Vector"])
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_name = RIPPLE_ATTR
    strength = nt.nodes.new("ShaderNodeMath")
    strength.operation = "MULTIPLY"
    nt.links.new(attr.outputs["Fac"], strength.inputs[0])
    strength.inputs[1].default_value = RIPPLE_STRENGTH
    bump = nt.nodes.new("ShaderNodeBump")
    bump.inputs["Distance"].default_value = 0.5 * RIPPLE_SIZE * length
    nt.links.new(strength.outputs[0], bump.inputs["Strength"])
    nt.links.new(noise.outputs["Fac"], bump.inputs["Height"])
    nt.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    return noise


def add_sea(sc, cfg: Render, info: RunInfo, water, run_dir: Path | None) -> Sea:
    """The sea object (the water's material, with ripples) at its first shape: still water at
    the level, met by the floor at the walls until a frame's fluid is loaded."""
    import bpy

    from .scene import make_mesh

    lo, hi = np.array(info.domain["lower"], float), np.array(info.domain["upper"], float)
    size = horizontal_size(info)
    length = wave_length(cfg, info)
    r = info.particle_radius
    blend = blend_distance(cfg, info)
    layout = sea_layout(lo, hi, step=min(r, length / (2 * WAVE_SAMPLES)), extent=EXTENT * size,
                        fine=length / (2 * WAVE_SAMPLES), fine_until=blend + 2 * length)
    sea = Sea(obj=None, layout=layout, level=still_level(cfg, info, run_dir), blend=blend,
              height=wave_height(cfg, info), length=length, direction=cfg.sea_wave_direction,
              g=float(np.linalg.norm(info.gravity)) or 9.81, r=r, ripple_w=add_ripples(water, length))
    xy = layout.xy()
    verts = np.column_stack([xy, np.full(len(xy), sea.level)])
    me = make_mesh("sea", verts, layout.faces)
    me.attributes.new(RIPPLE_ATTR, "FLOAT", "POINT")
    obj = bpy.data.objects.new("sea", me)
    obj.data.materials.append(water)
    sc.collection.objects.link(obj)
    sea.obj = obj
    update_sea(sea, np.zeros((0, 3)), 0.0)
    return sea


def update_sea(sea: Sea, fluid_verts: np.ndarray, t: float) -> None:
    """Shape the sea for a frame at time ``t`` whose fluid mesh has vertices ``fluid_verts``."""
    edge, inset = edge_heights(sea.layout, fluid_verts, sea.r, sea.level, reach=sea.blend)
    z, s = sea_heights(sea.layout, edge, sea.level, sea.blend, t, sea.height, sea.length, sea.direction, sea.g)
    me = sea.obj.data
    co = np.column_stack([sea_xy(sea.layout, inset, sea.blend), z]).astype(np.float32)
    me.vertices.foreach_set("co", co.ravel())
    me.attributes[RIPPLE_ATTR].data.foreach_set("value", s.astype(np.float32))
    me.update()
    # the ripples change by about one noise feature per period of a deep-water wave of their size
    period = math.sqrt(2 * math.pi * RIPPLE_SIZE * sea.length / sea.g)
    sea.ripple_w.inputs["W"].default_value = float(t) / period
