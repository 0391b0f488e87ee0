"""Dataset readers (ARCTIC, H2O), ARCTIC processing and the ArcticNet-SF sample format.

* :mod:`~hogsa_loader.datasets.conventions` — ARCTIC camera, crop and validity rules.
* :mod:`~hogsa_loader.datasets.types` — :class:`SequenceData`, the dataset-independent
  sequence interface both readers return.
* :mod:`~hogsa_loader.datasets.arctic` — :class:`ArcticRoot`, reader of a real ARCTIC root.
* :mod:`~hogsa_loader.datasets.arctic_processing` — ARCTIC's ``process_seq`` /
  ``build_split`` (processed splits).
* :mod:`~hogsa_loader.datasets.sample` / :mod:`~hogsa_loader.datasets.augment` — the one
  function that turns a posed (hands, object, camera, image) into ArcticNet-SF's
  ``(inputs, targets, meta_info)``, with ARCTIC's augmentation.
* :mod:`~hogsa_loader.datasets.arctic_dataset` — :class:`ArcticDataset`, the torch Dataset.
* :mod:`~hogsa_loader.datasets.h2o` — :class:`H2ORoot`, reader (and test-tree writer) of H2O.
"""

from hogsa_loader.datasets.arctic import ArcticRoot
from hogsa_loader.datasets.arctic_dataset import ArcticDataset
from hogsa_loader.datasets.h2o import H2ORoot
from hogsa_loader.datasets.sample import HandLabels, ObjectLabels, make_arctic_sample
from hogsa_loader.datasets.types import CameraTrack, HandTrack, ObjectTrack, SequenceData

__all__ = [
    "ArcticDataset",
    "ArcticRoot",
    "CameraTrack",
    "H2ORoot",
    "HandLabels",
    "HandTrack",
    "ObjectLabels",
    "ObjectTrack",
    "SequenceData",
    "make_arctic_sample",
]
