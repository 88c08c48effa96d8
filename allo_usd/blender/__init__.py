"""SceneDescription -> Blender scene -> Cycles arrays. Uses bpy only; never imports pxr."""
