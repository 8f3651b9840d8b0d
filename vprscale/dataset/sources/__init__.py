"""Readers of the real descriptor layouts (Deep1B fvecs and fbin, the FAS100K npz), the synthetic
generator that writes them, and the row-source interface every one of them implements."""
