"""hogsa-loader: photoreal bimanual hand-object augmentation as a PyTorch data loader.

Data flows one way: assets (hand model, object templates) -> models (posed meshes,
Gaussians) -> render -> compose -> sample.

The main names are here, imported on first use (``import hogsa_loader`` imports no torch):

- :class:`HOGSADataset` — the endless synthetic stream (a torch ``IterableDataset``);
- :func:`wrap_train_loader` — ARCTIC's training loader with synthetic samples mixed in;
- :class:`MixedLoader` — real and synthetic batches with an exact synthetic share;
- :class:`SynthShardDataset` — samples exported as shards (``hogsa export``), read back;
- :func:`load_bundle` / :func:`write_bundle` / :class:`Bundle` — the trained models of a dataset;
- :class:`LoaderConfig` and :func:`with_options` — every setting of the stream.
"""

__version__ = "0.1.0"

#: public name -> module that defines it
_EXPORTS = {
    "Bundle": "hogsa_loader.models.bundle",
    "load_bundle": "hogsa_loader.models.bundle",
    "write_bundle": "hogsa_loader.models.bundle",
    "HOGSADataset": "hogsa_loader.sample.dataset",
    "MixedLoader": "hogsa_loader.sample.mixing",
    "LoaderConfig": "hogsa_loader.sample.config",
    "with_options": "hogsa_loader.sample.config",
    "SynthShardDataset": "hogsa_loader.sample.export.reader",
    "wrap_train_loader": "hogsa_loader.integrations.arctic",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):  # lazy: importing the package stays cheap
    if name in _EXPORTS:
        import importlib  # deferred: importing the package stays cheap (no torch)

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'hogsa_loader' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
