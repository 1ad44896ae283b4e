"""The notebooks' verdicts on the micro models, read from the committed test-split runs.

A notebook's live run covers a few pairs: it is a glimpse. Whether a paper's trend holds for the
micro models is read here from the committed JSON of the test split (:mod:`.evaluate_split`,
:mod:`.evaluate_layers`, at least 100 pairs where the run allowed, with intervals):

    from freereg_lib.training import verdicts
    print("\\n".join(verdicts.table1()))   # notebook 04; table4() notebook 03; table2() notebook 01
"""
from __future__ import annotations


import numpy as np

from freereg_lib.report.committed_charts import committed as load  # a committed JSON by name, None when absent
from freereg_lib.report.committed_charts import wilson_interval
from freereg_lib.report.vocabulary import Value, verdict, verdict_line

SPLIT_JSON = "test_split.json"
LAYERS_JSON = "test_split_layers.json"
TUNED_JSON = "fusion/test_split_fpfh0.15_w0.5.json"
DDIM_JSON = "ddim_iterations_test.json"
COMBINATIONS_JSON = "dev_layer_combinations.json"
MONO_JSON = "mono_modality_test.json"


def _ci(s: dict) -> str:
    return f"{s['mean']:.1f} % [{s['ci'][0]:.1f}, {s['ci'][1]:.1f}]"


def _points(d: dict) -> str:
    """A paired difference (:func:`~freereg_lib.training.evaluate_split.paired_difference`) with its interval."""
    return f"{d['diff']:+.1f} points [{d['diff_ci'][0]:+.1f}, {d['diff_ci'][1]:+.1f}]"


def _sig(p: float) -> str:
    from freereg_lib.training.evaluate import PERMUTATIONS

    shown = f"p < {1 / PERMUTATIONS:.4f}" if p <= 1.0 / (PERMUTATIONS + 1) + 1e-12 else f"p = {p:.4f}"
    return f"{shown}, {'significant' if p < 0.05 else 'not significant'} at 5 %"


def glimpse(n_pairs: int) -> str:
    """The label of a notebook's live verdict lines."""
    return (f"Glimpse: {n_pairs} live pair(s), too few to decide anything (RR moves in steps of "
            f"{100 / max(n_pairs, 1):.0f} points); the verdicts are the committed test split's, below.")


def _header(r: dict, name: str) -> str:
    return (f"Committed test split (freereg_lib/models/micro/weights/{name}): {r['n_pairs']} synthetic indoor pairs "
            f"never used for a choice, noise seed {r['noise_seed']} for every method; 95 % bootstrap intervals:")


def _setting(r: dict, fpfh_voxel: float | None = None) -> str:
    """The setting a committed split's verdicts were measured at, named in each verdict line."""
    from freereg_lib.config import config_for

    cfg = r.get("config") or {}
    voxel = fpfh_voxel if fpfh_voxel is not None else cfg.get("fpfh_voxel", config_for("synthetic_indoor").fpfh_voxel)
    return (f"micro backend, FPFH voxel {voxel:g} m, w = {cfg.get('fusion_w', 0.5):g}, "
            f"{cfg.get('ransac_iters', 50000)} RANSAC iterations")


def _value(name: str, stat: dict) -> Value:
    return Value(name, stat["mean"], tuple(stat["ci"]))


def _per_pair_test(a, b) -> tuple[float, float]:
    """Mean difference in points and the paired permutation p of two per-pair lists of rates in [0, 1]."""
    from freereg_lib.training.evaluate import paired_permutation_p

    x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return 100 * float(np.mean(x - y)), paired_permutation_p(x, y)


def _compare(claim: str, r: dict, a: tuple[str, str], b: tuple[str, str], metric: str, setting: str,
             names: tuple[str, str] | None = None) -> str:
    """A verdict line for ``metric`` of variant ``a`` (method, solver) above ``b`` on a committed split,
    its paired test computed from the per-pair values."""
    res = r["results"]
    ra, rb = res[" ".join(a)], res[" ".join(b)]
    per = {"IR": "IR_per_pair", "RR": "registered_per_pair"}
    if metric == "FMR":
        fmr = float((r.get("config") or {}).get("fmr_ratio", 0.05))
        xa, xb = (np.asarray(v["IR_per_pair"], dtype=np.float64) > fmr for v in (ra, rb))
    else:
        xa, xb = ra[per[metric]], rb[per[metric]]
    diff, p = _per_pair_test(xa, xb)
    na, nb = names or (" + ".join(a), " + ".join(b))
    return verdict_line(f"{claim} ({metric})", _value(na, ra[metric]), _value(nb, rb[metric]), diff, p,
                        r["n_pairs"], setting)


def table1() -> list[str]:
    """Table 1's reading on the micro models: fused FreeReg above FreeReg-D and FreeReg-G (IR, FMR, and
    RR with each half's own solver and with Kabsch), and Kabsch above PnP with the fused matches."""
    r = load(SPLIT_JSON)
    if r is None:
        return [f"(no committed {SPLIT_JSON}: run python -m freereg_lib.training.evaluate_split)"]
    at = _setting(r)
    lines = [_header(r, SPLIT_JSON)]
    for metric in ("IR", "FMR"):
        for other in ("FreeReg-D", "FreeReg-G"):
            lines.append("  " + _compare(f"fused above {other}", r, ("FreeReg", "kabsch"), (other, "kabsch"), metric,
                                         at, ("FreeReg", other)))
    for other, solver in (("FreeReg-D", "pnp"), ("FreeReg-G", "kabsch")):  # each half with the paper's solver for it
        lines.append("  " + _compare(f"fused above {other}, {solver}", r, ("FreeReg", solver), (other, solver), "RR", at))
    lines.append("  " + _compare("Kabsch above PnP with the fused matches, the paper's indoor order (63.8 vs 40.0 on "
                                 "3DMatch)", r, ("FreeReg", "kabsch"), ("FreeReg", "pnp"), "RR", at))
    return lines + tuned_fpfh()


def tuned_fpfh() -> list[str]:
    """The same test pairs with FPFH's voxel chosen on the development set (:mod:`.fusion_sweep`)."""
    r = load(TUNED_JSON)
    if r is None:
        return []
    voxel = float(r["fpfh"]["best"].split(":")[0])
    at = _setting({"config": {"fusion_w": 0.5}}, voxel) + ", the voxel chosen on the development set"
    res = {f"{m} kabsch": r["results"][f"w={w} kabsch"] for m, w in (("FreeReg", "0.5"), ("FreeReg-D", "1"),
                                                                     ("FreeReg-G", "0"))}
    view = {"n_pairs": r["n_pairs"], "results": res}
    lines = [f"With FPFH's voxel chosen on the development set (freereg_lib/models/micro/weights/{TUNED_JSON}), "
             f"the same {r['n_pairs']} test pairs:"]
    for other in ("FreeReg-D", "FreeReg-G"):
        lines.append("  " + _compare(f"fused above {other}", view, ("FreeReg", "kabsch"), (other, "kabsch"), "IR", at,
                                     ("FreeReg", other)))
    lines.append("  " + _compare("fused above FreeReg-D, Kabsch", view, ("FreeReg", "kabsch"), ("FreeReg-D", "kabsch"),
                                 "RR", at) + " (the paper's fused RR: 63.8 %)")
    return lines


def table4() -> list[str]:
    """Table 4's reading: w = 0.5 above its ends w = 1 (FreeReg-D) and w = 0 (FreeReg-G), Kabsch."""
    r = load(SPLIT_JSON)
    if r is None:
        return [f"(no committed {SPLIT_JSON}: run python -m freereg_lib.training.evaluate_split)"]
    at = _setting(r)
    w = r["config"]["fusion_w"]
    lines = [_header(r, SPLIT_JSON) + f" w = 1, {w:g} and 0 only (Kabsch)"]
    for metric in ("IR", "RR"):
        for other, end in (("FreeReg-D", 1), ("FreeReg-G", 0)):
            lines.append("  " + _compare(f"the paper's peak inside (0, 1): w = {w:g} above w = {end}", r,
                                         ("FreeReg", "kabsch"), (other, "kabsch"), metric, at,
                                         (f"w = {w:g}", f"w = {end}")))
    return lines + tuned_fpfh()


def table9() -> list[str]:
    """Table 9's reading: fused FreeReg's RR ladder, PnP above Kabsch at the tightest rung and Kabsch
    above PnP at the loosest, each rung's paired test from the per-pair errors."""
    r = load(SPLIT_JSON)
    if r is None or "ladder" not in r["results"]["FreeReg pnp"]:
        return [f"(no committed {SPLIT_JSON} with ladders)"]
    p, k = r["results"]["FreeReg pnp"], r["results"]["FreeReg kabsch"]
    rungs = list(p["ladder"])
    lines = [_header(r, SPLIT_JSON),
             "  FreeReg RR % PnP / Kabsch: " + ", ".join(f"{x[3:]} {p['ladder'][x]:.1f} / {k['ladder'][x]:.1f}"
                                                        for x in rungs)]
    at = _setting(r)
    for rung, (a, b) in ((rungs[0], (p, k)), (rungs[-1], (k, p))):
        claim = f"{'PnP above Kabsch' if a is p else 'Kabsch above PnP'} at {rung[3:]}"
        pa, pb = a.get("ladder_per_pair", {}).get(rung), b.get("ladder_per_pair", {}).get(rung)
        va = Value("PnP" if a is p else "Kabsch", a["ladder"][rung], wilson_interval(a["ladder"][rung], r["n_pairs"]))
        vb = Value("Kabsch" if a is p else "PnP", b["ladder"][rung], wilson_interval(b["ladder"][rung], r["n_pairs"]))
        if pa is None or pb is None:
            lines.append("  " + verdict_line(claim, va, vb, va.value - vb.value, None, r["n_pairs"], at))
        else:
            diff, pval = _per_pair_test(pa, pb)
            lines.append("  " + verdict_line(claim, va, vb, diff, pval, r["n_pairs"], at))
    return lines


def table2() -> list[str]:
    """Table 2's reading: the layer groups' order and the best combination, micro against paper."""
    r = load(LAYERS_JSON)
    if r is None:
        return [f"(no committed {LAYERS_JSON}: run python -m freereg_lib.training.evaluate_layers)"]
    v = r["verdict"]
    lines = [_header(r, LAYERS_JSON) + " FreeReg-D matches per Table 2 row (no pose solved)"]
    for m in ("IR", "IN"):
        o = v[f"{m} group order"]
        same = o["micro"] == o["paper"]
        lines.append(f"  {m} by layer group: micro {' > '.join(o['micro'])}; paper (3DMatch) {' > '.join(o['paper'])}"
                     f" -> {'the same order' if same else 'the micro models disagree with the paper'}")
        b = v[f"best combination by {m}"]
        m_row = r["rows"]["m"][m]
        if b["micro"] == "m":
            lines.append(f"  best combination by {m}: (0, 4, 6), as the paper ({m_row['mean']:.1f})")
        else:
            best = r["rows"][b["micro"]][m]
            lines.append(f"  best combination by {m}: {tuple(b['micro_layers'])} {best['mean']:.1f} "
                         f"[{best['ci'][0]:.1f}, {best['ci'][1]:.1f}] against (0, 4, 6) {m_row['mean']:.1f} "
                         f"[{m_row['ci'][0]:.1f}, {m_row['ci'][1]:.1f}] ({_sig(b['p_best_vs_m'])}; the paper's best: "
                         f"row {b['paper']}) -> " + ("(0, 4, 6) is not the best combination here" if b["p_best_vs_m"] < 0.05
                                                     else "a tie within the noise: no evidence against (0, 4, 6)"))
    return lines


def table13() -> list[str]:
    """Table 13's reading: fewer DDIM iterations, faster features, and what registration gives up."""
    r = load(DDIM_JSON)
    if r is None:
        return [f"(no committed {DDIM_JSON}: run python -m freereg_lib.training.evaluate_ddim)"]
    res, lo, hi = r["results"], min(r["steps"]), max(r["steps"])
    t_lo, t_hi = res[f"{lo} seconds"], res[f"{hi} seconds"]
    test = r["tests"][f"RR kabsch: {lo} - {hi} iterations"]
    ci = test["diff_ci"]
    lines = [_header(r, DDIM_JSON) + f" fused FreeReg, Kabsch-RANSAC (the paper's Table 13 row), "
             f"DDIM iterations {r['steps']}; made by: {'; '.join(r.get('commands', []))}"]
    lines += [f"  {s:2d} iterations: RR {_ci(res[f'{s} kabsch']['RR'])}, IR {res[f'{s} kabsch']['IR']['mean']:.1f} %, "
              f"diffusion half {res[f'{s} seconds']:.2f} s a pair" for s in r["steps"]]
    lines.append(f"  faster with {lo} iterations: {'yes' if t_lo < t_hi else 'no'} ({t_lo:.2f} s against {t_hi:.2f} s, "
                 f"x{t_hi / t_lo:.1f}; the paper: 4.7 s against 9.3 s a whole pair, x2.0; one timing, no verdict)")
    lines.append("  " + verdict_line(f"fewer iterations lose RR (the paper: -1.4 points; interval of the difference "
                                     f"[{ci[0]:+.1f}, {ci[1]:+.1f}])", Value(f"{lo} iterations", res[f'{lo} kabsch']['RR']['mean'],
                                                                           tuple(res[f'{lo} kabsch']['RR']['ci'])),
                                     Value(f"{hi} iterations", res[f'{hi} kabsch']['RR']['mean'],
                                           tuple(res[f'{hi} kabsch']['RR']['ci'])),
                                     test["diff"], test["p"], r["n_pairs"], "micro backend, fused FreeReg, Kabsch",
                                     expected_sign=-1))
    return lines


def table8() -> list[str]:
    """Table 8's reading: which three- or four-layer combination the development set prefers, and
    where the paper's choice (0, 4, 6) ranks, beside the paper's validation scene."""
    r = load(COMBINATIONS_JSON)
    if r is None:
        return [f"(no committed {COMBINATIONS_JSON}: run python -m freereg_lib.training.evaluate_combinations)"]
    rows, chosen = r["rows"], r["chosen"]
    lines = [f"Committed development set (freereg_lib/models/micro/weights/{COMBINATIONS_JSON}): {r['n_pairs']} "
             f"synthetic indoor pairs, where the micro models' choices are made (Table 8 is the paper's choice "
             f"table, on its validation scene BFO); FreeReg-D matches, no pose solved:"]
    for m in ("IR", "IN"):
        v = r["verdict"][m]
        best = v["micro_best"]
        b = rows[best][m]
        c = rows[chosen][m]
        test = ("" if v["p_best_vs_chosen"] is None else f"; best against (0, 4, 6): {_sig(v['p_best_vs_chosen'])}, "
                f"optimistic: the best was picked among {v['n_rows']} after the fact")
        lines.append(f"  by {m}: best {tuple(rows[best]['layers'])} {b['mean']:.1f} [{b['ci'][0]:.1f}, {b['ci'][1]:.1f}], "
                     f"(0, 4, 6) {c['mean']:.1f} [{c['ci'][0]:.1f}, {c['ci'][1]:.1f}] ranks {v['chosen_rank_micro']} of "
                     f"{v['n_rows']}{test}; the paper's best {tuple(v['paper_best_layers'])}, its (0, 4, 6) ranks "
                     f"{v['chosen_rank_paper']}; rank correlation with the paper {v['rank_correlation']:+.2f}")
    return lines


def _verdict(diff: float, p: float, paper_diff: float, n: int) -> str:
    """A paired difference read against the paper's sign, in the one vocabulary."""
    return verdict(diff, p, n, 1 if paper_diff > 0 else -1)


def table10() -> list[str]:
    """Table 10's reading: fused FreeReg between two images (RGB) and between two depth maps (DPT)
    against the image-to-cloud FreeReg on the same pairs, beside the paper's rows (its Table 10 and
    Table 1's FreeReg, Kabsch, on 3DMatch)."""
    from freereg_lib.data import paper

    r = load(MONO_JSON)
    if r is None:
        return [f"(no committed {MONO_JSON}: run python -m freereg_lib.training.evaluate_mono)"]
    mono = paper.table("table_mono_modality").set_index(["method", "input"])
    t1 = paper.table("table1_main")
    cross = t1[(t1.dataset == "3DMatch") & (t1.method == "FreeReg") & (t1.solver == "Kabsch")].iloc[0]
    theirs = {m: {k: float(mono.loc[("FreeReg", m), f"3DMatch_{k}"]) for k in ("FMR", "IR", "IN", "RR")}
              for m in ("RGB", "DPT")}
    theirs["cross"] = {k: float(cross[k]) for k in ("FMR", "IR", "IN", "RR")}
    res, tests = r["results"], r["tests"]
    lines = [_header(r, MONO_JSON) + " fused FreeReg on both views of each pair, Kabsch-RANSAC; made by: "
             + "; ".join(r.get("commands", []))]
    names = {"RGB": "RGB to RGB", "DPT": "depth to depth", "cross": "image to cloud"}
    for m, name in names.items():
        x, t = res[f"{m} kabsch"], theirs[m]
        lines.append(f"  {name:14s}: FMR {x['FMR']['mean']:5.1f} %, IR {_ci(x['IR'])}, IN {x['IN']:5.1f}, "
                     f"RR {_ci(x['RR'])}; the paper (3DMatch): FMR {t['FMR']:.1f}, IR {t['IR']:.1f}, "
                     f"IN {t['IN']:.1f}, RR {t['RR']:.1f}")
    for a, b in (("RGB", "cross"), ("DPT", "cross"), ("DPT", "RGB")):
        rr, ir = tests[f"RR kabsch: {a} - {b}"], tests[f"IR: {a} - {b}"]
        p_rr, p_ir = theirs[a]["RR"] - theirs[b]["RR"], theirs[a]["IR"] - theirs[b]["IR"]
        lines.append(f"  {names[a]} - {names[b]} (the paper: RR {p_rr:+.1f}, IR {p_ir:+.1f} points): RR {_points(rr)} "
                     f"({_sig(rr['p'])}) -> "
                     f"{_verdict(rr['diff'], rr['p'], p_rr, r['n_pairs'])}; IR {ir['diff']:+.1f} points ({_sig(ir['p'])}) -> "
                     f"{_verdict(ir['diff'], ir['p'], p_ir, r['n_pairs'])}")
    words = {a: _verdict(tests[f"RR kabsch: {a} - cross"]["diff"], tests[f"RR kabsch: {a} - cross"]["p"], 1.0,
                         r["n_pairs"]) for a in ("RGB", "DPT")}
    lines.append("  the paper's point, registration within one modality easier than image to cloud (RR above image "
                 f"to cloud): RGB to RGB {words['RGB']}; depth to depth {words['DPT']}")
    return lines
