"""The runtime floor: errors, blocks of rows, publishing and locks, Zarr I/O, checkpointed passes,
progress and the Dask cluster. Nothing here knows what a place, a hash or a recall is."""
