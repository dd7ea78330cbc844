"""docs/config.md is generated from the typed configs and must be current."""

from pathlib import Path

from neuralrt.configdoc import config_reference, config_rows
from neuralrt.methods.lsnif_config import LSNIFConfig

DOC = Path(__file__).resolve().parents[1] / "docs" / "config.md"


def test_every_key_is_documented_and_the_page_is_current():
    rows = config_rows(LSNIFConfig.preset("hq"))
    assert len({key for key, _, _ in rows}) == len(rows) > 20
    page = config_reference()
    for key, _, _ in rows:
        assert f"`{key}`" in page
    assert DOC.read_text() == page, "docs/config.md is stale: run `python -m neuralrt.configdoc > docs/config.md`"
