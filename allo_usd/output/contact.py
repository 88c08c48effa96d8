"""Contact sheets of an assembled dataset: one or more per split, large enough to see an anomaly.

A sheet shows up to PER_SHEET images in COLUMNS columns, each tile TILE_MIN to TILE_MAX pixels
wide (the image's own width within those bounds: a 1920x1080 render is halved, a tiny test
render enlarged pixel for pixel), so an anomaly covering 0.1% of a 1920x1080 image (about 45x45
pixels) is still about 22x22 pixels on the sheet. Each anomaly is outlined in OUTLINE (a ring
just outside its mask, so its own pixels stay visible) and boxed with a margin, so a small one
is found at a glance; the image itself is not tinted. Anomalies come first, then normal images,
each under its index, scene name (wrapped, never cut) and folder. A split with more images than
`limit` is sampled evenly; its sheets are CATEGORY_SPLIT.png, CATEGORY_SPLIT_2.png, ...
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from allo_usd.output.writers import write_png

TILE_MIN, TILE_MAX = 480, 960   # tile width in pixels
COLUMNS, PER_SHEET = 3, 12
OUTLINE = (255, 0, 255)         # magenta: not a colour of space, the station, its foil or the bodies
ANOMALY = 2                     # the anomaly class of a 3-class mask (0 background, 1 station and bodies)
BACKGROUND, TEXT, PAD = (24, 24, 24), (225, 225, 225), 8


def font(size: int = 18):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def label_lines(text: str, width: float, draw) -> list[str]:
    """`text` in lines no wider than `width` pixels, broken after '_' or '-' where possible (a
    part wider than a line is broken anywhere); joined, the lines give back the whole text."""
    parts = [c for part in re.findall(r"[^_-]+[_-]?|[_-]", text)
             for c in ([part] if draw.textlength(part) <= width else list(part))]
    lines = [""]
    for part in parts:
        if lines[-1] and draw.textlength(lines[-1] + part) > width:
            lines.append(part)
        else:
            lines[-1] += part
    return lines


def read_pixels(path: Path, mode: str | None = None) -> np.ndarray:
    """An image file's pixels (the file closed again)."""
    with Image.open(path) as im:
        return np.asarray(im.convert(mode) if mode else im)


def tile_size(width: int, height: int) -> tuple[int, int]:
    tile_w = min(max(width, TILE_MIN), TILE_MAX)
    return tile_w, max(1, round(tile_w * height / width))


def outlined(rgb: np.ndarray, anomaly: np.ndarray, size: tuple[int, int]) -> Image.Image:
    """The image at `size` with the anomaly (a boolean mask) ringed and boxed in OUTLINE. The mask
    is scaled with a box filter and any covered pixel kept, so a tiny anomaly never vanishes."""
    from allo_usd.core.interrupts import import_held

    binary_dilation = import_held("scipy.ndimage").binary_dilation   # numpy's C API as it loads: Ctrl-C held

    tile = Image.fromarray(rgb).resize(size, Image.Resampling.LANCZOS if size[0] < rgb.shape[1]
                                       else Image.Resampling.NEAREST)
    if not anomaly.any():
        return tile
    m = np.asarray(Image.fromarray(anomaly.astype(np.uint8) * 255).resize(size, Image.Resampling.BOX)) > 0
    pixels = np.array(tile)
    pixels[binary_dilation(m, iterations=2) & ~m] = OUTLINE
    tile = Image.fromarray(pixels)
    ys, xs = np.nonzero(m)
    margin = 12
    ImageDraw.Draw(tile).rectangle((xs.min() - margin, ys.min() - margin, xs.max() + margin, ys.max() + margin),
                                   outline=OUTLINE, width=2)
    return tile


def sample(rows: list[dict], limit: int) -> list[dict]:
    """Anomalies first (by folder, then index), then normal images; evenly sampled down to `limit`."""
    rows = sorted(rows, key=lambda r: (r["kind"] != "anomaly", r["image"]))
    if len(rows) > limit:
        rows = [rows[i] for i in np.linspace(0, len(rows) - 1, limit).round().astype(int)]
    return rows


def sheet_paths(folder: Path, category: str, split: str, pages: int) -> list[Path]:
    return [folder / f"{category}_{split}{'' if p == 0 else f'_{p + 1}'}.png" for p in range(pages)]


def split_sheets(out: Path, rows: list[dict], folder: Path, category: str, split: str, limit: int = 48,
                 per_sheet: int = PER_SHEET) -> list[Path]:
    """Draw the sheets of one split (rows: manifest rows with paths relative to `out`) into
    `folder`; earlier pages of this category and split beyond the new count are removed."""
    picked = sample(rows, limit)
    pages = [picked[i:i + per_sheet] for i in range(0, len(picked), per_sheet)]
    paths = sheet_paths(folder, category, split, len(pages))
    for n, (page, path) in enumerate(zip(pages, paths), 1):
        header = (f"{category} / {split}: page {n} of {len(pages)}, {len(picked)} of {len(rows)} images"
                  + (" (evenly sampled)" if len(picked) < len(rows) else "")
                  + "; anomalies outlined and boxed in magenta")
        draw_sheet(out, page, path, header)
    stale = re.compile(rf"^{re.escape(category)}_{split}(?:_\d+)?\.png$")
    for old in folder.glob(f"{category}_{split}*.png"):
        if stale.match(old.name) and old not in paths:
            old.unlink(missing_ok=True)
    return paths


def draw_sheet(out: Path, rows: list[dict], path: Path, header: str) -> Path:
    height, width = read_pixels(out / rows[0]["image"]).shape[:2]
    tile_w, tile_h = tile_size(width, height)
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    measure.font = font()  # label_lines measures with it
    line_h = measure.textbbox((0, 0), "Ag_")[3] + 4
    labels = [_label(r, tile_w, measure) for r in rows]
    label_h = line_h * max(map(len, labels)) + 2
    cols = min(COLUMNS, len(rows))
    nrows = -(-len(rows) // cols)
    top = line_h + 2 * PAD
    sheet = Image.new("RGB", (cols * (tile_w + PAD) + PAD, top + nrows * (tile_h + label_h + PAD) + PAD), BACKGROUND)
    draw = ImageDraw.Draw(sheet)
    draw.font = measure.font
    draw.text((PAD, PAD), header, fill=TEXT)
    for i, (r, lines) in enumerate(zip(rows, labels)):
        x, y = PAD + (i % cols) * (tile_w + PAD), top + (i // cols) * (tile_h + label_h + PAD)
        rgb = read_pixels(out / r["image"], "RGB")
        anomaly = read_pixels(out / r["allo_mask"]) == ANOMALY if r["kind"] == "anomaly" else np.zeros(1, bool)
        sheet.paste(outlined(rgb, anomaly, (tile_w, tile_h)), (x, y + label_h))
        colour = OUTLINE if r["kind"] == "anomaly" else TEXT
        for k, line in enumerate(lines):
            draw.text((x, y + k * line_h), line, fill=colour)
    return write_png(path, np.asarray(sheet))


def _label(row: dict, width: int, measure) -> list[str]:
    """The tile's label: index and whole scene name (wrapped), then its folder (and anomaly share)."""
    folder = Path(row["image"]).parent.name
    share = f", anomaly {float(row['anomaly_fraction']):.3%} of the image" if row["kind"] == "anomaly" else ""
    return label_lines(f"{int(row['index']):06d}_{row['name']}", width, measure) + [f"{folder}{share}"]
