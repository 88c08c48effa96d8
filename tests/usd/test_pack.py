"""One scene as one file (README, "One scene as one file"; allo_usd.usd.pack): `allo-usd pack LAYER
--out SCENE.usdz` writes the scene and every file it composes as one package, which plain usd-core
opens alone in any folder, and `allo-usd render SCENE.usdz` renders the same bytes as the tree's
layer. A package is one file whose contents are its own: one that reaches outside itself is
refused, and pack never writes over an existing file unless asked, nor through a link."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from pxr import Sdf

from tests.support.helpers import one_line_error as _one_line_error, sandboxed_cli
from allo_usd.core.errors import AlloError, LayerError
from allo_usd.plan.model import Quality, demo_plan
from allo_usd.run.author import author_scene
from allo_usd.usd.dependencies import walk
from allo_usd.usd.pack import check_destination, pack
from allo_usd.usd.read import open_stage, read_scene
from allo_usd.usd.safety import ENV_ROOTS

ROOT = Path(__file__).resolve().parents[2]
SCENE = "s2030_d001_p41_power_drill-red_z0"  # the demo plan's: textures, an anomaly with two variant files
SECRET = "TOPSECRET_4711"


def cli(*args, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return sandboxed_cli(*args, cwd=cwd)


def one_line_error(r: subprocess.CompletedProcess, *words: str) -> str:
    return _one_line_error(r, *words, hidden=SECRET)


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """An anomalous scene of the demo plan, authored into a tree at 64x36 with 2 samples, and its
    package (`allo-usd pack`), moved alone into another folder."""
    root = tmp_path_factory.mktemp("pack")
    plan = demo_plan().model_copy(update={"quality": Quality(preset="demo", resolution=(64, 36), samples=2)})
    layer = author_scene(plan, SCENE, root / "tree")
    r = cli("pack", layer, "--out", root / "made" / f"{SCENE}.usdz")
    assert r.returncode == 0, r.stderr
    assert f"-> {root / 'made' / SCENE}.usdz" in r.stdout and r.stderr == ""
    alone = root / "elsewhere" / f"{SCENE}.usdz"
    alone.parent.mkdir()
    shutil.move(root / "made" / f"{SCENE}.usdz", alone)
    return root, layer, alone


PLAIN_USD = r"""
import json, sys
from pxr import Ar, Sdf, Usd, UsdUtils
path = sys.argv[1]
stage = Usd.Stage.Open(path)
layers, assets, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(path))
outside = [l.realPath for l in stage.GetUsedLayers()
           if not l.anonymous and l.realPath != path and Ar.SplitPackageRelativePathOuter(l.realPath)[0] != path]
textures = []
for prim in stage.TraverseAll():
    for a in prim.GetAttributes():
        if a.GetTypeName() == Sdf.ValueTypeNames.Asset and a.Get() is not None and a.Get().path:
            textures.append(a.Get().resolvedPath)
print(json.dumps({"errors": [str(e) for e in stage.GetCompositionErrors()], "unresolved": list(unresolved),
                  "outside": outside, "textures": textures, "prims": len(list(stage.TraverseAll()))}))
"""


@pytest.mark.slow
def test_a_package_holds_every_file_the_scene_reads_and_opens_alone_in_plain_usd_core(tree):
    root, layer, alone = tree
    # plain usd-core, no allo-usd on the path, in the package's new folder
    r = subprocess.run([sys.executable, "-c", PLAIN_USD, str(alone)], capture_output=True, text=True,
                       cwd=alone.parent, env={k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",
                                                                                               ENV_ROOTS)})
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["errors"] == [] and got["unresolved"] == [] and got["outside"] == [], got
    assert got["prims"] > 100
    assert got["textures"] and all(t.startswith(f"{alone}[") for t in got["textures"]), got["textures"]

    # every layer, asset and texture the render of the tree's layer reads is in the package, and nothing else
    read = walk(layer).files
    zf = Sdf.ZipFile.Open(str(alone))
    names = list(zf.GetFileNames())
    assert len(names) == len(read) and names[0] == f"{SCENE}.usda"
    assert any(n.endswith(".png") for n in names) and sum(n.endswith(".usdc") and "/" in n for n in names) >= 2
    entry_sha = {hashlib.sha256(bytes(zf.GetFile(n))).hexdigest() for n in names if n.endswith(".png")}
    tree_sha = {hashlib.sha256(Path(f).read_bytes()).hexdigest() for f in read if f.endswith(".png")}
    assert entry_sha == tree_sha  # the textures' bytes, as they are

    # the walk of the package lists the package alone; it reads as a scene without any root but its own
    assert walk(alone).files == [os.path.realpath(alone)]
    assert read_scene(alone).render.resolution == (64, 36)

    # the same scene packs to the same bytes (zip timestamps fixed); --force replaces a regular file
    again = root / "again.usdz"
    pack(layer, again)
    pack(layer, again, replace=True)
    assert again.read_bytes() == alone.read_bytes()


@pytest.mark.render
def test_rendering_the_package_gives_the_bytes_of_the_trees_layer(tree):
    root, layer, alone = tree
    r = cli("render", layer, "--out", root / "from_tree", "--device", "cpu")
    assert r.returncode == 0, r.stderr
    r = cli("render", alone, "--out", root / "from_package", "--device", "cpu", cwd=alone.parent)
    assert r.returncode == 0, r.stderr
    for suffix in (".png", ".exr", "_mask.png"):
        a, b = root / "from_tree" / f"{SCENE}{suffix}", root / "from_package" / f"{SCENE}{suffix}"
        assert a.read_bytes() == b.read_bytes(), suffix
    tree_meta = json.loads((root / "from_tree" / f"{SCENE}.json").read_text())
    meta = json.loads((root / "from_package" / f"{SCENE}.json").read_text())
    digest = hashlib.sha256(alone.read_bytes()).hexdigest()
    assert meta["inputs"] == {f"./{SCENE}.usdz": digest}  # the package is the one input
    assert meta["class_pixels"] == tree_meta["class_pixels"] and meta["class_pixels"]["anomaly"] > 0
    assert meta["scene"]["anomaly"] == tree_meta["scene"]["anomaly"]
    # resumable like a layer: a second run skips it (same identity), a changed package renders again
    before = (root / "from_package" / f"{SCENE}.png").stat().st_mtime_ns
    r = cli("render", alone, "--out", root / "from_package", "--device", "cpu")
    assert r.returncode == 0, r.stderr
    assert (root / "from_package" / f"{SCENE}.png").stat().st_mtime_ns == before


def _package(path: Path, text: str, extra: dict | None = None) -> Path:
    """A package written with USD's own zip writer: a root layer `text`, then `extra` entries."""
    path.parent.mkdir(parents=True, exist_ok=True)
    work = path.parent / f"{path.stem}_src"
    work.mkdir(exist_ok=True)
    (work / "scene.usda").write_text(text)
    writer = Sdf.ZipFileWriter.CreateNew(str(path))
    writer.AddFile(str(work / "scene.usda"), "scene.usda")
    for name, data in (extra or {}).items():
        (work / Path(name).name).write_bytes(data)
        writer.AddFile(str(work / Path(name).name), name)
    writer.Save()
    return path


HEAD = '#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Z"\n    subLayers = [\n{subs}    ]\n)\n\n'


@pytest.fixture
def secret(tmp_path):
    """Outside files a package names: a layer and a texture holding SECRET (inside ALLO_ASSET_ROOTS,
    which conftest sets to pytest's temp dir: a package's own walk ignores every root but itself)."""
    d = tmp_path / "outside"
    d.mkdir()
    (d / "secret.usda").write_text(f"#usda 1.0\n{SECRET} = 3\n")
    (d / "secret.png").write_bytes(b"\x89PNG\r\n\x1a\n" + SECRET.encode())
    inner = tmp_path / "other.usdz"
    _package(inner, f"#usda 1.0\n{SECRET} = 3\n")
    return d


@pytest.mark.parametrize("how", ["sublayer", "reference", "texture", "other_package", "relative_up"])
def test_a_package_that_reaches_outside_itself_is_refused(tmp_path, secret, capfd, how):
    outside = secret / "secret.usda"
    subs, body = "", 'def Xform "World"\n{\n}\n'
    if how == "sublayer":
        subs = f"        @{outside}@\n"
    elif how == "reference":
        body += f'def Xform "Hidden" (\n    references = @{outside}@\n)\n{{\n}}\n'
    elif how == "texture":
        body += f'def Shader "Tex"\n{{\n    asset inputs:file = @{secret / "secret.png"}@\n}}\n'
    elif how == "other_package":
        subs = f"        @{tmp_path / 'other.usdz'}[scene.usda]@\n"
    else:
        subs = "        @../outside/secret.usda@\n"  # inside a package, .. stays inside it: an entry it lacks
    package = _package(tmp_path / "pkg" / "evil.usdz", HEAD.format(subs=subs) + body)
    with pytest.raises(LayerError) as info:
        open_stage(package)
    message = str(info.value)
    if how == "relative_up":
        assert "does not compose" in message
    else:
        assert "outside the package" in message or "another package" in message, message
        assert "allo-usd pack" in message
    printed = capfd.readouterr()
    assert SECRET not in message + printed.out + printed.err


@pytest.mark.slow
def test_render_of_a_package_reaching_outside_is_one_line(tmp_path, secret):
    package = _package(tmp_path / "evil.usdz", HEAD.format(subs=f"        @{secret / 'secret.usda'}@\n") +
                       'def Xform "World"\n{\n}\n')
    r = cli("render", package, "--out", tmp_path / "out")
    one_line_error(r, "evil.usdz", "lies outside the package", "allo-usd pack")
    assert not (tmp_path / "out" / "evil.png").exists()


@pytest.mark.slow
def test_a_broken_package_is_one_line_too(tmp_path):
    bad = tmp_path / "bad.usdz"
    bad.write_bytes(b"PK\x03\x04 not really a zip " * 4)
    one_line_error(cli("render", bad, "--out", tmp_path / "out"), "bad.usdz")
    png_first = tmp_path / "png_first.usdz"
    (tmp_path / "img.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    writer = Sdf.ZipFileWriter.CreateNew(str(png_first))
    writer.AddFile(str(tmp_path / "img.png"), "img.png")
    writer.Save()
    with pytest.raises(LayerError, match="first entry of the package, img.png, is not a USD layer"):
        walk(png_first)


def test_pack_refuses_existing_files_links_special_files_and_other_names(tmp_path):
    existing = tmp_path / "old.usdz"
    existing.write_bytes(b"keep me")
    with pytest.raises(AlloError, match="exists; pass --force"):
        check_destination(existing)
    assert check_destination(existing, replace=True) == existing
    target = tmp_path / "target.usdz"
    target.write_bytes(b"keep me too")
    for name, to in (("link.usdz", target), ("dangling.usdz", tmp_path / "nowhere.usdz")):
        (tmp_path / name).symlink_to(to)
        for replace in (False, True):  # a link is never written through, --force or not
            with pytest.raises(AlloError, match="is a symbolic link"):
                check_destination(tmp_path / name, replace)
    (tmp_path / "dir.usdz").mkdir()
    os.mkfifo(tmp_path / "fifo.usdz")
    for special in ("dir.usdz", "fifo.usdz"):
        with pytest.raises(AlloError, match="is not a regular file"):
            check_destination(tmp_path / special, replace=True)
    for wrong in ("scene.usda", "scene.zip", "scene"):
        with pytest.raises(AlloError, match=r"must end in \.usdz"):
            check_destination(tmp_path / wrong)
    assert existing.read_bytes() == b"keep me" and target.read_bytes() == b"keep me too"
    assert not (tmp_path / "nowhere.usdz").exists()


@pytest.mark.slow
def test_pack_command_onto_an_existing_file_or_a_link_is_refused(tree, tmp_path):
    _, layer, _ = tree
    existing = tmp_path / "old.usdz"
    existing.write_bytes(b"keep me")
    one_line_error(cli("pack", layer, "--out", existing), "exists", "--force")
    target = tmp_path / "target.usdz"
    target.write_bytes(b"keep me too")
    (tmp_path / "link.usdz").symlink_to(target)
    one_line_error(cli("pack", layer, "--out", tmp_path / "link.usdz", "--force"), "symbolic link")
    assert existing.read_bytes() == b"keep me" and target.read_bytes() == b"keep me too"
    assert (tmp_path / "link.usdz").is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.usdz", "old.usdz", "target.usdz"]  # no temporary


def test_pack_applies_the_render_gate_before_packing(tiny_base, tmp_path, monkeypatch):
    """A layer reaching outside its roots is refused as the render refuses it; an asset path in
    metadata (which USD's packager would follow and a render never reads) is refused too; nothing
    is written."""
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.usda").write_text(f"#usda 1.0\n{SECRET} = 3\n")
    layer = write_scene_layer(make_spec(), tmp_path / "layers" / "s.usda", tiny_base)
    assert pack(layer, tmp_path / "good.usdz")["files"] == len(walk(layer).files)  # the tiny stage packs

    # an asset path in a prim's metadata, inside the roots (conftest's ALLO_ASSET_ROOTS) or not
    sneaky = layer.with_name("sneaky.usda")
    sneaky.write_text(layer.read_text() + f'\nover "Extra" (\n    assetInfo = {{\n        asset identifier = '
                                          f'@{outside / "secret.usda"}@\n    }}\n)\n{{\n}}\n')
    with pytest.raises(LayerError, match="in its metadata") as info:
        pack(sneaky, tmp_path / "sneaky.usdz")
    assert SECRET not in str(info.value)

    monkeypatch.delenv(ENV_ROOTS, raising=False)  # only what the layer is granted
    evil = tmp_path / "mine" / "evil.usda"
    evil.parent.mkdir()
    evil.write_text(HEAD.format(subs="        @../outside/secret.usda@\n") + 'def Xform "World"\n{\n}\n')
    with pytest.raises(LayerError, match="resolves outside the allowed roots") as info:
        pack(evil, tmp_path / "evil.usdz")
    assert SECRET not in str(info.value)
    assert sorted(p.name for p in tmp_path.glob("*.usdz")) == ["good.usdz"] and not list(tmp_path.glob(".*"))
    with pytest.raises(AlloError, match="already a package"):
        pack(tmp_path / "good.usdz", tmp_path / "twice.usdz")


# ---------------------------------------------------------------- tracebacks turned into one line

def test_an_empty_package_is_refused_by_name_not_by_usds_exception(tmp_path):
    """USD raises (Tf.ErrorException) for a 0-byte .usdz instead of answering "no entries"."""
    empty = tmp_path / "empty.usdz"
    empty.write_bytes(b"")
    with pytest.raises(LayerError, match=r"empty\.usdz is an empty file \(0 bytes\), not a USD package; pack"):
        walk(empty)


@pytest.mark.slow
def test_an_empty_package_is_one_line_in_inspect_render_and_diff(tmp_path):
    empty = tmp_path / "empty.usdz"
    empty.write_bytes(b"")
    for args in (("inspect", empty), ("render", empty, "--out", tmp_path / "out"), ("diff", empty, empty)):
        one_line_error(cli(*args), "empty.usdz", "empty file", "allo-usd pack")


@pytest.mark.parametrize("name", ["a\nb.usdz", "a\tb.usdz", "a\x7fb.usdz", "a\x85b.usdz"])
def test_an_out_path_with_a_control_character_is_refused_naming_it(tmp_path, name):
    """USD refuses control characters in asset paths: the packed temporary could not be opened, and
    the refusal blamed the layer and named the temporary. The refusal names --out, escaped on one
    line, and the rule."""
    with pytest.raises(AlloError) as info:
        check_destination(tmp_path / name)
    message = str(info.value)
    assert "\n" not in message and "\t" not in message
    assert message.startswith(f"--out {tmp_path}/a") and "control characters" in message, message
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_pack_out_with_a_newline_is_one_line_naming_out(tree, tmp_path):
    _, layer, _ = tree
    line = one_line_error(cli("pack", layer, "--out", tmp_path / "a\nb.usdz"), "--out", "a\\nb.usdz",
                          "control characters")
    assert "temporary" not in line and ".usdz." not in line, line  # not the temporary's name
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_pack_onto_a_full_disk_is_one_line_and_leaves_nothing(tree, small_tmpfs):
    """USD's packager reports no failed write: on a full device it left a package cut short, which
    the timestamp fix read as a zip (BadZipFile traceback). Now: exit 2, one line naming --out and
    the fix, no temporary left; the same command packs once there is room."""
    _, layer, _ = tree
    out = small_tmpfs / "scene.usdz"   # the package is ~5.6 MB; the device holds 1 MiB
    line = one_line_error(cli("pack", layer, "--out", out), str(out), "no space left", "free space")
    assert "BadZipFile" not in line
    assert list(small_tmpfs.iterdir()) == []


def test_a_texture_a_package_lacks_is_fixed_by_packing_again(tmp_path):
    """A texture that does not resolve is "restore the asset's textures/ folder" in a tree; in a
    package the package lacks the entry: the fix is to pack the scene again with the texture in."""
    from pxr import Usd

    from allo_usd.usd.read_material import _read_texture

    body = ('def Xform "World"\n{\n}\ndef Shader "Tex"\n{\n    uniform token info:id = "UsdUVTexture"\n'
            '    asset inputs:file = @../outside/tex.png@\n}\n')
    package = _package(tmp_path / "pkg" / "scene.usdz", HEAD.format(subs="") + body)
    stage = Usd.Stage.Open(str(package))
    with pytest.raises(LayerError) as info:
        _read_texture("/M", stage.GetPrimAtPath("/Tex"))
    message = str(info.value)
    assert "is not an entry of the package" in message and str(package) in message, message
    assert "allo-usd pack" in message and "textures/ folder" not in message, message
