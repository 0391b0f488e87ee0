"""Drop-in for ARCTIC's training loop: wrap its train DataLoader with synthetic samples.

Example (ArcticNet-SF training, real-format data)::

    from torch.utils.data import DataLoader
    from hogsa_loader.sample import ArcticDataset
    from hogsa_loader.integrations.arctic import wrap_train_loader

    real = DataLoader(ArcticDataset("./data", split="p1_train"), batch_size=64, shuffle=True, num_workers=8)
    train_loader = wrap_train_loader(real, "bundle/", ratio=0.5, data_root="./data", device="cuda")
    for inputs, targets, meta_info in train_loader:   # 32 real + 32 synthetic, collated alike
        ...
"""

from __future__ import annotations

from typing import Any, Literal, Optional, Union

from torch.utils.data import DataLoader

from hogsa_loader.assets.arctic import protocol_views
from hogsa_loader.errors import PathLike
from hogsa_loader.models.bundle import Bundle, load_bundle
from hogsa_loader.sample.config import LoaderConfig, with_options
from hogsa_loader.sample.dataset import HOGSADataset
from hogsa_loader.sample.mixing import MixedLoader, MixMode
from hogsa_loader.sample.poses import PoseSource
from hogsa_loader.sample.synth import Refiner

__all__ = ["METHODS", "Method", "method_options", "wrap_train_loader"]

#: The synthetic samples of the HOGSA paper and its ablations (:func:`method_options`).
Method = Literal["hogsa", "no_pom", "no_srm", "views_only"]
METHODS: tuple[str, ...] = ("hogsa", "no_pom", "no_srm", "views_only")


def method_options(method: str, bundle: Bundle) -> dict[str, Any]:
    """The loader options of ``method`` for ``bundle``.

    * ``"hogsa"`` (the paper's method): POM-optimised grasps of the bundle's pose banks
      (``poses="bank"``), each render refined by its SRM (``srm=True``);
    * ``"no_pom"``: perturbed annotated grasps (``poses="perturb"``), with the SRM;
    * ``"no_srm"``: the pose bank's grasps, without the SRM;
    * ``"views_only"``: the annotated grasps unchanged (no new pose: new cameras,
      backgrounds and appearance only), with the SRM.

    Raises:
        ValueError: an unknown method, or one that needs what ``bundle`` lacks (a pose bank,
            an SRM), naming it.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    poses = "perturb" if method in ("no_pom", "views_only") else "bank"
    srm = method != "no_srm"
    missing = [
        what
        for what, need, have in (
            ("a pose bank", poses == "bank", bool(bundle.pose_banks)),
            ("an SRM", srm, bundle.srm is not None),
        )
        if need and not have
    ]
    if missing:
        raise ValueError(f"method={method!r} needs {' and '.join(missing)}, which bundle {bundle.path} lacks")
    if method == "views_only":
        return {"poses": poses, "pose_options": {"finger_std": 0.0, "arti_std": 0.0, "hand_trans_std": 0.0}, "srm": srm}
    return {"poses": poses, "srm": srm}


def _method_defaults(
    b: Bundle, method: Optional[str], config: Optional[LoaderConfig], options: dict[str, Any]
) -> dict[str, Any]:
    """The ``poses`` / ``srm`` options ``method`` (or, without one, the paper's method where the
    bundle has it) adds to ``options``."""
    if method is not None:
        preset = method_options(method, b)
        clash = {k: options[k] for k in preset if k in options and options[k] != preset[k]}
        if clash:
            raise ValueError(f"method={method!r} means {preset}; conflicting options {clash}")
        return preset
    if config is not None:  # the caller's config decides
        return {}
    return {"poses": "bank" if b.pose_banks else "perturb", "srm": b.srm is not None}


def _unwrap(dataset: Any) -> Any:
    """The dataset inside ``torch.utils.data.Subset``-like wrappers (``.dataset`` chains)."""
    seen = 0
    while dataset is not None and not hasattr(dataset, "setup") and hasattr(dataset, "dataset") and seen < 8:
        dataset, seen = dataset.dataset, seen + 1
    return dataset


def _root_of(dataset: Any) -> Optional[PathLike]:
    root = getattr(dataset, "root", None)
    return getattr(root, "data_root", None)


def _loader_protocol(dataset: Any) -> Optional[str]:
    """``"p1"`` / ``"p2"`` of the real dataset's setup (``.setup`` of
    :class:`~hogsa_loader.sample.ArcticDataset`, ``.args.setup`` of ARCTIC's own dataset;
    ``p1a`` / ``p2a`` are the same views), or None when it does not say."""
    setup = getattr(dataset, "setup", None) or getattr(getattr(dataset, "args", None), "setup", None)
    if setup is None:
        return None
    try:
        views = protocol_views(str(setup))
    except ValueError:  # a setup this library does not know: the caller says (protocol=)
        return None
    return "p2" if views == protocol_views("p2") else "p1"


def _real_options(real_ds: Any, config: LoaderConfig, options: dict[str, Any]) -> dict[str, Any]:
    """``protocol``, ``arctic`` (the sample config) and ``interfield`` of the real dataset,
    for those the caller left at their defaults (in ``config`` and ``options``)."""
    found = {
        "protocol": _loader_protocol(real_ds),
        "arctic": getattr(real_ds, "cfg", None),
        "interfield": getattr(real_ds, "interfield", None),
    }
    default = LoaderConfig().sample
    return {
        name: value
        for name, value in found.items()
        if value is not None and name not in options and getattr(config.sample, name) == getattr(default, name)
    }


def _in_workers(syn: HOGSADataset, num_workers: int) -> Any:
    """The synthetic stream, in ``num_workers`` persistent DataLoader workers when > 0 (CPU only)."""
    if num_workers == 0:
        return syn
    if syn.device.startswith("cuda"):
        raise ValueError("num_workers > 0 with device='cuda': DataLoader workers must not touch CUDA; use 0")
    return DataLoader(syn, batch_size=None, num_workers=num_workers, persistent_workers=True)


def wrap_train_loader(
    train_loader: DataLoader,
    bundle: Union[PathLike, Bundle],
    ratio: float = 0.5,
    *,
    data_root: Optional[PathLike] = None,
    num_workers: int = 0,
    drop_last: bool = True,
    mode: MixMode = "replace",
    distribute: bool = True,
    method: Optional[Method] = None,
    config: Optional[LoaderConfig] = None,
    backgrounds: Any = None,
    poses: Optional[PoseSource] = None,
    refiner: Optional[Refiner] = None,
    **options: Any,
) -> MixedLoader:
    """Mix synthetic HOGSA samples into an ARCTIC train loader.

    Args:
        train_loader: the real DataLoader (ArcticNet-SF ``(inputs, targets, meta_info)``
            batches); its batch size B is kept (``mode="replace"``).
        bundle: bundle folder or :class:`~hogsa_loader.models.bundle.Bundle`.
        ratio: synthetic share; each batch has exactly ``round(ratio·B)`` (half up)
            synthetic samples (``mode="replace"``; with ``"add"``,
            ``added_synthetic(ratio, b)`` are appended to a real batch of b).
        data_root: ARCTIC data root (default: ``train_loader.dataset.root.data_root`` of a
            :class:`~hogsa_loader.sample.ArcticDataset`).
        num_workers: DataLoader workers of the synthetic stream (CPU rendering only;
            keep 0 with ``device="cuda"`` — workers must not touch CUDA).
        drop_last: see :class:`~hogsa_loader.sample.mixing.MixedLoader` (``"replace"`` only;
            with ``"add"`` the train loader's own ``drop_last`` applies).
        mode: ``"replace"`` (synthetic samples take ``round(ratio·B)`` places of each batch of
            B) or ``"add"`` (each real batch kept whole, synthetic samples appended so that
            their share is about ``ratio``); see :class:`~hogsa_loader.sample.mixing.MixedLoader`.
        distribute: on several processes, give a ``train_loader`` without a distributed
            sampler a ``DistributedSampler`` (see Returns); False when each process's real
            dataset is already its own share.
        method: ``"hogsa"`` (the paper's method: pose-bank grasps refined by the SRM),
            ``"no_pom"``, ``"no_srm"`` or ``"views_only"`` (its ablations; :func:`method_options`). By default
            (None) the paper's method where the bundle has it: bank poses when it holds a pose
            bank, the SRM when it holds one (else perturbed annotated grasps, unrefined), unless
            ``config`` or ``poses``/``srm`` options say otherwise. A method given together with
            a ``poses`` or ``srm`` option that contradicts it is refused.
        config: the synthetic stream's :class:`~hogsa_loader.sample.config.LoaderConfig`.
        backgrounds: an explicit background source, as for
            :class:`~hogsa_loader.sample.dataset.HOGSADataset`.
        poses: an explicit pose source, as for ``HOGSADataset``.
        refiner: an explicit refiner, as for ``HOGSADataset``.
        **options: loader options by name, applied to ``config``
            (:func:`~hogsa_loader.sample.config.with_options`: ``device``, ``seed``,
            ``coco_root``, ``poses``, ``srm``, ``batch_size``, ``protocol`` ...). ``protocol``,
            ``arctic`` (the sample config) and ``interfield`` default to the real dataset's (so
            both halves of a batch have the same keys; the protocol is read from ``.setup``
            or, for ARCTIC's own dataset, ``.args.setup``, through ``Subset`` wrappers;
            ``p1a``/``p2a`` count as ``p1``/``p2``). Pass ``protocol=`` when the real
            dataset says neither (the default is then ``p1``, allocentric).

    Returns:
        a :class:`~hogsa_loader.sample.mixing.MixedLoader`. On several processes (torchrun,
        PyTorch Lightning's DDP) each rank gets its own share of both halves: the synthetic
        stream splits itself by rank, and a ``train_loader`` without a distributed sampler is
        given a ``DistributedSampler`` (shuffled with the config's ``seed`` when it shuffles).
    """
    real_ds = _unwrap(getattr(train_loader, "dataset", None))
    root = data_root if data_root is not None else _root_of(real_ds)
    if root is None:
        raise ValueError("data_root is needed (the train loader's dataset does not say where its data is)")
    bundle = bundle if isinstance(bundle, Bundle) else load_bundle(bundle, data_root=root)
    options = {**_method_defaults(bundle, method, config, options), **options}
    config = LoaderConfig() if config is None else config
    config = with_options(config, **_real_options(real_ds, config, options), **options)
    syn = HOGSADataset(bundle, root, config, backgrounds=backgrounds, poses=poses, refiner=refiner)
    source = _in_workers(syn, num_workers)
    return MixedLoader(
        train_loader, source, ratio, drop_last=drop_last, mode=mode, seed=config.run.seed, distribute=distribute
    )
