"""Materials and the diffuse spheres (bpy inside functions).

One definition of how a run looks, for ``whitecap render`` (with the scene's
``[render]`` values) and the add-on (with their defaults). Each material is
found by name when it exists, else made: a run loaded twice into one .blend
reuses them.
"""

from __future__ import annotations

from ..io.diffuse_types import COUNT_NAMES, DIFFUSE_RADIUS
from ..io.record import OBSTACLE_COLOR, Obstacle

# [render]'s defaults (config.Render): the add-on, which has no scene, uses these.
WATER_COLOR = (0.55, 0.8, 0.9)
WATER_ABSORPTION = 3.0  # [1/m]
WATER_ROUGHNESS = 0.02
WATER_IOR = 1.33
#: Obstacle presets: (roughness, metallic).
OBSTACLE_PRESETS = {"stone": (0.8, 0.0), "clay": (0.6, 0.0), "metal": (0.3, 1.0), "plastic": (0.35, 0.0)}
GLASS_COLOR = (0.93, 0.97, 0.96)
#: Spray: colour, opacity and glow (emission strength) of the white mist material.
SPRAY_COLOR, SPRAY_ALPHA, SPRAY_GLOW = (0.9, 0.93, 0.95), 0.6, 0.3
#: The "glass" preset's Fresnel reflectance: window glass [-].
THIN_GLASS_IOR = 1.5
#: Render-time copies of a diffuse particle ([render] diffuse_copies) scatter within this many
#: fluid particle radii of it: about where the particle's own generation cylinder spreads them.
COPY_JITTER = 1.0
#: Random Value seed of each diffuse type's radius draw (type code + 1).
SEEDS = tuple(t + 1 for t in range(len(COUNT_NAMES)))
#: Material names per kind (the add-on's sequence types and the renderer's objects).
NAMES = {"FLUID": "whitecap_water", "FOAM": "whitecap_foam", "SPRAY": "whitecap_spray",
         "BUBBLES": "whitecap_bubbles", "PARTICLES": "whitecap_particles"}
#: Diffuse type code -> sequence kind.
DIFFUSE_KINDS = ("SPRAY", "FOAM", "BUBBLES")


def diffuse_radius(t: int, r: float, own=None) -> tuple[float, float]:
    """[min, max] sphere radius [m] of diffuse type ``t`` (0 spray, 1 foam, 2 bubbles) for
    particle radius ``r``: ``own`` ([render] spray/foam/bubble_radius) where set, else
    :data:`~whitecap.io.diffuse_types.DIFFUSE_RADIUS` x r."""
    if own is not None:
        return float(own[0]), float(own[1])
    return DIFFUSE_RADIUS[t][0] * r, DIFFUSE_RADIUS[t][1] * r


def _principled(mat):
    mat.use_nodes = True
    return mat.node_tree, mat.node_tree.nodes.get("Principled BSDF")


def _water(mat, color=WATER_COLOR, absorption=WATER_ABSORPTION, roughness=WATER_ROUGHNESS):
    nt, b = _principled(mat)
    b.inputs["Base Color"].default_value = (*color, 1.0)
    b.inputs["Transmission Weight"].default_value = 1.0
    b.inputs["IOR"].default_value = WATER_IOR
    b.inputs["Roughness"].default_value = roughness
    absorb = nt.nodes.new("ShaderNodeVolumeAbsorption")
    absorb.inputs["Color"].default_value = (*color, 1.0)
    absorb.inputs["Density"].default_value = absorption
    nt.links.new(absorb.outputs[0], nt.nodes.get("Material Output").inputs["Volume"])


def _foam(mat):
    """Transparent + Emission mixed by a noise texture: soft, broken-up foam."""
    mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out, mix = nt.nodes.new("ShaderNodeOutputMaterial"), nt.nodes.new("ShaderNodeMixShader")
    transp, emit = nt.nodes.new("ShaderNodeBsdfTransparent"), nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (0.95, 0.97, 1.0, 1.0)
    emit.inputs["Strength"].default_value = 1.2
    # The glow is the foam's own brightness, not a light for the scene: sampling thousands
    # of tiny emitters as lights only adds noise and time.
    mat.cycles.emission_sampling = "NONE"
    noise, ramp = nt.nodes.new("ShaderNodeTexNoise"), nt.nodes.new("ShaderNodeValToRGB")
    noise.inputs["Scale"].default_value = 40.0
    ramp.color_ramp.elements[0].position = 0.35
    ramp.color_ramp.elements[1].position = 0.65
    nt.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], mix.inputs["Fac"])
    nt.links.new(transp.outputs[0], mix.inputs[1])
    nt.links.new(emit.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], out.inputs["Surface"])


def _spray(mat):
    """Spray is droplets too small to see one by one, thrown up in a cloud: together they scatter
    light white, as mist does. A white, matte surface, partly see-through, with a faint glow of
    its own (a storm's dim sky leaves it grey otherwise); no refraction: a clear bead shows the
    dark sea through itself and reads as a glass ball."""
    _, b = _principled(mat)
    b.inputs["Base Color"].default_value = (*SPRAY_COLOR, 1.0)
    b.inputs["Transmission Weight"].default_value = 0.0
    b.inputs["Roughness"].default_value = 0.5
    b.inputs["Alpha"].default_value = SPRAY_ALPHA
    b.inputs["Emission Color"].default_value = (*SPRAY_COLOR, 1.0)
    b.inputs["Emission Strength"].default_value = SPRAY_GLOW
    mat.cycles.emission_sampling = "NONE"  # its own brightness, not a light for the scene (as foam)


def _bubbles(mat):
    _, b = _principled(mat)
    b.inputs["Base Color"].default_value = (0.9, 0.97, 1.0, 1.0)
    b.inputs["Transmission Weight"].default_value = 1.0
    b.inputs["IOR"].default_value = 1.0 / WATER_IOR  # air inside water
    b.inputs["Roughness"].default_value = 0.05


def _particles(mat):
    _, b = _principled(mat)
    b.inputs["Base Color"].default_value = (0.2, 0.45, 0.9, 1.0)
    b.inputs["Roughness"].default_value = 0.4


BUILDERS = {"FLUID": _water, "FOAM": _foam, "SPRAY": _spray, "BUBBLES": _bubbles, "PARTICLES": _particles}


def material(kind: str, **params):
    """The material of a kind (FLUID, FOAM, SPRAY, BUBBLES, PARTICLES; others get PARTICLES'),
    found by name or made; ``params`` (water: color, absorption, roughness) apply when made."""
    import bpy

    kind = kind if kind in BUILDERS else "PARTICLES"
    mat = bpy.data.materials.get(NAMES[kind])
    if mat is None:
        mat = bpy.data.materials.new(NAMES[kind])
        BUILDERS[kind](mat, **params)
    return mat


def thin_glass(mat, color) -> None:
    """A pane without thickness (an imported tank's wall that encloses the fluid): light passes
    straight through, tinted by ``color``, and glass's Fresnel share is reflected. A refracting
    glass needs walls with two faces (render/stage.glass_material)."""
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.remove(nt.nodes.get("Principled BSDF"))
    through = nt.nodes.new("ShaderNodeBsdfTransparent")
    through.inputs["Color"].default_value = (*color, 1.0)
    mirror = nt.nodes.new("ShaderNodeBsdfGlossy")
    mirror.inputs["Roughness"].default_value = 0.0
    fresnel = nt.nodes.new("ShaderNodeFresnel")
    fresnel.inputs["IOR"].default_value = THIN_GLASS_IOR
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(fresnel.outputs[0], mix.inputs[0])
    nt.links.new(through.outputs[0], mix.inputs[1])
    nt.links.new(mirror.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], nt.nodes.get("Material Output").inputs["Surface"])


def obstacle_material(entry: Obstacle):
    """A new material for one obstacle of run.json (``material`` preset and ``color``, without one
    the preset's); one per obstacle, since a texture (render/stage.apply_texture) changes it."""
    import bpy

    preset = entry.material
    mat = bpy.data.materials.new(f"whitecap_obstacle_{preset}")
    if preset == "glass":
        thin_glass(mat, tuple(entry.color or GLASS_COLOR))
        return mat
    _, b = _principled(mat)
    rough, metal = OBSTACLE_PRESETS.get(preset, (0.7, 0.0))
    b.inputs["Base Color"].default_value = (*(entry.color or OBSTACLE_COLOR), 1.0)
    b.inputs["Roughness"].default_value = rough
    b.inputs["Metallic"].default_value = metal
    return mat


# ---------------------------------------------------------------------------- spheres
def sphere_nodes(name: str, rmin: float, rmax: float, material, seed: int, copies: int = 1, jitter: float = 0.0,
                 file_radius: bool = False, instances: bool = False):
    """A Geometry Nodes group that draws a mesh's vertices as spheres: Mesh to Points with a
    radius from Random Value in [Radius min, Radius max] seeded by the point's ``id`` (a particle
    keeps its size from frame to frame), or, with the File radius input on, the file's ``radius``
    attribute where the points carry one; then the material. With ``copies`` > 1 each point is
    duplicated and the copies moved by a random offset in [-jitter, jitter]^3 seeded by
    (id, copy). The radius inputs are the modifier's, so a panel can change them. With
    ``instances`` each point carries an instanced ico sphere of its radius instead (EEVEE draws
    instances; it does not draw point clouds)."""
    import bpy

    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    for sock_name, value in (("Radius min", rmin), ("Radius max", rmax)):
        s = ng.interface.new_socket(sock_name, in_out="INPUT", socket_type="NodeSocketFloat")
        s.min_value, s.default_value, s.subtype = 0.0, float(value), "DISTANCE"
    s = ng.interface.new_socket("File radius", in_out="INPUT", socket_type="NodeSocketBool")
    s.default_value = bool(file_radius)
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    m2p = ng.nodes.new("GeometryNodeMeshToPoints")
    m2p.mode = "VERTICES"
    rnd = ng.nodes.new("FunctionNodeRandomValue")
    rnd.data_type = "FLOAT"
    ng.links.new(gin.outputs["Radius min"], [s_ for s_ in rnd.inputs if s_.name == "Min" and s_.enabled][0])
    ng.links.new(gin.outputs["Radius max"], [s_ for s_ in rnd.inputs if s_.name == "Max" and s_.enabled][0])
    rnd.inputs["Seed"].default_value = seed
    pid = ng.nodes.new("GeometryNodeInputNamedAttribute")
    pid.data_type = "INT"
    pid.inputs["Name"].default_value = "id"
    ng.links.new(pid.outputs["Attribute"], rnd.inputs["ID"])
    drawn = [s_ for s_ in rnd.outputs if s_.enabled][0]
    own = ng.nodes.new("GeometryNodeInputNamedAttribute")
    own.data_type = "FLOAT"
    own.inputs["Name"].default_value = "radius"
    use = ng.nodes.new("FunctionNodeBooleanMath")
    use.operation = "AND"
    ng.links.new(gin.outputs["File radius"], use.inputs[0])
    ng.links.new(own.outputs["Exists"], use.inputs[1])
    switch = ng.nodes.new("GeometryNodeSwitch")
    switch.input_type = "FLOAT"
    ng.links.new(use.outputs[0], switch.inputs["Switch"])
    ng.links.new(drawn, switch.inputs["False"])
    ng.links.new(own.outputs["Attribute"], switch.inputs["True"])
    setm = ng.nodes.new("GeometryNodeSetMaterial")
    setm.inputs["Material"].default_value = material
    ng.links.new(gin.outputs["Geometry"], m2p.inputs["Mesh"])
    ng.links.new(switch.outputs[0], m2p.inputs["Radius"])
    points = m2p.outputs["Points"]
    if copies > 1:
        points = _jittered_copies(ng, points, pid.outputs["Attribute"], copies, jitter, seed)
    if instances:
        ico = ng.nodes.new("GeometryNodeMeshIcoSphere")
        ico.inputs["Radius"].default_value = 1.0
        ico.inputs["Subdivisions"].default_value = 2
        smooth = ng.nodes.new("GeometryNodeSetShadeSmooth")
        ng.links.new(ico.outputs["Mesh"], smooth.inputs["Geometry"])
        ng.links.new(smooth.outputs["Geometry"], setm.inputs["Geometry"])
        inst = ng.nodes.new("GeometryNodeInstanceOnPoints")
        ng.links.new(points, inst.inputs["Points"])
        ng.links.new(setm.outputs["Geometry"], inst.inputs["Instance"])
        radius = ng.nodes.new("GeometryNodeInputRadius")
        ng.links.new(radius.outputs[0], inst.inputs["Scale"])
        ng.links.new(inst.outputs["Instances"], gout.inputs[0])
        return ng
    ng.links.new(points, setm.inputs["Geometry"])
    ng.links.new(setm.outputs["Geometry"], gout.inputs[0])
    return ng


#: The mesh template's voxel size, in particle radii: fine enough that two touching particles
#: merge into one surface and a lone one stays a rounded blob.
MESH_VOXEL = 0.5


def mesh_nodes(name: str, radius: float, material, voxel: float | None = None):
    """A Geometry Nodes group that shows a sequence as a mesh: a file's faces as they are; points
    without faces (particles) as the surface around them, Points to Volume (spheres of ``Radius``)
    then Volume to Mesh at ``Voxel size`` (default :data:`MESH_VOXEL` x radius); smooth shading,
    then the material. Radius and voxel size are the modifier's inputs, so a panel can change them."""
    import bpy

    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    for sock_name, value in (("Radius", radius), ("Voxel size", voxel or MESH_VOXEL * radius)):
        s = ng.interface.new_socket(sock_name, in_out="INPUT", socket_type="NodeSocketFloat")
        s.min_value, s.default_value, s.subtype = 0.0, float(value), "DISTANCE"
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    size = ng.nodes.new("GeometryNodeAttributeDomainSize")
    size.component = "MESH"
    ng.links.new(gin.outputs["Geometry"], size.inputs["Geometry"])
    m2p = ng.nodes.new("GeometryNodeMeshToPoints")
    m2p.mode = "VERTICES"
    ng.links.new(gin.outputs["Geometry"], m2p.inputs["Mesh"])
    p2v = ng.nodes.new("GeometryNodePointsToVolume")
    v2m = ng.nodes.new("GeometryNodeVolumeToMesh")
    for node in (p2v, v2m):
        node.inputs["Resolution Mode"].default_value = "Size"
        ng.links.new(gin.outputs["Voxel size"], node.inputs["Voxel Size"])
    ng.links.new(m2p.outputs["Points"], p2v.inputs["Points"])
    ng.links.new(gin.outputs["Radius"], p2v.inputs["Radius"])
    ng.links.new(p2v.outputs["Volume"], v2m.inputs["Volume"])
    switch = ng.nodes.new("GeometryNodeSwitch")
    switch.input_type = "GEOMETRY"
    ng.links.new(size.outputs["Face Count"], switch.inputs["Switch"])  # faces: the file's own mesh
    ng.links.new(v2m.outputs["Mesh"], switch.inputs["False"])
    ng.links.new(gin.outputs["Geometry"], switch.inputs["True"])
    smooth = ng.nodes.new("GeometryNodeSetShadeSmooth")
    ng.links.new(switch.outputs[0], smooth.inputs["Mesh"])
    setm = ng.nodes.new("GeometryNodeSetMaterial")
    setm.inputs["Material"].default_value = material
    ng.links.new(smooth.outputs["Mesh"], setm.inputs["Geometry"])
    ng.links.new(setm.outputs["Geometry"], gout.inputs[0])
    return ng


def _jittered_copies(ng, points, pid, copies: int, jitter: float, seed: int):
    """Duplicate Elements (copies - 1 more per point), then Set Position by a Random Value
    vector whose ID is id*copies + copy index + 1: the same offsets every frame."""
    dup = ng.nodes.new("GeometryNodeDuplicateElements")
    dup.domain = "POINT"
    dup.inputs["Amount"].default_value = copies - 1
    ng.links.new(points, dup.inputs["Geometry"])
    join = ng.nodes.new("GeometryNodeJoinGeometry")
    ng.links.new(points, join.inputs[0])
    mul = ng.nodes.new("ShaderNodeMath")
    mul.operation = "MULTIPLY_ADD"
    ng.links.new(pid, mul.inputs[0])
    mul.inputs[1].default_value = float(copies)
    ng.links.new(dup.outputs["Duplicate Index"], mul.inputs[2])
    one = ng.nodes.new("ShaderNodeMath")
    one.operation = "ADD"
    ng.links.new(mul.outputs[0], one.inputs[0])
    one.inputs[1].default_value = 1.0  # copy 0 is the particle itself
    rnd = ng.nodes.new("FunctionNodeRandomValue")
    rnd.data_type = "FLOAT_VECTOR"
    [s for s in rnd.inputs if s.name == "Min" and s.enabled][0].default_value = (-jitter, -jitter, -jitter)
    [s for s in rnd.inputs if s.name == "Max" and s.enabled][0].default_value = (jitter, jitter, jitter)
    rnd.inputs["Seed"].default_value = seed + 100
    ng.links.new(one.outputs[0], rnd.inputs["ID"])
    setp = ng.nodes.new("GeometryNodeSetPosition")
    ng.links.new(dup.outputs["Geometry"], setp.inputs["Geometry"])
    ng.links.new([s for s in rnd.outputs if s.enabled][0], setp.inputs["Offset"])
    ng.links.new(setp.outputs["Geometry"], join.inputs[0])
    return join.outputs[0]


def diffuse_objects(collection, r: float, radii=(None, None, None), copies: int = 1, make_mesh=None) -> dict:
    """One object per diffuse type (named from io/diffuse_types.COUNT_NAMES), drawn as spheres of
    the type's radius range (:func:`diffuse_radius`) with its material; type code -> object.
    ``make_mesh(name)`` makes each object's mesh (default: an empty one)."""
    import bpy

    out = {}
    for t, name in enumerate(COUNT_NAMES):
        me = make_mesh(name) if make_mesh else bpy.data.meshes.new(f"{name}_empty")
        obj = bpy.data.objects.new(name, me)
        add_spheres(obj, t, r, radii[t], copies)
        collection.objects.link(obj)
        out[t] = obj
    return out


def add_spheres(obj, t: int, r: float, own=None, copies: int = 1):
    """Give a diffuse type's object its sphere modifier ("whitecap_spheres"); returns the node group."""
    rmin, rmax = diffuse_radius(t, r, own)
    mod = obj.modifiers.new("whitecap_spheres", "NODES")
    mod.node_group = sphere_nodes(f"{COUNT_NAMES[t]}_spheres", rmin, rmax, material(DIFFUSE_KINDS[t]), SEEDS[t],
                                  copies=copies, jitter=COPY_JITTER * r)
    return mod.node_group
