"""Pages of the documentation site generated at build time (mkdocs-gen-files; see mkdocs.yml).

- `configuration.md` gets a reference appended: one table per config dataclass of
  `cmat/config.py` and per algorithm's section (its `options.py`): field, type, default, and the
  field's docstring (`cmat.configfile.field_docs`).
- `suites.md` gets a table of every suite as `cmat/envs/suites.py` declares it.
- `results/NAME/index.md` for every committed `experiments/results/NAME/results.md`, with the
  directory's figures (PNG, GIF) written next to it so that they show.

`mkdocs build` runs it; it imports only `cmat.config`, `cmat.configfile` (with the algorithms'
registry entries and `options.py`) and `cmat.envs.suites`, which import neither JAX nor the
networks.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path
from typing import Any

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
FIGURES = (".png", ".gif", ".svg", ".jpg", ".jpeg")
LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")
CODE_SPAN = re.compile(r"(`+)(.+?)\1")


def cmat_modules() -> tuple[Any, Any, Any, Any]:
    """`cmat.config`, `cmat.configfile`, `cmat.algorithms` and `cmat.envs.suites` of this
    checkout (first on the path)."""
    sys.path.insert(0, str(ROOT))
    import cmat.algorithms
    import cmat.config
    import cmat.configfile
    import cmat.envs.suites

    return cmat.config, cmat.configfile, cmat.algorithms, cmat.envs.suites


def escape(text: str) -> str:
    """Docstring text for a Markdown table cell: code spans kept, Markdown's emphasis and HTML
    characters and the cell separator escaped elsewhere."""
    parts, last = [], 0
    for match in CODE_SPAN.finditer(text):
        parts.append(escape_plain(text[last:match.start()]))
        parts.append(match.group(0))  # the table extension keeps a code span's pipes
        last = match.end()
    parts.append(escape_plain(text[last:]))
    return "".join(parts)


def escape_plain(text: str) -> str:
    for char in ("\\", "*", "_", "|", "[", "]"):
        text = text.replace(char, "\\" + char)
    return text.replace("<", "&lt;").replace(">", "&gt;")


def code(value: str) -> str:
    return f"`{value}`"


def default_text(field: dataclasses.Field[Any]) -> str:
    if field.default is not dataclasses.MISSING:
        return code(repr(field.default))
    if field.default_factory is not dataclasses.MISSING:
        value = field.default_factory()
        if dataclasses.is_dataclass(value):
            return f"the `{type(value).__name__}` table"
        return code(repr(value))
    return "required"


def config_reference() -> str:
    config, configfile, algorithms, _ = cmat_modules()
    docs = configfile.field_docs()
    sections: list[tuple[type, tuple[str, ...], dict[str, str]]] = [
        (config.TrainConfig, ("",), docs),
        (config.NetworkConfig, ("network.",), docs),
        (config.PPOConfig, ("ppo.",), docs),
    ]
    by_class: dict[type, list[str]] = {}
    for algo, entry in algorithms.builtin_entries().items():
        by_class.setdefault(entry.options, []).append(algo)
    for cls, algos in by_class.items():
        if dataclasses.fields(cls):  # an algorithm without options has no table
            sections.append((cls, tuple(f"{algo}." for algo in algos),
                             configfile.field_docs(algos[0])))
    lines = [
        "",
        "## Reference",
        "",
        "Every field, generated from the dataclasses in `cmat/config.py` and the algorithms' "
        "`options.py` when this site was built (the same text `cmat config` prints under each "
        "value). A run's config holds the section of its algorithm only. The defaults are the "
        "dataclass layer only: the suite, the algorithm and a preset may set a field before "
        "your file and `--set` do (above).",
    ]
    for cls, prefixes, section_docs in sections:
        summary = " ".join((cls.__doc__ or "").split())
        keys = ("top-level keys" if prefixes == ("",)
                else ", ".join(f"`{prefix}*`" for prefix in prefixes))
        lines += ["", f"### `{cls.__name__}`: {keys}", "", escape(summary), "",
                  "| field | type | default | meaning |", "|---|---|---|---|"]
        for field in dataclasses.fields(cls):
            dotted = prefixes[0] + field.name
            if dotted not in section_docs and dataclasses.is_dataclass(field.default_factory):
                continue  # `network`, `ppo`, the algorithm's section: their own tables
            names = ", ".join(f"`{prefix}{field.name}`" for prefix in prefixes)
            lines.append(f"| {names} | {code(str(field.type))} | {default_text(field)} | "
                         f"{escape(section_docs.get(dotted, ''))} |")
    return "\n".join(lines) + "\n"


def flat(values: dict[str, Any], prefix: str = "") -> list[str]:
    items: list[str] = []
    for key, value in values.items():
        if isinstance(value, dict) and key != "env_kwargs":
            items += flat(value, f"{prefix}{key}.")
        else:
            items.append(f"{prefix}{key}={value!r}")
    return items


def suites_table() -> str:
    *_, suites = cmat_modules()
    lines = [
        "",
        "## As the code declares them",
        "",
        "Generated from `cmat/envs/suites.py` (`SUITES`) when this site was built: each suite's "
        "settings layer, as `key=value` over the dataclass defaults, and the source `cmat "
        "config` names for it.",
        "",
        "| suite | stepped | settings | source |",
        "|---|---|---|---|",
    ]
    for prefix, suite in suites.SUITES.items():
        settings = ", ".join(code(item) for item in flat(suite.settings))
        where = "on the host (Python)" if suite.host else "in-graph (JAX)"
        lines.append(f"| `{prefix}:` | {where} | {settings} | {escape(suite.source)} |")
    return "\n".join(lines) + "\n"


def results_page(directory: Path) -> tuple[str, list[Path]]:
    """The page of one experiment directory and the figures it shows."""
    text = (directory / "results.md").read_text(encoding="utf-8")
    shown: list[Path] = []

    def link(match: re.Match[str]) -> str:
        _, label, target = match.groups()
        if re.match(r"[a-z]+:|#|/", target):
            return match.group(0)
        path = (directory / target).resolve()
        if path.suffix.lower() in FIGURES and path.is_file() and path.parent == directory:
            shown.append(path)
            return match.group(0)
        # any other file of the repository is not part of the site: name it instead
        return f"{label} (`experiments/results/{directory.name}/{target}`)" if label else \
            f"`experiments/results/{directory.name}/{target}`"

    text = LINK.sub(link, text)
    figures = [path for path in sorted(directory.iterdir())
               if path.suffix.lower() in FIGURES and path not in shown]
    source = (f"*Generated from `experiments/results/{directory.name}/results.md` in the "
              f"repository when this site was built; the run data, `results.json` and "
              f"`spec.yaml` are in the same directory.*")
    block = ["## Figures", ""] + [f"![{path.stem}]({path.name})\n" for path in figures]
    title, _, rest = text.partition("\n")
    body = rest
    if figures:
        head, heading, tail = rest.partition("\n## ")
        body = (head.rstrip("\n") + "\n\n" + "\n".join(block) + "\n" + heading + tail
                if heading else rest.rstrip("\n") + "\n\n" + "\n".join(block))
    return f"{title}\n\n{source}\n{body}", shown + figures


def main() -> None:
    with mkdocs_gen_files.open("configuration.md", "a") as page:
        page.write(config_reference())
    with mkdocs_gen_files.open("suites.md", "a") as page:
        page.write(suites_table())
    for directory in sorted(RESULTS.iterdir()):
        if not (directory / "results.md").is_file():
            continue
        text, figures = results_page(directory)
        with mkdocs_gen_files.open(f"results/{directory.name}/index.md", "w") as page:
            page.write(text)
        for figure in figures:
            with mkdocs_gen_files.open(f"results/{directory.name}/{figure.name}", "wb") as out:
                out.write(figure.read_bytes())


main()
