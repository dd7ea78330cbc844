"""docs/config.md is generated from the typed configs of every registered method and must be current."""

from pathlib import Path

from neuralrt.configdoc import config_reference, config_rows
from neuralrt.methods import get_method, method_names

DOC = Path(__file__).resolve().parents[1] / "docs" / "config.md"


def test_every_method_and_key_is_documented_and_the_page_is_current():
    page = config_reference()
    for name in method_names():
        spec = get_method(name)
        assert f"## {name} (`{spec.config_class.__module__}.{spec.config_class.__name__}`)" in page
        for preset in spec.presets:
            assert f"`{preset}`" in page
        rows = config_rows(spec.config(next(iter(spec.presets))))
        assert len({key for key, _, _ in rows}) == len(rows) > 20
        for key, _, _ in rows:
            assert f"`{key}`" in page
    assert DOC.read_text() == page, "docs/config.md is stale: run `python -m neuralrt.configdoc > docs/config.md`"
