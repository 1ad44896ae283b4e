"""The notebooks' verdicts on the micro models, read from the committed test-split runs.

A notebook's live run covers a few pairs: it is a glimpse. Whether a paper's trend holds for the
micro models is read here from the committed JSON of the test split (:mod:`.evaluate_split`,
:mod:`.evaluate_layers`, at least 100 pairs where the run allowed, with intervals):

    from freereg_lib.training import verdicts
    print("\\n".join(verdicts.table1()))   # notebook 04; table4() notebook 03; table2() notebook 01
"""
from __future__ import annotations

import json
from pathlib import Path

SPLIT_JSON = "test_split.json"
LAYERS_JSON = "test_split_layers.json"
TUNED_JSON = "fusion/test_split_fpfh0.15_w0.5.json"
DDIM_JSON = "ddim_iterations_test.json"
COMBINATIONS_JSON = "dev_layer_combinations.json"
MONO_JSON = "mono_modality_test.json"


def _load(name: str) -> dict | None:
    from freereg_lib.models.micro.diffusion import WEIGHTS_DIR

    path = Path(WEIGHTS_DIR) / name
    return json.loads(path.read_text()) if path.exists() else None


def _ci(s: dict) -> str:
    return f"{s['mean']:.1f} % [{s['ci'][0]:.1f}, {s['ci'][1]:.1f}]"


def _points(d: dict) -> str:
    """A paired difference (:func:`~freereg_lib.training.evaluate_split.paired_difference`) with its interval."""
    return f"{d['diff']:+.1f} points [{d['diff_ci'][0]:+.1f}, {d['diff_ci'][1]:+.1f}]"


def _sig(p: float) -> str:
    from freereg_lib.training.evaluate import PERMUTATIONS

    shown = f"p < {1 / PERMUTATIONS:.4f}" if p <= 1.0 / (PERMUTATIONS + 1) + 1e-12 else f"p = {p:.4f}"
    return f"{shown}, {'significant' if p < 0.05 else 'not significant'} at 5 %"


def _ahead(a: float, b: float) -> str:
    return "holds" if a > b else ("cannot be told (a tie)" if a == b else "does not hold")


def _claim(above: bool, tests: dict, key: str, halves: dict[str, str]) -> str:
    """'holds' only when the fused value is above both halves and significantly so (paired test)."""
    if not above:
        return "does not hold here"
    weak = [f"{name} (p = {tests[key.format(other)]['p']:.2f})" for other, name in halves.items()
            if tests[key.format(other)]["p"] >= 0.05]
    return "holds here (significantly above both)" if not weak else (
        "not shown here: above both in the mean, not significantly above " + " and ".join(weak))


def glimpse(n_pairs: int) -> str:
    """The label of a notebook's live verdict lines."""
    return (f"Glimpse: {n_pairs} live pair(s), too few to decide anything (RR moves in steps of "
            f"{100 / max(n_pairs, 1):.0f} points); the verdicts are the committed test split's, below.")


def _header(r: dict, name: str) -> str:
    return (f"Committed test split (freereg_lib/models/micro/weights/{name}): {r['n_pairs']} synthetic indoor pairs "
            f"never used for a choice, noise seed {r['noise_seed']} for every method; 95 % bootstrap intervals:")


def table1() -> list[str]:
    """Table 1's reading on the micro models: fused FreeReg against FreeReg-D and FreeReg-G (IR, FMR),
    and which solver registers more with the fused matches."""
    r = _load(SPLIT_JSON)
    if r is None:
        return [f"(no committed {SPLIT_JSON}: run python -m freereg_lib.training.evaluate_split)"]
    res, tests = r["results"], r["tests"]
    lines = [_header(r, SPLIT_JSON)]
    for m in ("IR", "FMR"):
        f, d, g = (res[f"{k} kabsch"][m] for k in ("FreeReg", "FreeReg-D", "FreeReg-G"))
        above = f["mean"] > max(d["mean"], g["mean"])
        verdict = (_claim(above, tests, "IR: FreeReg - {}", {"FreeReg-D": "FreeReg-D", "FreeReg-G": "FreeReg-G"})
                   if m == "IR" else ("above both in the mean" if above else "not above both"))
        lines.append(f"  {m}: FreeReg {_ci(f)}, FreeReg-D {_ci(d)}, FreeReg-G {_ci(g)}; fused above both "
                     f"(the paper's indoor rows): {verdict}")
    for other in ("FreeReg-D", "FreeReg-G"):
        t = tests[f"IR: FreeReg - {other}"]
        lines.append(f"    IR, FreeReg - {other}: {t['diff']:+.1f} points ({_sig(t['p'])})")
    k, p = res["FreeReg kabsch"]["RR"], res["FreeReg pnp"]["RR"]
    lines.append(f"  RR with the fused matches: Kabsch {_ci(k)}, PnP {_ci(p)}; the paper's Kabsch ahead indoors "
                 f"(63.8 vs 40.0 on 3DMatch): {_ahead(k['mean'], p['mean'])} here"
                 + (f" ({_sig(tests['RR FreeReg: kabsch - pnp']['p'])})" if "RR FreeReg: kabsch - pnp" in tests else ""))
    for m in ("FreeReg-D", "FreeReg-G"):
        lines.append(f"  RR {m}: Kabsch {_ci(res[f'{m} kabsch']['RR'])}, PnP {_ci(res[f'{m} pnp']['RR'])}")
    return lines + tuned_fpfh()


def tuned_fpfh() -> list[str]:
    """The same test pairs with FPFH's voxel chosen on the development set (:mod:`.fusion_sweep`)."""
    r = _load(TUNED_JSON)
    if r is None:
        return []
    f, d, g = (r["results"][f"w={w} kabsch"] for w in ("0.5", "1", "0"))
    above = f["IR"]["mean"] > max(d["IR"]["mean"], g["IR"]["mean"])
    sig = above and f["p_IR_vs_D"] < 0.05 and f["p_IR_vs_G"] < 0.05
    return [f"With FPFH's voxel chosen on the development set ({r['fpfh']['best'].split(':')[0]} m; "
            f"freereg_lib/models/micro/weights/{TUNED_JSON}), the same {r['n_pairs']} test pairs:",
            f"  IR: FreeReg {_ci(f['IR'])}, FreeReg-D {_ci(d['IR'])}, FreeReg-G {_ci(g['IR'])}; fused above both: "
            + ("holds here (significantly above both: " if sig else "not shown here (")
            + f"{_sig(f['p_IR_vs_D'])} against FreeReg-D, {_sig(f['p_IR_vs_G'])} against FreeReg-G)",
            f"  RR, Kabsch: FreeReg {_ci(f['RR'])}, FreeReg-D {_ci(d['RR'])} (the paper's fused RR: 63.8 %)"]


def table4() -> list[str]:
    """Table 4's reading: w = 0.5 against its ends w = 1 (FreeReg-D) and w = 0 (FreeReg-G), Kabsch."""
    r = _load(SPLIT_JSON)
    if r is None:
        return [f"(no committed {SPLIT_JSON}: run python -m freereg_lib.training.evaluate_split)"]
    res, tests = r["results"], r["tests"]
    lines = [_header(r, SPLIT_JSON) + f" w = 1, {r['config']['fusion_w']:g} and 0 only (Kabsch)"]
    for m in ("IR", "RR"):
        one, half, zero = (res[f"{k} kabsch"][m] for k in ("FreeReg-D", "FreeReg", "FreeReg-G"))
        above = half["mean"] > max(one["mean"], zero["mean"])
        key = "IR" if m == "IR" else "RR kabsch"
        verdict = _claim(above, tests, key + ": FreeReg - {}", {"FreeReg-D": "w = 1", "FreeReg-G": "w = 0"})
        lines.append(f"  {m}: w = 1 {_ci(one)}, w = 0.5 {_ci(half)}, w = 0 {_ci(zero)}; the paper's peak inside "
                     f"(0, 1) above both ends: {verdict}")
        for other in ("FreeReg-D", "FreeReg-G"):
            t = tests[f"{key}: FreeReg - {other}"]
            lines.append(f"    w = 0.5 - w = {1 if other == 'FreeReg-D' else 0}: {t['diff']:+.1f} points ({_sig(t['p'])})")
    return lines + tuned_fpfh()


def table9() -> list[str]:
    """Table 9's reading: fused FreeReg's RR ladder, PnP against Kabsch."""
    r = _load(SPLIT_JSON)
    if r is None or "ladder" not in r["results"]["FreeReg pnp"]:
        return [f"(no committed {SPLIT_JSON} with ladders)"]
    p, k = r["results"]["FreeReg pnp"]["ladder"], r["results"]["FreeReg kabsch"]["ladder"]
    rungs = list(p)
    tight, loose = rungs[0], rungs[-1]
    return [_header(r, SPLIT_JSON),
            "  FreeReg RR % PnP / Kabsch: " + ", ".join(f"{x[3:]} {p[x]:.1f} / {k[x]:.1f}" for x in rungs),
            f"  PnP ahead at {tight[3:]}: {_ahead(p[tight], k[tight])} here; "
            f"Kabsch ahead at {loose[3:]}: {_ahead(k[loose], p[loose])} here"]


def table2() -> list[str]:
    """Table 2's reading: the layer groups' order and the best combination, micro against paper."""
    r = _load(LAYERS_JSON)
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
    r = _load(DDIM_JSON)
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
    lines.append(f"  faster with {lo} iterations: {_ahead(t_hi, t_lo)} here ({t_lo:.2f} s against {t_hi:.2f} s, "
                 f"x{t_hi / t_lo:.1f}; the paper: 4.7 s against 9.3 s a whole pair, x2.0)")
    lines.append(f"  RR with {lo} against {hi} iterations: {test['diff']:+.1f} points [{ci[0]:+.1f}, {ci[1]:+.1f}] "
                 f"({_sig(test['p'])}; the paper: -1.4) -> " + (
                     "a significant loss here" if test["p"] < 0.05 and test["diff"] < 0 else
                     "no significant change on these pairs (the interval says how large a change they can rule out)"))
    return lines


def table8() -> list[str]:
    """Table 8's reading: which three- or four-layer combination the development set prefers, and
    where the paper's choice (0, 4, 6) ranks, beside the paper's validation scene."""
    r = _load(COMBINATIONS_JSON)
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


def _verdict(diff: float, p: float, paper_diff: float) -> str:
    """A paired difference read against the paper's sign: 'as the paper' only when significant."""
    if diff == 0 or p >= 0.05:
        return "no significant difference here"
    return "as the paper" if (diff > 0) == (paper_diff > 0) else "the opposite of the paper"


def table10() -> list[str]:
    """Table 10's reading: fused FreeReg between two images (RGB) and between two depth maps (DPT)
    against the image-to-cloud FreeReg on the same pairs, beside the paper's rows (its Table 10 and
    Table 1's FreeReg, Kabsch, on 3DMatch)."""
    from freereg_lib.data import paper

    r = _load(MONO_JSON)
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
                     f"{_verdict(rr['diff'], rr['p'], p_rr)}; IR {ir['diff']:+.1f} points ({_sig(ir['p'])}) -> "
                     f"{_verdict(ir['diff'], ir['p'], p_ir)}")
    both = all(_verdict(tests[f"RR kabsch: {a} - cross"]["diff"], tests[f"RR kabsch: {a} - cross"]["p"], 1.0)
               == "as the paper" for a in ("RGB", "DPT"))
    lines.append("  the paper's point, registration within one modality easier than image to cloud (RR, both "
                 f"mono-modality rows significantly above): {'holds here' if both else 'not shown here'}")
    return lines
