"""Dataset readers (ARCTIC, H2O), ARCTIC processing and the ArcticNet-SF sample format."""
