"""Materials and the particle-sphere node group of the add-on (bpy only).

The values follow whitecap's renderer (render/scene.py with the default
``[render]`` settings), so a run loaded here looks like ``whitecap render``'s
frames. Each material is made once per .blend and found again by name, so
applying it twice reuses it.
"""

import bpy

WATER_COLOR = (0.55, 0.8, 0.9)  # [render] water_color default
WATER_ABSORPTION = 3.0  # [render] water_absorption default [1/m]
WATER_ROUGHNESS = 0.02  # [render] water_roughness default
OBSTACLE_PRESETS = {"stone": (0.8, 0.0), "clay": (0.6, 0.0), "metal": (0.3, 1.0), "plastic": (0.35, 0.0)}
THIN_GLASS_IOR = 1.5  # the "glass" preset's Fresnel reflectance: window glass [-]


def _principled(mat):
    mat.use_nodes = True
    return mat.node_tree, mat.node_tree.nodes.get("Principled BSDF")


def _water(mat):
    nt, b = _principled(mat)
    b.inputs["Base Color"].default_value = (*WATER_COLOR, 1.0)
    b.inputs["Transmission Weight"].default_value = 1.0
    b.inputs["IOR"].default_value = 1.33
    b.inputs["Roughness"].default_value = WATER_ROUGHNESS
    absorb = nt.nodes.new("ShaderNodeVolumeAbsorption")
    absorb.inputs["Color"].default_value = (*WATER_COLOR, 1.0)
    absorb.inputs["Density"].default_value = WATER_ABSORPTION
    nt.links.new(absorb.outputs[0], nt.nodes.get("Material Output").inputs["Volume"])


def _foam(mat):
    """Transparent + emission mixed by noise: soft, broken-up foam."""
    mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out, mix = nt.nodes.new("ShaderNodeOutputMaterial"), nt.nodes.new("ShaderNodeMixShader")
    transp, emit = nt.nodes.new("ShaderNodeBsdfTransparent"), nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (0.95, 0.97, 1.0, 1.0)
    emit.inputs["Strength"].default_value = 1.2
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
    _, b = _principled(mat)
    b.inputs["Base Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    b.inputs["Transmission Weight"].default_value = 0.6
    b.inputs["Roughness"].default_value = 0.3


def _bubbles(mat):
    _, b = _principled(mat)
    b.inputs["Base Color"].default_value = (0.9, 0.97, 1.0, 1.0)
    b.inputs["Transmission Weight"].default_value = 1.0
    b.inputs["IOR"].default_value = 1.0 / 1.33  # air inside water
    b.inputs["Roughness"].default_value = 0.05


def _particles(mat):
    _, b = _principled(mat)
    b.inputs["Base Color"].default_value = (0.2, 0.45, 0.9, 1.0)
    b.inputs["Roughness"].default_value = 0.4


# material name per sequence kind; the diffuse names match the renderer's
BUILDERS = {"FLUID": ("whitecap_water", _water), "FOAM": ("whitecap_foam", _foam),
            "SPRAY": ("whitecap_spray", _spray), "BUBBLES": ("whitecap_bubbles", _bubbles),
            "PARTICLES": ("whitecap_particles", _particles)}


def material(kind):
    """The material for a sequence kind, made on first use and reused after."""
    name, build = BUILDERS.get(kind, BUILDERS["PARTICLES"])
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        build(mat)
    return mat


def thin_glass(mat, color):
    """A pane without thickness (a closed tank's wall): seen straight through, tinted by
    ``color``, with glass's Fresnel reflection (whitecap's renderer uses this one too)."""
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


def obstacle_material(entry):
    preset = entry.get("material", "stone")
    color = tuple(entry.get("color", [0.8, 0.78, 0.72]))
    name = f"whitecap_obstacle_{preset}"
    mat = bpy.data.materials.get(name)
    if mat is None and preset == "glass":
        mat = bpy.data.materials.new(name)
        thin_glass(mat, color)
    if mat is None:
        mat = bpy.data.materials.new(name)
        _, b = _principled(mat)
        rough, metal = OBSTACLE_PRESETS.get(preset, (0.7, 0.0))
        b.inputs["Base Color"].default_value = (*color, 1.0)
        b.inputs["Roughness"].default_value = rough
        b.inputs["Metallic"].default_value = metal
    return mat


def sphere_nodes(name, material):
    """Mesh to Points at each point's ``radius`` attribute where the file has one, else at
    the group's Radius input; then the material. Returns (node group, Radius input id)."""
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    sock = ng.interface.new_socket("Radius", in_out="INPUT", socket_type="NodeSocketFloat")
    sock.min_value, sock.default_value = 0.0, 0.01
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    attr = ng.nodes.new("GeometryNodeInputNamedAttribute")
    attr.data_type = "FLOAT"
    attr.inputs["Name"].default_value = "radius"
    switch = ng.nodes.new("GeometryNodeSwitch")
    switch.input_type = "FLOAT"
    m2p = ng.nodes.new("GeometryNodeMeshToPoints")
    m2p.mode = "VERTICES"
    setm = ng.nodes.new("GeometryNodeSetMaterial")
    setm.inputs["Material"].default_value = material
    ng.links.new(attr.outputs["Exists"], switch.inputs["Switch"])
    ng.links.new(gin.outputs["Radius"], switch.inputs["False"])
    ng.links.new(attr.outputs["Attribute"], switch.inputs["True"])
    ng.links.new(gin.outputs["Geometry"], m2p.inputs["Mesh"])
    ng.links.new(switch.outputs[0], m2p.inputs["Radius"])
    ng.links.new(m2p.outputs["Points"], setm.inputs["Geometry"])
    ng.links.new(setm.outputs["Geometry"], gout.inputs[0])
    return ng, sock.identifier
