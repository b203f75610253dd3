"""The terrain in Blender: its procedural material and its place in the render scene.

A scene's ``[terrain]`` reaches the renderer as an obstacle with material
"terrain" (whitecap/terrain.py) whose render mesh is the fine surface. After
the obstacles are added (render/scene.build_scene), :func:`dress_terrain`
gives that object the terrain material, smooth shading and the name
``terrain_K`` (so the default camera frames the fluid, not the whole
terrain), and removes the tiled ground plane it replaces.

The material is procedural, built from Blender's Noise and Voronoi textures
(nothing to download). Layers, each blended by a mask with a noisy edge:

- the base preset (``terrain.material``): sand, rock, grass or concrete;
- rock on slopes steeper than ``rock_slope`` (the shading normal's z);
- grass above ``grass_above``;
- moss on the rock's ledges and in its crevices, where the landscape has grass;
- wet ground below ``water_level`` + ``wet_band``: darker and glossier, and so is rock deep in a
  channel (ambient occlusion), wherever the water runs; crevices are darker.

Rock has facets of their own shade (Voronoi cells), a warm stain, cracks (the edges of a warped
Voronoi, some of them) and grain; grass has a mottle of tufts, blades, and straw-dry and
bare-earth patches.

Bump mapping gives grain, ripples and rock relief (left out in preview, as
stage.surface_material does: a Bump node evaluates its height three times).
Node names start with ``terrain_`` so tests and users can find them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from ..config import Terrain
from ..io.record import Obstacle
from ..io.run import RunInfo
from ..terrain import TERRAIN_MATERIAL

#: Base colours (linear RGB, darker and lighter end), roughness and bump strength of the presets.
#: Rock's facets sit mostly at the lighter end, so that end is a weathered stone's albedo (about
#: 0.2): at 0.34 rock in sunlight under a blue sky read as snow beside grass (scenes/creek.toml).
#: Grass is a meadow's olive green (saturation about 0.6, not a lawn's 0.75).
PRESETS = {
    "sand": ((0.36, 0.23, 0.1), (0.62, 0.43, 0.21), 0.95, 0.25),
    "rock": ((0.045, 0.043, 0.04), (0.2, 0.185, 0.165), 0.75, 0.6),
    "grass": ((0.03, 0.045, 0.016), (0.105, 0.125, 0.045), 0.85, 0.35),
    "concrete": ((0.27, 0.265, 0.25), (0.5, 0.49, 0.46), 0.85, 0.2),
}
#: Rock: a warm (iron-stained) tint that large patches take on, and how dark its cracks are.
ROCK_WARM = (0.19, 0.15, 0.11)
CRACK_DARKEN = 0.3
#: Grass: dry (straw) and bare-earth patches among the green.
GRASS_DRY = (0.17, 0.14, 0.07)
EARTH = (0.07, 0.05, 0.033)
#: Moss on the rock of a landscape with grass: its colour and the shading normal's z above which
#: a ledge holds it (besides the crevices).
MOSS = (0.035, 0.05, 0.012)
MOSS_UP = 0.55
#: Crevices (ambient occlusion within AO_REACH × the texture's feature size): colour multiplied by
#: down to CREVICE_DARKEN, and below AO_DAMP occlusion the rock is damp (a creek's channel).
AO_REACH, CREVICE_DARKEN, AO_DAMP = 2.0, 0.55, (0.85, 0.55)
#: Occlusion rays per shading point: few, since every path sample casts its own (they average out).
AO_SAMPLES = 2
#: Wet ground: colour multiplied by this, roughness brought down to WET_ROUGHNESS.
WET_DARKEN = (0.45, 0.43, 0.42)
WET_ROUGHNESS = 0.35
#: Specular IOR level of dry ground (0.5 is a plain dielectric of IOR 1.5).
DRY_SPECULAR = 0.12


def _mix_rgb(nt, name: str, fac, a, b, blend: str = "MIX"):
    m = nt.nodes.new("ShaderNodeMix")
    m.name = m.label = name
    m.data_type = "RGBA"
    m.blend_type = blend
    m.clamp_result = True
    nt.links.new(fac, m.inputs[0])
    for sock, v in ((m.inputs[6], a), (m.inputs[7], b)):
        if isinstance(v, tuple):
            sock.default_value = (*v, 1.0)
        else:
            nt.links.new(v, sock)
    return m.outputs[2]


def _mix_float(nt, name: str, fac, a, b):
    m = nt.nodes.new("ShaderNodeMix")
    m.name = m.label = name
    m.data_type = "FLOAT"
    nt.links.new(fac, m.inputs[0])
    for sock, v in ((m.inputs[2], a), (m.inputs[3], b)):
        if isinstance(v, (int, float)):
            sock.default_value = float(v)
        else:
            nt.links.new(v, sock)
    return m.outputs[0]


def _map(nt, name: str, value, lo: float, hi: float):
    """0 at ``lo``, 1 at ``hi`` (either order), clamped, smooth in between."""
    m = nt.nodes.new("ShaderNodeMapRange")
    m.name = m.label = name
    m.interpolation_type = "SMOOTHSTEP"
    nt.links.new(value, m.inputs["Value"])
    m.inputs["From Min"].default_value = lo
    m.inputs["From Max"].default_value = hi
    return m.outputs["Result"]


def _math(nt, op: str, *args):
    """A Math node ``op`` of its inputs (sockets or numbers): MULTIPLY_ADD is a·b + c."""
    m = nt.nodes.new("ShaderNodeMath")
    m.operation = op
    for sock, v in zip(m.inputs, args):
        if isinstance(v, (int, float)):
            sock.default_value = float(v)
        else:
            nt.links.new(v, sock)
    return m.outputs[0]


def _noise(nt, name: str, coord, scale: float, detail: float = 4.0, roughness: float = 0.55):
    n = nt.nodes.new("ShaderNodeTexNoise")
    n.name = n.label = name
    n.inputs["Scale"].default_value = scale
    n.inputs["Detail"].default_value = detail
    n.inputs["Roughness"].default_value = roughness
    nt.links.new(coord, n.inputs["Vector"])
    return n.outputs["Fac"]


def _ramp(nt, name: str, fac, dark, light, mid=None):
    """Colour ramp from ``dark`` (0.3) to ``light`` (0.7), through ``mid`` at 0.5 where given."""
    r = nt.nodes.new("ShaderNodeValToRGB")
    r.name = r.label = name
    r.color_ramp.elements[0].position = 0.3
    r.color_ramp.elements[0].color = (*dark, 1.0)
    r.color_ramp.elements[1].position = 0.7
    r.color_ramp.elements[1].color = (*light, 1.0)
    if mid is not None:
        r.color_ramp.elements.new(0.5).color = (*mid, 1.0)
    nt.links.new(fac, r.inputs["Fac"])
    return r.outputs["Color"]


def _voronoi(nt, name: str, coord, scale: float, feature: str = "F1", randomness: float = 1.0):
    v = nt.nodes.new("ShaderNodeTexVoronoi")
    v.name = v.label = name
    v.feature = feature
    v.inputs["Scale"].default_value = scale
    v.inputs["Randomness"].default_value = randomness
    nt.links.new(coord, v.inputs["Vector"])
    return v


def _warp(nt, name: str, coord, scale: float, amount: float):
    """``coord`` moved by a noise's colour (centred) times ``amount``: breaks a texture's regular cells."""
    n = nt.nodes.new("ShaderNodeTexNoise")
    n.name = n.label = name
    n.inputs["Scale"].default_value = scale
    n.inputs["Detail"].default_value = 3.0
    nt.links.new(coord, n.inputs["Vector"])
    centred = nt.nodes.new("ShaderNodeVectorMath")
    centred.operation = "MULTIPLY_ADD"
    nt.links.new(n.outputs["Color"], centred.inputs[0])
    centred.inputs[1].default_value = (amount, amount, amount)
    nt.links.new(coord, centred.inputs[2])
    shift = nt.nodes.new("ShaderNodeVectorMath")
    shift.operation = "SUBTRACT"
    nt.links.new(centred.outputs[0], shift.inputs[0])
    shift.inputs[1].default_value = (0.5 * amount,) * 3
    return shift.outputs[0]


def _rock(nt, coord, feature: float):
    """Rock: facets (Voronoi cells, each its own shade), broad tone and a warm stain (noise),
    cracks along the cells' edges of a warped second Voronoi (dark and sunk), and grain."""
    dark, light, rough, _ = PRESETS["rock"]
    big = _noise(nt, "terrain_rock_noise", coord, 1.0 / feature, detail=6.0)
    cells = _voronoi(nt, "terrain_rock_cells", coord, 2.0 / feature)
    grain = _noise(nt, "terrain_rock_grain", coord, 30.0 / feature, detail=3.0, roughness=0.7)
    cracks = _voronoi(nt, "terrain_rock_cracks", _warp(nt, "terrain_rock_warp", coord, 1.5 / feature, 0.4 * feature),
                      1.3 / feature, feature="DISTANCE_TO_EDGE")
    crack = _map(nt, "terrain_rock_crack", cracks.outputs["Distance"], 0.015, 0.0)  # 1 on a crack
    # only some of the cells' edges are open cracks, fading in and out along their length
    crack = _math(nt, "MULTIPLY", crack, _map(nt, "terrain_rock_crack_mask",
                                             _noise(nt, "terrain_rock_crack_noise", coord, 2.0 / feature, 3.0),
                                             0.5, 0.62))
    shade = nt.nodes.new("ShaderNodeSeparateColor")
    nt.links.new(cells.outputs["Color"], shade.inputs[0])
    fac = _math(nt, "MULTIPLY_ADD", shade.outputs["Red"], 0.5, _math(nt, "MULTIPLY_ADD", grain, 0.3, big))
    fac = _math(nt, "SUBTRACT", fac, 0.4)
    mid = tuple(0.5 * (a + b) for a, b in zip(dark, light))
    colour = _ramp(nt, "terrain_rock", fac, dark, light, mid)
    stain = _map(nt, "terrain_rock_stain", _noise(nt, "terrain_rock_tint", coord, 0.4 / feature, detail=2.0),
                 0.5, 0.7)
    colour = _mix_rgb(nt, "terrain_rock_warm", _math(nt, "MULTIPLY", stain, 0.6), colour, ROCK_WARM)
    colour = _mix_rgb(nt, "terrain_rock_crack_colour", crack, colour, (CRACK_DARKEN,) * 3, blend="MULTIPLY")
    height = _math(nt, "MULTIPLY_ADD", cells.outputs["Distance"], 0.5, big)
    height = _math(nt, "MULTIPLY_ADD", grain, 0.25, height)
    height = _math(nt, "MULTIPLY_ADD", crack, -0.4, height)
    return colour, rough, height


def _grass(nt, coord, feature: float):
    """Grass: blades as fine noise over clumps, straw-dry and bare-earth patches (large noise)."""
    dark, light, rough, _ = PRESETS["grass"]
    big = _noise(nt, "terrain_grass_noise", coord, 1.0 / feature, detail=6.0)
    blades = _noise(nt, "terrain_grass_blades", _warp(nt, "terrain_grass_lean", coord, 3.0 / feature, 0.1 * feature),
                    60.0 / feature, detail=2.0, roughness=0.8)
    # tufts: a crisp mid-scale mottle, so the grass is not a soft blur at a distance
    tufts = _noise(nt, "terrain_grass_tufts", coord, 15.0 / feature, detail=1.0, roughness=0.5)
    tuft = _map(nt, "terrain_grass_tuft", tufts, 0.35, 0.65)
    fac = _math(nt, "MULTIPLY_ADD", blades, 0.4, _math(nt, "MULTIPLY_ADD", big, 1.0, -0.35))
    fac = _math(nt, "MULTIPLY_ADD", tuft, 0.25, fac)
    colour = _ramp(nt, "terrain_grass", fac, dark, light)
    dry = _map(nt, "terrain_grass_dry", _noise(nt, "terrain_grass_patches", coord, 0.35 / feature, detail=3.0),
               0.45, 0.68)
    dry = _math(nt, "MULTIPLY", dry, _map(nt, "terrain_grass_dry_blades", blades, 0.35, 0.6))
    colour = _mix_rgb(nt, "terrain_grass_dry_mix", _math(nt, "MULTIPLY", dry, 0.75), colour, GRASS_DRY)
    earth = _map(nt, "terrain_grass_earth", _noise(nt, "terrain_grass_bare", coord, 0.8 / feature, detail=4.0),
                 0.64, 0.72)
    colour = _mix_rgb(nt, "terrain_grass_earth_mix", earth, colour, EARTH)
    height = _math(nt, "MULTIPLY_ADD", big, 0.5, blades)
    height = _math(nt, "MULTIPLY_ADD", tuft, 0.5, height)
    return colour, rough, height


def _layer(nt, preset: str, coord, feature: float):
    """Colour, roughness and bump height of one preset, from noise and Voronoi textures."""
    if preset == "rock":
        return _rock(nt, coord, feature)
    if preset == "grass":
        return _grass(nt, coord, feature)
    dark, light, rough, _ = PRESETS[preset]
    big = _noise(nt, f"terrain_{preset}_noise", coord, 1.0 / feature, detail=6.0)
    if preset == "sand":
        grain = _noise(nt, "terrain_sand_grain", coord, 60.0 / feature, detail=2.0, roughness=0.7)
        # Ripples: a wave texture along x, bent by the large noise.
        wave = nt.nodes.new("ShaderNodeTexWave")
        wave.name = wave.label = "terrain_sand_ripples"
        wave.inputs["Scale"].default_value = 4.0 / feature
        wave.inputs["Distortion"].default_value = 6.0
        wave.inputs["Detail"].default_value = 1.0
        nt.links.new(coord, wave.inputs["Vector"])
        fac = _math(nt, "MULTIPLY_ADD", grain, 0.25, big)
        height = _math(nt, "MULTIPLY_ADD", wave.outputs["Fac"], 0.6, grain)
    else:  # concrete
        pores = _voronoi(nt, "terrain_concrete_pores", coord, 80.0 / feature)
        fac = big
        height = _math(nt, "MULTIPLY_ADD", pores.outputs["Distance"], 0.5, big)
    return _ramp(nt, f"terrain_{preset}", fac, dark, light), rough, height


def terrain_material(t: Terrain, relief: tuple[float, float], extent: float, preview: bool = False):
    """The terrain's material. ``relief``: the render surface's lowest and highest z [m];
    ``extent``: its larger side [m] (the texture's scale when ``texture_scale`` is unset)."""
    import bpy

    feature = t.texture_scale or max(extent / 40.0, 1e-3)
    wet_band = t.wet_band if t.wet_band is not None else 0.1 * max(relief[1] - relief[0], 1e-3)
    water = t.water_level if t.water_level is not None else relief[0]
    mat = bpy.data.materials.new("whitecap_terrain")
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    coord = nt.nodes.new("ShaderNodeTexCoord")
    coord.name = "terrain_coord"
    co = coord.outputs["Object"]
    geo = nt.nodes.new("ShaderNodeNewGeometry")
    geo.name = "terrain_geometry"
    pos = nt.nodes.new("ShaderNodeSeparateXYZ")
    pos.name = "terrain_position"
    nt.links.new(geo.outputs["Position"], pos.inputs[0])
    nrm = nt.nodes.new("ShaderNodeSeparateXYZ")
    nrm.name = "terrain_normal"
    nt.links.new(geo.outputs["Normal"], nrm.inputs[0])
    edge = _noise(nt, "terrain_edge_noise", co, 0.5 / feature, detail=3.0)  # wobbles the masks' edges
    edge_c = _math(nt, "SUBTRACT", edge, 0.5)

    colour, rough, height = _layer(nt, t.material, co, feature)
    bump_strength = PRESETS[t.material][3]
    if t.rock_slope < 89.9 and t.material != "rock":
        c = math.cos(math.radians(t.rock_slope))
        nz = _math(nt, "MULTIPLY_ADD", edge_c, 0.15, nrm.outputs["Z"])
        rock = _map(nt, "terrain_rock_mask", nz, c + 0.04, c - 0.04)
        rc, rr, rh = _layer(nt, "rock", co, feature)
        colour = _mix_rgb(nt, "terrain_rock_mix", rock, colour, rc)
        rough = _mix_float(nt, "terrain_rock_rough", rock, rough, rr)
        height = _mix_float(nt, "terrain_rock_height", rock, height, rh)
    else:
        rock = None
    ao = nt.nodes.new("ShaderNodeAmbientOcclusion")
    ao.name = "terrain_occlusion"
    ao.samples = AO_SAMPLES
    ao.inputs["Distance"].default_value = AO_REACH * feature
    open_sky = ao.outputs["AO"]
    crevice = _map(nt, "terrain_damp", open_sky, *AO_DAMP)  # 1 deep in a crevice or a channel
    landscape = t.grass_above is not None or t.material == "grass"
    if rock is not None and landscape:  # moss on the rock's ledges and in its crevices
        up = _map(nt, "terrain_moss_up", _math(nt, "MULTIPLY_ADD", edge_c, 0.3, nrm.outputs["Z"]), MOSS_UP,
                  MOSS_UP + 0.2)
        patches = _map(nt, "terrain_moss_patches", _noise(nt, "terrain_moss_noise", co, 0.7 / feature, detail=5.0),
                       0.42, 0.6)
        moss = _math(nt, "MULTIPLY", rock, _math(nt, "MULTIPLY", _math(nt, "MAXIMUM", up, crevice), patches))
        colour = _mix_rgb(nt, "terrain_moss", moss, colour, MOSS)
        rough = _mix_float(nt, "terrain_moss_rough", moss, rough, 0.9)
    if t.grass_above is not None and t.material != "grass":
        z = _math(nt, "MULTIPLY_ADD", edge_c, 2.0 * wet_band, pos.outputs["Z"])
        grass = _map(nt, "terrain_grass_mask", z, t.grass_above, t.grass_above + 0.5 * wet_band)
        if rock is not None:
            grass = _math(nt, "MULTIPLY", grass, _math(nt, "SUBTRACT", 1.0, rock))
        gc, gr, gh = _layer(nt, "grass", co, feature)
        colour = _mix_rgb(nt, "terrain_grass_mix", grass, colour, gc)
        rough = _mix_float(nt, "terrain_grass_rough", grass, rough, gr)
        height = _mix_float(nt, "terrain_grass_height", grass, height, gh)
    # Wet below the water line and a band above it, where the swash reaches.
    z = _math(nt, "MULTIPLY_ADD", edge_c, 0.6 * wet_band, pos.outputs["Z"])
    wet = _map(nt, "terrain_wet", z, water + wet_band, water)
    if rock is not None:  # rock deep in a channel is damp: darker and glossier (a creek's bed)
        wet = _math(nt, "MAXIMUM", wet, _math(nt, "MULTIPLY", _math(nt, "MULTIPLY", crevice, rock), 0.8))
    # crevices take less of the sky: darker (the occlusion the lighting misses at this mesh's scale)
    colour = _mix_rgb(nt, "terrain_crevice", _math(nt, "SUBTRACT", 1.0, open_sky), colour, (CREVICE_DARKEN,) * 3,
                      blend="MULTIPLY")
    colour = _mix_rgb(nt, "terrain_wet_colour", wet, colour, WET_DARKEN, blend="MULTIPLY")
    rough = _mix_float(nt, "terrain_wet_rough", wet, rough, WET_ROUGHNESS)
    nt.links.new(colour, bsdf.inputs["Base Color"])
    nt.links.new(rough, bsdf.inputs["Roughness"])
    # Dry grains scatter rather than mirror: a weak specular layer, or the sky's grazing reflection
    # greys the ground out; a water film makes it a smooth dielectric (full specular).
    nt.links.new(_mix_float(nt, "terrain_wet_specular", wet, DRY_SPECULAR, 0.5), bsdf.inputs["Specular IOR Level"])
    if not preview:
        bump = nt.nodes.new("ShaderNodeBump")
        bump.name = "terrain_bump"
        bump.inputs["Strength"].default_value = bump_strength
        bump.inputs["Distance"].default_value = 0.05 * feature
        nt.links.new(height, bump.inputs["Height"])
        nt.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def run_terrain(run_dir: Path | None) -> Terrain | None:
    """The run's ``[terrain]`` from its scene.toml (read as TOML: its paths need not resolve here)."""
    import tomllib

    p = Path(run_dir) / "scene.toml" if run_dir is not None else None
    if p is None or not p.is_file():
        return None
    t = tomllib.loads(p.read_text("utf-8")).get("terrain")
    return Terrain.model_validate(t) if isinstance(t, dict) else None


def scene_terrain(info: RunInfo, run_dir: Path | None) -> list[Obstacle]:
    """The run's scene.toml ``[terrain]`` as an obstacle entry, where run.json holds no terrain: a run
    whitecap did not simulate (``whitecap import``) set in a landscape at render time. Without a
    ``[domain]`` the terrain's collision solid (unused here) is cut to the run's domain. [] otherwise."""
    import tomllib

    from ..config import scene_from_dict

    p = Path(run_dir) / "scene.toml" if run_dir is not None else None
    if p is None or not p.is_file() or any(
            e.material == TERRAIN_MATERIAL for e in info.obstacles):
        return []
    raw = tomllib.loads(p.read_text("utf-8"))
    if "terrain" not in raw:
        return []
    raw.setdefault("domain", {"lower": list(info.domain["lower"]), "upper": list(info.domain["upper"])})
    scene = scene_from_dict(raw, str(p), p.parent)
    return [Obstacle.model_validate(o.model_dump()) for o in scene.obstacle if o.material == TERRAIN_MATERIAL]


def dress_terrain(sc, info: RunInfo, run_dir: Path | None, preview: bool = False,
                  extra: Sequence[Obstacle] = ()) -> list:
    """Give the obstacles that are terrain (material "terrain") the terrain material, smooth
    shading and the name ``terrain_K``; remove the ground plane they replace. Returns them.

    An obstacle whose material names a terrain preset (sand, rock, grass, concrete: a breakwater's
    concrete units, boulders) gets that preset's procedural material and smooth shading too, wet
    below the run's ``[terrain] water_level`` (none without a terrain), without the slope and height
    layers."""
    import bpy
    import numpy as np

    out = []
    t = None
    for k, entry in enumerate([*info.obstacles, *extra]):  # extra: scene_terrain's, after the run's own
        material = entry.material
        if material != TERRAIN_MATERIAL and material not in PRESETS:
            continue
        obj = sc.objects.get(f"obstacle_{k}")
        if obj is None:
            continue
        if t is None:
            t = run_terrain(run_dir) or Terrain(mesh="-")
        v = np.array([tuple(p.co) for p in obj.data.vertices]) if len(obj.data.vertices) else np.zeros((1, 3))
        relief = (float(v[:, 2].min()), float(v[:, 2].max()))
        extent = float(max(np.ptp(v[:, 0]), np.ptp(v[:, 1]), 1e-3))
        own = t if material == TERRAIN_MATERIAL else Terrain(
            mesh="-", material=material, rock_slope=90.0, water_level=t.water_level if t.water_level is not None
            else relief[0])
        obj.data.materials.clear()
        obj.data.materials.append(terrain_material(own, relief, extent, preview))
        obj.data.shade_smooth()
        if material != TERRAIN_MATERIAL:
            continue
        obj.name = obj.data.name = f"terrain_{k}"
        out.append(obj)
    ground = sc.objects.get("ground")
    if out and ground is not None:
        bpy.data.objects.remove(ground)
    return out
