"""ARCTIC's 11 objects, generated and written: :func:`make_object` builds one from its
flat-part spec (:mod:`hogsa_world.objects.procedural`: box, laptop, notebook, phone) or its
compound spec (:mod:`hogsa_world.objects.household`: the other seven), and
:func:`write_procedural_objects` writes them in ARCTIC's ``meta/object_vtemplates/`` layout."""

from __future__ import annotations

import functools
from dataclasses import fields
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from hogsa_loader.assets.objects.template import (
    BOTTOM,
    TOP,
    VTEMPLATES_DIR,
    ObjectTemplate,
    bbox_corners,
    farthest_point_sampling,
    max_pairwise_distance,
)
from hogsa_loader.errors import PathLike
from hogsa_world.object_files import write_object_meta, write_object_template
from hogsa_world.objects.compound import merge_pieces
from hogsa_world.objects.household import HOUSEHOLD_SPECS
from hogsa_world.objects.procedural import (
    FLAT_SPECS,
    NUM_MOCAP,
    PROCEDURAL_NAMES,
    ObjectSpec,
    PartMesh,
    build_parts,
    build_textured,
    object_rng,
)

__all__ = ["PROCEDURAL_NAMES", "make_and_write_objects", "make_object", "write_procedural_objects"]


def _part_samples(points_mm: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Keypoints (16 FPS), sub-samples (300 FPS), bbox corners and 5 MoCap markers (mm)."""
    kp = points_mm[farthest_point_sampling(points_mm, 16)]
    sub = points_mm[farthest_point_sampling(points_mm, 300)]
    start = int(rng.integers(0, points_mm.shape[0]))
    mocap = points_mm[farthest_point_sampling(points_mm, NUM_MOCAP, start=start)]
    return {"kp": kp, "sub": sub, "bbox": bbox_corners(points_mm), "mocap": mocap}


def _spec_and_parts(name: str, rng: np.random.Generator) -> tuple[Optional[ObjectSpec], dict[int, PartMesh]]:
    """Painting spec (None for parts that carry their painters) and both part meshes."""
    if name in FLAT_SPECS:
        spec = FLAT_SPECS[name](rng)
        return spec, build_parts(spec)
    compound = HOUSEHOLD_SPECS[name](rng)
    return None, {p: merge_pieces(compound.parts[p]) for p in (TOP, BOTTOM)}


def make_object(name: str, seed: int = 0) -> ObjectTemplate:
    """Generate one procedural textured articulated object.

    Args:
        name: one of :data:`PROCEDURAL_NAMES` (the 11 ARCTIC objects; ``box``,
            ``laptop``, ``notebook`` and ``phone`` here, the others in
            :mod:`hogsa_world.objects.household`).
        seed: colour/photo/print variation; the geometry does not depend on it.

    Returns:
        the template in metres, canonical frame of ARCTIC (hinge = z axis), with a
        textured mesh and a 1024x1024 atlas. The process keeps the objects it made and
        returns the kept one for the same name and seed; its arrays are read-only.
    """
    if name not in PROCEDURAL_NAMES:
        raise KeyError(f"no procedural object {name!r}; known: {list(PROCEDURAL_NAMES)}")
    return _kept_object(name, int(seed))


@functools.lru_cache(maxsize=2 * len(PROCEDURAL_NAMES))  # two seeds' worth: the tests, a demo's worlds
def _kept_object(name: str, seed: int) -> ObjectTemplate:
    template = _make_object(name, seed)
    for f in fields(template):
        value = getattr(template, f.name)
        if isinstance(value, np.ndarray):
            value.setflags(write=False)  # shared by every caller
    return template


def _make_object(name: str, seed: int) -> ObjectTemplate:
    rng = object_rng(name, seed)
    spec, parts = _spec_and_parts(name, rng)

    verts_mm = np.concatenate([parts[TOP].verts, parts[BOTTOM].verts])
    faces = np.concatenate([parts[TOP].faces, parts[BOTTOM].faces + parts[TOP].verts.shape[0]])
    labels = np.concatenate([np.full(parts[TOP].verts.shape[0], TOP), np.full(parts[BOTTOM].verts.shape[0], BOTTOM)])
    samples = {p: _part_samples(parts[p].verts, rng) for p in (TOP, BOTTOM)}
    tex = build_textured(spec, parts)
    m = 1e-3
    return ObjectTemplate(
        name=name,
        verts=verts_mm * m,
        faces=faces,
        parts=labels,
        kp_top=samples[TOP]["kp"] * m,
        kp_bottom=samples[BOTTOM]["kp"] * m,
        bbox_top=samples[TOP]["bbox"] * m,
        bbox_bottom=samples[BOTTOM]["bbox"] * m,
        mocap_top=samples[TOP]["mocap"] * m,
        mocap_bottom=samples[BOTTOM]["mocap"] * m,
        sub_top=samples[TOP]["sub"] * m,
        sub_bottom=samples[BOTTOM]["sub"] * m,
        diameter=max_pairwise_distance(verts_mm) * m,
        tex_verts=tex["verts"] * m,
        tex_faces=tex["faces"],
        tex_uv=tex["uv"],
        texture=tex["image"],
        tex_parts=tex["parts"],
    )


def make_and_write_objects(meta_dir: PathLike, names: Iterable[str], seed: int = 0) -> list[ObjectTemplate]:
    """:func:`write_procedural_objects`, returning the templates written (in memory)."""
    meta_dir = Path(meta_dir)
    templates = [make_object(n, seed=seed) for n in names]
    for t in templates:
        write_object_template(t, meta_dir / VTEMPLATES_DIR / t.name)
    write_object_meta(meta_dir, templates)
    return templates


def write_procedural_objects(
    meta_dir: PathLike, names: Iterable[str] = ("box", "laptop", "notebook"), seed: int = 0
) -> list[str]:
    """Generate objects and write them as ``meta_dir/object_vtemplates/<name>/``.

    Also writes (or updates) ``meta_dir/object_meta.json`` with each diameter in metres.

    Args:
        meta_dir: ARCTIC-style ``meta`` folder (created).
        names: objects to generate (see :data:`PROCEDURAL_NAMES`).
        seed: variation seed (same seed -> byte-identical files).

    Returns:
        the names written, in order.
    """
    return [t.name for t in make_and_write_objects(meta_dir, names, seed)]
