"""The micro models' card is regenerated from the committed JSON, byte for byte."""
import shutil
from pathlib import Path

from freereg_lib.models.micro import diffusion as M
from freereg_lib.training import card


def test_model_card_regenerates_from_the_committed_json(tmp_path):
    folder = tmp_path / "weights"
    shutil.copytree(M.WEIGHTS_DIR, folder)
    written = card.write_card(Path(folder))
    assert written.read_text() == (M.WEIGHTS_DIR / "MODEL_CARD.md").read_text(), (
        "MODEL_CARD.md is not what `python -m freereg_lib.training.card` writes from the committed JSON")
