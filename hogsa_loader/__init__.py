"""hogsa-loader: photoreal bimanual hand-object augmentation as a PyTorch data loader.

Data flows one way: assets (hand model, object templates) -> models (posed meshes,
Gaussians) -> render -> compose -> sample.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
