"""The dataset recipes (paper Table I), one TOML file per scale: shipped inside the package as
``vprscale.recipes``, so that ``vprscale build --scale 20K`` finds them in a wheel install too."""
