"""Stored preprocessed parts (`pipe data preprocess`, data.prepared=): read back bit for bit as computed, and
refused by name when made with other settings or from another version of the dataset."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_DOMAIN, compose_config

from pipe.cli import main as pipe_cli
from pipe.data.prepared import MANIFEST, PreprocessSettings, prepare_domain, write_prepared
from pipe.data.slices import SLICE_SIZE
from pipe.errors import PipeError

SETTINGS = PreprocessSettings(points=128, cloud_seed=0, rate_hz=50.0, steady_samples=1)


@pytest.fixture
def tiny_copy(tiny_data, tmp_path):
    """The tiny dataset's four D-subs, in a folder the test may change."""
    return Path(shutil.copytree(tiny_data, tmp_path / "data"))


def configs():
    cfg = compose_config(["experiment=smoke", "paths.output_dir=unused", *TINY_DOMAIN])
    return cfg.data, cfg.domain


def assert_same_parts(computed, read):
    for split in ("train", "val", "test"):
        assert [p.name for p in computed.splits[split]] == [p.name for p in read.splits[split]]
        for a, b in zip(computed.splits[split], read.splits[split]):
            assert a.cloud.points.dtype == b.cloud.points.dtype == np.float32
            np.testing.assert_array_equal(a.cloud.points, b.cloud.points)
            np.testing.assert_array_equal(a.cloud.centre, b.cloud.centre)
            assert (a.cloud.centre_method, a.cloud.mesh) == (b.cloud.centre_method, b.cloud.mesh)
            assert a.cloud.slices.shape == (SLICE_SIZE,) and np.isfinite(a.cloud.slices).all()
            np.testing.assert_array_equal(a.cloud.slices, b.cloud.slices)
            assert len(a.profiles) == len(b.profiles) > 0
            for x, y in zip(a.profiles, b.profiles):
                for field in ("time", "depth", "force", "force_clean"):
                    np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
            for x, y in zip(a.static_curves, b.static_curves):
                np.testing.assert_array_equal(x.depth, y.depth)
                np.testing.assert_array_equal(x.force, y.force)


def test_stored_parts_read_back_as_computed(tiny_copy, tmp_path):
    data_cfg, domain_cfg = configs()
    assert PreprocessSettings.from_config(data_cfg) == SETTINGS
    assert write_prepared(tiny_copy, tmp_path / "prepared", SETTINGS) == sorted(
        p.name for p in (tiny_copy / "parts").iterdir())
    assert_same_parts(prepare_domain(tiny_copy, data_cfg, domain_cfg),
                      prepare_domain(tiny_copy, data_cfg, domain_cfg, tmp_path / "prepared"))


def test_the_folder_is_the_same_wherever_the_dataset_lies(tiny_copy, tmp_path):
    """DVC hashes the folder: a checkout elsewhere, or a later run, must not make the stages after it run again."""
    moved = Path(shutil.copytree(tiny_copy, tmp_path / "elsewhere" / "data"))
    write_prepared(tiny_copy, tmp_path / "a", SETTINGS)
    time.sleep(2.1)                                             # zip members carry a time to the 2 s
    write_prepared(moved, tmp_path / "b", SETTINGS)
    folders = [tmp_path / "a", tmp_path / "b"]
    files = [sorted(p.relative_to(f) for p in f.rglob("*") if p.is_file()) for f in folders]
    assert files[0] == files[1]
    assert all((folders[0] / f).read_bytes() == (folders[1] / f).read_bytes() for f in files[0])


def test_the_command_writes_what_training_reads(tiny_copy, tmp_path, capsys):
    data_cfg, domain_cfg = configs()
    out = tmp_path / "prepared"
    assert pipe_cli(["data", "preprocess", str(tiny_copy), str(out), "--points", "128", "--rate-hz", "50"]) == 0
    assert "data.prepared=" in capsys.readouterr().out
    assert_same_parts(prepare_domain(tiny_copy, data_cfg, domain_cfg),
                      prepare_domain(tiny_copy, data_cfg, domain_cfg, out))
    assert pipe_cli(["data", "preprocess", str(tiny_copy), str(out)]) == 0   # train.py's defaults: 1024 points
    with pytest.raises(PipeError, match="'points': 1024"):
        prepare_domain(tiny_copy, data_cfg, domain_cfg, out)


@pytest.mark.parametrize("change, message", [
    (lambda cfg, data: cfg.__setitem__("points", 64), "was preprocessed with"),
    (lambda cfg, data: (data / "parts" / "vga" / "note.txt").write_text("a new file"),
     "another version of the dataset"),
])
def test_a_stale_folder_is_refused_by_name(tiny_copy, tmp_path, change, message):
    data_cfg, domain_cfg = configs()
    write_prepared(tiny_copy, tmp_path / "prepared", SETTINGS)
    change(data_cfg, tiny_copy)
    with pytest.raises(PipeError, match=message) as error:
        prepare_domain(tiny_copy, data_cfg, domain_cfg, tmp_path / "prepared")
    assert MANIFEST in str(error.value) and "pipe data preprocess" in str(error.value)


@pytest.mark.parametrize("earlier", [1, 2])
def test_a_folder_of_an_earlier_format_is_refused_by_name(tiny_copy, tmp_path, earlier):
    """Format 1 had no mesh slices, format 2 cut a face lying in a slice's plane on whichever side rounding put
    it: such a folder is made again, never read with the slices missing or cut the old way."""
    data_cfg, domain_cfg = configs()
    write_prepared(tiny_copy, tmp_path / "prepared", SETTINGS)
    manifest = tmp_path / "prepared" / MANIFEST
    manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "format": earlier}))
    with pytest.raises(PipeError, match=f"was written in format {earlier} of prepared parts, this version of pipe "
                                        "reads format 3; preprocess again: pipe data preprocess"):
        prepare_domain(tiny_copy, data_cfg, domain_cfg, tmp_path / "prepared")


def test_a_missing_folder_or_part_is_refused_and_a_failed_write_keeps_the_old_folder(tiny_copy, tmp_path,
                                                                                       monkeypatch):
    data_cfg, domain_cfg = configs()
    with pytest.raises(PipeError, match=f"without {MANIFEST}"):
        prepare_domain(tiny_copy, data_cfg, domain_cfg, tmp_path / "nothing")
    out = tmp_path / "prepared"
    write_prepared(tiny_copy, out, SETTINGS)
    (out / "parts" / "dsub26.npz").unlink()
    with pytest.raises(PipeError, match="dsub26.npz"):
        prepare_domain(tiny_copy, data_cfg, domain_cfg, out)
    before = sorted(p.name for p in (out / "parts").iterdir())
    import pipe.data.prepared as prepared

    monkeypatch.setattr(prepared, "prepare_part", lambda *a: (_ for _ in ()).throw(RuntimeError("broken mesh")))
    with pytest.raises(RuntimeError, match="broken mesh"):
        write_prepared(tiny_copy, out, replace(SETTINGS, points=64))
    assert sorted(p.name for p in (out / "parts").iterdir()) == before       # the earlier folder, whole
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "mine.txt").write_text("not preprocessed parts")
    with pytest.raises(PipeError, match="is not a folder of preprocessed parts"):
        write_prepared(tiny_copy, tmp_path / "other", SETTINGS)
