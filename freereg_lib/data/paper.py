"""The paper's own numbers, and tables that put them beside a re-run.

The CSVs under ``freereg_lib/data/paper_tables/`` are copied verbatim from the paper's
tables; nothing here computes them.
"""
from __future__ import annotations

from pathlib import Path

import pandas as pd

TABLES = Path(__file__).resolve().parent / "paper_tables"
FLOATS = Path(__file__).resolve().parent / "paper_floats.csv"


def floats() -> pd.DataFrame:
    """The paper's 23 floats (main text and appendix, in the LaTeX's order): ``number``
    ("Fig. 3", "Table 10"), ``kind`` (figure / table) and what each ``shows``."""
    return pd.read_csv(FLOATS)


def table(name: str) -> pd.DataFrame:
    """A paper table by file stem, e.g. ``"table1_main"`` or ``"table4_fusion_weight"``."""
    path = TABLES / f"{name}.csv"
    if not path.is_file():
        known = sorted(p.stem for p in TABLES.glob("*.csv"))
        raise FileNotFoundError(f"no paper table {name!r} in {TABLES}; known: {known}")
    return pd.read_csv(path)


def side_by_side(
    paper: pd.DataFrame, ours: pd.DataFrame, keys: list[str], metrics: list[str], backend: str
) -> pd.DataFrame:
    """Rows of ``ours`` joined to the paper's on ``keys``; columns ``<m>_paper`` then ``<m>``.

    The ``backend`` column names what produced the re-run numbers. Rows missing on either
    side show NaN rather than disappearing.
    """
    left = paper[keys + [m for m in metrics if m in paper.columns]].rename(
        columns={m: f"{m}_paper" for m in metrics}
    )
    right = ours[keys + [m for m in metrics if m in ours.columns]]
    out = left.merge(right, on=keys, how="outer")
    cols = keys + [c for m in metrics for c in (f"{m}_paper", m) if c in out.columns]
    out = out[cols].copy()
    out.insert(len(keys), "backend", backend)
    return out
