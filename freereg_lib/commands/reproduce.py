"""``make reproduce``: run the companion's main job on the embedded default and print the table.

With the notebooks present it executes all five with papermill on their defaults
(synthetic scenes; the micro models in 01-04, the stub in 00 and 05) into a run folder, then prints where the executed
notebooks, figures and tables are, and the benchmark's table beside the paper's. Then it renders the
executed notebooks as a book (``<out>/site/index.html``, :mod:`freereg_lib.commands.book`) and rewrites
the README's gallery (``figures/gallery/``, :mod:`freereg_lib.commands.gallery`) from the figures of the run;
``--no-book`` skips both.
``--quick`` skips the notebooks and registers a handful of synthetic pairs directly.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
NOTEBOOKS = ROOT / "notebooks"


def quick(n_pairs: int, seed: int) -> None:
    """Register ``n_pairs`` synthetic indoor pairs with the stub backend and print the table."""
    from freereg_lib import pipeline
    from freereg_lib.config import config_for
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    cfg = config_for("synthetic_indoor", seed=seed)
    backend = get_backend("stub", cfg)
    pairs = synthetic.make_pairs(n_pairs, "indoor", seed=seed)
    rows = pipeline.run_pairs(pairs, backend, cfg)
    table = pipeline.summarize(rows, cfg)
    cols = ["method", "solver", "FMR", "IR", "IN", "RR", "RE", "TE", "n_pairs", "n_failed"]
    print(f"\nFreeReg on {n_pairs} synthetic indoor pairs, backend: {backend.label}; "
          f"Kabsch-RANSAC scoring {cfg.kabsch_scoring!r}")
    print(table[cols].to_markdown(index=False, floatfmt=".1f"))


def notebooks(out: Path, seed: int) -> int:
    """Execute every notebook with papermill into ``out``; returns the number that failed."""
    import papermill as pm
    from tqdm.auto import tqdm

    out.mkdir(parents=True, exist_ok=True)
    failed = []
    books = sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb"))
    for nb in tqdm(books, desc="notebooks"):
        target = out / nb.name
        try:
            pm.execute_notebook(
                str(nb), str(target), parameters={"seed": seed, "out_dir": str(out / nb.stem)},
                kernel_name="python3", cwd=str(NOTEBOOKS), progress_bar=False,
            )
        except Exception as exc:  # keep going: the executed copy holds the error
            failed.append((nb.name, str(exc).strip().splitlines()[-1] if str(exc).strip() else repr(exc)))
    print(f"\nExecuted notebooks: {out}")
    print(f"Figures:            {ROOT / 'figures'}")
    for stem in sorted(p.stem for p in books):
        tables = sorted((out / stem).glob("*.csv")) if (out / stem).is_dir() else []
        if tables:
            print(f"Tables of {stem}: " + ", ".join(str(t.relative_to(out)) for t in tables))
    bench = out / "04_benchmark" / "table1_side_by_side.md"
    if bench.is_file():
        print("\n" + bench.read_text())
    for name, why in failed:
        print(f"FAILED {name}: {why}", file=sys.stderr)
    return len(failed)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="freereg reproduce", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/reproduce", help="run folder for executed notebooks")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="skip the notebooks; register synthetic pairs directly")
    ap.add_argument("--pairs", type=int, default=6, help="pairs for --quick")
    ap.add_argument("--no-book", action="store_true", help="do not write the site and the README's gallery")
    args = ap.parse_args(argv)
    if args.quick or not any(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb")):
        quick(args.pairs, args.seed)
        return 0
    out = Path(args.out).resolve()
    failed = notebooks(out, args.seed)
    if not args.no_book:
        from freereg_lib.commands.book import BookError

        try:
            book(out)
        except BookError as exc:
            print(f"book: {exc}", file=sys.stderr)
            return 1
    return 1 if failed else 0


def book(out: Path) -> None:
    """The book of the run (``out/site``) and the README's gallery, from the figures of the run."""
    from freereg_lib.commands.book import build_book
    from freereg_lib.commands.gallery import write_gallery

    index = build_book(out, figures_dir=ROOT / "figures")
    print(f"\nSite:               {index}")
    written = write_gallery(ROOT / "figures")
    print("Gallery (README):   " + ", ".join(f"{p.name} ({p.stat().st_size // 1024} KB)" for p in written))


if __name__ == "__main__":
    sys.exit(main())
