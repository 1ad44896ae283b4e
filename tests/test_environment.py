"""The conda environment mirrors the pip pins, so both routes give the same versions."""
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def _pins(lines):
    return {ln.split("==")[0].lower(): ln.split("==")[1] for ln in lines if "==" in ln}


def test_conda_env_mirrors_requirements():
    req = _pins(
        ln.strip() for ln in (ROOT / "environment/requirements.txt").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    )
    env = yaml.safe_load((ROOT / "environment/environment.yml").read_text())
    pip_list = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict))
    assert _pins(pip_list) == req
    assert req["torch"] == "2.13.0"
    assert all("==" in ln for ln in pip_list if not ln.startswith("-e"))


def test_nbformat_imports_without_the_iri_grammar():
    """Every notebook kernel imports nbformat (through myst-nb's glue); jsonschema >= 4.25 would
    have it build rfc3987-syntax's parser, 1.1 s of CPU per process."""
    code = "import sys, nbformat; print('rfc3987_syntax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
