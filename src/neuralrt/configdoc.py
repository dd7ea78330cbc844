"""The configuration reference page (``docs/config.md``), generated from the typed configs.

One section per registered method (read from the method registry): every key of its config, its
value in each preset, and its description come from the pydantic fields themselves, so the page
cannot drift from the code (a test regenerates it).
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


def method_reference(name: str) -> str:
    """Markdown section for one registered method: one table per config section, a column per preset."""
    from .methods import get_method

    spec = get_method(name)
    presets = {preset: make() for preset, make in spec.presets.items()}
    rows = {preset: config_rows(cfg) for preset, cfg in presets.items()}
    first = next(iter(rows.values()))
    cls = spec.config_class
    sections = [k for k, f in cls.model_fields.items() if isinstance(getattr(presets[next(iter(presets))], k), BaseModel)]
    defaults = ", ".join(f"`{p}` on {'other devices' if d == '*' else d}" for d, p in spec.default_presets.items())
    lines = [
        f"## {name} (`{cls.__module__}.{cls.__name__}`)",
        "",
        spec.summary + ".",
        "",
        "Presets: " + ", ".join(f"`{p}`" for p in presets) + f" (`{cls.__name__}.preset(name)`, "
        f"`neuralrt train --method {name} --preset NAME`; default: {defaults}). Sections: {', '.join(sections)}.",
    ]
    section = None
    for i, (key, _, description) in enumerate(first):
        head = key.split(".")[0] if "." in key else ""
        if head != section:
            section = head
            title = f"`{section}`" if section else "top level"
            lines += ["", f"### {title}", "", "| key | " + " | ".join(presets) + " | meaning |",
                      "|---|" + "---|" * len(presets) + "---|"]
        values = " | ".join(_fmt(rows[p][i][1]) for p in presets)
        lines.append(f"| `{key}` | {values} | {description} |")
    return "\n".join(lines) + "\n"


def config_reference() -> str:
    """The whole page: a section per registered method (read from the method registry)."""
    from .methods import method_names

    head = [
        "# Configuration reference",
        "",
        "Generated from the typed configs by `python -m neuralrt.configdoc` (a test keeps it current).",
        "Every model file stores its full config in its header; `neuralrt info MODEL --json` shows it.",
        "`neuralrt train --list-presets` lists the presets of every method.",
        "",
    ]
    return "\n".join(head) + "\n" + "\n".join(method_reference(name) for name in method_names())


if __name__ == "__main__":
    print(config_reference(), end="")
