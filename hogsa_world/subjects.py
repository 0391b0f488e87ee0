"""Per-subject identity: hand shape (MANO betas), skin tone, gender, image-index offset.

Every subject draws from its own random stream ``(seed, crc32(sid))`` so adding a subject
to a preset does not change the others. Genders follow ARCTIC's subjects (:data:`ARCTIC_GENDERS`).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

__all__ = ["Subject", "ARCTIC_GENDERS", "SKIN_TONES", "make_subject", "subject_rng"]

#: Gender of ARCTIC's subjects (comments of ARCTIC's ``src/arctic/split.py``).
ARCTIC_GENDERS: dict[str, str] = {
    "s01": "female",
    "s02": "female",
    "s03": "male",
    "s04": "male",
    "s05": "female",
    "s06": "male",
    "s07": "male",
    "s08": "female",
    "s09": "female",
    "s10": "male",
}

#: Skin albedo anchors (linear-ish RGB in [0, 1]), light to dark; a subject picks a point
#: between two neighbours. The synthetic hand's default skin is (0.80, 0.60, 0.50).
SKIN_TONES: np.ndarray = np.array(
    [
        [0.92, 0.74, 0.64],
        [0.84, 0.63, 0.52],
        [0.74, 0.53, 0.40],
        [0.60, 0.41, 0.30],
        [0.44, 0.29, 0.21],
        [0.32, 0.21, 0.15],
    ]
)


@dataclass(frozen=True)
class Subject:
    """One subject.

    Attributes:
        sid: subject id (``s01``..).
        split: ``train`` / ``val`` / ``test``.
        gender: ``male`` / ``female`` (``misc.json``).
        betas: (10,) float32 MANO shape, shared by both hands.
        skin_rgb: (3,) skin albedo multiplier target (RGB in [0, 1]).
        ioi_offset: image file number = GT frame index + ``ioi_offset``.
    """

    sid: str
    split: str
    gender: str
    betas: np.ndarray
    skin_rgb: np.ndarray
    ioi_offset: int

    def to_json(self) -> dict:
        """JSON-friendly summary (for ``hogsa_world.json``)."""
        return {
            "sid": self.sid,
            "split": self.split,
            "gender": self.gender,
            "betas": [round(float(b), 6) for b in self.betas],
            "skin_rgb": [round(float(c), 4) for c in self.skin_rgb],
            "ioi_offset": int(self.ioi_offset),
        }


def subject_rng(seed: int, sid: str, stream: str = "subject") -> np.random.Generator:
    """Random stream of one subject (independent of the other subjects)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(sid.encode()), zlib.crc32(stream.encode())])


def make_subject(sid: str, split: str, seed: int, first: bool) -> Subject:
    """Draw a subject.

    Args:
        sid: subject id.
        split: its split.
        seed: world seed.
        first: the first subject of the world gets ``ioi_offset = 0``; all others get a
            non-zero offset in 1..6 so that off-by-offset bugs show.

    Returns:
        the subject.
    """
    rng = subject_rng(seed, sid)
    betas = np.clip(rng.normal(0.0, 0.8, size=10), -1.8, 1.8).astype(np.float32)
    k = rng.uniform(0, len(SKIN_TONES) - 1)
    i = int(np.floor(k))
    skin = SKIN_TONES[i] * (1 - (k - i)) + SKIN_TONES[min(i + 1, len(SKIN_TONES) - 1)] * (k - i)
    skin = np.clip(skin * rng.uniform(0.97, 1.03, size=3), 0.05, 1.0)
    gender = ARCTIC_GENDERS.get(sid, ("female", "male")[int(rng.integers(0, 2))])
    offset = 0 if first else int(rng.integers(1, 7))
    return Subject(sid=sid, split=split, gender=gender, betas=betas, skin_rgb=skin, ioi_offset=offset)
