"""The manifest's est_psnr_db and est_psnr_low_db columns: the render JSON's accuracy.estimated_psnr_db and
lower_psnr_db, each checked as any value of an untrusted JSON is (a finite number in range), empty when the
render made no estimate; a manifest written before the columns reads and re-assembles."""

from __future__ import annotations

import csv
import math

import numpy.testing  # noqa: F401  (scipy, which the dataset loads, imports it lazily, and it runs lscpu)
import pytest

from allo_usd.output.annotations import ACCURACY_COLUMNS, accuracy_columns
from allo_usd.output.dataset import assemble, read_manifest
from allo_usd.output.dataset_files import COLUMNS

from tests.support.renders import edit, fake_render


@pytest.mark.parametrize("accuracy,cell", [
    ({"estimated_psnr_db": 41.25, "stopped_by": "target"}, 41.25), ({"estimated_psnr_db": 38}, 38.0),
    (None, ""), ({}, ""), ({"estimated_psnr_db": None}, ""), ("41", ""), ([41], ""),
    ({"estimated_psnr_db": "41"}, ""), ({"estimated_psnr_db": math.nan}, ""), ({"estimated_psnr_db": math.inf}, ""),
    ({"estimated_psnr_db": 1e308}, ""), ({"estimated_psnr_db": -3.0}, ""), ({"estimated_psnr_db": True}, ""),
    ({"estimated_psnr_db": 10 ** 400}, ""), ({"estimated_psnr_db": {"x": 1}}, ""),
])
def test_the_column_takes_only_a_finite_estimate_in_range(accuracy, cell):
    assert accuracy_columns({"accuracy": accuracy})["est_psnr_db"] == cell
    bound = {"lower_psnr_db": accuracy["estimated_psnr_db"]} if isinstance(accuracy, dict) and accuracy else accuracy
    assert accuracy_columns({"accuracy": bound}) == {"est_psnr_db": "", "est_psnr_low_db": cell}


def test_the_columns_are_the_manifests_last():
    assert ACCURACY_COLUMNS == ("est_psnr_db", "est_psnr_low_db") and COLUMNS[-2:] == ACCURACY_COLUMNS


def test_the_manifest_has_the_estimate_of_each_render_and_an_empty_cell_without(tmp_path):
    renders = tmp_path / "renders"
    fake_render(renders, "d000_p01")
    estimated = fake_render(renders, "d001_p02")
    hostile = fake_render(renders, "d002_p03")
    edit(estimated, lambda m: m.update(accuracy={"mode": "target", "estimated_psnr_db": 40.5, "lower_psnr_db": 39.25}))
    edit(hostile, lambda m: m.update(accuracy={"estimated_psnr_db": "40 dB; DROP TABLE"}))
    out = tmp_path / "ds"
    rows = {r["name"]: r for r in read_manifest(assemble([renders], out))}
    assert {n: r["est_psnr_db"] for n, r in rows.items()} == {"d000_p01": "", "d001_p02": "40.5", "d002_p03": ""}
    assert {n: r["est_psnr_low_db"] for n, r in rows.items()} == {"d000_p01": "", "d001_p02": "39.25", "d002_p03": ""}
    assert "DROP" not in (out / "manifest.csv").read_text()
    # a render that estimated its accuracy since: its row follows on the next assembly
    edit(hostile, lambda m: m.update(accuracy={"estimated_psnr_db": 37.0}))
    assert {r["name"]: r["est_psnr_db"] for r in read_manifest(assemble([renders], out))}["d002_p03"] == "37.0"


def test_a_manifest_from_before_the_column_reads_and_assembles_again(tmp_path):
    renders = tmp_path / "renders"
    fake_render(renders, "d000_p01")
    edit(fake_render(renders, "d001_p02"), lambda m: m.update(accuracy={"estimated_psnr_db": 44.0}))
    out = tmp_path / "ds"
    manifest = assemble([renders], out)
    fresh = manifest.read_bytes()
    with open(manifest, newline="") as f:
        rows = list(csv.DictReader(f))
    with open(manifest, "w", newline="") as f:   # as the code before the column wrote it
        w = csv.DictWriter(f, fieldnames=[c for c in COLUMNS if c != "est_psnr_db"], extrasaction="ignore",
                           lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    assert all(r.get("est_psnr_db") is None for r in read_manifest(manifest))
    assert assemble([renders], out).read_bytes() == fresh
