"""Bounds shared by plans, authoring and the reader, so nothing authors what cannot render."""

from __future__ import annotations


# The largest image a scene may ask for: per side, and in all (8192 x 4608 fits; 8192 x 8192 would take
# about 1 GB per pass). One bound for plans, authoring and the reader, so nothing authors what cannot render.
MAX_SIDE_PX = 8192


MAX_PIXELS = 40_000_000

# The smallest side Blender renders (RenderSettings.resolution_x/_y hard minimum; a smaller one is
# silently rendered at 4 px). tests/usd/test_reader_bounds.py checks it against bpy.
MIN_SIDE_PX = 4


def resolution_problem(width: int, height: int) -> str | None:
    """Why (width, height) is not a renderable image size, or None if it is."""
    if not (MIN_SIDE_PX <= width <= MAX_SIDE_PX and MIN_SIDE_PX <= height <= MAX_SIDE_PX) or width * height > MAX_PIXELS:
        return (f"resolution {width}x{height} is outside {MIN_SIDE_PX}..{MAX_SIDE_PX} per side or above {MAX_PIXELS:,} "
                "pixels in all; choose a real image size, e.g. 1920x1080")
    return None
