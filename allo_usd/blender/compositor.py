"""Lens glare through the Blender 5.0 compositor, built only for scenes that declare it.

In 5.0 the compositor is a node group on `scene.compositing_node_group` (there is no
`scene.node_tree`), its output is a Group Output node, and the Glare node's options are input
sockets. With compositing on, the multilayer EXR gains a `Composite.Combined` layer beside the
render layer's own `Combined`; the renderer reads the composite when one was built.
"""

from __future__ import annotations

GLARE = {"Type": "Fog Glow", "Quality": "High", "Threshold": 1.0, "Strength": 0.6, "Size": 0.7}


def build_glare(params: dict = GLARE):
    import bpy

    scene = bpy.context.scene
    tree = bpy.data.node_groups.new("Compositor", "CompositorNodeTree")
    layers = tree.nodes.new("CompositorNodeRLayers")
    glare = tree.nodes.new("CompositorNodeGlare")
    for name, value in params.items():
        glare.inputs[name].default_value = value
    out = tree.nodes.new("NodeGroupOutput")
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    tree.links.new(layers.outputs["Image"], glare.inputs["Image"])
    tree.links.new(glare.outputs["Image"], out.inputs[0])
    scene.compositing_node_group = tree
    scene.render.use_compositing = True
    return tree


def no_compositor() -> None:
    import bpy

    scene = bpy.context.scene
    scene.compositing_node_group = None
    scene.render.use_compositing = False


def has_compositor() -> bool:
    import bpy

    return bpy.context.scene.compositing_node_group is not None
