"""The documentation pages, shipped inside the package as ``vprscale.docs``: an installed
vprscale's ``--help`` points at them on disk (a wheel has no checkout beside it)."""
