"""``generate_world``: write a complete ARCTIC-format world with rendered images."""

from __future__ import annotations

import json
import multiprocessing
import os
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional

import cv2
import numpy as np
import torch
from tqdm import tqdm

from hogsa_loader.assets.arctic_processing import write_processed_splits
from hogsa_loader.assets.conventions import EGO_IMAGE_SIZE, MASK_IDS
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects.template import load_object_template, read_object_meta
from hogsa_loader.errors import PathLike
from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.io.images import write_image
from hogsa_loader.io.locks import writer_lock
from hogsa_loader.render import raster_kernels
from hogsa_loader.render.mesh_raster import warm_up_kernels
from hogsa_loader.system import available_cores, can_fork, run_forked
from hogsa_world.cameras import AlloRig, allocentric_rig, ego_calibration, ego_trajectory
from hogsa_world.decimation import write_decimation_files
from hogsa_world.grasp import HandKit, fit_part_boxes
from hogsa_world.hand import GENERATOR_VERSION, synthetic_hand_pair
from hogsa_world.mano_pickle import write_mano_pickle
from hogsa_world.motion import build_motion
from hogsa_world.objects.catalogue import PROCEDURAL_NAMES, make_and_write_objects
from hogsa_world.presets import SequencePlan, WorldPreset
from hogsa_world.preview import write_world_preview
from hogsa_world.quality import sequence_quality
from hogsa_world.scene_render import (
    HAND_BASE_SKIN,
    SubjectRenderer,
    crop_boxes,
    foreground,
    object_meshes,
    pose_sequence,
)
from hogsa_world.stage import build_stage
from hogsa_world.stand_ins import add_split_stand_ins, smplx_raw
from hogsa_world.stand_ins import record as stand_in_record
from hogsa_world.subjects import make_subject

if TYPE_CHECKING:
    from hogsa_world.subjects import Subject

__all__ = ["SCHEMA_VERSION", "GENERATOR", "generate_world", "WORLD_META", "MASK_DIR"]

SCHEMA_VERSION = 1
GENERATOR = "hogsa-world/1"
WORLD_META = "hogsa_world.json"
MASK_DIR = "masks"
HAND_MODEL_SEED = 0  # one fixed hand model per world, as ARCTIC has one MANO


def _rng(seed: int, *names: str) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF] + [zlib.crc32(n.encode()) for n in names])


def _write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n", encoding="utf-8")


def _same_world(record: dict, fingerprint: dict) -> bool:
    return all(record.get(k) == v for k, v in fingerprint.items())


def _write_json_atomic(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode("utf-8"))


def _read_json_or_none(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _save_npy(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        np.save(fh, obj, allow_pickle=True)


def _mat_list(a: np.ndarray) -> list:
    return [[float(x) for x in row] for row in a]


def _egocam_dict(R: np.ndarray, T: np.ndarray, K: np.ndarray, dist8: np.ndarray, rng: np.random.Generator) -> dict:
    """The ``.egocam.dist.npy`` dict (float32), with plausible marker/mount placeholders."""
    markers = rng.normal(0, 0.04, size=(4, 3)) + np.array([0.0, -0.06, 0.02])
    return {
        "R_k_cam_np": R.astype(np.float32),
        "T_k_cam_np": T.astype(np.float32),
        "intrinsics": K.astype(np.float32),
        "dist8": dist8.astype(np.float32),
        "ego_markers.ref": markers.astype(np.float32),
        "ego_markers.label": [f"ego_{i}" for i in range(4)],
        "R0": np.eye(3, dtype=np.float32),
        "T0": np.zeros((3, 1), np.float32),
    }


@dataclass
class _Job:
    """One sequence to render: its subject, plan and stored annotations (as written)."""

    subject: "Subject"
    plan: SequencePlan
    mano: dict
    obj_params: np.ndarray
    ego: dict


def _write_assets(root: Path, preset: WorldPreset, seed: int) -> tuple[dict, dict, list]:
    """MANO pickles, object templates (+ object_meta.json), decimation maps; returns what
    was written, re-read.

    Returns:
        (models side -> ManoModelData, templates of the preset's objects name ->
        ObjectTemplate, stage MeshParts).
    """
    mano_dir = root / "body_models" / "mano"
    meta = root / "arctic_data" / "data" / "meta"
    right, left = synthetic_hand_pair(seed=HAND_MODEL_SEED)
    write_mano_pickle(right, mano_dir / "MANO_RIGHT.pkl")
    write_mano_pickle(left, mano_dir / "MANO_LEFT.pkl")
    models = {side: load_mano(mano_dir, side=side) for side in ("right", "left")}
    every_object = make_and_write_objects(meta, PROCEDURAL_NAMES, seed=seed)  # ARCTIC opens all 11
    write_decimation_files(meta, models, {t.name: t for t in every_object})
    obj_meta = read_object_meta(meta / "object_meta.json")
    templates = {n: load_object_template(meta / "object_vtemplates" / n, object_meta=obj_meta) for n in preset.objects}
    return models, templates, build_stage(_rng(seed, "stage"))


def _write_annotations(data: Path, preset: WorldPreset, seed: int, kits: dict, templates: dict) -> tuple[list, list]:
    """Subjects, cameras and motion -> raw_seqs, misc.json, splits_json.

    Returns:
        (subjects, jobs) with the annotations exactly as stored (float32 arrays).
    """
    F = preset.num_frames
    misc, subjects, jobs = {}, [], []
    for si, plan in enumerate(preset.subjects):
        subj = make_subject(plan.sid, plan.split, seed, first=(si == 0))
        subjects.append(subj)
        rig = allocentric_rig(_rng(seed, "allocentric-rig"), _rng(seed, plan.sid, "calibration"))
        ego_K, ego_dist = ego_calibration(_rng(seed, plan.sid, "ego-calibration"))
        misc[plan.sid] = {
            "world2cam": [_mat_list(m) for m in rig.world2cam],
            "intris_mat": [_mat_list(m) for m in rig.K],
            "image_size": [list(EGO_IMAGE_SIZE)] + [[int(w), int(h)] for (w, h) in rig.sizes],
            "ioi_offset": int(subj.ioi_offset),
            "gender": subj.gender,
        }
        for seq in plan.sequences:
            rng = _rng(seed, plan.sid, seq.name)
            motion = build_motion(
                F,
                seq.object,
                seq.action,
                templates[seq.object],
                kits,
                subj.betas,
                rng,
                grasp_iters=preset.grasp_iters,
                grasp_style=preset.grasp_style,
                style_rng=_rng(seed, plan.sid, seq.name, "grasp-style"),
            )
            R_ego, T_ego = ego_trajectory(F, rng, motion.focus)
            mano = {side: motion.hands[side] for side in ("right", "left")}
            obj_params = motion.object_params.astype(np.float32)
            ego = _egocam_dict(R_ego, T_ego, ego_K, ego_dist, rng)
            base = data / "raw_seqs" / plan.sid
            _save_npy(base / f"{seq.name}.mano.npy", mano)
            _save_npy(base / f"{seq.name}.object.npy", obj_params)
            _save_npy(base / f"{seq.name}.egocam.dist.npy", ego)
            _save_npy(base / f"{seq.name}.smplx.npy", smplx_raw(F))
            jobs.append(_Job(subj, seq, mano, obj_params, ego))
    _write_json(data / "meta" / "misc.json", misc)
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    for s, plan in zip(subjects, preset.subjects):
        splits[s.split].extend(f"{s.sid}/{q.name}" for q in plan.sequences)
    for p in ("p1", "p2"):
        _write_json(data / "splits_json" / f"protocol_{p}.json", splits)
    return subjects, jobs


PARTIAL_RECORD = ".hogsa_world_partial.json"


def _partial_fingerprint(preset: WorldPreset, seed: int) -> dict:
    """What a partly rendered world must match to be resumed: generators, preset and seed."""
    digest = zlib.crc32(repr(preset).encode("utf-8"))
    return {
        "generator": GENERATOR,
        "hand_generator": GENERATOR_VERSION,
        "preset": preset.name,
        "preset_crc32": int(digest),
        "seed": int(seed),
    }


def _sequence_finished(data: Path, preset: WorldPreset, job, recorded: frozenset) -> bool:
    """True when ``job`` is recorded as finished by this world's partial record and its last
    image and mask decode (files are written frame by frame, views 0..8, image before mask)."""
    sid, name = job.subject.sid, job.plan.name
    if f"{sid}/{name}" not in recorded:
        return False
    stem = f"{preset.num_frames - 1 + job.subject.ioi_offset:05d}"
    last_mask = data / MASK_DIR / sid / name / "8" / f"{stem}.png"
    last_image = data / "cropped_images" / sid / name / "8" / f"{stem}.jpg"
    return (
        last_mask.is_file()
        and last_image.is_file()
        and cv2.imread(str(last_mask), cv2.IMREAD_UNCHANGED) is not None
        and cv2.imread(str(last_image)) is not None
    )


def _render(
    data: Path,
    preset: WorldPreset,
    jobs: list,
    models: dict,
    kits: dict,
    templates: dict,
    stage: list,
    progress: bool,
    finished: frozenset = frozenset(),
    on_finished: Optional[Callable[[str], None]] = None,
    workers: int = 1,
) -> list[dict]:
    """Render every frame and view of every job (but the ``(sid, sequence)`` pairs in
    ``finished``, already on disk; ``on_finished("sid/seq")`` after each rendered one), one
    sequence per task on ``workers`` processes; returns per-sequence records with quality."""

    F, size = preset.num_frames, preset.cropped_size
    misc = json.loads((data / "meta" / "misc.json").read_text())
    layers = {side: kits[side].layer for side in ("right", "left")}
    hand_faces = {side: torch.as_tensor(models[side].faces) for side in ("right", "left")}
    bar = tqdm(
        total=len(jobs) * F * 9, desc="hogsa world", unit="img", disable=not progress, smoothing=0.05, mininterval=2.0
    )
    records, tasks = [], []
    for sid in dict.fromkeys(j.subject.sid for j in jobs):
        mine = [j for j in jobs if j.subject.sid == sid]
        m = misc[sid]
        rig = AlloRig(
            world2cam=np.array(m["world2cam"]),
            K=np.array(m["intris_mat"]),
            sizes=[tuple(x) for x in m["image_size"][1:]],
        )
        posed = [pose_sequence(layers, j.mano, j.obj_params, templates[j.plan.object]) for j in mine]
        boxes = [crop_boxes(rig, p.obj_mesh, size) for p in posed]  # (8, F, 3) each
        # the static background is rendered at the pixel density of this subject's densest crop
        density = np.max([size / (1.5 * 200 * b[..., 2]) for b in boxes], axis=(0, 2))
        tone = np.clip(np.asarray(mine[0].subject.skin_rgb) / HAND_BASE_SKIN, 0.2, 1.3)
        colors = {
            side: torch.as_tensor(np.clip(models[side].vertex_colors * tone, 0, 1), dtype=torch.float32)
            for side in ("right", "left")
        }
        for job, p, bb in zip(mine, posed, boxes, strict=True):
            if (sid, job.plan.name) in finished:
                bar.update(F * 9)
            else:
                tasks.append(_RenderTask(job, p, bb, density, rig, mine[0].ego, colors))
            quality = sequence_quality(
                p.joints,
                {k: v.numpy() for k, v in p.hands.items()},
                job.obj_params.astype(np.float64),
                fit_part_boxes(templates[job.plan.object]),
            )
            records.append(
                {
                    "sid": sid,
                    "seq": job.plan.name,
                    "object": job.plan.object,
                    "action": job.plan.action,
                    "split": job.subject.split,
                    "num_frames": F,
                    "quality": quality,
                }
            )
    shared = _RenderShared(data, preset, tasks, stage, hand_faces, templates)
    done = on_finished or (lambda name: None)
    if workers <= 1 or len(tasks) <= 1 or not can_fork():
        renderers: dict = {}
        for task in tasks:
            bar.set_postfix_str(task.name)
            done(_render_task(shared, task, bar, renderers))
    else:
        _render_in_processes(shared, min(workers, len(tasks)), bar, done)
    bar.close()
    return records


@dataclass
class _RenderTask:
    """One sequence to render, with what its subject's renderer needs."""

    job: "_Job"
    posed: object
    boxes: np.ndarray
    density: np.ndarray
    rig: object
    ego: dict
    colors: dict

    @property
    def name(self) -> str:
        return f"{self.job.subject.sid}/{self.job.plan.name}"


@dataclass
class _RenderShared:
    """What every render task reads (inherited by forked render processes)."""

    data: Path
    preset: WorldPreset
    tasks: list
    stage: list
    hand_faces: dict
    templates: dict


def _render_task(shared: _RenderShared, task: _RenderTask, bar, renderers: dict) -> str:
    """Render one sequence with its subject's renderer (kept in ``renderers``, one subject at
    a time: its stage backgrounds are rendered once); returns ``sid/seq``."""
    sid = task.job.subject.sid
    renderer = renderers.get(sid)
    if renderer is None:
        renderers.clear()
        renderer = renderers[sid] = SubjectRenderer(
            task.rig,
            task.ego["intrinsics"].astype(np.float64),
            task.ego["dist8"].astype(np.float64),
            shared.stage,
            shared.hand_faces,
            task.colors,
            shared.preset.cropped_size,
            shared.preset.ego_image_scale,
            shared.preset.supersample,
        )
    _render_sequence(
        shared.data,
        shared.preset,
        task.job,
        task.posed,
        task.boxes,
        task.density,
        renderer,
        shared.templates[task.job.plan.object],
        bar,
    )
    return task.name


_SHARED: Optional[_RenderShared] = None  # set in the parent before the render processes fork
_COUNTER = None  # images rendered, shared by the render processes
_RENDERERS: dict = {}  # a render process's subject renderer


class _CountingBar:
    """The ``update`` of a progress bar, counted in shared memory for the parent's bar."""

    def __init__(self, counter) -> None:
        self.counter = counter

    def update(self, n: int = 1) -> None:
        with self.counter.get_lock():
            self.counter.value += n


def _process_init(counter) -> None:
    global _COUNTER
    _COUNTER = counter
    _RENDERERS.clear()


def _process_task(i: int) -> str:
    assert _SHARED is not None
    return _render_task(_SHARED, _SHARED.tasks[i], _CountingBar(_COUNTER), _RENDERERS)


def _render_in_processes(shared: _RenderShared, workers: int, bar, done: Callable[[str], None]) -> None:
    """Render ``shared.tasks`` on ``workers`` forked processes (one torch thread each), calling
    ``done`` in the parent for every sequence that finishes
    (:func:`hogsa_loader.system.run_forked`: on an error the others are stopped; a resumed
    run renders their sequences again)."""
    global _SHARED
    warm_up_kernels()  # the processes inherit the compiled kernels
    counter = multiprocessing.get_context("fork").Value("q", 0)
    start = bar.n
    _SHARED = shared
    try:
        run_forked(
            _process_task,
            [()] * len(shared.tasks),
            workers,
            on_result=lambda i, name: done(name),
            initializer=_process_init,
            initargs=(counter,),
            poll=lambda: bar.update(start + counter.value - bar.n),
        )
    finally:
        _SHARED = None
    bar.update(start + counter.value - bar.n)


def _render_sequence(
    data: Path, preset: WorldPreset, job: _Job, posed, boxes: np.ndarray, density: np.ndarray, renderer, template, bar
) -> None:
    """Write the cropped images and masks of one sequence (all frames, views 0..8)."""
    sid, name = job.subject.sid, job.plan.name
    meshes = object_meshes(template)
    dirs = {}
    for v in range(9):
        dirs[v] = (data / "cropped_images" / sid / name / str(v), data / MASK_DIR / sid / name / str(v))
        for d in dirs[v]:
            d.mkdir(parents=True, exist_ok=True)
    w2e = np.zeros((preset.num_frames, 4, 4))
    w2e[:, :3, :3] = job.ego["R_k_cam_np"]
    w2e[:, :3, 3] = job.ego["T_k_cam_np"][..., 0]
    w2e[:, 3, 3] = 1.0
    for i in range(preset.num_frames):
        stem = f"{i + job.subject.ioi_offset:05d}"
        fg = foreground(posed, i, renderer.hand_faces, renderer.hand_colors, meshes)
        for v in range(9):
            if v == 0:
                rgb, mask = renderer.render_ego(w2e[i], fg)
            else:
                rgb, mask = renderer.render_allo(v, boxes[v - 1, i], fg, float(density[v - 1]))
            # a failed write raises (naming the file), so the sequence is never recorded finished
            jpeg = [cv2.IMWRITE_JPEG_QUALITY, preset.jpeg_quality]
            write_image(dirs[v][0] / f"{stem}.jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), jpeg, durable=False)
            write_image(dirs[v][1] / f"{stem}.png", mask, [cv2.IMWRITE_PNG_COMPRESSION, 3], durable=False)
            bar.update()


def _default_workers() -> int:
    """Render processes by default: one per CPU core this process may use (at most 8) where
    forking is safe (:func:`hogsa_loader.system.can_fork`); else 1."""
    return max(1, min(8, available_cores())) if can_fork() else 1


class _Progress:
    """The partial record ``out/.hogsa_world_partial.json`` of a world being written: its
    fingerprint and the sequences finished so far."""

    def __init__(self, root: Path, preset: WorldPreset, seed: int, resume: bool) -> None:
        self.path = root / PARTIAL_RECORD
        fingerprint = _partial_fingerprint(preset, seed)
        old = _read_json_or_none(self.path) if resume and self.path.is_file() else None
        done = sorted(old.get("finished", [])) if isinstance(old, dict) and _same_world(old, fingerprint) else []
        self.recorded = frozenset(done)
        self.record = {**fingerprint, "finished": done}
        _write_json_atomic(self.path, self.record)

    def mark_finished(self, name: str) -> None:
        """Record ``sid/seq`` as rendered."""
        self.record["finished"] = sorted({*self.record["finished"], name})
        _write_json_atomic(self.path, self.record)

    def keep(self, data: Path, preset: WorldPreset, jobs: list) -> frozenset:
        """The ``(sid, seq)`` pairs recorded as finished whose files are complete (recorded anew)."""
        finished = frozenset(
            (j.subject.sid, j.plan.name) for j in jobs if _sequence_finished(data, preset, j, self.recorded)
        )
        self.record["finished"] = sorted(f"{sid}/{name}" for sid, name in finished)
        _write_json_atomic(self.path, self.record)
        return finished


def _world_record(preset: WorldPreset, seed: int, subjects: list, records: list[dict]) -> dict:
    """The ``hogsa_world.json`` content (``timings`` left empty)."""
    return {
        "schema_version": SCHEMA_VERSION,
        "generator": GENERATOR,
        "preset": preset.name,
        "seed": int(seed),
        "num_frames": preset.num_frames,
        "cropped_size": preset.cropped_size,
        "ego_image_scale": preset.ego_image_scale,
        "grasp_style": preset.grasp_style,
        "ego_image_size": list(EGO_IMAGE_SIZE),
        "ego_cropped_size": list(preset.ego_size),
        "mask_dir": MASK_DIR,
        "mask_ids": dict(MASK_IDS),
        "rendered_frames": "all",
        # shading of the two backends differs by float rounding (a uint8 level on rare pixels)
        "mesh_rasteriser": "numba" if raster_kernels.AVAILABLE else "torch",
        "hand_model_seed": HAND_MODEL_SEED,
        "subjects": [s.to_json() for s in subjects],
        "sequences": records,
        "object_templates": list(PROCEDURAL_NAMES),
        **stand_in_record(),
        "timings": {},
    }


def _write_extras(
    root: Path, preset: WorldPreset, preview: bool, process_splits: bool, progress: bool, timings: dict[str, float]
) -> None:
    """``world_preview.png`` and ARCTIC's processed ``splits/`` (each when asked; the test split
    when the preset has a test subject), timed into ``timings``."""
    if preview:
        t0 = time.perf_counter()
        write_world_preview(root, root / "world_preview.png", frames=preset.preview_frames)
        timings["preview_s"] = time.perf_counter() - t0
    if process_splits:
        t0 = time.perf_counter()
        splits = ("train", "val", "test") if any(s.split == "test" for s in preset.subjects) else ("train", "val")
        written = write_processed_splits(root, protocols=("p1", "p2"), splits=splits, progress=progress)
        add_split_stand_ins(written.values())
        timings["splits_s"] = time.perf_counter() - t0


def _write_inputs(
    root: Path, data: Path, preset: WorldPreset, seed: int, timings: dict[str, float], say: Callable[[str], None]
) -> tuple[dict, dict, dict, list, list, list]:
    """Write the assets, then the motion and annotations; time both into ``timings``.

    Returns:
        (models, kits, templates, stage, subjects, jobs): the outputs of :func:`_write_assets`,
        one :class:`HandKit` per side, and the outputs of :func:`_write_annotations`.
    """
    t0 = time.perf_counter()
    models, templates, stage = _write_assets(root, preset, seed)
    kits = {side: HandKit(m) for side, m in models.items()}
    timings["assets_s"] = time.perf_counter() - t0
    say(f"assets written ({timings['assets_s']:.1f} s)")

    t0 = time.perf_counter()
    subjects, jobs = _write_annotations(data, preset, seed, kits, templates)
    timings["motion_s"] = time.perf_counter() - t0
    say(f"motion and annotations written ({timings['motion_s']:.1f} s)")
    return models, kits, templates, stage, subjects, jobs


def generate_world(
    out: PathLike,
    preset: WorldPreset,
    seed: int = 0,
    progress: bool = True,
    process_splits: bool = True,
    preview: bool = True,
    log: Optional[Callable[[str], None]] = None,
    resume: bool = False,
    workers: Optional[int] = None,
) -> dict:
    """Generate a world: ARCTIC's ``./data`` tree with rendered images.

    Layout written under ``out``::

        body_models/mano/MANO_{RIGHT,LEFT}.pkl          the synthetic MANO-schema hands
        arctic_data/data/meta/misc.json                 per-subject cameras, sizes, ioi_offset, gender
        arctic_data/data/meta/object_meta.json, object_vtemplates/<obj>/...   all 11 ARCTIC objects
        arctic_data/data/meta/mano_decimator_195.npy, downsamplers.npy        decimation maps
        arctic_data/data/meta/hogsa_world.json          generator record (sizes, mask ids, stand-ins, timings)
        arctic_data/data/raw_seqs/<sid>/<seq>.{mano,object,egocam.dist,smplx}.npy
        arctic_data/data/splits_json/protocol_p{1,2}.json
        arctic_data/data/cropped_images/<sid>/<seq>/<view>/<frame:05d>.jpg
        arctic_data/data/masks/<sid>/<seq>/<view>/<frame:05d>.png
        arctic_data/data/splits/<p>_<split>.npy         (ARCTIC processing, from the files above)
        world_preview.png

    The same seed gives byte-identical files (``hogsa_world.json`` differs only in
    ``timings``): named random streams, ``np.save``, sorted JSON, fixed OpenCV settings. All 11
    ARCTIC object templates are written (ARCTIC's ``ObjectTensors`` opens them all). SMPL-X
    fields are NaN stand-ins (:mod:`hogsa_world.stand_ins`).

    Args:
        out: output folder (ARCTIC's ``./data``); created.
        preset: sizes and content.
        seed: world seed.
        progress: tqdm progress bars; log: optional line printer.
        process_splits: run ARCTIC's processing into ``splits/`` at the end.
        preview: write ``world_preview.png``.
        resume: keep the sequences that an interrupted call on ``out`` with the same preset,
            seed and generators finished (recorded in ``out/.hogsa_world_partial.json`` while
            a world is written; kept when their last image and mask decode). Annotations,
            splits and the preview are always rewritten.
        workers: processes rendering sequences side by side (forked, one torch thread each;
            the files are the same for any count). Default: one per usable CPU core, at most
            8, on Linux; 1 elsewhere (forking is not safe there).

    Returns:
        the ``hogsa_world.json`` content.
    """
    say = log or (lambda s: None)
    root = Path(os.path.abspath(out))
    root.mkdir(parents=True, exist_ok=True)
    with writer_lock(root, ".hogsa_world.lock", what="hogsa world"):  # two writers of one world: refused
        return _generate(root, preset, seed, resume, workers, progress, preview, process_splits, say)


def _generate(root: Path, preset, seed, resume, workers, progress, preview, process_splits, say) -> dict:
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    data = root / "arctic_data" / "data"
    partial = _Progress(root, preset, seed, resume)

    models, kits, templates, stage, subjects, jobs = _write_inputs(root, data, preset, seed, timings, say)
    finished = partial.keep(data, preset, jobs)
    if finished:
        say(f"resuming: {len(finished)} of {len(jobs)} sequences already rendered")
    t0 = time.perf_counter()
    if workers is None:
        workers = _default_workers()
    records = _render(
        data, preset, jobs, models, kits, templates, stage, progress, finished, partial.mark_finished, workers=workers
    )
    timings["render_s"] = time.perf_counter() - t0

    record = _world_record(preset, seed, subjects, records)
    _write_json(data / "meta" / WORLD_META, record)  # read by the processing and the preview
    _write_extras(root, preset, preview, process_splits, progress, timings)
    timings["total_s"] = time.perf_counter() - t_start
    record["timings"] = {k: round(v, 2) for k, v in timings.items()}
    _write_json(data / "meta" / WORLD_META, record)
    partial.path.unlink()
    return record
