"""Build hooks (the rest of the build is pyproject.toml's): a wheel or sdist records the commit
it was built from in the package, so that an installed vprscale's outputs name it in their
provenance as a checkout's do (vprscale/core/commit.py)."""

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

ROOT = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("vprscale_commit", ROOT / "vprscale" / "core" / "commit.py")
commit = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(commit)


class BuildPy(build_py):
    """Copies the package, then writes the checkout's commit into the copy (from an sdist: the
    sdist's record, copied as package data)."""

    def run(self) -> None:
        super().run()
        if not self.editable_mode:
            commit.record(ROOT, Path(self.build_lib) / "vprscale")


class Sdist(sdist):
    """Writes the checkout's commit into the source tree being archived."""

    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        super().make_release_tree(base_dir, files)
        commit.record(ROOT, Path(base_dir) / "vprscale")


setup(cmdclass={"build_py": BuildPy, "sdist": Sdist})
