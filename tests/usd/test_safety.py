"""A layer may only reach files under the allowed roots; Blender never runs scripts from files."""

from __future__ import annotations

import pytest

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.core.errors import LayerError
from allo_usd.usd.read import read_scene
from allo_usd.usd.safety import ENV_ROOTS, allowed_roots

from tests.support.helpers import make_spec


@pytest.fixture
def narrow_roots(tiny_base, monkeypatch):
    """Only the tiny base stage's directory is allowed (plus each layer's own directory)."""
    monkeypatch.setenv(ENV_ROOTS, str(tiny_base.parent))


def test_layer_over_allowed_base_reads(tiny_base, tmp_path, narrow_roots):
    layer = write_scene_layer(make_spec(), tmp_path / "layers" / "s.usda", tiny_base)
    assert read_scene(layer).meta["seed"] == 7
    assert tiny_base.parent.resolve() in allowed_roots(layer)


def test_sublayer_outside_the_roots_is_rejected(tiny_base, tmp_path, narrow_roots):
    outside = tmp_path / "elsewhere" / "extra.usda"
    outside.parent.mkdir()
    outside.write_text("#usda 1.0\n")
    layer = write_scene_layer(make_spec(), tmp_path / "layers" / "s.usda", tiny_base)
    text = layer.read_text().replace("subLayers = [", f"subLayers = [\n        @{outside}@,", 1)
    layer.write_text(text)
    with pytest.raises(LayerError, match="extra.usda resolves outside the allowed roots"):
        read_scene(layer)


def test_asset_attribute_outside_the_roots_is_rejected(tiny_base, tmp_path, narrow_roots):
    texture = tmp_path / "elsewhere" / "secret.png"
    texture.parent.mkdir()
    texture.write_bytes(b"\x89PNG")
    layer = write_scene_layer(make_spec(), tmp_path / "layers" / "s.usda", tiny_base)
    layer.write_text(layer.read_text() + f'\nover "Extra"\n{{\n    asset inputs:file = @{texture}@\n}}\n')
    with pytest.raises(LayerError, match=r"secret.png resolves outside the allowed roots \(.*stages"):
        read_scene(layer)


def test_symlink_out_of_a_root_is_rejected(tiny_base, tmp_path, narrow_roots):
    target = tmp_path / "elsewhere" / "extra.usda"
    target.parent.mkdir()
    target.write_text("#usda 1.0\n")
    layer = write_scene_layer(make_spec(), tmp_path / "layers" / "s.usda", tiny_base)
    (layer.parent / "link.usda").symlink_to(target)
    layer.write_text(layer.read_text().replace("subLayers = [", "subLayers = [\n        @./link.usda@,", 1))
    with pytest.raises(LayerError, match="outside the allowed roots"):
        read_scene(layer)


@pytest.mark.bpy
def test_blender_never_auto_runs_scripts(tmp_path):
    """A .blend whose text block is registered to run on load does not run after build.reset()."""
    import bpy

    from allo_usd.blender.build import reset

    marker = tmp_path / "ran.txt"
    reset()
    text = bpy.data.texts.new("evil.py")
    text.write(f"open({str(marker)!r}, 'w').write('ran')\n")
    text.use_module = True  # "Register": run when the file is loaded, if auto-exec is on
    blend = tmp_path / "evil.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.context.preferences.filepaths.use_scripts_auto_execute = True
    reset()
    assert bpy.context.preferences.filepaths.use_scripts_auto_execute is False
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    assert "evil.py" in bpy.data.texts  # the file loaded ...
    assert not marker.exists()          # ... and its script did not run
    reset()


def test_a_refusal_names_the_file_the_rule_and_the_fix_in_one_short_line(tiny_base, tmp_path, monkeypatch):
    """The refusal listed every root (a tree grants five folders, ALLO_ASSET_ROOTS adds its own): about
    600 characters. Now the first roots and how many more, the file, and the fix."""
    granted = [tmp_path / f"a_granted_asset_folder_{i}" for i in range(6)]
    monkeypatch.setenv(ENV_ROOTS, ":".join(map(str, [tiny_base.parent, *granted])))
    outside = tmp_path / "elsewhere" / "extra.usda"
    outside.parent.mkdir()
    outside.write_text("#usda 1.0\n")
    layer = write_scene_layer(make_spec(), tmp_path / "layers" / "s.usda", tiny_base)
    layer.write_text(layer.read_text().replace("subLayers = [", f"subLayers = [\n        @{outside}@,", 1))
    with pytest.raises(LayerError) as info:
        read_scene(layer)
    message = str(info.value)
    roots = allowed_roots(layer)
    assert len(roots) == 9 and "\n" not in message
    assert f"{layer}: layer {outside} resolves outside the allowed roots ({roots[0]}, {roots[1]} and 7 more); " \
           in message, message
    assert not any(str(r) in message for r in granted), message
    assert message.endswith(f"or add its folder to {ENV_ROOTS}"), message
    assert len(message) < 200 + len(str(layer)) + len(str(outside)) + len(str(roots[0])) + len(str(roots[1])), message
