"""The method: PCA, CoarseHash, the inverted lists, the query engine and online matching (docs/method.md)."""
