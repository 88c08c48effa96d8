"""Everything that touches pxr: schema, prim layout, the allo: attribute table, authoring, reading, inspect/diff, sandbox.

Which module holds what (pxr is imported inside functions, so importing a module loads no USD):

Shared vocabulary (layout, attributes and description import no pxr; blender/ may use them)
    schema          explicit registration of the codeless Allo*API schema
    layout          prim paths of the base stage and scene layers
    attributes      every allo: attribute's name and Sdf value type, once
    description     the plain, frozen SceneDescription that crosses from read (pxr) to blender (bpy)

Authoring
    asset           a plain Asset as a USD asset: a .usda interface over .usdc geometry
    base_stage      the base stage: station, bodies, camera rig, inspection light, render settings
    build_stage     a complete base stage from the procedural station or a real model file
    stage_geometry  what a base stage offers authoring before any scene layer exists: the rig's
                    poses and lens, triangles for ray casting, the station's joints
    scene_layer     a SceneSpec as the opinions of a layer (sky, pose and scene prims), and
                    write_scene_layer: one self-contained scene layer over the base stage
    compose         the authored tree: shared sky and camera-sample layers, small scene layers over them
    usda_writer     a layer's opinions (Prim lists) as its .usda text, Sdf's byte for byte, written atomically
    hazard          a plan's own hazard files converted into anomaly assets inside the authored tree

Reading
    sniff           cheap looks at a layer file: is it a scene layer, what its render costs, which
                    passes it orders (resume checks); pxr loaded once with Ctrl-C held back
    dependencies    every file a composition reads, checked before USD opens any of them (walk)
    safety          the roots a scene layer may reach, and the composed stage checked against them
    read            what a scene layer says: open_stage, the gate, then one reader per prim type
                    into a SceneDescription (read_scene)
    reader_bounds   what the reader lets through (the bounds table) and the checks that hold a layer to it

Tools
    inspect         describe and diff scene layers from the USD alone
    pack            one scene and every file its composition reads as one .usdz package
"""
