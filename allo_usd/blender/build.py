"""Build a Blender scene from a SceneDescription (bpy only).

One builder per description type. Every object is named after its USD prim path, so a
Blender scene can be traced back to the layer that made it. Transforms go in as full
matrices (float32 in Blender) through `place`, which sets `rotation_mode = 'QUATERNION'`
first: Blender stores an assigned `matrix_world` decomposed into location, rotation and scale
in the object's rotation mode, so the default 'XYZ' would round-trip every rotation through
Euler angles (docs/physics.md section 4); a quaternion keeps it a rotation at any pitch.

Sun lamps follow the light linking the reader resolved (`SunDesc.link`): Cycles light linking
through a receiver collection per lamp, whose members are all EXCLUDE (the lamp lights every
object but them: the station's sun and the bodies) or all INCLUDE (only them: a body's own sun).
"""

from __future__ import annotations

import math

import numpy as np

from allo_usd.usd.description import (CameraDesc, MaterialDesc, MeshDesc, RenderDesc, SceneDescription, SpotDesc,
                                      SunDesc)


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


def place(obj, m: np.ndarray) -> None:
    """Set an object's world matrix, decomposed into a quaternion (never Euler angles)."""
    obj.rotation_mode = "QUATERNION"
    obj.matrix_world = _matrix(m)


def build_material(desc: MaterialDesc):
    bpy = _bpy()
    mat = bpy.data.materials.new(desc.path)
    tree = mat.node_tree
    bsdf = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = (*desc.base_color, 1.0)
    bsdf.inputs["Metallic"].default_value = desc.metallic
    bsdf.inputs["Roughness"].default_value = desc.roughness
    bsdf.inputs["IOR"].default_value = desc.ior  # 1.0: no specular layer, a Lambertian surface
    if desc.base_color_texture:
        tex = tree.nodes.new("ShaderNodeTexImage")
        tex.image = bpy.data.images.load(desc.base_color_texture, check_existing=True)
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
        bsdf.inputs["Emission Color"].default_value = (*(c / strength for c in desc.emissive_color), 1.0)
        bsdf.inputs["Emission Strength"].default_value = strength
    return mat


def build_mesh(desc: MeshDesc, material):
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
    me.update(calc_edges=True)
    me.validate(clean_customdata=False)
    me.materials.append(material)
    obj = bpy.data.objects.new(desc.path, me)
    place(obj, desc.matrix)
    obj.pass_index = desc.class_id
    if desc.ray_visibility == "cameraOnly":  # the Sun's disc: seen, but neither shadowing nor lighting
        obj.visible_diffuse = obj.visible_glossy = obj.visible_shadow = False
        obj.visible_transmission = obj.visible_volume_scatter = False
    elif desc.ray_visibility == "noShadow":  # Moon, Earth: the eclipse is in the sun lamp's intensity
        obj.visible_shadow = False
    bpy.context.scene.collection.objects.link(obj)
    return obj


def build_camera(desc: CameraDesc):
    bpy = _bpy()
    cam = bpy.data.cameras.new(desc.path)
    cam.lens_unit = "MILLIMETERS"
    cam.lens = desc.focal_length_mm
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = desc.sensor_width_mm
    cam.sensor_height = desc.sensor_height_mm
    cam.clip_start, cam.clip_end = desc.clip
    obj = bpy.data.objects.new(desc.path, cam)
    place(obj, desc.matrix)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.camera = obj
    return obj


def set_sun(obj, desc: SunDesc) -> None:
    """A sun lamp's values and direction (everything but its light linking)."""
    from allo_usd.core.geometry import rotation_towards

    light = obj.data
    light.energy = desc.irradiance          # Cycles sun strength is irradiance, W/m^2
    light.angle = math.radians(desc.angle_deg)
    light.color = desc.color
    m = np.eye(4)
    m[:3, :3] = rotation_towards(desc.direction)
    place(obj, m)


def receivers_name(desc: SunDesc) -> str:
    return f"{desc.path} receivers"


def build_sun(desc: SunDesc):
    """A SUN lamp named after its prim; with a link, a receiver collection of the linked mesh objects."""
    bpy = _bpy()
    light = bpy.data.lights.new(desc.path, type="SUN")
    obj = bpy.data.objects.new(desc.path, light)
    set_sun(obj, desc)
    scene_objects = bpy.context.scene.collection.objects
    scene_objects.link(obj)
    if desc.link is not None:
        coll = bpy.data.collections.new(receivers_name(desc))
        for path in desc.link.paths:
            coll.objects.link(scene_objects[path])
        state = "EXCLUDE" if desc.link.exclude else "INCLUDE"
        for member in coll.collection_objects:
            member.light_linking.link_state = state
        obj.light_linking.receiver_collection = coll
    return obj


def spot_power_w(desc: SpotDesc) -> float:
    """Radiant power of a sphere of radius r with surface radiance L: 4 pi^2 r^2 L."""
    return 4.0 * math.pi ** 2 * desc.radius ** 2 * desc.intensity


def build_spot(desc: SpotDesc):
    bpy = _bpy()
    light = bpy.data.lights.new(desc.path, type="SPOT")
    light.energy = spot_power_w(desc)
    light.shadow_soft_size = desc.radius
    light.spot_size = min(max(math.radians(2.0 * desc.cone_angle_deg), 0.01745), math.pi)
    light.spot_blend = min(max(desc.softness, 0.0), 1.0)
    light.color = desc.color
    obj = bpy.data.objects.new(desc.path, light)
    place(obj, desc.matrix)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def configure_render(render: RenderDesc) -> None:
    bpy = _bpy()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.render.resolution_x, scene.render.resolution_y = render.resolution
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    mask_only = "color" not in render.outputs
    scene.cycles.samples = 1 if mask_only else render.samples  # the class mask comes from sample 0
    scene.cycles.use_adaptive_sampling = render.adaptive_threshold > 0 and not mask_only
    if render.adaptive_threshold > 0:
        scene.cycles.adaptive_threshold = render.adaptive_threshold
    scene.cycles.use_denoising = render.denoise and not mask_only
    if render.denoise:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
        scene.cycles.denoising_prefilter = render.denoise_prefilter
        scene.cycles.denoising_quality = render.denoise_quality
        scene.cycles.denoising_use_gpu = False
    scene.cycles.seed = render.seed
    scene.cycles.use_animated_seed = False
    scene.cycles.max_bounces = 0 if mask_only else render.max_bounces
    scene.cycles.diffuse_bounces = min(4, render.max_bounces)
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0  # the default 10 eats ~10% of a 1361 W/m^2 sun
    scene.cycles.film_exposure = render.exposure
    scene.render.film_transparent = False
    if render.threads > 0:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = render.threads
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
    layer.use_pass_z = "depth" in render.outputs


def build_scene(desc: SceneDescription) -> None:
    """Build `desc` into a fresh Blender scene."""
    reset()
    mats = {key: build_material(m) for key, m in desc.materials.items()}
    for mesh in desc.meshes:
        build_mesh(mesh, mats[mesh.material])
    build_camera(desc.camera)
    for sun in desc.suns:
        build_sun(sun)
    if desc.spot is not None:
        build_spot(desc.spot)
    configure_render(desc.render)
    from allo_usd.blender.compositor import build_glare, no_compositor

    if desc.effects.glare:
        build_glare()
    else:
        no_compositor()  # a scene that declares no glare gets no compositor at all
