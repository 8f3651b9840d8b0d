"""Descriptors held as a list column of Parquet files (``file.parquet:emb``, or a directory of
Parquet files read as one table in name order): how VectorDBBench and many embedding stores
keep vectors, and the metadata LAION-style pipelines write beside their shards; local, or by URL
(a file, or on object storage a prefix of Parquet objects), read by byte ranges. A column of
``list``, ``large_list`` or ``fixed_size_list`` of floats or integers, every row of one length;
read a row group at a time inside each read."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from vprscale.core.errors import InputError
from vprscale.core.objects import is_url, public
from vprscale.dataset.sources.base import RowSource, part_spans
from vprscale.dataset.sources.chunks import local_chunks
from vprscale.dataset.sources.fingerprint import file_fingerprint
from vprscale.dataset.sources.remote import remote_file, remote_fingerprint, remote_objects


def _list_columns(schema: pa.Schema) -> list[str]:
    return [f.name for f in schema if pa.types.is_list(f.type) or pa.types.is_large_list(f.type)
            or pa.types.is_fixed_size_list(f.type)]


class ParquetRowsSource(RowSource):
    """The list column ``column`` of a Parquet file, or of every ``.parquet`` file of a directory
    in name order (numbers as numbers); ``column`` None: the files' one list column."""

    def __init__(self, path: str | os.PathLike, column: str | None) -> None:
        if is_url(str(path)):  # a file, or on object storage a prefix of Parquet objects
            self.path: Path | str = public(str(path))
            self.files: list[Path | str] = remote_objects(str(path), ".parquet")
        else:
            self.path = Path(path).absolute()  # tasks may run in another directory (a cluster's workers)
            self.files = _local_files(self.path)
        groups, schema = [], None
        for i, f in enumerate(self.files):
            shown = public(f) if isinstance(f, str) else f
            try:
                meta = pq.ParquetFile(_open(f)).metadata
            except (OSError, pa.ArrowException) as exc:
                raise InputError(f"{shown}: not a readable Parquet file ({str(exc).splitlines()[0][:160]})") from None
            if schema is None:
                schema = meta.schema.to_arrow_schema()
                names = _list_columns(schema)
                if column is None and len(names) != 1:
                    raise InputError(f"{self.path}: name the column of descriptors ({self.path}:COLUMN); list "
                                     f"columns: {', '.join(names) or 'none'}")
                column = column or names[0]
                if column not in names:
                    raise InputError(f"{self.path}: no list column {column!r} (list columns: "
                                     f"{', '.join(names) or 'none'})")
                value = schema.field(column).type.value_type
                if not (pa.types.is_floating(value) or pa.types.is_integer(value)):
                    raise InputError(f"{self.path}:{column}: lists of {value}, not of numbers")
            else:
                here = meta.schema.to_arrow_schema()
                if column not in here.names:
                    raise InputError(f"{shown}: no column {column!r}, which the files before it hold (columns: "
                                     f"{', '.join(here.names) or 'none'})")
                if here.field(column).type != schema.field(column).type:
                    raise InputError(f"{shown}: column {column!r} is {here.field(column).type}, the files before it "
                                     f"{schema.field(column).type}")
            groups += [(i, g, meta.row_group(g).num_rows) for g in range(meta.num_row_groups)]
        self.column = column
        self.name = f"{self.path}:{column}"
        self._files = [remote_fingerprint(f) if isinstance(f, str) else file_fingerprint(f) for f in self.files]
        self.groups = [(i, g) for i, g, _ in groups]
        self.starts = np.concatenate([[0], np.cumsum([n for _, _, n in groups], dtype=np.int64)])
        self.n_rows = int(self.starts[-1])
        kind = schema.field(column).type
        if pa.types.is_fixed_size_list(kind):
            self.dim = int(kind.list_size)
        else:
            first = next((k for k, (a, b) in enumerate(zip(self.starts[:-1], self.starts[1:], strict=True)) if b > a),
                         None)
            self.dim = 0 if first is None else self._first_length(first)
        if self.n_rows and self.dim == 0:
            raise InputError(f"{self.name}: row 0 holds no values")

    def _first_length(self, k: int) -> int:
        """The length of the first row of row group ``k`` (the width every row must have)."""
        lists = self._group(k)
        if lists.is_null()[0].as_py():
            raise InputError(f"{self.name}: row {int(self.starts[k])} is null")
        return len(lists[0])

    def _group(self, k: int) -> pa.ListArray:
        i, g = self.groups[k]
        return pq.ParquetFile(_open(self.files[i])).read_row_group(g, columns=[self.column]).column(0).combine_chunks()

    def _read(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, self.dim), np.float32)
        for k, lo, hi in part_spans(self.starts, start, stop):
            a, b = int(self.starts[k]) + lo, int(self.starts[k]) + hi  # absolute rows
            lists = self._group(k).slice(lo, hi - lo)
            if lists.null_count:
                raise InputError(f"{self.name}: row {a + int(np.flatnonzero(lists.is_null())[0])} is null")
            if not pa.types.is_fixed_size_list(lists.type):
                lengths = np.diff(lists.offsets.to_numpy())
                bad = np.flatnonzero(lengths != self.dim)
                if len(bad):
                    raise InputError(f"{self.name}: row {a + int(bad[0])} holds {int(lengths[bad[0]])} values, the "
                                     f"rows before it {self.dim}")
            values = lists.flatten().to_numpy(zero_copy_only=False)
            out[a - start : b - start] = values.reshape(b - a, self.dim)
        return out

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "parquet", "column": self.column, "rows": self.n_rows, "dim": self.dim,
                "files": self._files}


def _local_files(path: Path) -> list[Path | str]:
    """A Parquet file, or every ``.parquet`` file of a directory in name order (numbers as numbers)."""
    if path.is_dir():
        return list(local_chunks(path, ".parquet", ".parquet files"))
    if path.is_file():
        return [path]
    raise InputError(f"{path}: no such file or directory")


def _open(f: Path | str) -> Any:
    """A local file as its path; one at a URL as a file object over its byte ranges."""
    return remote_file(f) if isinstance(f, str) else f
