"""The batch pipelines (``vprscale run quickstart``, ``vprscale run paper``): shipped inside the
package as ``vprscale.pipelines``, so that a wheel install runs them by name."""
