"""The configuration reference page (``docs/config.md``), generated from the typed configs.

Every key of a config model, its default in each preset, and its description come from the
pydantic fields themselves, so the page cannot drift from the code (a test regenerates it).
Run ``python -m neuralrt.configdoc > docs/config.md`` after changing a config.
"""

from __future__ import annotations

from pydantic import BaseModel

__all__ = ["config_rows", "config_reference"]


def config_rows(model: BaseModel, prefix: str = "") -> list[tuple[str, object, str]]:
    """(dotted key, value in ``model``, description) for every leaf field, in declaration order."""
    rows = []
    for name, field in type(model).model_fields.items():
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            rows += config_rows(value, f"{prefix}{name}.")
        else:
            rows.append((prefix + name, value, (field.description or "").replace("|", "\\|")))
    return rows


def _fmt(value) -> str:
    if isinstance(value, tuple):
        value = list(value)
    return f"`{value}`"


def config_reference() -> str:
    """Markdown page: one table per config section, a column per LSNIF preset."""
    from .methods.lsnif_config import PRESETS

    presets = {name: make() for name, make in PRESETS.items()}
    rows = {name: config_rows(cfg) for name, cfg in presets.items()}
    first = next(iter(rows.values()))
    lines = [
        "# Configuration reference",
        "",
        "Generated from the typed configs by `python -m neuralrt.configdoc` (a test keeps it current).",
        "Every model file stores its full config in its header; `neuralrt info MODEL --json` shows it.",
        "",
        "## LSNIF (`neuralrt.methods.lsnif_config.LSNIFConfig`)",
        "",
        "Presets: " + ", ".join(f"`{p}`" for p in presets) + " (`LSNIFConfig.preset(name)`). "
        "Sections: voxel, features, encoding, network, loss, training, inference.",
    ]
    section = None
    for i, (key, _, description) in enumerate(first):
        head = key.split(".")[0]
        if head != section:
            section = head
            lines += ["", f"### `{section}`", "", "| key | " + " | ".join(presets) + " | meaning |",
                      "|---|" + "---|" * len(presets) + "---|"]
        values = " | ".join(_fmt(rows[p][i][1]) for p in presets)
        lines.append(f"| `{key}` | {values} | {description} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(config_reference(), end="")
