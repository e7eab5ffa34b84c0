"""Per-launch tables: the rows of ``fabkit explore`` and ``fabkit robustness`` as CSV
(floats written exactly, so they read back bit for bit) or Parquet. Beside
:mod:`fabkit.io`, which writes the bytes atomically."""

from __future__ import annotations

import math

import numpy as np

from .errors import SpecError


def table_format(path: str | None) -> str | None:
    """'csv' | 'parquet' from ``--out``'s extension (None without --out); SpecError
    for another extension, or for Parquet without pyarrow."""
    if path is None:
        return None
    p = str(path).lower()
    if p.endswith(".csv"):
        return "csv"
    if p.endswith(".parquet") or p.endswith(".pq"):
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise SpecError("Parquet needs pyarrow (pip install 'fabkit[parquet]'); or give a .csv file",
                            key="--out") from None
        return "parquet"
    raise SpecError(f"must end in .csv or .parquet, got {str(path)!r}", key="--out")


def table_bytes(columns: dict, fmt: str) -> bytes:
    """The columns (equal lengths) as CSV (floats written exactly, nan empty) or Parquet."""
    names = list(columns)
    cols = [list(np.asarray(c).tolist()) if not isinstance(c, list) else c for c in columns.values()]
    if fmt == "parquet":
        import io

        import pyarrow as pa
        import pyarrow.parquet as pq

        buf = io.BytesIO()
        pq.write_table(pa.table({k: c for k, c in zip(names, cols)}), buf)
        return buf.getvalue()
    import csv
    import io

    def cell(x):
        if isinstance(x, float):
            return repr(x) if math.isfinite(x) else ""
        return "" if x is None else x

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    for row in zip(*cols):
        w.writerow([cell(x) for x in row])
    return buf.getvalue().encode()
