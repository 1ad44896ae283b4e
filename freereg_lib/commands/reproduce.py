"""``make reproduce``: run the companion's main job on the embedded default and print the table.

With the notebooks present it executes them all with papermill on their defaults (synthetic scenes;
the micro models in 01-04, 06 and 07, the stub in 00 and 05), one a core side by side, into a run
folder, then prints where the executed notebooks, figures and tables are, and the benchmark's table
beside the paper's. Then it renders the
executed notebooks as a book (``<out>/site/index.html``, :mod:`freereg_lib.commands.book`) and rewrites
the README's gallery (``figures/gallery/``, :mod:`freereg_lib.commands.gallery`) from the figures of the run;
``--no-book`` skips both.
It ends by checking this machine against the committed test split (``--check-pairs`` of its pairs
recomputed, :mod:`freereg_lib.commands.agreement`) and prints the agreement line.
``--quick`` skips the notebooks and registers a handful of synthetic pairs directly.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from freereg_lib.commands.process_io import redirect_stderr

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


def _execute(nb: Path, target: Path, seed: int, out_dir: Path) -> tuple[float, str | None]:
    """Run one notebook with papermill; ``(seconds, None)`` or ``(seconds, the error's last line)``."""
    import papermill as pm

    t0 = time.perf_counter()
    try:
        pm.execute_notebook(str(nb), str(target), parameters={"seed": seed, "out_dir": str(out_dir)},
                            kernel_name="python3", cwd=str(nb.parent), progress_bar=False,
                            shutdown_kernel="immediate")  # as batch.run_job: no ~1 s teardown a kernel
    except Exception as exc:  # keep going: the executed copy holds the error
        text = str(exc).strip()
        return time.perf_counter() - t0, text.splitlines()[-1] if text else repr(exc)
    return time.perf_counter() - t0, None


def notebooks(out: Path, seed: int, jobs: int | None = None) -> int:
    """Execute every notebook with papermill into ``out``, ``jobs`` at a time (default: one a core, at
    most one a notebook); returns the number that failed.

    The notebooks are independent (each writes its own ``out/<stem>`` and figures with its own prefix)
    and each kernel's models run on one thread (``cpu_threads``), so running them side by side changes
    no number: it uses the cores that one kernel at a time leaves idle, and beside another busy process
    each kernel still runs a whole core's work instead of spinning threads."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from tqdm.auto import tqdm

    out.mkdir(parents=True, exist_ok=True)
    books = sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb"))
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(books)))
    failed, seconds = [], {}
    with ProcessPoolExecutor(max_workers=jobs, initializer=redirect_stderr, initargs=(out / "kernels.log",)) as pool:
        futures = {pool.submit(_execute, nb, out / nb.name, seed, out / nb.stem): nb for nb in books}
        for fut in tqdm(as_completed(futures), total=len(futures), desc=f"notebooks ({jobs} at a time)"):
            nb = futures[fut]
            seconds[nb.name], error = fut.result()
            if error is not None:
                failed.append((nb.name, error))
    print("\nSeconds per notebook: " + ", ".join(f"{name[:2]} {seconds[name]:.0f}" for name in sorted(seconds)))
    print(f"\nExecuted notebooks: {out}")
    print(f"Figures:            {ROOT / 'figures'}")
    for stem in sorted(p.stem for p in books):
        tables = sorted((out / stem).glob("*.csv")) if (out / stem).is_dir() else []
        if tables:
            print(f"Tables of {stem}: " + ", ".join(str(t.relative_to(out)) for t in tables))
    print("\n" + committed_table1())
    bench = out / "04_benchmark" / "table1_side_by_side.md"
    if bench.is_file():
        print("\nA glimpse, no verdict: this run's live pairs (a pair moves RR by 100 / n points, and which pair "
              "flips depends on the CPU: docs/reproducibility.md)\n\n" + bench.read_text())
    for name, why in failed:
        print(f"FAILED {name}: {why}", file=sys.stderr)
    return len(failed)


def committed_table1() -> str:
    """Table 1 of the committed test split (the verdict, with intervals), as Markdown."""
    from freereg_lib.data import paper
    from freereg_lib.report import committed_charts

    split = committed_charts.committed("test_split.json")
    if split is None:
        return "(no committed test split: python -m freereg_lib.training.evaluate_split)"
    return committed_charts.table1_markdown(split, paper.table("table1_main"))


def agreement(out: Path, n_pairs: int, jobs: int | None) -> bool:
    """This machine against the committed test split on ``n_pairs`` of its pairs
    (:mod:`freereg_lib.commands.agreement`): prints the agreement line; False when a verdict changed."""
    from freereg_lib.commands import agreement as check
    from freereg_lib.models.micro.diffusion import WEIGHTS_DIR

    jobs = max(1, min(jobs or os.cpu_count() or 1, n_pairs))
    print(f"\nChecking this machine against the committed test split: {n_pairs} of its pairs recomputed "
          f"({jobs} at a time)")
    line, result = check.check(n_pairs, out / "agreement", Path(WEIGHTS_DIR) / "test_split.json", jobs, fresh=True)
    print(f"{line}\n(details: {out / 'agreement' / 'agreement.md'}; all 100 pairs: "
          f"python -m freereg_lib.commands.agreement --pairs 100)")
    return all(v["unchanged"] for v in result["verdicts"].values())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="freereg reproduce", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/reproduce", help="run folder for executed notebooks")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="skip the notebooks; register synthetic pairs directly")
    ap.add_argument("--pairs", type=int, default=6, help="pairs for --quick")
    ap.add_argument("--no-book", action="store_true", help="do not write the site and the README's gallery")
    ap.add_argument("--check-pairs", type=int, default=10,
                    help="committed test-split pairs recomputed to check this machine against them (0: no check)")
    ap.add_argument("--jobs", type=int, default=None,
                    help="notebooks run side by side (default: one a core); each kernel's models use one thread")
    args = ap.parse_args(argv)
    if args.jobs is not None and args.jobs < 1:
        ap.error(f"--jobs must be at least 1, got {args.jobs}")
    if args.check_pairs < 0:
        ap.error(f"--check-pairs must be 0 or more, got {args.check_pairs}")
    if args.quick or not any(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb")):
        quick(args.pairs, args.seed)
        return 0
    out = Path(args.out).resolve()
    failed = notebooks(out, args.seed, args.jobs)
    if args.check_pairs:
        agreement(out, args.check_pairs, args.jobs)
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
