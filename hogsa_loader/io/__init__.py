"""Ground-floor file I/O shared by every package of the library.

- :mod:`~hogsa_loader.io.atomic`: atomic file writes (temporary file, fsync, ``os.replace``).
- :mod:`~hogsa_loader.io.tensors`: checkpoints as safetensors + a JSON manifest with one
  shared header (:class:`ManifestFormat`) and one validator for every checkpoint kind.
- :mod:`~hogsa_loader.io.pickle_caps`: element and depth caps of what an unpickler built.
- :mod:`~hogsa_loader.io.mano_pickle`: restricted unpickler of MANO ``.pkl`` files.
- :mod:`~hogsa_loader.io.npy`: restricted reader of ``np.save``-d files (ARCTIC ``.npy``).
"""

from hogsa_loader.io.atomic import atomic_open, atomic_write, atomic_write_json
from hogsa_loader.io.tensors import (
    ManifestFormat,
    read_checked_tensors,
    read_manifest,
    read_tensors,
    save_checkpoint,
    write_tensors_and_manifest,
)

__all__ = [
    "ManifestFormat",
    "atomic_open",
    "atomic_write",
    "atomic_write_json",
    "read_checked_tensors",
    "read_manifest",
    "read_tensors",
    "save_checkpoint",
    "write_tensors_and_manifest",
]
