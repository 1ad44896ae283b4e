"""What a committed result records of the machine that produced it (freereg_lib.training.provenance)."""
from __future__ import annotations

import json

from freereg_lib.training import evaluate_split, provenance

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 7B13
flags\t\t: fpu sse4_2 avx avx2 fma f16c
processor\t: 1
model name\t: AMD EPYC 7B13
flags\t\t: fpu sse4_2 avx avx2 fma f16c
"""


def test_cpu_info_reads_the_model_and_the_isa_flags():
    info = provenance.cpu_info(CPUINFO)
    assert info["model"] == "AMD EPYC 7B13"
    assert info["isa_flags"] == ["sse4_2", "avx", "avx2", "fma", "f16c"]  # no AVX-512: another kernel path


def test_cpu_info_without_flags_says_unknown():
    assert provenance.cpu_info("model name : Some CPU\n")["isa_flags"] is None


def test_git_commit_outside_a_checkout_is_none(tmp_path):
    assert provenance.git_commit(tmp_path) == {"commit": None, "dirty": None}


def test_publish_records_the_machine(tmp_path, capsys):
    import torch  # noqa: F401  (the record names the loaded torch's kernel choices)

    out = tmp_path / "result.json"
    evaluate_split.publish({"n_pairs": 1}, "report", str(out))
    rec = json.loads(out.read_text())["provenance"]
    assert set(rec) == {"cpu", "kernels", "environment", "packages", "python", "os", "git"}
    assert rec["packages"]["torch"].startswith("2.13.0")
    assert rec["kernels"]["torch_threads"] >= 1 and rec["kernels"]["torch_cpu_capability"]
    assert len(rec["git"]["commit"] or "x" * 40) == 40
    assert capsys.readouterr().out == "report\n"
