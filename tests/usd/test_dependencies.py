"""Every file a layer's composition reads is checked before USD opens it (allo_usd.usd.dependencies):
allowed roots, regular file, bounded size, layer extension; a refused file's content is never echoed."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from allo_usd.core.errors import LayerError
from allo_usd.usd.dependencies import MAX_LAYER_BYTES, walk
from allo_usd.usd.read import read_scene
from allo_usd.usd.safety import ENV_ROOTS, allowed_roots
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

SECRET = "TOPSECRET_4711"
SECRET_LAYER = f"#usda 1.0\n{SECRET} = 3\n"  # USD's parse error quotes that line: it must never be parsed


@pytest.fixture
def narrow_roots(tiny_base, monkeypatch):
    """Only the tiny base stage's directory is allowed (plus each layer's own directory)."""
    monkeypatch.setenv(ENV_ROOTS, str(tiny_base.parent))


@pytest.fixture
def layer(tiny_base, tmp_path, narrow_roots):
    return write_scene_layer(make_spec(), tmp_path / "layers" / "s.usda", tiny_base)


def add_sublayer(layer, target: str) -> None:
    layer.write_text(layer.read_text().replace("subLayers = [", f"subLayers = [\n        @{target}@,", 1))


def refused(layer, match: str, capfd) -> str:
    """read_scene refuses the layer with `match`; neither the message nor anything USD printed
    holds the secret."""
    with pytest.raises(LayerError, match=match) as info:
        read_scene(layer)
    printed = capfd.readouterr()
    assert SECRET not in str(info.value) and SECRET not in printed.out + printed.err
    return str(info.value)


def test_outside_sublayer_is_refused_before_usd_reads_it(layer, tmp_path, capfd):
    secret = tmp_path / "outside" / "secret.usda"
    secret.parent.mkdir()
    secret.write_text(SECRET_LAYER)
    add_sublayer(layer, "../outside/secret.usda")
    message = refused(layer, r"layer .*outside/secret.usda resolves outside the allowed roots", capfd)
    assert message.startswith(str(layer))


@pytest.mark.parametrize("how", ["sublayer", "reference", "texture"])
def test_path_expressions_are_refused_before_usd_evaluates_them(layer, tmp_path, capfd, how):
    """USD evaluates `"${D}/secret.usda"` when it opens the stage, after any check of the text:
    the walk refuses variable expressions in every kind of path."""
    secret = tmp_path / "outside" / "secret.usda"
    secret.parent.mkdir()
    secret.write_text(SECRET_LAYER)
    text = layer.read_text().replace("subLayers = [", 'expressionVariables = {\n        string D = "../outside"\n'
                                     "    }\n    subLayers = [", 1)
    expression = '`"${D}/secret.usda"`'
    if how == "sublayer":
        text = text.replace("subLayers = [", f"subLayers = [\n        @{expression}@,", 1)
    elif how == "reference":
        text += f'\nover "Hidden" (\n    references = @{expression}@\n)\n{{\n}}\n'
    else:
        text += f'\nover "Hidden"\n{{\n    asset inputs:file = @{expression}@\n}}\n'
    layer.write_text(text)
    refused(layer, "is a variable expression, which allo-usd does not follow", capfd)


@pytest.mark.parametrize("target", ["/etc/passwd", "/proc/self/environ", "/dev/zero"])
def test_symlinks_to_system_files_are_refused(layer, target, capfd):
    (layer.parent / "link.usda").symlink_to(target)
    add_sublayer(layer, "./link.usda")
    refused(layer, r"link.usda resolves outside the allowed roots", capfd)


def test_reference_inside_a_variant_is_checked_too(layer, tmp_path, capfd):
    secret = tmp_path / "outside" / "secret.usda"
    secret.parent.mkdir()
    secret.write_text(SECRET_LAYER)
    layer.write_text(layer.read_text() + '\nover "Hidden" (\n    variants = { string v = "a" }\n'
                     '    prepend variantSets = "v"\n)\n{\n    variantSet "v" = {\n        "a" (\n'
                     '            references = @../outside/secret.usda@\n        ) {\n        }\n    }\n}\n')
    refused(layer, "secret.usda resolves outside the allowed roots", capfd)


def test_texture_in_a_variant_outside_the_roots_is_refused(layer, tmp_path, capfd):
    texture = tmp_path / "outside" / "photo.png"
    texture.parent.mkdir()
    texture.write_bytes(b"\x89PNG" + SECRET.encode())
    layer.write_text(layer.read_text() + '\nover "Hidden" (\n    variants = { string v = "a" }\n'
                     '    prepend variantSets = "v"\n)\n{\n    variantSet "v" = {\n        "a" {\n'
                     f'            asset inputs:file = @{texture}@\n        }}\n    }}\n}}\n')
    refused(layer, r"asset /Hidden\{v=a\}.inputs:file = .*photo.png resolves outside the allowed roots", capfd)


def test_oversized_sublayer_is_refused_unread(layer, capfd):
    big = layer.parent / "big.usda"
    with open(big, "wb") as f:  # sparse: no disk used, but a reader would allocate all of it
        f.truncate(MAX_LAYER_BYTES + 1)
    add_sublayer(layer, "./big.usda")
    refused(layer, rf"big.usda is too big \({MAX_LAYER_BYTES + 1:,} bytes > 256 MiB allowed\)", capfd)


def test_non_layer_file_as_sublayer_is_refused(layer, capfd):
    (layer.parent / "notes.txt").write_text(SECRET)
    add_sublayer(layer, "./notes.txt")
    refused(layer, r"notes.txt is not a USD layer \(its name must end in .usda", capfd)


@pytest.mark.process
def test_fifo_inside_the_roots_is_refused_without_opening_it(layer):
    """A FIFO would block USD's read forever: the walk only stats it. (A child process, so a
    regression shows as a timeout instead of a hung test run.)"""
    os.mkfifo(layer.parent / "pipe.usda")
    add_sublayer(layer, "./pipe.usda")
    code = ("from allo_usd.usd.read import read_scene\nfrom allo_usd.core.errors import LayerError\n"
            f"try:\n    read_scene({str(layer)!r})\nexcept LayerError as e:\n    print(e)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, ENV_ROOTS: os.environ[ENV_ROOTS]})
    assert "pipe.usda is not a regular file (a directory, FIFO, device or socket)" in r.stdout, r.stdout + r.stderr


def test_a_cached_walk_still_checks_a_file_that_changed(layer, tmp_path, capfd):
    (layer.parent / "extra.usda").write_text("#usda 1.0\n")
    add_sublayer(layer, "./extra.usda")
    first = walk(layer)
    assert str(layer.parent / "extra.usda") in first.files
    again = walk(layer)
    assert again.files == first.files and again.layers == []  # cached: nothing opened twice
    del first, again  # close the layers they opened
    secret = tmp_path / "outside" / "secret.usda"
    secret.parent.mkdir()
    secret.write_text(SECRET_LAYER)
    (layer.parent / "extra.usda").unlink()
    (layer.parent / "extra.usda").symlink_to(secret)  # the scene layer itself did not change
    refused(layer, "extra.usda resolves outside the allowed roots", capfd)


def test_syntax_error_keeps_usds_file_line_col(layer):
    bad = layer.parent / "bad.usda"
    bad.write_text('#usda 1.0\ndef Xform "World" {\n    double3 xformOp:translate = (1, 2\n}\n')
    add_sublayer(layer, "./bad.usda")
    with pytest.raises(LayerError, match=r"bad\.usda:4:1: "):
        read_scene(layer)
    layer.write_text(layer.read_text() + "\ndef Xform (\n")  # the scene layer itself
    with pytest.raises(LayerError, match=r"s\.usda:\d+:\d+: ") as info:
        read_scene(layer)
    assert "pxrInternal" not in str(info.value)


@pytest.mark.slow
def test_walk_lists_every_file_an_authored_scene_reads(tmp_path, monkeypatch):
    """Root first, then its stack (pose, sky, base stage), the base stage's layers and textures,
    and the anomaly asset with its variants' geometry."""
    from allo_usd.plan.model import demo_plan
    from allo_usd.run.author import author_plan

    monkeypatch.delenv(ENV_ROOTS)
    layers = author_plan(demo_plan(), tmp_path / "tree", limit=8, progress=False)
    scene = next(p for p in layers if "anomaly" in p.parts)
    files = [os.path.relpath(f, tmp_path / "tree") for f in walk(scene).files]
    assert files[0] == str(scene.relative_to(tmp_path / "tree"))
    assert files[1].startswith("poses/") and files[2].startswith("sky/") and files[3] == "stages/base.usda"
    assert "stages/station/textures/module_skin.png" in files and "stages/bodies/textures/moon_albedo.png" in files
    assert any(f.startswith("stages/anomalies/") and f.endswith(".usdc") for f in files)
    assert len(files) == len(set(files))


def test_a_plan_toml_makes_a_root_only_for_its_own_scenes(tmp_path, monkeypatch):
    """~/plan.toml must not make ~ a root for ~/Downloads/x.usda; a tree's scenes get their tree."""
    monkeypatch.delenv(ENV_ROOTS)
    home = tmp_path / "home"
    (home / "Downloads").mkdir(parents=True)
    (home / "plan.toml").write_text("")
    photo = home / "Private" / "photo.png"
    photo.parent.mkdir()
    photo.write_bytes(b"\x89PNG")
    layer = home / "Downloads" / "x.usda"
    layer.write_text('#usda 1.0\nover "World"\n{\n    asset inputs:file = @../Private/photo.png@\n}\n')
    assert home.resolve() not in allowed_roots(layer)
    with pytest.raises(LayerError, match="photo.png resolves outside the allowed roots"):
        walk(layer)
    tree = tmp_path / "tree"
    scene = tree / "scenes" / "train" / "normal" / "a.usda"
    scene.parent.mkdir(parents=True)
    (tree / "plan.toml").write_text("")
    roots = allowed_roots(scene)
    assert all((tree / d).resolve() in roots for d in ("scenes", "sky", "poses", "stages"))
    assert tree.resolve() not in roots  # only its authored folders: not tree/private/secret.usda
    secret = tree / "private" / "secret.usda"
    secret.parent.mkdir()
    secret.write_text("#usda 1.0\n")
    scene.write_text('#usda 1.0\n(\n    subLayers = [@../../../private/secret.usda@]\n)\n')
    with pytest.raises(LayerError, match="secret.usda resolves outside the allowed roots"):
        walk(scene)
    sky_roots = allowed_roots(tree / "sky" / "d000.usda")  # not in scenes/: its own folder only
    assert tree.resolve() not in sky_roots and (tree / "scenes").resolve() not in sky_roots
