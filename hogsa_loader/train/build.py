"""``hogsa build``: a dataset root to a bundle, stage by stage, cached and resumable.

:func:`build` trains HOGS for every training (subject, object) pair, ContactNet, the POM pose
bank and the SRM, then writes the bundle the loader reads; :func:`build_status` says what is
done and what is left. :class:`BuildConfig` holds every stage's settings (one TOML file:
:func:`read_config` / :func:`config_toml`); each stage's settings are those of its ``hogsa train``
job. Subjects come from the dataset's protocol: a held-out subject is read only when named in
``allow_held_out``. Under torchrun or srun the processes share the stages (one claim per stage).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
import typing
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Optional

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.h2o_poses import H2OPoseRoot
from hogsa_loader.assets.protocol import held_out_subjects, training_subjects
from hogsa_loader.assets.roots import DatasetRoot
from hogsa_loader.errors import PathLike, UsageError
from hogsa_loader.io.locks import FolderBusyError, writer_lock
from hogsa_loader.models.bundle import BUNDLE_SCHEMA_VERSION, write_bundle
from hogsa_loader.system import process_slot, rank_device
from hogsa_loader.train.config import Dataset, dataset_field, mano_dir_field, object_mesh_dir_field
from hogsa_loader.train.config import field_options as _opt
from hogsa_loader.train.hogs_config import HogsConfig
from hogsa_loader.train.hogs_trainer import HogsTrainer
from hogsa_loader.train.pom_config import ContactNetJobConfig, PoseBankConfig
from hogsa_loader.train.pom_jobs import build_pose_bank, fit_contactnet, open_pose_root, sequences_of
from hogsa_loader.train.srm_config import SRMTrainConfig
from hogsa_loader.train.srm_trainer import SRMTrainer
from hogsa_loader.train.stages import StageNode, StageRecords, in_stage_process, run_stage_graph, stage_key

__all__ = ["BuildConfig", "BuildDataConfig", "BuildRunConfig", "build", "build_status", "config_toml", "read_config"]

#: Fields of the stage configs that the build sets itself (no flag, no TOML key).
SET_BY_BUILD = frozenset(
    {
        ("hogs", "data", "root"),
        ("hogs", "data", "subject"),
        ("hogs", "data", "object"),
        ("hogs", "data", "sequences"),
        ("hogs", "data", "dataset"),
        ("hogs", "data", "mano_dir"),
        ("hogs", "data", "object_mesh_dir"),
        ("hogs", "run", "out"),
        ("hogs", "run", "seed"),
        ("hogs", "run", "device"),
        ("contactnet", "data", "root"),
        ("contactnet", "data", "dataset"),
        ("contactnet", "data", "mano_dir"),
        ("contactnet", "data", "object_mesh_dir"),
        ("contactnet", "data", "allow_held_out"),
        ("contactnet", "optim", "seed"),
        ("contactnet", "run", "out"),
        ("bank", "data", "root"),
        ("bank", "data", "dataset"),
        ("bank", "data", "mano_dir"),
        ("bank", "data", "object_mesh_dir"),
        ("bank", "data", "contactnet"),
        ("bank", "data", "subjects"),
        ("bank", "data", "sequences"),
        ("bank", "data", "allow_held_out"),
        ("bank", "run", "out"),
        ("bank", "run", "seed"),
        ("bank", "run", "device"),
        ("srm", "data", "root"),
        ("srm", "data", "hogs"),
        ("srm", "data", "runs"),
        ("srm", "data", "cache"),
        ("srm", "run", "out"),
        ("srm", "run", "seed"),
        ("srm", "run", "device"),
    }
)


@dataclass
class BuildDataConfig:
    """The dataset root and what of it the models learn from."""

    root: str = field(
        default="", metadata=_opt("dataset root (ARCTIC ./data, or the H2O root)", required=True, name="data")
    )
    dataset: Dataset = dataset_field()
    mano_dir: Optional[str] = mano_dir_field()
    object_mesh_dir: Optional[str] = object_mesh_dir_field()
    protocol: str = field(
        default="p1", metadata=_opt("ARCTIC protocol whose training split the models learn from (H2O has one)")
    )
    pairs: Optional[tuple[str, ...]] = field(
        default=None, metadata=_opt("SUBJECT/OBJECT pairs to model (default: every pair of the training split)")
    )
    sequences_like: Optional[tuple[str, ...]] = field(
        default=("grab_01", "use_01"),
        metadata=_opt("sequence name endings HOGS trains each pair on (the paper's choice); none: all sequences"),
    )
    allow_held_out: Optional[tuple[str, ...]] = field(
        default=None,
        metadata=_opt("held-out subjects (ARCTIC: s03, s05) to read all the same (recorded, with a warning)"),
    )


@dataclass
class BuildRunConfig:
    """Where the build writes, its seed and device."""

    out: str = field(default="", metadata=_opt("build folder (stages/, runs/, bundle/)", required=True, name="out"))
    seed: int = field(default=0, metadata=_opt("seed of every stage", name="seed"))
    device: str = field(default="cpu", metadata=_opt("torch device of every stage", "torch_device", name="device"))


@dataclass
class BuildConfig:
    """Every setting of ``hogsa build``: the data, the run, and each stage's job settings (those
    of ``hogsa train hogs|contactnet|bank|srm``, without what the build sets: roots, output
    folders, subjects, sequences, seeds, devices)."""

    data: BuildDataConfig = field(default_factory=BuildDataConfig, metadata={"flat": True})
    run: BuildRunConfig = field(default_factory=BuildRunConfig, metadata={"flat": True})
    hogs: HogsConfig = field(default_factory=HogsConfig, metadata={"job": True})
    contactnet: ContactNetJobConfig = field(default_factory=ContactNetJobConfig, metadata={"job": True})
    bank: PoseBankConfig = field(default_factory=PoseBankConfig, metadata={"job": True})
    srm: SRMTrainConfig = field(default_factory=SRMTrainConfig, metadata={"job": True})


# ---------------------------------------------------------------------------- TOML
def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def config_toml(config: BuildConfig) -> str:
    """``config`` as TOML: one table per group (``[hogs.optim]``); what the build sets itself is
    left out. TOML has no null: an unset (None) value is a comment line, read back as the
    default, except an unset list whose default is set (``sequences_like``), written ``[]``."""
    lines: list[str] = ["# hogsa build settings (hogsa build --print-config); unset values are commented out"]

    def table(obj: Any, path: tuple[str, ...]) -> None:
        rows, subs = [], []
        defaults = type(obj)()
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if path + (f.name,) in SET_BY_BUILD or f.metadata.get("cli", True) is False:
                continue
            if dataclasses.is_dataclass(value):
                subs.append((f.name, value))
            elif value is None and isinstance(getattr(defaults, f.name), tuple):
                rows.append(f"{f.name} = []")
            elif value is None:
                rows.append(f"# {f.name} =  ({f.metadata.get('help', '')})")
            else:
                rows.append(f"{f.name} = {_toml_value(value)}")
        if rows:
            lines.extend(["", f"[{'.'.join(path)}]" if path else "", *rows])
        for name, value in subs:
            table(value, path + (name,))

    table(config, ())
    return "\n".join(line for i, line in enumerate(lines) if line or (i and lines[i - 1])) + "\n"


def _from_dict(cls: type, data: dict[str, Any], where: str, base: Any, path: tuple[str, ...] = ()) -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        at = ".".join(path + (key,))
        if key not in names:
            raise UsageError(f"{where}: unknown setting {at!r} (known here: {', '.join(sorted(names))})")
        if path + (key,) in SET_BY_BUILD:
            raise UsageError(f"{where}: {at!r} is set by the build itself (from [data] and [run])")
        if dataclasses.is_dataclass(hints[key]):
            if not isinstance(value, dict):
                raise UsageError(f"{where}: {at!r} must be a table")
            kwargs[key] = _from_dict(hints[key], value, where, getattr(base, key), path + (key,))
        elif isinstance(value, list):  # [] is an unset list (TOML has no null)
            kwargs[key] = tuple(value) if value or not isinstance(getattr(base, key), tuple) else None
        else:
            kwargs[key] = value
    try:
        return replace(base, **kwargs)
    except (TypeError, ValueError) as exc:  # a group's own checks
        raise UsageError(f"{where}: [{'.'.join(path) or 'top'}] {exc}") from None


def read_config(path: PathLike, base: Optional[BuildConfig] = None) -> BuildConfig:
    """The :class:`BuildConfig` of a TOML file: ``base`` (default: the defaults) with the file's values.

    Raises:
        UsageError: the file is missing, not TOML, names a setting that does not exist or that
            the build sets itself, or holds a value its group refuses.
    """
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except OSError as exc:
        raise UsageError(f"--config {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise UsageError(f"--config {path}: not TOML ({exc})") from None
    return _from_dict(BuildConfig, data, str(path), base or BuildConfig())


# ---------------------------------------------------------------------------- what to build
def _training_sequences(root: DatasetRoot, protocol: str) -> list[str]:
    """``sid/seq`` of the protocol's training split (H2O, or an ARCTIC root without protocol
    files: every sequence of a subject the dataset's protocol does not hold out, the others'
    labels unread)."""
    if isinstance(root, ArcticRoot) and root.protocol_path(protocol).is_file():
        return list(root.protocol(protocol)["train"])
    held = held_out_subjects(root)
    if isinstance(root, H2OPoseRoot):
        return sequences_of(root, [s for s in root.subjects() if s not in held])
    return [s for s in root.sequences() if s.split("/", 1)[0] not in held]


def select_pairs(root: DatasetRoot, data: BuildDataConfig) -> list[tuple[str, str, list[str]]]:
    """Sorted ``(subject, object, sequences)`` the build models: ``data.pairs`` (or every pair of
    the training split), each with the sequences of its split (all when a requested pair's
    subject is an allowed held-out one).

    Raises:
        UsageError: a pair is malformed or has no sequence; a held-out subject is not allowed.
    """
    wanted = None
    if data.pairs:
        wanted = set()
        for item in data.pairs:
            sid, sep, obj = item.partition("/")
            if not sep or not sid or not obj:
                raise UsageError(f"--pairs: expected SUBJECT/OBJECT, got {item!r}")
            wanted.add((sid, obj))
    allow = list(data.allow_held_out or ())
    if wanted is not None:  # a requested held-out subject is refused before anything else
        training_subjects(root, sorted({s for s, _ in wanted}), allow, "hogsa build")
    seqs = _training_sequences(root, data.protocol)
    if allow:
        seqs += [s for s in sequences_of(root, allow) if s not in seqs]
    pairs: dict[tuple[str, str], list[str]] = {}
    for sid_seq in seqs:
        sid, seq = sid_seq.split("/", 1)
        key = (sid, seq.split("_", 1)[0])
        if wanted is None or key in wanted:
            pairs.setdefault(key, []).append(seq)
    if wanted is not None and set(pairs) != wanted:
        missing = sorted(f"{s}/{o}" for s, o in wanted - set(pairs))
        raise UsageError(f"--pairs: {', '.join(missing)} has no sequence in {root.root} (training split or allowed)")
    if not pairs:
        raise UsageError(f"--data {root.root}: no (subject, object) pair in the training split")
    if wanted is None:
        training_subjects(root, sorted({s for s, _ in pairs}), allow, "hogsa build")
    return [(sid, obj, sorted(s)) for (sid, obj), s in sorted(pairs.items())]


def _hogs_sequences(
    root: DatasetRoot, sid: str, seqs: list[str], like: Optional[tuple[str, ...]]
) -> Optional[tuple[str, ...]]:
    """The sequences HOGS trains a pair on: those ending in ``like`` (None: all of the pair's),
    as its job names them (H2O: ``scene/seq``)."""
    if not like:
        return None
    chosen = tuple(s for s in seqs if s.split("_", 1)[1] in like)
    if chosen and isinstance(root, H2OPoseRoot):
        return tuple("/".join(root.h2o_sequence(f"{sid}/{s}")[1:3]) for s in chosen)
    return chosen or None  # a pair without the named sequences trains on all of its own


def _dataset_fields(data: BuildDataConfig) -> dict[str, Any]:
    """``dataset``, ``mano_dir`` and ``object_mesh_dir`` as every stage's data group takes them
    (the folders absolute)."""
    folders = {k: getattr(data, k) and os.path.abspath(getattr(data, k)) for k in ("mano_dir", "object_mesh_dir")}
    return {"dataset": data.dataset, **folders}


#: Fields the build sets that name folders: left out of the keys (a moved build stays valid).
_PATHS = ("root", "out", "contactnet", "hogs", "cache")


def _keyed(job: Any, stage: str) -> dict[str, Any]:
    """``asdict(job)`` as a stage key holds it: without the folders the build fills in (the data
    is keyed by the data key, the outputs are where the key is recorded), and with the device's
    type only (``cuda:1`` of one rank and ``cuda`` of another build the same stage)."""
    d = asdict(job)
    for path in (p[1:] for p in SET_BY_BUILD if p[0] == stage):
        node = d
        for p in path[:-1]:
            node = node[p]
        if path[-1] in _PATHS:
            node.pop(path[-1], None)
        elif path[-1] == "device":
            node["device"] = str(node["device"]).split(":", 1)[0]
    return d


@dataclass
class _Plan:
    """The stage graph of one build."""

    data: Path
    out: Path
    pairs: list[tuple[str, str, list[str]]]
    nodes: list[StageNode]
    bundle: Path


def _progress() -> bool:
    return not in_stage_process() and not _QUIET


_QUIET = False


def _hogs_node(
    cfg: BuildConfig, root: DatasetRoot, plan_out: Path, data: Path, k_data: str, pair: tuple[str, str, list[str]]
) -> StageNode:
    sid, obj, seqs = pair
    run = plan_out / "runs" / "hogs" / f"{sid}_{obj}"
    hc = replace(
        cfg.hogs,
        data=replace(
            cfg.hogs.data,
            root=str(data),
            subject=sid,
            object=obj,
            sequences=_hogs_sequences(root, sid, seqs, cfg.data.sequences_like),
            **_dataset_fields(cfg.data),
        ),
        run=replace(cfg.hogs.run, out=str(run), seed=cfg.run.seed, device=cfg.run.device),
    )
    key = stage_key("hogs", k_data, sid, obj, hc.data.sequences, _keyed(hc, "hogs"))

    def train() -> dict[str, Any]:
        m = HogsTrainer(hc, progress=_progress()).train()
        return {"psnr": m["psnr"], "ssim": m["ssim"], "iters": m["iters"]}

    return StageNode(f"hogs/{sid}_{obj}", key, [run], train)


def _contactnet_node(cfg: BuildConfig, cn: Path, data: Path, k_data: str, subjects: list[str]) -> StageNode:
    job = replace(
        cfg.contactnet,
        data=replace(
            cfg.contactnet.data, root=str(data), allow_held_out=cfg.data.allow_held_out, **_dataset_fields(cfg.data)
        ),
        optim=replace(cfg.contactnet.optim, seed=cfg.run.seed),
        run=replace(cfg.contactnet.run, out=str(cn)),
    )
    key = stage_key("contactnet", k_data, subjects, _keyed(job, "contactnet"))

    def fit() -> dict[str, Any]:
        m = fit_contactnet(job, progress=_progress())
        return {k: m[k] for k in ("val_mae", "val_iou05")}

    return StageNode("contactnet", key, [cn], fit)


def _bank_node(cfg: BuildConfig, bank: Path, data: Path, cn: StageNode, seqs: list[str]) -> StageNode:
    job = replace(
        cfg.bank,
        data=replace(
            cfg.bank.data,
            root=str(data),
            contactnet=str(cn.outputs[0]),
            sequences=tuple(seqs),
            allow_held_out=cfg.data.allow_held_out,
            **_dataset_fields(cfg.data),
        ),
        run=replace(cfg.bank.run, out=str(bank), seed=cfg.run.seed, device=cfg.run.device),
    )
    key = stage_key("bank", cn.key, seqs, _keyed(job, "bank"))
    return StageNode("bank", key, [bank], lambda: build_pose_bank(job, progress=_progress()), needs=("contactnet",))


def _srm_node(cfg: BuildConfig, out: Path, data: Path, hogs: list[StageNode]) -> StageNode:
    srm, cache = out / "runs" / "srm", out / "cache" / "srm"
    runs = tuple(n.outputs[0].name for n in hogs)  # this build's runs only (not others left in the folder)
    job = replace(
        cfg.srm,
        data=replace(cfg.srm.data, root=str(data), hogs=str(out / "runs" / "hogs"), runs=runs, cache=str(cache)),
        run=replace(cfg.srm.run, out=str(srm), seed=cfg.run.seed, device=cfg.run.device),
    )
    key = stage_key("srm", [n.key for n in hogs], _keyed(job, "srm"))

    def train() -> dict[str, Any]:
        trainer = SRMTrainer(job, progress=_progress(), log=lambda s: None)
        m = trainer.train()
        used = {f.resolve() for ps in trainer.sets for f in ps.cache_files}
        for stale in cache.glob("coarse_*.safetensors"):  # renders of HOGS weights or labels no longer in use
            if stale.resolve() not in used:
                stale.unlink()
        return {"delta_psnr": m["delta_psnr"], "delta_ssim": m["delta_ssim"]}

    return StageNode("srm", key, [srm], train, needs=tuple(n.name for n in hogs))


def plan_build(config: BuildConfig, data_key: Optional[str] = None) -> _Plan:
    """The stage graph of ``config`` (nothing is built): HOGS per pair, ContactNet, the pose
    bank, the SRM and the bundle, each with its key and outputs.

    Args:
        config: the settings.
        data_key: the cache key of the dataset (default: its absolute path); a caller that
            builds the dataset itself passes the key of that build.
    """
    if not config.data.root:
        raise UsageError("--data: give the dataset root")
    if not config.run.out:
        raise UsageError("--out: give the build folder")
    data = Path(os.path.abspath(config.data.root))
    out = Path(os.path.abspath(config.run.out))
    root = open_pose_root(replace(config.data, root=str(data)))
    pairs = select_pairs(root, config.data)
    k_data = data_key or stage_key("data", str(data))
    allow = list(config.data.allow_held_out or ())
    subjects = training_subjects(root, None, allow, "ContactNet")  # what ContactNet trains on
    hogs = [_hogs_node(config, root, out, data, k_data, p) for p in pairs]
    cn = _contactnet_node(config, out / "runs" / "contactnet", data, k_data, subjects)
    bank = _bank_node(config, out / "runs" / "pose_bank", data, cn, [f"{s}/{q}" for s, _, qs in pairs for q in qs])
    srm = _srm_node(config, out, data, hogs)
    bundle = out / "bundle"
    runs = [n.outputs[0] for n in hogs]
    k_bundle = stage_key("bundle", [n.key for n in hogs], cn.key, bank.key, srm.key, BUNDLE_SCHEMA_VERSION)
    write = StageNode(
        "bundle",
        k_bundle,
        [bundle],
        lambda: str(
            write_bundle(bundle, root, runs, srm=srm.outputs[0], contactnet=cn.outputs[0], pose_banks=[bank.outputs[0]])
        ),
        needs=(*(n.name for n in hogs), "contactnet", "bank", "srm"),
    )
    return _Plan(data, out, pairs, [*hogs, cn, bank, srm, write], bundle)


# ---------------------------------------------------------------------------- running it
def _claimed_run(stages: StageRecords, node: StageNode) -> bool:
    """Build ``node`` if no live process holds its claim; False when another one does (an
    error of the stage itself is raised)."""
    claim = writer_lock(stages.dir, f".{node.name.replace('/', '_')}.claim", what=f"stage {node.name}")
    try:
        claim.__enter__()
    except FolderBusyError:
        return False
    try:
        stages.run(node.name, node.key, node.outputs, node.build)
    finally:
        claim.__exit__(None, None, None)
    return True


def _run_shared(stages: StageRecords, nodes: list[StageNode], say: Callable[[str], None], poll_s: float) -> None:
    """One of several processes: build every stage no other process has claimed, each once the
    stages it needs are built; wait for the rest (a claim of a process that died is taken over:
    the kernel releases its lock)."""
    names = {n.name: n for n in nodes}
    while True:
        left = [n for n in nodes if not stages.is_cached(n.name, n.key, n.outputs)]
        if not left:
            return
        progressed = False
        for n in left:
            if all(stages.is_cached(d, names[d].key, names[d].outputs) for d in n.needs):
                if not stages.is_cached(n.name, n.key, n.outputs) and _claimed_run(stages, n):
                    progressed = True
        if not progressed:
            time.sleep(poll_s)


def build(
    config: BuildConfig,
    log: Optional[Callable[[str], None]] = print,
    data_key: Optional[str] = None,
    poll_s: float = 2.0,
    progress: bool = True,
) -> tuple[Path, dict[str, float]]:
    """Build (or reuse) every stage of ``config`` and the bundle.

    Stages (``OUT = config.run.out``; each records ``OUT/stages/<name>.json`` with a key of its
    settings and of the stages it builds on, and is reused while the key is unchanged)::

        hogs/<sid>_<obj>  OUT/runs/hogs/<sid>_<obj>  HOGS per training (subject, object) pair
        contactnet        OUT/runs/contactnet        ContactNet on the training subjects
        bank              OUT/runs/pose_bank         POM pose bank of the pairs' sequences
        srm               OUT/runs/srm               SRM on the HOGS runs (coarse renders cached
                          OUT/cache/srm              for rebuilds)
        bundle            OUT/bundle                 what HOGSADataset reads

    One process builds the stages side by side on forked processes where the graph allows;
    under torchrun or srun (``WORLD_SIZE`` / ``SLURM_STEP_NUM_TASKS`` > 1) every process takes the
    stages no other one has claimed (a lock per stage: a claim dies with its process) and all
    return once the bundle is written. A stage interrupted mid-way is rebuilt.

    Returns:
        ``(bundle_folder, stage_seconds)`` (seconds of the stages this process built; 0 reused).

    Raises:
        UsageError: bad settings or a held-out subject not allowed; HogsaError from a stage.
    """
    global _QUIET
    say = log or (lambda s: None)
    rank, world = process_slot()
    config = replace(config, run=replace(config.run, device=rank_device(config.run.device)))
    plan = plan_build(config, data_key)
    plan.out.mkdir(parents=True, exist_ok=True)
    stages = StageRecords(plan.out, say)
    say(f"[build] {len(plan.pairs)} pairs: {', '.join(f'{s}/{o}' for s, o, _ in plan.pairs)}")
    _QUIET = log is None or not progress
    try:
        if world > 1:
            with writer_lock(stages.dir, ".build.lock", what="a single-process build"):
                pass  # refused while a single-process build writes this folder
            say(f"[build] process {rank} of {world}, device {config.run.device}")
            _run_shared(stages, plan.nodes, say, poll_s)
        else:
            with writer_lock(stages.dir, ".build.lock", what="a build"):
                run_stage_graph(stages, plan.nodes, say)
    finally:
        _QUIET = False
    return plan.bundle, dict(stages.seconds)


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else 0


def build_status(config: BuildConfig, data_key: Optional[str] = None) -> list[dict[str, Any]]:
    """What is built and what is left: one row per stage (``name``, ``state`` ``"done"`` /
    ``"stale"`` (built with other settings) / ``"todo"``, ``seconds`` it took, ``bytes`` of its
    outputs, ``needs``)."""
    plan = plan_build(config, data_key)
    stages = StageRecords(plan.out, lambda s: None)
    rows = []
    for n in plan.nodes:
        rec = stages.record(n.name)
        if stages.is_cached(n.name, n.key, n.outputs):
            state = "done"
        elif rec is not None:
            state = "stale"
        else:
            state = "todo"
        rows.append(
            {
                "name": n.name,
                "state": state,
                "seconds": rec.get("seconds") if rec else None,
                "bytes": sum(_size(p) for p in n.outputs) if state == "done" else 0,
                "needs": list(n.needs),
            }
        )
    return rows
