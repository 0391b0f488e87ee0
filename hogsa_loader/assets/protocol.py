"""Which subjects a dataset holds out for evaluation, and the one rule that keeps them out of
every training stage.

ARCTIC's protocols p1 (allocentric) and p2 (egocentric) hold out s05 (validation) and s03
(test); ``splits_json/protocol_<p>.json`` lists their sequences under ``"val"`` and
``"test"``. H2O's protocol holds out subject 4 (test; the HOGSA paper trains on subjects 1–3).
A training stage reads a held-out subject only when the user names it in ``allow_held_out``;
it then warns, and records the names in what it writes.
"""

from __future__ import annotations

import re
import warnings
from typing import Iterable, Optional, Union

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.h2o import H2ORoot
from hogsa_loader.assets.h2o_poses import H2OPoseRoot
from hogsa_loader.errors import UsageError

__all__ = ["ARCTIC_HELD_OUT", "H2O_HELD_OUT", "HeldOutWarning", "held_out_subjects", "training_subjects"]

#: ARCTIC's held-out subjects (protocols p1 and p2) and the split each is held out for; used
#: where a root has no ``splits_json/protocol_*.json``.
ARCTIC_HELD_OUT = {"s03": "test", "s05": "val"}
#: H2O's held-out subject (its folders ``subject4``, ``subject4_ego``, ``subject4_pose``).
H2O_HELD_OUT = {"subject4": "test"}


class HeldOutWarning(UserWarning):
    """A training stage reads a held-out subject because the user named it."""


def held_out_subjects(root: Union[ArcticRoot, H2ORoot, H2OPoseRoot]) -> dict[str, str]:
    """The subjects ``root`` holds out, each with the split it is held out for.

    Args:
        root: an ARCTIC root (its protocol files' ``val`` and ``test`` sequences; without any
            protocol file, :data:`ARCTIC_HELD_OUT`) or an H2O root (:data:`H2O_HELD_OUT`), also
            as an :class:`~hogsa_loader.assets.h2o_poses.H2OPoseRoot`.

    Returns:
        ``{subject: "val" | "test"}``.
    """
    if isinstance(root, H2OPoseRoot):
        root = root.h2o
    if isinstance(root, H2ORoot):  # subject4, or its ego / pose download (subject4_ego, subject4_pose)
        held = {s: "test" for s in root.subjects() if re.fullmatch(r"subject4(?:_ego|_pose)?", s)}
        return held or dict(H2O_HELD_OUT)
    out: dict[str, str] = {}
    found = False
    for protocol in ("p1", "p2"):
        if not root.protocol_path(protocol).is_file():
            continue
        found = True
        listed = root.protocol(protocol)
        for split in ("val", "test"):
            for sid_seq in listed.get(split, []):
                out.setdefault(sid_seq.split("/", 1)[0], split)
    return out if found else dict(ARCTIC_HELD_OUT)


def training_subjects(
    root: Union[ArcticRoot, H2ORoot, H2OPoseRoot],
    requested: Optional[Iterable[str]] = None,
    allow_held_out: Iterable[str] = (),
    stage: str = "this stage",
) -> list[str]:
    """The subjects a training stage may read.

    Args:
        root: the dataset.
        requested: the subjects the stage was asked for (``None``: every subject of ``root``
            that is not held out).
        allow_held_out: held-out subjects the user named to be read all the same.
        stage: what reads them, for messages (``"ContactNet"``).

    Returns:
        the sorted subjects: ``requested`` (or all), without held-out subjects unless allowed.

    Raises:
        UsageError: a requested subject is held out and not in ``allow_held_out``, or an
            allowed name is not a held-out subject of ``root``.
    """
    held = held_out_subjects(root)
    allowed = set(allow_held_out)
    unknown = sorted(allowed - set(held))
    if unknown:
        raise UsageError(f"allow_held_out names {unknown}, which {root} does not hold out (held out: {sorted(held)})")
    if requested is None:
        chosen = [s for s in root.subjects() if s not in held or s in allowed]
    else:
        chosen = list(dict.fromkeys(requested))
        refused = [s for s in chosen if s in held and s not in allowed]
        if refused:
            splits = ", ".join(f"{s} ({held[s]})" for s in refused)
            raise UsageError(
                f"{stage}: {splits} held out by the dataset's protocol; name them in allow_held_out "
                "(--allow-held-out) to train on them anyway"
            )
    used = sorted(set(chosen) & allowed)
    if used:
        warnings.warn(
            f"{stage} reads held-out subject(s) {used} as asked: figures on their split are no longer held out",
            HeldOutWarning,
            stacklevel=2,
        )
    return sorted(chosen)
