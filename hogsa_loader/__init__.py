"""hogsa-loader: photoreal bimanual hand-object augmentation as a PyTorch data loader.

Data flows one way: assets (hand model, object templates) -> models (posed meshes,
Gaussians) -> render -> compose -> sample.
"""

__version__ = "0.1.0"

__all__ = ["__version__", "Bundle", "load_bundle", "write_bundle"]


def __getattr__(name: str):  # lazy: importing the package stays cheap
    if name in ("Bundle", "load_bundle", "write_bundle"):
        from hogsa_loader import bundle  # deferred: importing the package stays cheap (no torch)

        return getattr(bundle, name)
    raise AttributeError(f"module 'hogsa_loader' has no attribute {name!r}")
