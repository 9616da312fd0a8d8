"""radarpc: radar spectra to point clouds, and the models that consume them."""
__version__ = "0.1.0"
