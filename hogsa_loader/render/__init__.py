"""Classical rendering utilities (mesh rasterisation, previews)."""
