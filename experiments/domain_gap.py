#!/usr/bin/env python
"""Why synthetic frames help a baseline or not: domain gap and pose coverage of the downstream data.

Reads the folder of ``experiments/downstream.py`` (its exports in ``synthetic/`` and the world they
were rendered from: ``setup/world``, or the ``--setup-data`` root their ``index.json`` names) and
measures, per synthetic variant:

* **domain gap** — a small CNN trained to tell real training patches from synthetic ones
  (held-out accuracy; 50 % = indistinguishable). The same classifier on real training vs
  real validation patches (another subject) is the control: the accuracy that a change of
  subject and sequence alone gives. Low-level image statistics beside it: sharpness
  (variance of the Laplacian of the grey patch), mean saturation, mean brightness.
* **pose coverage** — for every validation frame, the nearest articulated hand of a pose
  set, as the root-relative joint error (mm) between the two hands posed with the same
  (zero) global rotation and mean shape: the real training poses, the synthetic poses, and
  both. It bounds what more poses can add: a variant whose poses are no nearer to the
  validation hands than the real ones adds views and appearance, not articulation.
* **object articulation** — the range of the object's articulation angle per set.
* **labels** — the synthetic samples dropped at export, by reason (a sample whose 2D labels
  do not lie on its rendered pixels is never exported).
* **the task model's view** — ARCTIC's metrics of a trained ArcticNet-SF (by default the
  downstream real arm's seed-0 model) on its own training frames, on the held-out subject and
  on each variant's frames. Synthetic frames it handles as well as its training frames hold
  little it has not learned; much worse, new content (poses, views) or a gap it does not
  bridge. Its training-frame error against its held-out error tells an underfit model (both
  high: more data cannot help yet) from an overfit one.

Outputs in ``--out`` (default: ``DOWNSTREAM/analysis``): ``domain_gap.json``,
``domain_gap.md`` and ``domain_gap.png`` (patches of each source side by side).

Usage::

    python experiments/domain_gap.py --downstream runs/downstream
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch
from torch import nn

from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, dataclass_from_args

VARIANTS = ("full", "no_pom", "no_srm")


@dataclass
class GapConfig:
    """The analysis of one downstream folder."""

    downstream: str = field(default="runs/downstream", metadata={"help": "folder of experiments/downstream.py"})
    out: Optional[str] = field(default=None, metadata={"help": "output folder (default: DOWNSTREAM/analysis)"})
    variants: tuple[str, ...] = field(default=VARIANTS, metadata={"help": "synthetic variants to analyse"})
    img_res: int = field(default=96, metadata={"help": "patch side of the classifier (the export's size)"})
    per_class: int = field(default=640, metadata={"help": "training patches per class"})
    test_per_class: int = field(default=256, metadata={"help": "held-out patches per class"})
    steps: int = field(default=300, metadata={"help": "classifier steps"})
    batch_size: int = field(default=32, metadata={"help": "classifier batch (half per class)"})
    seed: int = field(default=0, metadata={"help": "draws of patches and classifier initialisation"})
    threads: int = field(default=0, metadata={"help": "torch threads (0: all available cores)"})
    model: Optional[str] = field(
        default=None,
        metadata={
            "help": "a downstream run's model.safetensors (with its model.json) for the task model's view "
            "(default: DOWNSTREAM/runs/real/seed0/model.safetensors when it exists; 'none' skips it)"
        },
    )
    model_frames: int = field(default=256, metadata={"help": "frames per source for the task model's view"})


# ----------------------------------------------------------------------------- sources


def find_export(downstream: Path, variant: str, img_res: int) -> Path:
    """The newest complete export of ``variant`` at ``img_res`` under ``downstream/synthetic``."""
    found = []
    for d in sorted((downstream / "synthetic").glob(f"{variant}-*")):
        index = d / "index.json"
        if not index.is_file():
            continue
        rec = json.loads(index.read_text())
        if rec.get("complete") and int(rec.get("info", {}).get("img_res", -1)) == img_res:
            found.append((index.stat().st_mtime, d))
    if not found:
        where = downstream / "synthetic"
        raise SystemExit(f"domain_gap: error: no export of variant {variant!r} at {img_res} px in {where}")
    return max(found)[1]


def export_drops(export: Path) -> dict[str, Any]:
    """What an export folder's ``index.json`` records of its samples: requested, written and
    dropped (in all once complete, and by reason where every shard recorded its reasons)."""
    index = json.loads((export / "index.json").read_text())
    written = int(index.get("num_samples_written", 0))
    rec: dict[str, Any] = {"requested": index.get("num"), "written": written}
    if index.get("complete") and index.get("num") is not None:
        rec["dropped"] = int(index["num"]) - written
    for reason, n in (index.get("dropped") or {}).items():
        rec[reason] = int(n)
    return rec


def _with_splits(world: Path) -> Optional[Path]:
    """The ARCTIC data root of ``world`` (the world folder or its ``arctic_data/data``) that has
    ``splits/``; None when neither has."""
    return next((c for c in (world / "arctic_data" / "data", world) if (c / "splits").is_dir()), None)


def world_root(downstream: Path, exports: Sequence[Path] = ()) -> Path:
    """The ARCTIC data root of a downstream folder: the one root its exports were rendered from
    (``data`` in their ``index.json``; a folder made with ``--setup-data`` has no world of its
    own), else the world it built (``setup/world``); exports of several roots are refused."""
    named = {json.loads((e / "index.json").read_text()).get("info", {}).get("data") for e in exports}
    roots = sorted(str(r) for r in named if r is not None)
    if len(roots) > 1:
        raise SystemExit(f"domain_gap: error: the exports were rendered from several data roots: {roots}")
    root = _with_splits(Path(roots[0])) if roots else None
    root = root or _with_splits(downstream / "setup" / "world")
    if root is None:
        where = downstream / "setup" / "world"
        raise SystemExit(f"domain_gap: error: no world with splits/ under {where}; the exports' data roots: {roots}")
    return root


def real_dataset(root: Path, split: str, img_res: int) -> Any:
    from hogsa_loader.sample.arctic_dataset import ArcticDataset
    from hogsa_loader.sample.augment import ArcticConfig

    return ArcticDataset(root, split=split, augment=False, seed=0, config=ArcticConfig(img_res=img_res))


def synthetic_dataset(export: Path, img_res: int) -> Any:
    from hogsa_loader.sample.augment import ArcticConfig
    from hogsa_loader.sample.export import SynthShardSamples

    return SynthShardSamples(export, augment=False, seed=0, cfg=ArcticConfig(img_res=img_res))


def draw(ds: Any, n: int, rng: np.random.Generator) -> list[int]:
    """``n`` distinct indices of ``ds`` (all of them when it is smaller)."""
    return sorted(rng.permutation(len(ds))[: min(n, len(ds))].tolist())


def patches(ds: Any, idx: Sequence[int]) -> tuple[torch.Tensor, list[dict[str, Any]]]:
    """Normalised images (N, 3, R, R) and the targets of ``ds[idx]``."""
    imgs, targets = [], []
    for i in idx:
        inputs, t, _ = ds[i]
        imgs.append(inputs["img"])
        targets.append(t)
    return torch.stack(imgs), targets


# ----------------------------------------------------------------------------- the task model's view

TASK_METRICS = ("mpjpe/ra/h", "cdev/ho", "mrrpe/r/l", "aae")


def task_model_path(downstream: Path, given: Optional[str]) -> Optional[Path]:
    """The model of the task model's view: ``given`` (None for 'none'), else the real arm's
    seed-0 model of the downstream folder when it exists."""
    if given is not None:
        return None if given == "none" else Path(given)
    default = downstream / "runs" / "real" / "seed0" / "model.safetensors"
    return default if default.is_file() else None


def load_task_model(path: Path, root: Path) -> tuple[nn.Module, Any, int]:
    """The ArcticNet-SF of a downstream run (``model.safetensors`` beside its ``model.json``),
    its body layers and patch side.

    Raises:
        AssetError: naming the file when the manifest or a tensor is missing or wrong.
    """
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines.arcticnet_sf import load_saved_model
    from hogsa_loader.baselines.engine import BodyLayers

    layers = BodyLayers.from_root(ArcticRoot(root))
    model, settings = load_saved_model(path, layers.mano_r, layers.mano_l, layers.objects)
    return model, layers, int(settings["model"]["img_res"])


def task_view(
    model: nn.Module, layers: Any, img_res: int, sources: dict[str, Any], n: int, seed: int
) -> dict[str, dict[str, float]]:
    """ARCTIC's metrics of ``model`` on ``n`` frames (a fixed draw) of each source dataset."""
    from torch.utils.data import DataLoader, Subset

    from hogsa_loader.baselines.engine import evaluate

    out = {}
    for name, ds in sources.items():
        idx = draw(ds, n, np.random.default_rng([seed, 7]))
        ev = evaluate(model, DataLoader(Subset(ds, idx), batch_size=32), layers, img_res, "cpu", temporal=False)
        values = {k: float(ev["summary"][k]) for k in TASK_METRICS}
        out[name] = {"frames": len(idx), **{k: (v if np.isfinite(v) else None) for k, v in values.items()}}
    return out


# ----------------------------------------------------------------------------- domain gap


class PatchClassifier(nn.Module):
    """Four strided conv blocks, global average pooling, one logit: real (0) vs other (1)."""

    def __init__(self) -> None:
        super().__init__()
        chans = [3, 16, 32, 64, 64]
        layers: list[nn.Module] = []
        for a, b in zip(chans[:-1], chans[1:], strict=True):
            layers += [nn.Conv2d(a, b, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(b), nn.ReLU(inplace=True)]
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(chans[-1], 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, 3, R, R) → (B,) logits."""
        return self.head(self.features(x).mean((2, 3)))[:, 0]


def classifier_accuracy(
    a: tuple[torch.Tensor, torch.Tensor], b: tuple[torch.Tensor, torch.Tensor], cfg: GapConfig
) -> dict[str, float]:
    """Held-out accuracy of a :class:`PatchClassifier` separating source ``a`` (train, test) from ``b``."""
    g = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    net = PatchClassifier()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    half = cfg.batch_size // 2
    net.train()
    for _ in range(cfg.steps):
        ia = torch.randint(len(a[0]), (half,), generator=g)
        ib = torch.randint(len(b[0]), (half,), generator=g)
        x = torch.cat([a[0][ia], b[0][ib]])
        flip = torch.rand(len(x), generator=g) < 0.5
        x = torch.where(flip[:, None, None, None], x.flip(-1), x)
        y = torch.cat([torch.zeros(half), torch.ones(half)])
        loss = nn.functional.binary_cross_entropy_with_logits(net(x), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        pa = torch.cat([net(x) for x in a[1].split(64)])
        pb = torch.cat([net(x) for x in b[1].split(64)])
    correct = int((pa < 0).sum()) + int((pb > 0).sum())
    return {
        "accuracy": correct / (len(pa) + len(pb)),
        "test_a": len(pa),
        "test_b": len(pb),
        "train_a": len(a[0]),
        "train_b": len(b[0]),
        "final_loss": float(loss),
    }


def to_uint8(imgs: torch.Tensor) -> np.ndarray:
    """Normalised (N, 3, R, R) → (N, R, R, 3) uint8 RGB."""
    from hogsa_loader.view.grid import input_image

    return np.stack([input_image(im) for im in imgs])


def image_statistics(imgs: torch.Tensor) -> dict[str, float]:
    """Mean (and std) over patches of sharpness, saturation and brightness."""
    import cv2

    sharp, sat, val = [], [], []
    for im in to_uint8(imgs):
        grey = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
        sharp.append(cv2.Laplacian(grey, cv2.CV_64F).var())
        hsv = cv2.cvtColor(im, cv2.COLOR_RGB2HSV)
        sat.append(hsv[..., 1].mean())
        val.append(hsv[..., 2].mean())
    out = {}
    for name, xs in (("sharpness", sharp), ("saturation", sat), ("brightness", val)):
        out[name] = float(np.mean(xs))
        out[name + "_std"] = float(np.std(xs))
    return out


# ----------------------------------------------------------------------------- pose coverage


def articulated_joints(targets: Sequence[dict[str, Any]], mano_r: nn.Module, mano_l: nn.Module) -> np.ndarray:
    """Root-relative joints (M, 21, 3) in metres of every valid hand of ``targets``, posed with
    zero global rotation and zero shape (left hands mirrored onto the right: x → −x)."""
    out = []
    for side, layer in (("r", mano_r), ("l", mano_l)):
        poses = [
            np.asarray(t[f"mano.pose.{side}"], dtype=np.float32)[3:]
            for t in targets
            if float(t["right_valid" if side == "r" else "left_valid"]) > 0.5
        ]
        if not poses:
            continue
        with torch.no_grad():
            j = layer(hand_pose=torch.from_numpy(np.stack(poses))).joints
        j = (j - j[:, :1]).numpy()
        if side == "l":
            j = j * np.array([-1.0, 1.0, 1.0], dtype=j.dtype)
        out.append(j)
    return np.concatenate(out) if out else np.zeros((0, 21, 3), np.float32)


def nearest_joint_error(query: np.ndarray, bank: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(Q,) mean joint distance (m) from each query hand (Q, 21, 3) to its nearest in ``bank`` (N, 21, 3)."""
    if len(bank) == 0:
        return np.full(len(query), np.nan)
    b = torch.from_numpy(bank).float()
    best = []
    for q in torch.from_numpy(query).float().split(chunk):
        d = (q[:, None] - b[None]).norm(dim=-1).mean(-1)  # (q, N)
        best.append(d.min(1).values)
    return torch.cat(best).numpy()


def unique_poses(targets: Sequence[dict[str, Any]], imgnames: Sequence[str]) -> list[dict[str, Any]]:
    """One target per (subject, sequence, frame): the views of a frame share its articulation."""
    seen, out = set(), []
    for t, name in zip(targets, imgnames, strict=True):
        parts = str(name).replace("\\", "/").split("/")
        key = (parts[-4], parts[-3], parts[-1])
        if key not in seen:
            seen.add(key)
            out.append(t)
    return out


# ----------------------------------------------------------------------------- report


def markdown(rec: dict[str, Any]) -> str:
    lines = [
        "# Domain gap and pose coverage of the downstream data",
        "",
        f"World `{rec['world']}`; patches {rec['config']['img_res']}² without augmentation; "
        f"classifier: {rec['config']['per_class']} training and {rec['config']['test_per_class']} held-out "
        f"patches per class, {rec['config']['steps']} steps.",
        "",
        "| real training vs | classifier accuracy | sharpness | saturation | brightness |",
        "|---|---|---|---|---|",
    ]
    st = rec["statistics"]

    def stats(name: str) -> str:
        s = st[name]
        return f"{s['sharpness']:.0f} ± {s['sharpness_std']:.0f} | {s['saturation']:.1f} | {s['brightness']:.1f}"

    lines.append(f"| (itself) | — | {stats('real_train')} |")
    for name, acc in rec["classifier"].items():
        lines.append(f"| {name} | {100 * acc['accuracy']:.1f} % | {stats(name)} |")
    lines += [
        "",
        "Nearest articulated hand of each validation hand (root-relative joint error, mm; "
        "zero global rotation, zero shape):",
        "",
        "| pose set | hands | mean | median | 90th percentile |",
        "|---|---|---|---|---|",
    ]
    for name, c in rec["coverage"].items():
        lines.append(f"| {name} | {c['hands']} | {c['mean_mm']:.1f} | {c['median_mm']:.1f} | {c['p90_mm']:.1f} |")
    lines += ["", "| set | object articulation (rad): min | median | max |", "|---|---|---|---|"]
    for name, a in rec["articulation"].items():
        lines.append(f"| {name} | {a['min']:.3f} | {a['median']:.3f} | {a['max']:.3f} |")
    if rec.get("task_model"):
        tm = rec["task_model"]
        lines += [
            "",
            f"The task model's view (`{tm['model']}`; {tm['img_res']}² frames, no augmentation):",
            "",
            "| frames | n | MPJPE_h (mm) | CDev_ho (mm) | MRRPE_rl (mm) | AAE (°) |",
            "|---|---|---|---|---|---|",
        ]
        for name, m in tm["metrics"].items():
            cells = [("—" if m[k] is None else f"{m[k]:.1f}") for k in TASK_METRICS]
            lines.append(f"| {name} | {m['frames']} | " + " | ".join(cells) + " |")
    if rec.get("dropped"):
        lines += [
            "",
            "Synthetic samples dropped at export (by reason): "
            + "; ".join(f"{v}: {d}" for v, d in rec["dropped"].items()),
        ]
    return "\n".join(lines) + "\n"


def picture(sources: dict[str, torch.Tensor], path: Path, per_row: int = 8) -> None:
    """One row of ``per_row`` patches per source, labelled."""
    import cv2

    rows = []
    for name, imgs in sources.items():
        tiles = list(to_uint8(imgs[:per_row]))
        r = tiles[0].shape[0]
        tiles += [np.zeros((r, r, 3), np.uint8)] * (per_row - len(tiles))
        row = np.concatenate(tiles, axis=1)
        label = np.full((22, row.shape[1], 3), 255, np.uint8)
        cv2.putText(label, name, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        rows += [label, row]
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(rows), cv2.COLOR_RGB2BGR))


def run(cfg: GapConfig) -> dict[str, Any]:
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.system import available_cores

    torch.set_num_threads(cfg.threads or available_cores())
    t0 = time.perf_counter()
    downstream = Path(cfg.downstream).resolve()
    out = Path(cfg.out) if cfg.out else downstream / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    found = {v: find_export(downstream, v, cfg.img_res) for v in cfg.variants}
    root = world_root(downstream, list(found.values()))
    rng = np.random.default_rng(cfg.seed)
    n = cfg.per_class + cfg.test_per_class

    def split_sets(imgs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        k = min(cfg.test_per_class, len(imgs) // 4)
        return imgs[k:], imgs[:k]

    mpath = task_model_path(downstream, cfg.model)
    if mpath is not None:
        model, mlayers, mres = load_task_model(mpath, root)  # before any work: a wrong file stops here
        if mres != cfg.img_res:
            raise SystemExit(f"domain_gap: error: {mpath} takes {mres}² patches; run with --img-res {mres}")
    print(f"[domain_gap] world {root}", flush=True)
    real_tr = real_dataset(root, "p1_train", cfg.img_res)
    real_va = real_dataset(root, "p1_val", cfg.img_res)
    idx_tr, idx_va = draw(real_tr, n, rng), draw(real_va, n, rng)
    imgs_tr, t_tr = patches(real_tr, rng.permutation(idx_tr))
    imgs_va, _ = patches(real_va, rng.permutation(idx_va))
    sources = {"real_train": imgs_tr, "real_val": imgs_va}
    exports, dropped = {}, {}
    for v in cfg.variants:
        exp = found[v]
        ds = synthetic_dataset(exp, cfg.img_res)
        imgs, _ = patches(ds, rng.permutation(draw(ds, n, rng)))
        sources[f"synthetic_{v}"] = imgs
        exports[v] = str(exp)
        dropped[v] = export_drops(exp)
        print(f"[domain_gap] {v}: {len(ds)} frames in {exp}", flush=True)
    stats = {name: image_statistics(imgs) for name, imgs in sources.items()}
    a = split_sets(imgs_tr)
    classifier = {}
    for name, imgs in sources.items():
        if name == "real_train":
            continue
        classifier[name] = classifier_accuracy(a, split_sets(imgs), cfg)
        print(f"[domain_gap] real_train vs {name}: accuracy {100 * classifier[name]['accuracy']:.1f} %", flush=True)

    # pose coverage: every frame of each set (views of a frame counted once)
    root_obj = ArcticRoot(root)
    layers = root_obj.mano_layers()
    all_tr = [real_tr[i][1] for i in range(0, len(real_tr))] if len(real_tr) <= 4000 else None
    if all_tr is None:
        all_tr = [real_tr[i][1] for i in draw(real_tr, 4000, rng)]
        names_tr = None
    else:
        names_tr = real_tr.imgnames
    pose_tr = unique_poses(all_tr, names_tr) if names_tr is not None else all_tr
    pose_va = unique_poses([real_va[i][1] for i in range(len(real_va))], real_va.imgnames)
    j_tr = articulated_joints(pose_tr, layers["right"], layers["left"])
    j_va = articulated_joints(pose_va, layers["right"], layers["left"])
    coverage: dict[str, Any] = {}
    articulation: dict[str, Any] = {}

    def cover(name: str, bank: np.ndarray) -> None:
        e = nearest_joint_error(j_va, bank) * 1000.0
        coverage[name] = {
            "hands": int(len(bank)),
            "mean_mm": float(np.mean(e)),
            "median_mm": float(np.median(e)),
            "p90_mm": float(np.percentile(e, 90)),
        }

    def arti(name: str, ts: Sequence[dict[str, Any]]) -> None:
        r = np.array([float(t["object.radian"]) for t in ts])
        articulation[name] = {"min": float(r.min()), "median": float(np.median(r)), "max": float(r.max())}

    cover("real_train", j_tr)
    arti("real_train", pose_tr)
    arti("real_val", pose_va)
    for v in cfg.variants:
        ds = synthetic_dataset(Path(exports[v]), cfg.img_res)
        ts = [ds[i][1] for i in range(len(ds))]
        j_syn = articulated_joints(ts, layers["right"], layers["left"])
        cover(f"synthetic_{v}", j_syn)
        cover(f"real_train + synthetic_{v}", np.concatenate([j_tr, j_syn]))
        arti(f"synthetic_{v}", ts)
    coverage["(validation hands)"] = {"hands": int(len(j_va)), "mean_mm": 0.0, "median_mm": 0.0, "p90_mm": 0.0}
    task_model = None
    if mpath is not None:
        sets = {"real_train": real_dataset(root, "p1_train", mres), "real_val": real_dataset(root, "p1_val", mres)}
        sets.update({f"synthetic_{v}": synthetic_dataset(Path(exports[v]), mres) for v in cfg.variants})
        task_model = {
            "model": str(mpath),
            "img_res": mres,
            "metrics": task_view(model, mlayers, mres, sets, cfg.model_frames, cfg.seed),
        }
        for name, m in task_model["metrics"].items():
            print(f"[domain_gap] task model on {name}: MPJPE_h {m['mpjpe/ra/h']:.1f} mm", flush=True)
    rec = {
        "config": asdict(cfg),
        "world": str(root),
        "exports": exports,
        "classifier": classifier,
        "statistics": stats,
        "coverage": coverage,
        "articulation": articulation,
        "dropped": dropped,
        "task_model": task_model,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    (out / "domain_gap.json").write_text(json.dumps(rec, indent=1) + "\n")
    (out / "domain_gap.md").write_text(markdown(rec))
    picture(sources, out / "domain_gap.png")
    print(markdown(rec), flush=True)
    print(f"[domain_gap] {out / 'domain_gap.json'}, domain_gap.md, domain_gap.png; {rec['seconds']:.0f} s", flush=True)
    return rec


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_dataclass_arguments(p, GapConfig, GapConfig())
    run(dataclass_from_args(GapConfig, p.parse_args(argv)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
