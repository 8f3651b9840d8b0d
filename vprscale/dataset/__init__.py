"""Dataset engineering: the sources, the recipe, the streamed build and the store layouts (docs/dataset.md)."""
