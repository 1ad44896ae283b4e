"""The check of this machine against the committed test split (freereg_lib.commands.agreement)."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from freereg_lib.commands import agreement
from freereg_lib.models.micro.diffusion import WEIGHTS_DIR


def _committed_path():
    return Path(WEIGHTS_DIR) / "test_split.json"


def test_sample_pairs_spreads_over_the_split():
    assert agreement.sample_pairs(100, 10) == [0, 10, 20, 30, 40, 50, 60, 70, 80, 90]
    assert agreement.sample_pairs(100, 3) == [0, 33, 66]
    assert agreement.sample_pairs(5, 10) == [0, 1, 2, 3, 4]
    with pytest.raises(agreement.AgreementError, match="--pairs must be at least 1"):
        agreement.sample_pairs(100, 0)


def _hand_made():
    variants = agreement.VARIANTS
    committed = {"n_pairs": 2, "results": {f"{m} {s}": {"IR_per_pair": [0.10, 0.20], "registered_per_pair": [0, 1]}
                                           for m, s in variants}}
    rec = {"k": 1, "pair": "p1", "rows": [{"method": m, "solver": s, "IR": 0.20, "registered": True} for m, s in variants]}
    return committed, rec


def test_compare_pair_names_each_kind_of_difference():
    committed, rec = _hand_made()
    assert agreement.compare_pair(committed, rec)["status"] == "identical"
    rec["rows"][0]["IR"] = 0.21  # within the tolerance of 0.02
    assert agreement.compare_pair(committed, rec)["status"] == "close"
    rec["rows"][1]["IR"] = 0.30
    out = agreement.compare_pair(committed, rec)
    assert out["status"] == "differs"
    assert [f["status"] for f in out["fields"].values()][:3] == ["close", "differs", "identical"]
    rec["rows"][2]["registered"] = False
    out = agreement.compare_pair(committed, rec)
    assert out["status"] == "flipped"
    assert list(out["fields"].values())[2] == {"IR_committed": 0.20, "IR_here": 0.20, "registered_committed": 1,
                                                "registered_here": 0, "status": "flipped"}


def test_verdict_class():
    assert agreement.verdict_class(0.0, 1.0) == "level"
    assert agreement.verdict_class(3.0, 0.01) == "above, significant"
    assert agreement.verdict_class(-3.0, 0.2) == "below, not significant"


def test_a_committed_file_the_check_cannot_use_is_named(tmp_path):
    bad = tmp_path / "split.json"
    with pytest.raises(agreement.AgreementError, match="split.json: cannot read"):
        agreement.load_committed(bad)
    res = json.loads(_committed_path().read_text())
    res["results"]["FreeReg pnp"]["IR_per_pair"] = res["results"]["FreeReg pnp"]["IR_per_pair"][:-1]
    bad.write_text(json.dumps(res))
    with pytest.raises(agreement.AgreementError, match=r"results\['FreeReg pnp'\] needs IR_per_pair"):
        agreement.load_committed(bad)


@pytest.fixture(scope="module")
def two_pairs(tmp_path_factory):
    """The check on 2 committed pairs (0, 50), recomputed once on this machine (about 20 s)."""
    out = tmp_path_factory.mktemp("agreement")
    status = agreement.main(["--pairs", "2", "--out", str(out)])
    return out, status, json.loads((out / "agreement.json").read_text())


def test_the_check_runs_on_two_committed_pairs(two_pairs, capsys):
    out, status, result = two_pairs
    assert result["pairs_checked"] == [0, 50]
    assert len(result["verdicts"]) == 9
    assert result["summary"].startswith("this machine reproduces the committed results: ")
    # Two pairs of 100 cannot turn a verdict whose p is far from 5 %.
    assert result["verdicts"]["IR: FreeReg - FreeReg-G"]["unchanged"]
    assert status == (0 if all(v["unchanged"] for v in result["verdicts"].values()) else 1)
    assert (out / "agreement.md").read_text().count("| synthetic-indoor/seed") == 2


def test_the_check_fails_when_a_committed_row_is_altered(two_pairs, tmp_path):
    out, _, result = two_pairs
    here = {p["k"]: p["fields"] for p in result["pairs"]}
    committed = json.loads(_committed_path().read_text())
    altered = copy.deepcopy(committed)
    # Pair 50: a registered outcome the opposite of this machine's in one field, an IR far from it in another.
    altered["results"]["FreeReg kabsch"]["registered_per_pair"][50] = 1 - here[50]["FreeReg kabsch"]["registered_here"]
    altered["results"]["FreeReg-D pnp"]["IR_per_pair"][50] = here[50]["FreeReg-D pnp"]["IR_here"] + 0.5
    path = tmp_path / "altered.json"
    path.write_text(json.dumps(altered))
    agreement.main(["--pairs", "2", "--out", str(out), "--committed", str(path)])  # resumes: no pair recomputed
    again = {p["k"]: p for p in json.loads((out / "agreement.json").read_text())["pairs"]}
    assert again[50]["status"] == "flipped"
    assert again[50]["fields"]["FreeReg kabsch"]["status"] == "flipped"
    assert again[50]["fields"]["FreeReg-D pnp"]["status"] in ("differs", "flipped")
    assert again[0]["status"] == next(p for p in result["pairs"] if p["k"] == 0)["status"]  # pair 0 untouched


def test_fresh_recomputes_only_the_pairs_it_checks(tmp_path, monkeypatch):
    written = []
    monkeypatch.setattr(agreement, "_one_pair", lambda k, folder: (written.append(k), (folder / f"{k}.jsonl").write_text(
        json.dumps({"k": k, "rows": []}) + "\n")))

    class Serial:  # the pool's work in this process, so the stand-in above is what runs
        def __init__(self, **_):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def submit(self, fn, *args):
            from concurrent.futures import Future

            fut = Future()
            fut.set_result(fn(*args))
            return fut

    monkeypatch.setattr("concurrent.futures.ProcessPoolExecutor", Serial)
    other = tmp_path / "7.jsonl"
    agreement.recompute([0, 10], tmp_path, progress=False)
    other.write_text("a user's file\n")
    agreement.recompute([0, 10], tmp_path, progress=False)  # kept: nothing recomputed
    agreement.recompute([0, 10], tmp_path, progress=False, fresh=True)
    assert written == [0, 10, 0, 10] and other.read_text() == "a user's file\n"
