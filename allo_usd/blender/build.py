"""Build a Blender scene from a SceneDescription (bpy only).

One builder per description type. Every object is named after its USD prim path, so a
Blender scene can be traced back to the layer that made it. Transforms go in as full
matrices (float32 in Blender) through `place`, which sets `rotation_mode = 'QUATERNION'`
first: Blender stores an assigned `matrix_world` decomposed into location, rotation and scale
in the object's rotation mode, so the default 'XYZ' would round-trip every rotation through
Euler angles (docs/physics.md section 4); a quaternion keeps it a rotation at any pitch.

Every value from the description goes in through `assign`, which reads it back: Blender clamps an
out-of-range float silently (a focal length of 1e-30 becomes 1 mm), so a value it would change is
a LayerError instead. The reader (`allo_usd.usd.reader_bounds`) already bounds every value to the bpy hard
limits; this catches a description made some other way. A texture Blender cannot decode is a
LayerError too (Blender only logs it and renders magenta or black).

Every lamp follows the light linking the reader resolved (its `link`): Cycles light linking
through a receiver collection per lamp, whose members are all EXCLUDE (the lamp lights every
object but them: the station's sun and the bodies) or all INCLUDE (only them: a body's own sun).

Lamps: a DistantLight is a SUN lamp, the inspection SphereLight and every other SphereLight a SPOT
(ShapingAPI) or POINT lamp, a RectLight / DiskLight an AREA lamp (RECTANGLE / DISK), a CylinderLight
an emission-only cylinder mesh (no camera rays, no pass index: never in the mask), the DomeLight the
world's background. UsdLux inputs:diffuse / inputs:specular 0 turn the lamp's diffuse / glossy ray
visibility off, ShadowAPI's shadows off is Cycles' use_shadow off.
"""

from __future__ import annotations

import math

import numpy as np

from allo_usd.core.errors import LayerError
from allo_usd.plan.settings import COLOR_PASSES
from allo_usd.usd.description import (DISPLAY_COLOR_ATTRIBUTE, AreaDesc, CameraDesc, CylinderDesc, DomeDesc, LampRays,
                                      MaterialDesc, MeshDesc, RenderDesc, SceneDescription, SpotDesc, SunDesc)


def _bpy():
    import bpy

    return bpy


def reset() -> None:
    """An empty factory scene; scripts in loaded files never auto-run."""
    bpy = _bpy()
    bpy.context.preferences.filepaths.use_scripts_auto_execute = False
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _matrix(m: np.ndarray):
    from mathutils import Matrix

    return Matrix([list(map(float, row)) for row in np.asarray(m)])


def _floats(value) -> np.ndarray:
    try:
        return np.asarray(tuple(value), dtype=np.float64)
    except TypeError:
        return np.asarray([value], dtype=np.float64)


def assign(owner, prop: str, value, what: str) -> None:
    """owner.prop = value, refusing a value Blender does not keep (it clamps floats to the property's
    hard limits silently): a LayerError naming `what` (the attribute that recorded it)."""
    try:
        setattr(owner, prop, value)
    except (TypeError, ValueError, OverflowError) as exc:  # an int outside C int range, a wrong type
        raise LayerError(f"{what} = {value!r} cannot be given to Blender ({exc}); fix the layer") from None
    got = getattr(owner, prop)
    if not np.allclose(_floats(got), _floats(value), rtol=1e-6, atol=0.0, equal_nan=False):
        rna = owner.bl_rna.properties[prop] if prop in owner.bl_rna.properties else None
        limits = f" (Blender's {owner.bl_rna.identifier}.{prop} takes {rna.hard_min:g}..{rna.hard_max:g})" \
            if rna is not None and hasattr(rna, "hard_min") else ""
        shown = tuple(_floats(got)) if len(_floats(got)) > 1 else _floats(got)[0]
        raise LayerError(f"{what} = {value!r} would become {shown} in Blender{limits}; fix the layer")


def load_texture(path: str, material: str):
    """A texture image, loaded and decoded now (Blender loads lazily and only logs a broken file)."""
    bpy = _bpy()
    try:
        image = bpy.data.images.load(path, check_existing=True)
    except RuntimeError as exc:
        raise LayerError(f"texture {path} of material {material} cannot be loaded by Blender "
                         f"({str(exc).strip()}); restore the file") from None
    width, height = image.size  # asking for the size decodes the file
    if not (image.has_data and width * height > 0):
        bpy.data.images.remove(image)
        raise LayerError(f"texture {path} of material {material} is not an image Blender can decode (broken or "
                         "cut short); restore the real image (fix the asset)")
    return image


def place(obj, m: np.ndarray) -> None:
    """Set an object's world matrix, decomposed into a quaternion (never Euler angles)."""
    obj.rotation_mode = "QUATERNION"
    obj.matrix_world = _matrix(m)


def set_principled(bsdf, desc: MaterialDesc) -> None:
    """The Principled BSDF's plain values (the node graph aside)."""
    inputs, where = bsdf.inputs, f"material {desc.path}"
    assign(inputs["Base Color"], "default_value", (*desc.base_color, 1.0), f"{where} diffuseColor")
    assign(inputs["Metallic"], "default_value", desc.metallic, f"{where} metallic")
    assign(inputs["Roughness"], "default_value", desc.roughness, f"{where} roughness")
    assign(inputs["IOR"], "default_value", desc.ior, f"{where} ior")  # 1.0: no specular layer, a Lambertian surface
    assign(inputs["Alpha"], "default_value", desc.opacity, f"{where} opacity")  # 0: fully transparent (the Sun's sphere)


def build_material(desc: MaterialDesc):
    bpy = _bpy()
    mat = bpy.data.materials.new(desc.path)
    tree = mat.node_tree
    bsdf = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
    set_principled(bsdf, desc)
    if desc.color_attribute:   # USD's display colour and opacity per face vertex (MeshDesc.colors), linear
        attr = tree.nodes.new("ShaderNodeAttribute")
        attr.attribute_type = "GEOMETRY"
        attr.attribute_name = desc.color_attribute
        tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
        tree.links.new(attr.outputs["Alpha"], bsdf.inputs["Alpha"])
    if desc.base_color_texture:
        tex = tree.nodes.new("ShaderNodeTexImage")
        tex.image = load_texture(desc.base_color_texture, desc.path)
        tex.image.colorspace_settings.name = "sRGB"
        uvmap = tree.nodes.new("ShaderNodeUVMap")
        uvmap.uv_map = "st"
        tree.links.new(uvmap.outputs["UV"], tex.inputs["Vector"])
        mix = tree.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.blend_type = "MULTIPLY"
        mix.inputs["Factor"].default_value = 1.0
        tree.links.new(tex.outputs["Color"], mix.inputs["A"])
        mix.inputs["B"].default_value = (*desc.base_color, 1.0)
        tree.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
    strength = max(desc.emissive_color)
    if strength > 0:
        assign(bsdf.inputs["Emission Color"], "default_value", (*(c / strength for c in desc.emissive_color), 1.0),
               f"material {desc.path} emissiveColor")
        assign(bsdf.inputs["Emission Strength"], "default_value", strength, f"material {desc.path} emissiveColor")
    return mat


def build_mesh(desc: MeshDesc, material, subset_materials=()):
    """A mesh object in `material`; `subset_materials`: the Blender materials of desc.subsets, in order
    (material slots 1, 2, ...: each subset's faces take its slot)."""
    bpy = _bpy()
    me = bpy.data.meshes.new(desc.path)
    me.vertices.add(len(desc.points))
    me.vertices.foreach_set("co", desc.points.ravel())
    me.loops.add(len(desc.face_indices))
    me.loops.foreach_set("vertex_index", desc.face_indices)
    me.polygons.add(len(desc.face_counts))
    starts = np.concatenate([[0], np.cumsum(desc.face_counts)[:-1]]).astype(np.int32)
    me.polygons.foreach_set("loop_start", starts)
    me.polygons.foreach_set("use_smooth", np.full(len(desc.face_counts), desc.smooth))
    if desc.uv is not None:
        layer = me.uv_layers.new(name="st")
        layer.data.foreach_set("uv", desc.uv.ravel())
    if desc.colors is not None:   # linear RGBA per face vertex: a float colour attribute (no sRGB encoding)
        colors = me.color_attributes.new(DISPLAY_COLOR_ATTRIBUTE, "FLOAT_COLOR", "CORNER")
        colors.data.foreach_set("color", np.ascontiguousarray(desc.colors, dtype=np.float32).ravel())
    me.update(calc_edges=True)
    me.validate(clean_customdata=False)
    me.materials.append(material)
    if desc.subsets:   # GeomSubsets bound to other materials: one slot each, their faces' material_index
        slot = np.zeros(len(desc.face_counts), dtype=np.int32)
        for i, ((_, faces), mat) in enumerate(zip(desc.subsets, subset_materials, strict=True), start=1):
            me.materials.append(mat)
            slot[faces] = i
        me.polygons.foreach_set("material_index", slot)
    obj = bpy.data.objects.new(desc.path, me)
    place(obj, desc.matrix)
    if desc.ray_visibility == "cameraOnly":  # the Sun's disc: seen, but neither shadowing nor lighting
        obj.visible_diffuse = obj.visible_glossy = obj.visible_shadow = False
        obj.visible_transmission = obj.visible_volume_scatter = False
    elif desc.ray_visibility == "noShadow":  # Moon, Earth: the eclipse is in the sun lamp's intensity
        obj.visible_shadow = False
    bpy.context.scene.collection.objects.link(obj)
    return obj


def set_lens(cam, desc: CameraDesc) -> None:
    """Focal length, sensor size (mm), clipping range (m) and lens shift of a Blender camera."""
    assign(cam, "lens", desc.focal_length_mm, f"{desc.path} focal length (mm)")
    assign(cam, "sensor_width", desc.sensor_width_mm, f"{desc.path} horizontal aperture (mm)")
    assign(cam, "sensor_height", desc.sensor_height_mm, f"{desc.path} vertical aperture (mm)")
    assign(cam, "clip_start", desc.clip[0], f"{desc.path} clipping range near (m)")
    assign(cam, "clip_end", desc.clip[1], f"{desc.path} clipping range far (m)")
    # Lens shift for the aperture offsets: with sensor_fit HORIZONTAL Blender counts both shifts in
    # sensor widths (shift_x moves the view right, shift_y up), as UsdGeom.Camera moves its window by
    # the offsets (core.camera_model): shift = offset / horizontal aperture.
    assign(cam, "shift_x", desc.horizontal_offset_mm / desc.sensor_width_mm,
           f"{desc.path} horizontalApertureOffset / horizontalAperture")
    assign(cam, "shift_y", desc.vertical_offset_mm / desc.sensor_width_mm,
           f"{desc.path} verticalApertureOffset / horizontalAperture")
    # Depth of field as UsdGeom.Camera has it: fStop 0 none; else the lens at that f-number focused at
    # focusDistance (m). Blender's aperture is focal length / f-number, as USD's.
    cam.dof.use_dof = desc.f_stop > 0
    if desc.f_stop > 0:
        assign(cam.dof, "aperture_fstop", desc.f_stop, f"{desc.path} fStop")
        assign(cam.dof, "focus_distance", desc.focus_distance_m, f"{desc.path} focusDistance (m)")


def build_camera(desc: CameraDesc):
    bpy = _bpy()
    cam = bpy.data.cameras.new(desc.path)
    cam.lens_unit = "MILLIMETERS"
    cam.sensor_fit = "HORIZONTAL"
    set_lens(cam, desc)
    obj = bpy.data.objects.new(desc.path, cam)
    place(obj, desc.matrix)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.camera = obj
    return obj


def set_sun(obj, desc: SunDesc) -> None:
    """A sun lamp's values and direction (everything but its light linking)."""
    from allo_usd.core.geometry import rotation_towards

    light = obj.data
    assign(light, "energy", desc.irradiance, f"{desc.path} irradiance")  # Cycles sun strength is irradiance, W/m^2
    obj.visible_camera = desc.camera_visible  # Cycles draws the disc (angle, radiance irradiance / its solid angle)
    assign(light, "angle", math.radians(desc.angle_deg), f"{desc.path} angle (radians)")
    assign(light, "color", desc.color, f"{desc.path} color")
    m = np.eye(4)
    m[:3, :3] = rotation_towards(desc.direction)
    place(obj, m)


def receivers_name(desc: SunDesc) -> str:
    return f"{desc.path} receivers"


def set_rays(obj, rays: LampRays | None) -> None:
    """A lamp's (or emitting mesh's) diffuse / glossy ray visibility and, for a lamp, its shadows; None:
    Blender's defaults, left untouched."""
    if rays is None:
        return
    obj.visible_diffuse = rays.diffuse
    obj.visible_glossy = rays.specular
    if obj.type == "LIGHT":
        obj.data.use_shadow = rays.shadow


def link_receivers(obj, desc) -> None:
    """With a link (`desc.link`), a receiver collection of the linked mesh objects, all EXCLUDE or all
    INCLUDE."""
    if desc.link is None:
        return
    bpy = _bpy()
    scene_objects = bpy.context.scene.collection.objects
    coll = bpy.data.collections.new(receivers_name(desc))
    for path in desc.link.paths:
        coll.objects.link(scene_objects[path])
    state = "EXCLUDE" if desc.link.exclude else "INCLUDE"
    for member in coll.collection_objects:
        member.light_linking.link_state = state
    obj.light_linking.receiver_collection = coll


def lamp_object(light, desc, position):
    """The scene object of a lamp datablock, named after its prim: `position` sets its transform, then
    its ray visibility (desc.rays) and light linking (desc.link) as every lamp builder sets them."""
    obj = _bpy().data.objects.new(desc.path, light)
    position(obj)
    set_rays(obj, desc.rays)
    _bpy().context.scene.collection.objects.link(obj)
    link_receivers(obj, desc)
    return obj


def build_sun(desc: SunDesc):
    """A SUN lamp named after its prim; with a link, a receiver collection of the linked mesh objects."""
    bpy = _bpy()
    light = bpy.data.lights.new(desc.path, type="SUN")
    return lamp_object(light, desc, lambda obj: set_sun(obj, desc))


def spot_power_w(desc: SpotDesc) -> float:
    """Radiant power of a sphere of radius r with surface radiance L: 4 pi^2 r^2 L (area 4 pi r^2 times
    the pi L a Lambertian surface emits per unit area). L is UsdLux's un-normalised SphereLight intensity
    (the reader divides a normalised one by the area first), and Blender's point/spot power is this."""
    return 4.0 * math.pi ** 2 * desc.radius ** 2 * desc.intensity


def build_spot(desc: SpotDesc):
    """A SphereLight: a SPOT lamp with its cone when shaped, else a POINT lamp (every direction)."""
    bpy = _bpy()
    light = bpy.data.lights.new(desc.path, type="SPOT" if desc.shaped else "POINT")
    assign(light, "energy", spot_power_w(desc), f"{desc.path} power (W)")
    assign(light, "shadow_soft_size", desc.radius, f"{desc.path} radius")
    if desc.shaped:
        assign(light, "spot_size", math.radians(2.0 * desc.cone_angle_deg),
               f"{desc.path} cone (2 x half angle, radians)")
        assign(light, "spot_blend", desc.softness, f"{desc.path} cone softness")
    assign(light, "color", desc.color, f"{desc.path} color")
    return lamp_object(light, desc, lambda obj: place(obj, desc.matrix))


def build_area(desc: AreaDesc):
    """A RectLight / DiskLight: an AREA lamp (RECTANGLE / DISK; Blender's area lamp, like UsdLux's, emits
    along local -Z from one side, Lambertian at the default spread of 180 degrees) whose energy is its
    power in W, radiance x world-space area x pi (Cycles scales the size by the object's scale)."""
    bpy = _bpy()
    light = bpy.data.lights.new(desc.path, type="AREA")
    light.shape = desc.shape
    assign(light, "size", desc.size[0], f"{desc.path} width / diameter (m)")
    if desc.shape == "RECTANGLE":
        assign(light, "size_y", desc.size[1], f"{desc.path} height (m)")
    assign(light, "energy", desc.power, f"{desc.path} power (W)")
    assign(light, "color", desc.color, f"{desc.path} color")
    return lamp_object(light, desc, lambda obj: place(obj, desc.matrix))


CYLINDER_SIDES = 64


def cylinder_name(desc: CylinderDesc) -> str:
    return f"{desc.path} emitter"


def build_cylinder(desc: CylinderDesc):
    """A CylinderLight: a cylinder mesh along local X (CYLINDER_SIDES sides whose perimeter is the
    circle's, so its side area and power are the cylinder's), no caps, its outside emitting the
    radiance (Emission strength = W/m^2/sr; back faces emit nothing). Not seen by camera rays and not
    casting shadows (a UsdLux light is no occluder); pass index 0, so never in the mask."""
    bpy = _bpy()
    name = cylinder_name(desc)
    n = CYLINDER_SIDES
    r = desc.radius * math.pi / (n * math.sin(math.pi / n))  # the polygon's perimeter = 2 pi radius
    a = np.arange(n) * 2.0 * math.pi / n
    ring = np.stack([np.zeros(n), r * np.cos(a), r * np.sin(a)], -1)
    half = desc.length / 2.0
    points = np.concatenate([ring + [-half, 0, 0], ring + [half, 0, 0]])
    faces = [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n)]  # outward normals
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(p) for p in points], [], faces)
    me.polygons.foreach_set("use_smooth", np.ones(n, dtype=bool))
    me.update()
    mat = bpy.data.materials.new(name)
    tree = mat.node_tree
    for node in list(tree.nodes):
        if node.type != "OUTPUT_MATERIAL":
            tree.nodes.remove(node)
    emission = tree.nodes.new("ShaderNodeEmission")
    assign(emission.inputs["Color"], "default_value", (*desc.color, 1.0), f"{desc.path} color")
    assign(emission.inputs["Strength"], "default_value", desc.radiance, f"{desc.path} radiance")
    facing = tree.nodes.new("ShaderNodeNewGeometry")
    mix = tree.nodes.new("ShaderNodeMixShader")  # back faces: the empty second shader, no emission
    tree.links.new(facing.outputs["Backfacing"], mix.inputs["Fac"])
    tree.links.new(emission.outputs["Emission"], mix.inputs[1])
    tree.links.new(mix.outputs["Shader"], next(x for x in tree.nodes if x.type == "OUTPUT_MATERIAL").inputs["Surface"])
    mat.cycles.emission_sampling = "FRONT"
    me.materials.append(mat)
    obj = bpy.data.objects.new(name, me)
    place(obj, desc.matrix)
    obj.visible_camera = False
    obj.visible_shadow = False
    set_rays(obj, desc.rays)
    bpy.context.scene.collection.objects.link(obj)
    link_receivers(obj, desc)
    return obj


def build_lamp(desc):
    """One of SceneDescription.lights."""
    if isinstance(desc, SpotDesc):
        return build_spot(desc)
    if isinstance(desc, AreaDesc):
        return build_area(desc)
    return build_cylinder(desc)


def lamp_name(desc) -> str:
    """The Blender object of one of SceneDescription.lights."""
    return cylinder_name(desc) if isinstance(desc, CylinderDesc) else desc.path


def set_dome(desc: DomeDesc | None) -> None:
    """The world's background: the dome's radiance (Background colour x strength) and ray visibility;
    None: the black space configure_render makes (strength 0, Blender's default colour)."""
    world = _bpy().context.scene.world
    bg = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
    vis = world.cycles_visibility
    for n in [n for n in world.node_tree.nodes if n.name.startswith(DOME_NODE)]:   # a textured dome's, if any
        world.node_tree.nodes.remove(n)
    if desc is None:
        bg.inputs["Color"].default_value = (0.05, 0.05, 0.05, 1.0)  # a new world's (bpy.data.worlds.new)
        bg.inputs["Strength"].default_value = 0.0
        vis.diffuse = vis.glossy = True
        return
    assign(bg.inputs["Color"], "default_value", (*desc.color, 1.0), f"{desc.path} color")
    assign(bg.inputs["Strength"], "default_value", desc.strength, f"{desc.path} intensity x 2^exposure")
    rays = desc.rays or LampRays()
    vis.diffuse, vis.glossy = rays.diffuse, rays.specular
    if desc.texture:
        dome_texture(world.node_tree, bg, desc)


DOME_NODE = "USD dome: "   # the name prefix of the world nodes that map a DomeLight's texture


def dome_texture(tree, bg, desc: DomeDesc) -> None:
    """The dome's lat-long image times its colour into the Background: for a world ray D, the dome's
    own direction d = R^T D (R = desc.rotation), longitude atan2(d.x, d.z) and latitude asin(d.y) (UsdLux
    DomeLight: the OpenEXR lat-long map, pole +Y, longitude 0 towards +Z, pi/2 towards +X; the image's
    left edge is longitude +pi, its top row latitude +pi/2), so u = 1/2 - longitude / 2 pi and
    v = 1/2 + latitude / pi (Blender's v counts from the bottom row). The image keeps the colour space
    Blender gives its file (sRGB for 8-bit images, linear for float ones, as USD's `auto`)."""
    nodes, links = tree.nodes, tree.links

    def node(kind: str, name: str, **values):
        n = nodes.new(kind)
        n.name = n.label = DOME_NODE + name
        for key, value in values.items():
            setattr(n, key, value)
        return n

    def calc(operation: str, name: str, a, b=None):
        n = node("ShaderNodeMath", name, operation=operation)
        for i, x in enumerate((a, b)):
            if x is None:
                continue
            if isinstance(x, float):
                n.inputs[i].default_value = x
            else:
                links.new(x, n.inputs[i])
        return n.outputs[0]

    direction = node("ShaderNodeTexCoord", "ray").outputs["Generated"]   # the world ray's direction
    local = []
    for axis in range(3):   # d = R^T D, one row of R^T (a column of R) at a time
        dot = node("ShaderNodeVectorMath", f"d{'xyz'[axis]}", operation="DOT_PRODUCT")
        links.new(direction, dot.inputs[0])
        dot.inputs[1].default_value = tuple(float(v) for v in desc.rotation[:, axis])
        local.append(dot.outputs["Value"])
    longitude = calc("ARCTAN2", "longitude", local[0], local[2])
    latitude = calc("ARCSINE", "latitude", calc("MINIMUM", "y<=1", calc("MAXIMUM", "y>=-1", local[1], -1.0), 1.0))
    u = calc("SUBTRACT", "u", 0.5, calc("DIVIDE", "lon/2pi", longitude, 2.0 * math.pi))
    v = calc("ADD", "v", 0.5, calc("DIVIDE", "lat/pi", latitude, math.pi))
    uv = node("ShaderNodeCombineXYZ", "uv")
    links.new(u, uv.inputs["X"])
    links.new(v, uv.inputs["Y"])
    image = node("ShaderNodeTexImage", "image", interpolation="Linear", extension="REPEAT")
    image.image = load_texture(desc.texture, desc.path)
    links.new(uv.outputs["Vector"], image.inputs["Vector"])
    tint = node("ShaderNodeMix", "colour", data_type="RGBA", blend_type="MULTIPLY")
    tint.inputs["Factor"].default_value = 1.0
    links.new(image.outputs["Color"], tint.inputs["A"])
    tint.inputs["B"].default_value = (*desc.color, 1.0)
    links.new(tint.outputs["Result"], bg.inputs["Color"])




def configure_render(render: RenderDesc, device=None) -> None:
    """The layer's render settings, on `device` (an allo_usd.blender.device.Device; None: the CPU),
    which is not part of the layer."""
    from allo_usd.blender.device import activate

    bpy = _bpy()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    activate(device)   # after every factory reset: it resets the Cycles preferences too
    assign(scene.render, "resolution_x", render.resolution[0], "render resolution width")
    assign(scene.render, "resolution_y", render.resolution[1], "render resolution height")
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    mask_only = not set(COLOR_PASSES) & set(render.outputs)   # no colour: the first hit is all we need
    assign(scene.cycles, "samples", 1 if mask_only else render.samples, "render samples")  # the mask: sample 0
    scene.cycles.use_adaptive_sampling = render.adaptive_threshold > 0 and not mask_only
    if render.adaptive_threshold > 0:
        assign(scene.cycles, "adaptive_threshold", render.adaptive_threshold, "render adaptive threshold")
    scene.cycles.use_denoising = render.denoise and not mask_only
    if render.denoise:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
        scene.cycles.denoising_prefilter = render.denoise_prefilter
        scene.cycles.denoising_quality = render.denoise_quality
        scene.cycles.denoising_use_gpu = False
    assign(scene.cycles, "seed", render.seed, "render seed")
    scene.cycles.use_animated_seed = False
    assign(scene.cycles, "max_bounces", 0 if mask_only else render.max_bounces, "render max bounces")
    scene.cycles.diffuse_bounces = min(4, render.max_bounces)
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0  # the default 10 eats ~10% of a 1361 W/m^2 sun
    assign(scene.cycles, "film_exposure", render.exposure, "render exposure")
    scene.render.film_transparent = False
    if render.threads > 0:
        scene.render.threads_mode = "FIXED"
        assign(scene.render, "threads", render.threads, "render threads")
    else:
        scene.render.threads_mode = "AUTO"
    scene.render.use_persistent_data = True
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.dither_intensity = 0.0
    world = scene.world if scene.world is not None and scene.world.name == "Space" else bpy.data.worlds.new("Space")
    world.color = (0.0, 0.0, 0.0)
    bg = next((n for n in world.node_tree.nodes if n.type == "BACKGROUND"), None) if world.node_tree else None
    if bg is not None:
        bg.inputs["Strength"].default_value = 0.0
    scene.world = world
    layer = scene.view_layers[0]
    layer.use_pass_combined = True
    layer.use_pass_object_index = True
    layer.pass_alpha_threshold = 0.0  # every surface writes the index, the transparent Sun sphere too (class 1)
    layer.use_pass_z = "depth" in render.outputs
    layer.use_pass_normal = "normal" in render.outputs


# Object ids: an object is a station or body mesh prim, or a whole anomaly object (all the meshes of
# one anomaly object share its id: MeshDesc.object, the prim its anomaly label is applied on, e.g.
# /World/Anomaly for the scene's planned anomaly, /World/Wrench for a user's referenced wrench).
# Object id = 1 + the index of the object's path among the scene's sorted object paths (0 is the
# background); each mesh object's pass_index is its object's id, so one object index pass gives the
# instance mask, the class mask (through each id's class) and per-object pixel counts. Stable: a
# function of the scene's mesh paths and labels only. Blender's pass_index is at most MAX_OBJECT_ID.
MAX_OBJECT_ID = 32767


def _object_path(mesh) -> str:
    return mesh.object_path


def object_ids(desc: SceneDescription) -> tuple[tuple[str, int], ...]:
    """(object path, class id) of object id 1, 2, ...: the scene's objects in sorted path order."""
    table = tuple(sorted({(_object_path(m), m.class_id) for m in desc.meshes}))
    if len({path for path, _ in table}) != len(table):
        path = next(p for (p, _), (q, _) in zip(table, table[1:]) if p == q)
        raise LayerError(f"{desc.layer}: the meshes of object {path} have more than one class label; fix the layer "
                         "(label the object's prims with one class)")
    if len(table) > MAX_OBJECT_ID:
        raise LayerError(f"{desc.layer} has {len(table)} objects; the object index pass numbers at most "
                         f"{MAX_OBJECT_ID}: merge meshes (fix the layer)")
    return table


def set_object_ids(desc: SceneDescription) -> None:
    """Every mesh object's pass_index is its object's id (object_ids)."""
    objects = _bpy().context.scene.collection.objects
    ids = {path: i for i, (path, _) in enumerate(object_ids(desc), start=1)}
    for mesh in desc.meshes:
        objects[mesh.path].pass_index = ids[_object_path(mesh)]


def build_scene(desc: SceneDescription, device=None) -> None:
    """Build `desc` into a fresh Blender scene that renders on `device` (None: the CPU)."""
    reset()
    mats = {key: build_material(m) for key, m in desc.materials.items()}
    for mesh in desc.meshes:
        build_mesh(mesh, mats[mesh.material], [mats[key] for key, _ in mesh.subsets])
    build_camera(desc.camera)
    for sun in desc.suns:
        build_sun(sun)
    if desc.spot is not None:
        build_spot(desc.spot)
    for lamp in desc.lights:
        build_lamp(lamp)
    configure_render(desc.render, device)
    if desc.dome is not None:
        set_dome(desc.dome)
    set_object_ids(desc)
    from allo_usd.blender.compositor import build_glare, no_compositor

    if desc.effects.glare:
        build_glare()
    else:
        no_compositor()  # a scene that declares no glare gets no compositor at all
