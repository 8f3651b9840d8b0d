"""Jobs: pipelines, the Dask cluster, progress, benchmarks and the online localisation command."""
