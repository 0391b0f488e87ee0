"""Fuzz every reader of untrusted files: only typed errors, in bounded time and memory.

Each target mutates one valid file of a generated world, bundle, run or export in a scratch
copy and runs the library's reader on it. Mutations are drawn by hypothesis: bytes
(truncated, bit-flipped, spliced, zeroed), structure (a field replaced by random JSON or a
random array, deleted, or a shared-reference container bomb). A case passes when the reader
accepts the file or refuses it with :class:`~hogsa_loader.errors.AssetError` (and, for a
run folder, the documented ``ValueError`` of settings that differ); any other exception is
a failure, recorded with its message.

Targets: ``mano_pickle`` (``load_mano``), ``arctic_raw`` (``raw_seqs/*.npy`` through
``ArcticRoot.sequence``), ``arctic_misc`` (``meta/misc.json``), ``arctic_split``
(``splits/*.npy`` through ``load_split``), ``h2o_text`` (every H2O text parser),
``bundle`` (the bundle's ``manifest.json`` and its other files through ``load_bundle``),
``part_checkpoint`` (a HOGS part's ``manifest.json`` / ``tensors.safetensors`` through
``load_part``), ``run_folder`` (a training run's ``config.json`` / ``latest.json`` through
``latest_checkpoint``) and ``shard`` (an export's tar shards and index files through
``SynthShardDataset``), ``npy_sparse`` (a world's ``meta/downsamplers.npy``, sparse maps
with crafted index arrays, through ``read_npy``).

Usage::

    python tests/robustness/fuzz_readers.py --out runs/fuzz                      # 1000 cases per reader
    python tests/robustness/fuzz_readers.py --out /tmp/fz --cases 50 --targets mano_pickle,shard

Writes ``fuzz.json`` and ``fuzz.md`` in ``--out``: per reader the cases, how many were
accepted / refused / failed, the median and worst time per case and the worst traced
allocation peak per case (``tracemalloc``: Python and NumPy allocations).
"""

from __future__ import annotations

import argparse
import copy
import io
import json
import pickle
import resource
import shutil
import sys
import time
import tracemalloc
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
from hypothesis import HealthCheck, given, reject, settings
from hypothesis import seed as hypothesis_seed
from hypothesis import strategies as st
from hypothesis.errors import UnsatisfiedAssumption

from hogsa_loader.errors import AssetError
from hogsa_world.mano_pickle import release_pickle_bytes, write_mano_pickle

#: Random JSON documents (the values a hostile manifest may hold).
JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=6),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=4), children, max_size=4),
    max_leaves=10,
)


# --------------------------------------------------------------------------------------
# Mutations
# --------------------------------------------------------------------------------------

#: What the current case did (for the report of its slowest and failing cases).
TRACE: list[str] = []


def note(msg: str) -> None:
    TRACE.append(msg[:200])


def mutate_bytes(draw: Callable, raw: bytes) -> bytes:
    """Truncate, flip bits in, splice junk into, zero a run of, or repeat a slice of ``raw``."""
    b = bytearray(raw)
    if not b:
        note("bytes of an empty file replaced by junk")
        return draw(st.binary(min_size=1, max_size=32))
    mode = draw(st.sampled_from(["truncate", "flip", "splice", "zero", "repeat"]))
    i = draw(st.integers(0, max(0, len(b) - 1)))
    note(f"bytes {mode} at {i} of {len(b)}")
    if mode == "truncate":
        return bytes(b[:i])
    if mode == "flip":  # distinct positions: every flip changes the file
        for j in draw(st.sets(st.integers(0, len(b) - 1), min_size=1, max_size=8)):
            b[j] ^= draw(st.integers(1, 255))
        return bytes(b)
    if mode == "splice":
        return bytes(b[:i] + draw(st.binary(min_size=1, max_size=32)) + b[i:])
    if mode == "zero":
        n = draw(st.integers(1, 64))
        b[i : i + n] = bytes(len(b[i : i + n]))
        return bytes(b)
    n = draw(st.integers(1, 64))
    return bytes(b[: i + n] + b[i:])


def crafted_sparse(draw: Callable, mat: Any) -> Any:
    """A copy of the sparse matrix ``mat`` whose stored arrays or shape no longer agree: indices
    out of range (huge, negative), a decreasing or shortened ``indptr``, lengths that differ,
    a wrong dtype or an absurd shape. scipy does not check these on pickling, and its compiled
    routines write out of bounds on some of them."""
    m = mat.copy()
    field = draw(st.sampled_from(["indices", "indptr", "data", "shape"]))
    mode = draw(st.sampled_from(["huge", "negative", "reverse", "truncate", "float"]))
    note(f"sparse {field} {mode}")
    if field == "shape":
        m._shape = draw(st.sampled_from([(2**31, 2**31), (-1, 5), (m.shape[0], 1), (1, m.shape[1]), (0, 0)]))
        return m
    a = getattr(m, field)
    if mode == "huge":
        a[: draw(st.integers(1, max(1, len(a))))] = draw(st.sampled_from([2**30, 2**31 - 1, 10**6]))
    elif mode == "negative":
        a[draw(st.integers(0, max(0, len(a) - 1)))] = -draw(st.integers(1, 2**30))
    elif mode == "reverse":
        setattr(m, field, a[::-1].copy())
    elif mode == "truncate":
        setattr(m, field, a[: draw(st.integers(0, max(0, len(a) - 1)))].copy())
    else:
        setattr(m, field, a.astype(np.float64))
    return m


def random_array(draw: Callable) -> Any:
    """An array of a random shape and dtype, possibly holding nan / inf / huge values."""
    shape = tuple(draw(st.lists(st.integers(0, 6), max_size=4)))
    dtype = draw(st.sampled_from(["float32", "float64", "int64", "uint8", "bool", "complex64", "U3", "object"]))
    if dtype == "object":
        return np.array([None] * int(np.prod(shape, dtype=np.int64)), dtype=object)
    a = np.zeros(shape, dtype=dtype)
    if a.size and dtype.startswith("float"):
        a.reshape(-1)[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf, 1e300]))
    return a


def container_bomb(draw: Callable) -> Any:
    """A nested container whose levels share one reference: tiny when pickled, up to 10^18
    elements when expanded."""
    kind = draw(st.sampled_from([list, tuple, dict]))
    x: Any = [0.5]
    for _ in range(draw(st.integers(2, 6))):
        w = draw(st.integers(2, 1000))
        x = {str(i): x for i in range(w)} if kind is dict else kind([x] * w)
    return x


def junk(draw: Callable, bombs: bool = True) -> Any:
    """A value to put where a field was: random JSON, a random array or a container bomb."""
    choices = ["json", "array", "bomb"] if bombs else ["json", "array"]
    kind = draw(st.sampled_from(choices))
    value = draw(JSON_VALUES) if kind == "json" else random_array(draw) if kind == "array" else container_bomb(draw)
    note(f"junk {kind}: {_describe(value)}")
    return value


def _describe(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"array {value.dtype} {value.shape}"
    if isinstance(value, (list, tuple, dict)):
        widths = []
        while isinstance(value, (list, tuple, dict)) and value and len(widths) < 8:
            widths.append(len(value))
            value = next(iter(value.values())) if isinstance(value, dict) else value[0]
        return f"nested {'x'.join(map(str, widths))}"
    return repr(value)[:60]


def mutate_tree(draw: Callable, doc: Any, bombs: bool = True, json_only: bool = False) -> Any:
    """``doc`` (nested dicts / lists / arrays) with 1-3 nodes replaced by junk or deleted."""
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, 3))):
        if not isinstance(doc, (dict, list)) or not doc or draw(st.integers(0, 9)) == 0:
            return draw(JSON_VALUES) if json_only else junk(draw, bombs)
        node = doc
        while True:
            keys = list(node) if isinstance(node, dict) else list(range(len(node)))
            if not keys:
                break
            k = draw(st.sampled_from(keys))
            child = node[k]
            if isinstance(child, (dict, list)) and child and draw(st.booleans()):
                node = child
                continue
            if draw(st.integers(0, 4)) == 0:
                note(f"delete {k!r}")
                del node[k]
            else:
                note(f"replace {k!r}")
                node[k] = draw(JSON_VALUES) if json_only else junk(draw, bombs)
            break
    return doc


def mutate_json_file(draw: Callable, path: Path, good: bytes) -> None:
    """Rewrite a JSON file: its bytes mutated, or its document with nodes replaced / deleted."""
    if draw(st.booleans()):
        path.write_bytes(mutate_bytes(draw, good))
    else:
        doc = mutate_tree(draw, json.loads(good), json_only=True)
        path.write_text(json.dumps(doc, allow_nan=True))


def mutate_npy_file(draw: Callable, path: Path, good: bytes) -> None:
    """Rewrite a ``.npy`` file: its bytes mutated, or its (pickled) content with nodes replaced."""
    from hogsa_loader.assets.arctic import read_npy

    if draw(st.booleans()):
        path.write_bytes(mutate_bytes(draw, good))
        return
    value = read_npy(path)
    note(f"npy content of {path.name}")
    if isinstance(value, np.ndarray) and value.dtype != object:
        value = random_array(draw) if draw(st.booleans()) else value.reshape(-1)[: draw(st.integers(0, value.size))]
    else:
        value = mutate_tree(draw, value)
    boxed = value
    if not isinstance(value, np.ndarray):
        boxed = np.empty((), dtype=object)
        boxed[()] = value
    buf = io.BytesIO()
    np.save(buf, boxed, allow_pickle=True)
    path.write_bytes(buf.getvalue())


# --------------------------------------------------------------------------------------
# What the targets read
# --------------------------------------------------------------------------------------


@dataclass
class Resources:
    """Valid inputs the targets mutate (read-only; targets copy what they change).

    Attributes:
        world: a ``tiny`` world (``hogsa world --preset tiny``).
        bundle: a bundle built on ``world``.
        shards: an export folder written from ``bundle``.
        scratch: a folder the targets may write in.
    """

    world: Path
    bundle: Path
    shards: Path
    scratch: Path


def build_resources(scratch: Path, world: Optional[Path] = None, log: Callable[[str], None] = print) -> Resources:
    """Generate the tiny world (unless ``world`` is given), an untrained bundle and a 4-frame
    export in ``scratch``."""
    from hogsa_loader.cli.main import main as hogsa
    from hogsa_world.untrained import write_untrained_bundle

    world = Path(world) if world is not None else scratch / "world"
    bundle, shards = scratch / "bundle", scratch / "shards"
    if not (world / "arctic_data" / "data" / "meta" / "hogsa_world.json").is_file():
        log(f"[fuzz] tiny world -> {world}")
        assert hogsa(["world", "--out", str(world), "--preset", "tiny", "--seed", "0", "--quiet"]) == 0
    if not (bundle / "bundle" / "manifest.json").is_file():
        log(f"[fuzz] untrained bundle -> {bundle}")
        write_untrained_bundle(world, bundle)
    if not (shards / "index.json").is_file():
        log(f"[fuzz] 4-frame export -> {shards}")
        assert (
            hogsa(
                [
                    "export",
                    "--bundle",
                    str(bundle / "bundle"),
                    "--data",
                    str(world),
                    "--out",
                    str(shards),
                    "--num",
                    "4",
                    "--shard-size",
                    "2",
                    "--batch-size",
                    "2",
                    "--poses",
                    "perturb",
                    "--no-srm",
                    "--render-size",
                    "96",
                    "--quiet",
                ]
            )
            == 0
        )
    return Resources(world, bundle / "bundle", shards, scratch / "cases")


# --------------------------------------------------------------------------------------
# Targets
# --------------------------------------------------------------------------------------


@dataclass
class Target:
    """A reader under fuzz: ``prepare(res) -> ctx`` once, then ``case(draw, ctx)`` per example
    (mutate, read; returns normally when the reader accepted the input)."""

    name: str
    prepare: Callable[[Resources], dict[str, Any]]
    case: Callable[[Callable, dict[str, Any]], None]
    allowed: tuple[type, ...] = (AssetError,)


def _fresh(res: Resources, name: str) -> Path:
    d = res.scratch / name
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    return d


def _copy_tree(src: Path, dst: Path) -> dict[Path, bytes]:
    """Copy ``src`` to ``dst``; returns ``{file: bytes}`` of the copy (to restore it per case)."""
    shutil.copytree(src, dst)
    return {p: p.read_bytes() for p in sorted(dst.rglob("*")) if p.is_file()}


def _restore(files: dict[Path, bytes]) -> None:
    for p, data in files.items():
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)


# MANO pickle -------------------------------------------------------------------------


def _prepare_mano(res: Resources) -> dict[str, Any]:
    from hogsa_loader.assets.hands import mano_io

    d = _fresh(res, "mano")
    model = mano_io.load_mano(res.world / "body_models" / "mano", side="right")
    good = mano_io.schema_dict(model)
    path = d / "MANO_RIGHT.pkl"
    write_mano_pickle(model, path)
    return {"path": path, "good": good, "bytes": path.read_bytes()}


def _dump_mano(doc: dict[str, Any]) -> bytes:
    return release_pickle_bytes(doc)


def _case_mano(draw: Callable, ctx: dict[str, Any]) -> None:
    from hogsa_loader.assets.hands.mano_io import load_mano

    if draw(st.booleans()):
        data = mutate_bytes(draw, ctx["bytes"])
    else:
        doc = dict(ctx["good"])
        key = draw(st.sampled_from(sorted(doc)))
        choice = draw(st.integers(0, 5))
        if choice == 0:
            del doc[key]
        elif choice == 1:  # a J_regressor whose CSC arrays disagree with each other or its shape
            doc["J_regressor"] = crafted_sparse(draw, doc["J_regressor"])
        else:
            doc[key] = junk(draw)
        try:
            data = _dump_mano(doc)
        except (pickle.PicklingError, TypeError, RecursionError):  # not picklable: not a case
            reject()
    ctx["path"].write_bytes(data)
    load_mano(ctx["path"], side="right")


# ARCTIC ------------------------------------------------------------------------------


def _prepare_arctic(res: Resources) -> dict[str, Any]:
    """A reader-only copy of the world: meta (misc.json), raw_seqs of one sequence, splits."""
    d = _fresh(res, "arctic")
    src = res.world / "arctic_data" / "data"
    dst = d / "arctic_data" / "data"
    dst.mkdir(parents=True)
    (dst / "meta").mkdir()
    shutil.copy2(src / "meta" / "misc.json", dst / "meta" / "misc.json")
    sid, seq_file = sorted((p.parent.name, p.name) for p in (src / "raw_seqs").glob("*/*.mano.npy"))[0]
    seq = seq_file[: -len(".mano.npy")]
    (dst / "raw_seqs" / sid).mkdir(parents=True)
    for p in (src / "raw_seqs" / sid).glob(f"{seq}.*"):
        shutil.copy2(p, dst / "raw_seqs" / sid / p.name)
    shutil.copytree(src / "splits", dst / "splits")
    files = {p: p.read_bytes() for p in dst.rglob("*") if p.is_file()}
    return {"root": d, "sid": sid, "seq": seq, "files": files, "dst": dst}


def _arctic_root(ctx: dict[str, Any]) -> Any:
    from hogsa_loader.assets.arctic import ArcticRoot

    _restore(ctx["files"])
    return ArcticRoot(ctx["root"])


def _case_arctic_raw(draw: Callable, ctx: dict[str, Any]) -> None:
    root = _arctic_root(ctx)
    raw = sorted(p for p in ctx["files"] if p.parent.parent.name == "raw_seqs" and not p.name.endswith("smplx.npy"))
    path = draw(st.sampled_from(raw))
    mutate_npy_file(draw, path, ctx["files"][path])
    root.sequence(ctx["sid"], ctx["seq"])


def _case_arctic_misc(draw: Callable, ctx: dict[str, Any]) -> None:
    root = _arctic_root(ctx)
    path = ctx["dst"] / "meta" / "misc.json"
    mutate_json_file(draw, path, ctx["files"][path])
    root.sequence(ctx["sid"], ctx["seq"])


def _case_arctic_split(draw: Callable, ctx: dict[str, Any]) -> None:
    root = _arctic_root(ctx)
    path = ctx["dst"] / "splits" / "p1_val.npy"
    mutate_npy_file(draw, path, ctx["files"][path])
    root.load_split("p1_val")


def _prepare_npy_sparse(res: Resources) -> dict[str, Any]:
    """The world's ``meta/downsamplers.npy`` (a dict of sparse CSR maps per object)."""
    from hogsa_loader.io.npy import read_npy

    d = _fresh(res, "npy_sparse")
    src = res.world / "arctic_data" / "data" / "meta" / "downsamplers.npy"
    path = d / "downsamplers.npy"
    shutil.copyfile(src, path)
    return {"path": path, "bytes": path.read_bytes(), "good": read_npy(src)}


def _case_npy_sparse(draw: Callable, ctx: dict[str, Any]) -> None:
    from hogsa_loader.io.npy import read_npy

    if draw(st.booleans()):
        data = mutate_bytes(draw, ctx["bytes"])
    else:
        doc = {k: dict(v) for k, v in ctx["good"].items()}
        obj = draw(st.sampled_from(sorted(doc)))
        doc[obj]["D"] = crafted_sparse(draw, doc[obj]["D"])
        buf = io.BytesIO()
        np.save(buf, np.array(doc, dtype=object), allow_pickle=True)
        data = buf.getvalue()
    ctx["path"].write_bytes(data)
    read_npy(ctx["path"])


# H2O text files ----------------------------------------------------------------------


def _prepare_h2o(res: Resources) -> dict[str, Any]:
    from hogsa_loader.assets import h2o_io as h

    eye = np.eye(4).ravel()
    good = {
        "cam_pose": (h.parse_h2o_cam_pose, h.format_h2o_line(eye)),
        "obj_pose_rt": (h.parse_h2o_obj_pose_rt_strict, h.format_h2o_line([2, *eye])),
        "hand_pose_mano": (h.parse_h2o_hand_pose_mano, h.format_h2o_line(np.r_[1, np.zeros(61), 1, np.zeros(61)])),
        "hand_pose": (h.parse_h2o_hand_pose, h.format_h2o_line(np.r_[1, np.zeros(63), 0, np.zeros(63)])),
        "obj_pose": (h.parse_h2o_obj_pose, h.format_h2o_line(np.r_[1, np.zeros(63)])),
        "cam_intrinsics": (h.parse_h2o_cam_intrinsics, "600 600 640 360 1280 720"),
        "action_label": (h.parse_h2o_action_label, "3"),
        "verb_label": (h.parse_h2o_verb_label, "3"),
    }
    for name, (parse, line) in good.items():
        parse(line, f"{name}.txt")  # the untouched line is valid
    return {"good": good}


_TOKENS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.sampled_from(["nan", "-inf", "Infinity", "1_0", "0x1f", "1,2", "1e999", "--1", ".", "e5", "١", ""]),
    st.text(max_size=6),
)


def _case_h2o(draw: Callable, ctx: dict[str, Any]) -> None:
    name = draw(st.sampled_from(sorted(ctx["good"])))
    parse, line = ctx["good"][name]
    mode = draw(st.sampled_from(["bytes", "token", "count"]))
    toks = line.split()
    data: Any
    if mode == "bytes":
        data = mutate_bytes(draw, line.encode())
    elif mode == "token":
        for _ in range(draw(st.integers(1, 4))):
            toks[draw(st.integers(0, len(toks) - 1))] = draw(_TOKENS)
        data = " ".join(toks)
    else:
        data = " ".join(toks[: draw(st.integers(0, len(toks)))] + draw(st.lists(_TOKENS, max_size=4)))
    parse(data, f"{name}.txt")


# Bundle ------------------------------------------------------------------------------


def _prepare_bundle(res: Resources) -> dict[str, Any]:
    d = _fresh(res, "bundle")
    files = _copy_tree(res.bundle, d / "bundle")
    return {"bundle": d / "bundle", "files": files, "world": res.world}


def _case_bundle(draw: Callable, ctx: dict[str, Any]) -> None:
    from hogsa_loader.models.bundle import load_bundle

    _restore(ctx["files"])
    manifest = ctx["bundle"] / "manifest.json"
    if draw(st.integers(0, 3)) == 0:  # one of the bundle's other files damaged or removed
        path = draw(st.sampled_from(sorted(p for p in ctx["files"] if p != manifest)))
        if draw(st.booleans()):
            path.unlink()
        else:
            path.write_bytes(mutate_bytes(draw, ctx["files"][path]))
    else:
        mutate_json_file(draw, manifest, ctx["files"][manifest])
    load_bundle(ctx["bundle"], ctx["world"])


# HOGS part checkpoint ------------------------------------------------------------------


def _prepare_part(res: Resources) -> dict[str, Any]:
    from hogsa_loader.assets.arctic import ArcticRoot

    d = _fresh(res, "part")
    src = next(p.parent for p in sorted(res.bundle.rglob("manifest.json")) if "hand_right" in str(p))
    files = _copy_tree(src, d / "hand_right")
    return {"folder": d / "hand_right", "files": files, "template": ArcticRoot(res.world).mano_layers()["right"]}


def _case_part(draw: Callable, ctx: dict[str, Any]) -> None:
    from hogsa_loader.models.gaussians.checkpoint import load_part

    _restore(ctx["files"])
    path = draw(st.sampled_from(sorted(ctx["files"])))
    if path.suffix == ".json":
        mutate_json_file(draw, path, ctx["files"][path])
    else:
        path.write_bytes(mutate_bytes(draw, ctx["files"][path]))
    load_part(ctx["folder"], ctx["template"])


# Training run folder -------------------------------------------------------------------


def _prepare_run(res: Resources) -> dict[str, Any]:
    from hogsa_loader.train.run_folder import commit_checkpoint

    d = _fresh(res, "run")
    config = {"out": str(d), "iters": 10, "lr": 0.01, "image_size": 64}
    (d / "config.json").write_text(json.dumps(config))
    step = d / "checkpoints" / "step_10"
    step.mkdir(parents=True)
    (step / "trainer.json").write_text("{}")
    commit_checkpoint(step, 10)
    files = {p: p.read_bytes() for p in d.rglob("*") if p.is_file()}
    return {"run": d, "files": files, "config": config}


def _case_run(draw: Callable, ctx: dict[str, Any]) -> None:
    from hogsa_loader.train.run_folder import latest_checkpoint

    _restore(ctx["files"])
    jsons = sorted(p for p in ctx["files"] if p.name in ("config.json", "latest.json"))
    path = draw(st.sampled_from(jsons))
    mutate_json_file(draw, path, ctx["files"][path])
    try:
        latest_checkpoint(ctx["run"], ctx["config"], resumable=("iters",))
    except ValueError as exc:  # documented: a fixed setting differs from the saved config
        if isinstance(exc, AssetError) or "differ" not in str(exc):
            raise


# Export shards -----------------------------------------------------------------------


def _prepare_shards(res: Resources) -> dict[str, Any]:
    d = _fresh(res, "shards")
    files = _copy_tree(res.shards, d / "export")
    return {"folder": d / "export", "files": files}


def _case_shards(draw: Callable, ctx: dict[str, Any]) -> None:
    from hogsa_loader.sample.export import SynthShardDataset

    _restore(ctx["files"])
    path = draw(st.sampled_from(sorted(ctx["files"])))
    if path.suffix == ".json":
        mutate_json_file(draw, path, ctx["files"][path])
    elif draw(st.integers(0, 5)) == 0:
        path.unlink()
    else:
        path.write_bytes(mutate_bytes(draw, ctx["files"][path]))
    for _ in SynthShardDataset(ctx["folder"], arctic_samples=draw(st.booleans())):
        pass


TARGETS: dict[str, Target] = {
    t.name: t
    for t in [
        Target("mano_pickle", _prepare_mano, _case_mano),
        Target("arctic_raw", _prepare_arctic, _case_arctic_raw),
        Target("arctic_misc", _prepare_arctic, _case_arctic_misc),
        Target("arctic_split", _prepare_arctic, _case_arctic_split),
        Target("npy_sparse", _prepare_npy_sparse, _case_npy_sparse),
        Target("h2o_text", _prepare_h2o, _case_h2o),
        Target("bundle", _prepare_bundle, _case_bundle),
        Target("part_checkpoint", _prepare_part, _case_part),
        Target("run_folder", _prepare_run, _case_run),
        Target("shard", _prepare_shards, _case_shards),
    ]
}


# --------------------------------------------------------------------------------------
# Runner
# --------------------------------------------------------------------------------------


@dataclass
class Tally:
    """Outcomes of one target's cases."""

    cases: int = 0
    accepted: int = 0
    refused: int = 0
    failures: list[str] = field(default_factory=list)
    refusals: dict[str, int] = field(default_factory=dict)
    slowest: tuple[float, str] = (0.0, "")
    seconds: list[float] = field(default_factory=list)
    peak_bytes: int = 0
    rss_growth_bytes: int = 0

    def summary(self) -> dict[str, Any]:
        t = np.asarray(self.seconds or [0.0])
        return {
            "cases": self.cases,
            "accepted": self.accepted,
            "refused": self.refused,
            "failed": len(self.failures),
            "failures": self.failures[:20],
            "refusals": dict(sorted(self.refusals.items(), key=lambda kv: -kv[1])[:15]),
            "slowest_case": self.slowest[1],
            "median_s": float(np.median(t)),
            "worst_s": float(t.max()),
            "worst_peak_mib": self.peak_bytes / 2**20,
            "rss_growth_mib": self.rss_growth_bytes / 2**20,
        }


def _reason(exc: BaseException) -> str:
    """The kind of a refusal: its problem up to the first detail (a list of problems: the first)."""
    problem = str(getattr(exc, "problem", exc))
    if "\n  - " in problem:
        problem = problem.split("\n  - ", 1)[1]
    return problem.split("(")[0].split(":")[0].strip()[:80]


def _max_rss() -> int:
    """The process's peak resident memory so far (bytes; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def fuzz(target: Target, res: Resources, cases: int, seed: int = 0, trace_memory: bool = True) -> Tally:
    """Run ``cases`` hypothesis examples of ``target``; every outcome is tallied, none raised."""
    ctx = target.prepare(res)
    tally = Tally()

    @hypothesis_seed(seed)
    @settings(
        max_examples=cases,
        deadline=None,
        database=None,
        derandomize=False,  # ``seed`` decides, also under a derandomized profile
        suppress_health_check=list(HealthCheck),
    )
    @given(data=st.data())
    def run(data: Any) -> None:
        # an example hypothesis abandons while drawing (BaseException: StopTest) is not a case
        if trace_memory:
            tracemalloc.reset_peak()
        TRACE.clear()
        t0 = time.perf_counter()
        try:
            target.case(data.draw, ctx)
        except UnsatisfiedAssumption:  # the case rejected its own input: not counted
            raise
        except target.allowed as exc:
            tally.refused += 1
            tally.refusals[_reason(exc)] = tally.refusals.get(_reason(exc), 0) + 1
        except Exception as exc:  # noqa: BLE001 - every other exception is the finding
            tally.failures.append(f"{type(exc).__name__}: {str(exc)[:300]} [case: {'; '.join(TRACE)}]")
        else:
            tally.accepted += 1
        dt = time.perf_counter() - t0
        tally.cases += 1
        tally.seconds.append(dt)
        if dt > tally.slowest[0]:
            tally.slowest = (dt, "; ".join(TRACE))
        if trace_memory:
            tally.peak_bytes = max(tally.peak_bytes, tracemalloc.get_traced_memory()[1])

    rss0 = _max_rss()
    if trace_memory:
        tracemalloc.start()
    try:
        run()
    finally:
        if trace_memory:
            tracemalloc.stop()
    tally.rss_growth_bytes = _max_rss() - rss0
    return tally


def markdown(results: dict[str, dict[str, Any]], machine: str) -> str:
    lines = [
        f"Reader fuzz ({machine})",
        "",
        "| reader | cases | accepted | refused (AssetError) | failed | median ms | worst ms | worst traced MiB "
        "| peak RSS growth MiB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} | {r['cases']} | {r['accepted']} | {r['refused']} | {r['failed']} | "
            f"{1e3 * r['median_s']:.1f} | {1e3 * r['worst_s']:.0f} | {r['worst_peak_mib']:.1f} | "
            f"{r['rss_growth_mib']:.1f} |"
        )
    lines += [
        "",
        "Worst traced: the largest ``tracemalloc`` peak of one case, which counts memory reserved "
        "but never touched (a corrupt pickle length makes CPython's unpickler reserve that many bytes "
        "before it finds the data missing). Peak RSS growth: how much the process's resident peak "
        "rose over all cases of the reader (after the readers before it).",
    ]
    return "\n".join(lines) + "\n"


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="runs/fuzz", help="results and scratch folder")
    p.add_argument("--cases", type=int, default=1000, help="examples per reader")
    p.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated, of {', '.join(TARGETS)}")
    p.add_argument("--seed", type=int, default=0, help="hypothesis seed")
    p.add_argument("--world", default=None, help="an existing tiny world (hogsa world --preset tiny) to use")
    args = p.parse_args(argv)
    names = [n for n in args.targets.split(",") if n]
    unknown = [n for n in names if n not in TARGETS]
    if unknown or args.cases < 1:
        p.error(f"unknown targets {unknown}" if unknown else "--cases must be >= 1")
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    res = build_resources(out / "scratch", Path(args.world) if args.world else None)
    results: dict[str, dict[str, Any]] = {}
    if (out / "fuzz.json").is_file():
        results = json.loads((out / "fuzz.json").read_text()).get("results", {})
    import platform

    machine = f"{platform.processor() or platform.machine()}, {platform.python_version()}"
    for name in names:
        t0 = time.perf_counter()
        print(f"[fuzz] {name}: {args.cases} cases", flush=True)
        r = fuzz(TARGETS[name], res, args.cases, args.seed).summary()
        r["seconds"] = round(time.perf_counter() - t0, 1)
        results[name] = r
        print(
            f"[fuzz] {name}: {r['accepted']} accepted, {r['refused']} refused, {r['failed']} failed; "
            f"worst {1e3 * r['worst_s']:.0f} ms ({r['slowest_case']}), {r['worst_peak_mib']:.1f} MiB",
            flush=True,
        )
        for f in r["failures"][:5]:
            print(f"    {f}", flush=True)
        (out / "fuzz.json").write_text(json.dumps({"machine": machine, "results": results}, indent=1))
    (out / "fuzz.md").write_text(markdown(results, machine))
    print(markdown(results, machine))
    return 1 if any(r["failed"] for r in results.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
