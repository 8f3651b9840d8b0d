"""vprscale: out-of-core dataset engineering and evaluation for coarse-hash place recognition."""

__version__ = "0.1.0"
