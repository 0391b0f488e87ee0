"""Atomic writes never follow a link another user planted in an output folder: temporary files
have unguessable names and are created exclusively, and every writer goes through them."""

from __future__ import annotations

import json
import os
import uuid

import numpy as np
import pytest

from hogsa_loader.io.atomic import atomic_write, atomic_write_json


@pytest.fixture
def victim(tmp_path):
    """A file of another user's that a planted link points to."""
    path = tmp_path / "victim.txt"
    path.write_text("precious")
    return path


def _plant(link, victim):
    link.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(victim, link)


def test_a_link_at_the_temporary_name_is_not_followed(tmp_path, victim, monkeypatch):
    fixed = uuid.UUID(int=7)
    monkeypatch.setattr(uuid, "uuid4", lambda: fixed)  # as if the name had been guessed
    target = tmp_path / "out" / "index.json"
    _plant(target.with_name(f".{target.name}.{os.getpid()}.{fixed.hex}.tmp"), victim)
    with pytest.raises(FileExistsError):
        atomic_write(target, b"new")
    assert victim.read_text() == "precious" and not target.exists()


def test_a_link_at_the_target_is_replaced_not_written_through(tmp_path, victim):
    target = tmp_path / "out" / "index.json"
    _plant(target, victim)
    atomic_write_json(target, {"a": 1})
    assert victim.read_text() == "precious"
    assert not target.is_symlink() and json.loads(target.read_text()) == {"a": 1}


def test_temporary_names_are_unguessable(tmp_path, monkeypatch):
    from hogsa_loader.io import atomic

    names = {atomic._temp_name(tmp_path / "f.json").name for _ in range(3)}
    assert len(names) == 3 and all(len(n.split(".")[-2]) == 32 for n in names)  # 128 random bits each


@pytest.mark.parametrize("writer", ["world_record", "processed_split", "export_index", "stage_record"])
def test_writers_ignore_links_at_the_old_guessable_names(tmp_path, victim, writer):
    """Each writer that once used a fixed temporary name (``X.tmp``, ``.X.tmp.<pid>``) writes
    its file and leaves a link planted at that name, and its target, alone."""
    out = tmp_path / "out"
    if writer == "world_record":
        from hogsa_world.writer import _write_json_atomic

        target = out / ".hogsa_world_partial.json"
        _plant(target.with_name(target.name + ".tmp"), victim)
        _write_json_atomic(target, {"sequences": []})
        assert json.loads(target.read_text()) == {"sequences": []}
    elif writer == "processed_split":
        from hogsa_loader.assets.arctic_processing import _save_npy_atomic
        from hogsa_loader.io.npy import read_npy

        target = out / "p1_train.npy"
        _plant(target.with_name(target.name + ".tmp"), victim)
        _save_npy_atomic(target, {"data_dict": {}})
        assert read_npy(target) == {"data_dict": {}}
    elif writer == "export_index":
        from hogsa_loader.sample.export.writer import _atomic_write_json

        target = out / "index.json"
        _plant(target.with_name(f".{target.name}.tmp.{os.getpid()}"), victim)
        _atomic_write_json(target, {"complete": False, "x": np.int64(3)})
        assert json.loads(target.read_text()) == {"complete": False, "x": 3}
    else:
        from hogsa_loader.train.stages import StageRecords

        stages = StageRecords(out, say=lambda m: None)
        _plant(out / "stages" / "s.json.tmp", victim)
        assert stages.run("s", "k1", [], lambda: {"ok": 1}) == {"ok": 1}
        assert json.loads((out / "stages" / "s.json").read_text())["result"] == {"ok": 1}
    assert victim.read_text() == "precious"
