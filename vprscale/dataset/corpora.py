"""The billion-scale corpora a recipe can take as its large part in place of Deep1B
(docs/dataset.md, "Other corpora").

The recipe takes the corpus's rows as it takes Deep1B's: homogenised, then its exact PCA keeps
the recipe's D = 96 components, so a wider corpus (BIGANN's 128-d SIFT, Text2Image's 200-d) is
projected to the same width, and a narrower one is refused. The names only say which corpus a
file is, and hold its published width, form and where big-ann-benchmarks serves it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from vprscale.core.errors import InputError
from vprscale.core.objects import is_url


@dataclass(frozen=True)
class Corpus:
    """A public billion-scale corpus: its rows' width, its base file's form, and where it is served."""

    name: str
    dim: int
    suffix: str  # the base file's form: fbin (float32), u8bin, i8bin
    url: str | None  # the base file (None: no direct link; --url names one)
    terms: str  # the page that states its terms of use


CORPORA = {c.name: c for c in (
    Corpus("deep1b", 96, "fbin", "https://storage.yandexcloud.net/yandex-research/ann-datasets/DEEP/base.1B.fbin",
           "https://research.yandex.com/blog/benchmarks-for-billion-scale-similarity-search"),
    Corpus("bigann", 128, "u8bin", "https://dl.fbaipublicfiles.com/billion-scale-ann-benchmarks/bigann/base.1B.u8bin",
           "http://corpus-texmex.irisa.fr/"),
    Corpus("text2image", 200, "fbin",
           "https://storage.yandexcloud.net/yandex-research/ann-datasets/T2I/base.1B.fbin",
           "https://research.yandex.com/blog/benchmarks-for-billion-scale-similarity-search"),
    Corpus("turing", 100, "fbin",
           "https://comp21storage.z5.web.core.windows.net/comp21/MSFT-TURING-ANNS/base1b.fbin",
           "https://big-ann-benchmarks.com/MSFT-Turing-ANNS-terms.txt"),
    Corpus("spacev", 100, "i8bin", None, "https://github.com/microsoft/SPTAG/tree/main/datasets/SPACEV1B"),
)}


def parse_base(value: str) -> tuple[Corpus | None, str]:
    """``--base [CORPUS:]PATH``: the corpus it names (None: unnamed) and the path or URL."""
    if is_url(value):  # a URL's scheme is not a corpus
        return None, value
    name, sep, rest = value.partition(":")
    if sep and name in CORPORA:
        if not rest:
            raise InputError(f"--base {value}: give the {name} file after the colon ({name}:PATH or {name}:URL)")
        return CORPORA[name], rest
    if sep and re.fullmatch(r"[A-Za-z][\w-]+", name):  # a word no corpus has (one letter: a Windows drive)
        raise InputError(f"--base {value}: {name} is not a corpus vprscale knows ({', '.join(CORPORA)}); "
                         "give CORPUS:PATH, or the path alone")
    return None, value


def check_corpus(corpus: Corpus | None, name: str, dim: int) -> None:
    """A named corpus's file must have its published width."""
    if corpus is not None and dim != corpus.dim:
        raise InputError(f"{name}: {dim}-d rows, but {corpus.name}'s are {corpus.dim}-d (is it the {corpus.name} "
                         "base file?)")
