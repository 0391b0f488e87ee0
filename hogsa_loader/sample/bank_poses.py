"""``poses="bank"``: sample POM-optimised grasps from the bundle's pose banks.

Banks are written by ``hogsa train bank`` (:mod:`hogsa_loader.models.pom.bank`) and
copied into a bundle by ``hogsa_loader/cli/build_bundle.py --pose-bank``. Every entry names its
source (subject, sequence, frame) and object; an entry serves the (subject, object) HOGS
model of that subject and object. The bank stores poses in the same convention as
:class:`~hogsa_loader.assets.types.SequenceData` (ARCTIC world frame), so rows go to
:meth:`HogsModel.scene` unchanged.
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch

from hogsa_loader.errors import AssetError
from hogsa_loader.models.pom.bank import load_pose_bank
from hogsa_loader.sample.poses import PoseBatch, PoseContext, register_pose_source

__all__ = ["BankPoses"]

_HAND_KEYS = ("rot", "pose", "betas", "trans")


class BankPoses:
    """Uniformly sampled rows of pose banks, grouped by (subject, object).

    Args:
        context: the loader's :class:`PoseContext` (its bundle's ``pose_banks`` are used
            unless ``banks`` is given).
        banks: explicit bank folders (default: every bank of the bundle).
        accepted_only: keep only rows that passed GraspTTA's acceptance test.

    Raises:
        AssetError: no bank, or no usable row for one of the loader's (subject, object) keys.
    """

    name = "bank"

    def __init__(self, context: PoseContext, banks: Optional[Sequence[Any]] = None, accepted_only: bool = True) -> None:
        if banks is None:
            entries = getattr(context.bundle, "pose_banks", {}) or {}
            banks = [e.path for e in entries.values()]
        if not banks:
            where = getattr(context.bundle, "path", "the bundle")
            raise AssetError(
                where,
                "poses='bank' needs a pose bank "
                "(hogsa train bank, then python -m hogsa_loader.cli.build_bundle --pose-bank)",
            )
        rows: dict[tuple[str, str], list[dict[str, np.ndarray]]] = {}
        prov: dict[tuple[str, str], list[dict[str, Any]]] = {}
        for path in banks:
            bank = load_pose_bank(path)
            t = bank.tensors()
            for i, (sid, seq, frame) in enumerate(bank.sources):
                if accepted_only and float(t["accept"][i]) < 0.5:
                    continue
                key = (sid, bank.state.obj_names[i])
                row = {f"{s}_{k}": t[f"{s}_{k}"][i].double().numpy() for s in ("right", "left") for k in _HAND_KEYS}
                row["obj_arti"] = t["obj_arti"][i : i + 1].double().numpy()
                row["obj_rot"] = t["obj_rot"][i].double().numpy()
                row["obj_trans"] = t["obj_trans"][i].double().numpy()
                rows.setdefault(key, []).append(row)
                prov.setdefault(key, []).append(
                    {
                        "pose_source": "bank",
                        "bank": str(path),
                        "row": i,
                        "sequence": f"{sid}/{seq}",
                        "frame": int(frame),
                    }
                )
        missing = [k for k in context.keys if k not in rows]
        if missing:
            raise AssetError(
                banks[0], f"pose banks have no accepted grasp for (subject, object) {missing}; have {sorted(rows)}"
            )
        self.rows, self.prov = rows, prov

    @property
    def keys(self) -> list[tuple[str, str]]:
        return sorted(self.rows)

    def __len__(self) -> int:
        return sum(len(v) for v in self.rows.values())

    def sample(self, key: tuple[str, str], rngs: Sequence[np.random.Generator]) -> PoseBatch:
        """``len(rngs)`` rows of ``key``, row i drawn with ``rngs[i]`` only."""
        if key not in self.rows:
            raise KeyError(f"no pose-bank rows for (subject, object) {key}; have {self.keys}")
        table, prov = self.rows[key], self.prov[key]
        picks = [int(rng.integers(len(table))) for rng in rngs]
        poses = {k: torch.as_tensor(np.stack([table[j][k] for j in picks])) for k in table[0]}
        return PoseBatch(poses, [dict(prov[j]) for j in picks])


register_pose_source("bank", BankPoses)
