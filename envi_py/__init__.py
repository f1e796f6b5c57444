"""envi: environment imitation for verifying cyber-physical controllers against learned models."""

__version__ = "0.1.0"
