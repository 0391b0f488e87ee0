"""What the user holds, read and checked: dataset roots (ARCTIC, H2O), MANO, object templates.

* :mod:`~hogsa_loader.assets.arctic` — :class:`ArcticRoot`, reader of a real ARCTIC root.
* :mod:`~hogsa_loader.assets.h2o` — :class:`H2ORoot`, reader of an H2O root;
  :mod:`~hogsa_loader.assets.h2o_poses` — its grasps as the pose stages read them.
* :mod:`~hogsa_loader.assets.types` — :class:`SequenceData`, the dataset-independent
  sequence interface both readers return.
* :mod:`~hogsa_loader.assets.protocol` — held-out subjects of a root's evaluation protocol.
* :mod:`~hogsa_loader.assets.conventions` — ARCTIC camera, crop and validity rules.
* :mod:`~hogsa_loader.assets.arctic_processing` — ARCTIC's ``process_seq`` /
  ``build_split`` (processed splits).

MANO files are read by :mod:`hogsa_loader.assets.hands`, object templates by
:mod:`hogsa_loader.assets.objects`.
"""

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.h2o import H2ORoot
from hogsa_loader.assets.protocol import held_out_subjects, training_subjects
from hogsa_loader.assets.types import CameraTrack, HandTrack, ObjectTrack, SequenceData

__all__ = [
    "ArcticRoot",
    "CameraTrack",
    "H2ORoot",
    "HandTrack",
    "ObjectTrack",
    "SequenceData",
    "held_out_subjects",
    "training_subjects",
]
