"""Generates the configuration reference (``docs/reference/configuration.md`` of the site) from the typed schemas and
the yaml files, so that it cannot drift from either.

* **type and allowed range** come from the schemas, the dataclasses of :mod:`torchrl_bail.configuration.config` and its
schema
  modules, read through :func:`dataclasses.fields`: a field's annotation is its type, its ``metadata["expected"]``
  the allowed range;
* **default and one-line meaning** come from ``conf/``: every group option is composed by Hydra exactly as the
  command line composes it (the paper preset, then ``preset=quick`` and ``preset=study`` for their overrides), and
  the comment on a key's line in the yaml file that sets it is its meaning. A key documented once is documented for
  every option that shares its schema field (``envelope.lr`` of ``bail.yaml`` also serves ``pbail.yaml``); a comment
  that continues on the next lines (indented under the first) is one meaning.

Which node has which schema is read from the composed config (``OmegaConf.get_type``), never from a list kept here,
so a new group option, schema or field appears in the reference by itself, and a field without a comment anywhere
fails the build (:class:`MissingDocs`; ``tests/test_docs.py`` checks it too).

``python docs/gen_config_reference.py [OUT.md]`` writes the page (stdout without ``OUT``); ``docs/hooks.py`` runs it
at every ``mkdocs build``.
"""

from __future__ import annotations

import dataclasses
import html
import inspect
import re
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

#: the config groups that have a section of their own (the rest of ``conf/config.yaml`` is the top level)
GROUPS = ("env", "batch", "algo")
#: presets whose overrides are listed beside the defaults (the defaults are those of ``preset=paper``)
PRESETS = ("quick", "study")

_KEY = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w.-]*):(?P<rest>.*)$")


class MissingDocs(ValueError):
    """Schema fields whose key has no comment in any yaml file."""


@dataclass
class Row:
    key: str                    # dotted, relative to the section (``envelope.lr``)
    type: str
    allowed: str
    defaults: dict[str, Any]    # option -> default (paper preset)
    presets: dict[str, dict[str, Any]] = field(default_factory=dict)  # option -> preset label -> value, if changed
    doc: str = ""
    home: tuple = ()            # (group, block's schema, field's schema, key): who may lend a comment (_rows)
    value: Any = None           # the value in the option being read (collect's scratch)
    option_of: str | None = None  # the group whose option this key names (config.option_name): env.name, batch.kind


@dataclass
class Section:
    group: str | None           # None: the top level
    schema: type
    options: list[str]
    rows: list[Row]


# ---------------------------------------------------------------------------------------------------------------
# yaml comments
# ---------------------------------------------------------------------------------------------------------------


def _split_comment(rest: str) -> tuple[str, str | None, int]:
    """``' 0.99   # the discount'`` -> (value text, comment, column of '#' within ``rest``); quotes respected."""
    quote = None
    for i, ch in enumerate(rest):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or rest[i - 1] in " \t"):
            return rest[:i].strip(), rest[i + 1:].strip(), i
    return rest.strip(), None, -1


def yaml_comments(path: Path) -> dict[str, str]:
    """``{dotted key: comment}`` of one yaml file: the comment on a key's own line, joined with the comment lines
    right below it that are indented deeper than the key (a continued comment). Block comments (a comment line at
    the key's own indentation) introduce what follows and belong to no key."""
    comments: dict[str, str] = {}
    stack: list[tuple[int, str]] = []
    last: tuple[str, int] | None = None          # (dotted key, its indentation) of a comment that may continue
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            indent = len(line) - len(line.lstrip())
            if last is not None and indent > last[1]:
                comments[last[0]] += " " + stripped.lstrip("#").strip()
                continue
            last = None
            continue
        last = None
        match = _KEY.match(line)
        if not match or not stripped or stripped.startswith("- "):
            continue
        indent = len(match["indent"])
        while stack and stack[-1][0] >= indent:
            stack.pop()
        dotted = ".".join([k for _, k in stack] + [match["key"]])
        stack.append((indent, match["key"]))
        _, comment, _ = _split_comment(match["rest"])
        if comment:
            comments[dotted] = comment
            last = (dotted, indent)
    return comments


def _option_comments(conf: Path, group: str | None, option: str | None) -> dict[str, str]:
    """The comments of every key a group option's yaml files set, keyed relative to the group's root: the option's
    file and the partial files its defaults list pulls in (``_collection@_here_``, ``_sac_agent@sac``)."""
    if group is None:
        return yaml_comments(conf / "config.yaml")
    path = conf / group / f"{option}.yaml"
    comments = dict(yaml_comments(path))
    for entry in OmegaConf.load(path).get("defaults", []):
        if not isinstance(entry, str) or entry == "_self_":
            continue
        name, _, package = entry.partition("@")
        partial = conf / group / f"{name}.yaml"
        if not partial.is_file():          # a schema from the ConfigStore (base_<name>_schema)
            continue
        prefix = "" if package in ("", "_here_") else package + "."
        for key, text in yaml_comments(partial).items():
            comments.setdefault(prefix + key, text)
    return comments


# ---------------------------------------------------------------------------------------------------------------
# schemas
# ---------------------------------------------------------------------------------------------------------------


def type_name(annotation: Any) -> str:
    """A schema annotation as a reader writes it: ``int``, ``list[int]``, ``float or null``, ``any``."""
    if annotation is Any:
        return "any"
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Union:
        names = [type_name(a) for a in args if a is not type(None)]
        return " or ".join(names) + (" or null" if type(None) in args else "")
    if origin in (list, typing.List):  # noqa: UP006
        return f"list[{type_name(args[0])}]" if args else "list"
    return getattr(annotation, "__name__", str(annotation))


def _field_type(f: dataclasses.Field, annotation: Any) -> str:
    """A field's type; a closed set of values (``config.one_of``, ``resume``'s words) is an enum of strings."""
    choices = f.metadata.get("choices")
    if not choices or not all(isinstance(c, str) for c in choices):
        return type_name(annotation)
    return "enum" + (" or path" if f.metadata.get("or") else "")


def _allowed(f: dataclasses.Field, schema: type) -> str:
    """The allowed cell's text (markdown, code spans for values): a field's choices each in code, the name of
    ``schema`` in the registry a key names (``algo.name``), else its rule's ``expected`` text; a key naming its group
    option is filled in by :func:`collect`, which knows the options."""
    from torchrl_bail.configuration import algo_schemas, batch_schemas

    if f.metadata.get("registry"):
        module = next(m for m in (algo_schemas, batch_schemas) if hasattr(m, f.metadata["registry"]))
        names = [n for n, s in getattr(module, f.metadata["registry"]).items() if s is schema]
        where = f"{module.__name__.rsplit('.', 1)[-1]}.{f.metadata['registry']}"
        return " · ".join(f"`{n}`" for n in names) + f" (this schema's name in `{where}`)"
    choices = f.metadata.get("choices")
    if choices:
        return " · ".join(f"`{c}`" for c in choices) + (f" · {f.metadata['or']}" if f.metadata.get("or") else "")
    return f.metadata.get("expected", "")


def _home(schema: type, name: str) -> type:
    """The class of ``schema``'s MRO that declares field ``name``."""
    return next(c for c in schema.__mro__ if name in inspect.get_annotations(c))


def _rows(node: DictConfig, raw: dict, group: str | None, prefix: str = "", block: type | None = None) -> list[Row]:
    """One row per leaf field of ``node``'s schema (nested schemas become dotted keys); group nodes are skipped at
    the top level.

    A row's ``home`` says which other options may lend it their comment: the same key, declared by the same schema
    class, inside a block (the key's first part) declared by the same schema class. So ``bear.yaml`` shares the
    comments of ``vae.*`` with ``bcq.yaml`` (``TwinCriticVAEConfig`` declares ``vae`` for both), but not of
    ``actor.hidden``: BCQ's perturbation actor and BEAR's Gaussian actor are different blocks of the same type."""
    schema = OmegaConf.get_type(node)
    hints = typing.get_type_hints(schema)
    rows = []
    for f in dataclasses.fields(schema):
        child = node._get_node(f.name)
        if group is None and not prefix and f.name in GROUPS:
            continue
        declared = _home(schema, f.name)
        if isinstance(child, DictConfig) and dataclasses.is_dataclass(OmegaConf.get_type(child)):
            rows += _rows(child, raw[f.name], group, f"{prefix}{f.name}.", block or declared)
            continue
        key = prefix + f.name
        home = (group, (block or declared).__name__, declared.__name__, key)
        rows.append(Row(key=key, type=_field_type(f, hints[f.name]), allowed=_allowed(f, schema), defaults={},
                        home=home, value=raw.get(f.name), option_of=f.metadata.get("option_of")))
    return rows


def _options(conf: Path, group: str) -> list[str]:
    return sorted(p.stem for p in (conf / group).glob("*.yaml") if not p.stem.startswith("_"))


def collect(conf: Path | None = None) -> list[Section]:
    """Every section of the reference: the top level, then one per (group, schema), rows in schema order."""
    from hydra import compose, initialize_config_dir

    from torchrl_bail.configuration.hydra_setup import config_dir

    conf = Path(conf) if conf is not None else config_dir()
    config_dir()  # registers the schemas with Hydra's ConfigStore

    sections: dict[tuple, Section] = {}
    with initialize_config_dir(str(conf.resolve()), version_base="1.3"):
        for group in (None, *GROUPS):
            for option in ([None] if group is None else _options(conf, group)):
                _add_option(sections, conf, group, option)
        algos = _options(conf, "algo")
        plain = {a: _flat(OmegaConf.to_container(compose("config", [f"algo={a}"]), resolve=False)) for a in algos}
        for preset in PRESETS:
            _add_preset(sections, preset, _preset_changes(preset, plain), algos)
    _allow_option_names(sections)
    _share_docs(sections)
    return list(sections.values())


def _add_option(sections: dict[tuple, Section], conf: Path, group: str | None, option: str | None) -> None:
    """Composes ``group=option`` (the top level for ``None``) and adds its values, as that option's defaults, to
    the section of its schema (created on its first option); a row's doc is the first yaml comment found."""
    from hydra import compose

    cfg = compose("config", overrides=[] if group is None else [f"{group}={option}"])
    node = cfg if group is None else cfg[group]
    schema = OmegaConf.get_type(node)
    rows = _rows(node, OmegaConf.to_container(node, resolve=False), group)
    comments = _option_comments(conf, group, option)
    label = option or "default"
    section = sections.setdefault((group, schema), Section(group, schema, [], rows))
    section.options.append(label)
    by_key = {r.key: r for r in section.rows}
    for row in rows:
        kept = by_key[row.key]
        kept.defaults[label] = row.value
        if not kept.doc and comments.get(row.key):
            kept.doc = comments[row.key]


def _preset_changes(preset: str, plain: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``{dotted key: {algo: value}}``: what ``preset`` changes in each algorithm's composition (``plain``: algo ->
    its flat composition without a preset). preset/<p>.yaml sets the same values whatever the env and batch,
    algo_preset/<algo>_<p>.yaml depends on the algorithm, so one composition per (algorithm, preset) shows every
    preset's values."""
    from hydra import compose

    changed: dict[str, dict[str, Any]] = {}  # dotted key -> algo -> value under the preset
    for algo in plain:
        chosen = _flat(OmegaConf.to_container(compose("config", [f"algo={algo}", f"preset={preset}"]),
                                              resolve=False))
        for key, value in chosen.items():
            if plain[algo].get(key) != value:
                changed.setdefault(key, {})[algo] = value
    return changed


def _add_preset(sections: dict[tuple, Section], preset: str, changed: dict[str, dict[str, Any]],
                algos: list[str]) -> None:
    """Records ``preset``'s values (``changed``, from :func:`_preset_changes`) in every row they concern, for each
    option of its section; the algorithm's own section shows only its own preset file's."""
    for (group, _), section in sections.items():
        for row in section.rows:
            by_algo = changed.get(row.key if group is None else f"{group}.{row.key}", {})
            if group == "algo":  # the algorithm's own section: its own preset file
                by_algo = {a: v for a, v in by_algo.items() if [a] == section.options}
            for label, value in _preset_labels(preset, by_algo, algos, group == "algo"):
                for option in section.options:
                    row.presets.setdefault(option, {})[label] = value


def _allow_option_names(sections: dict[tuple, Section]) -> None:
    """A key that names its option (env.name, batch.kind): the options shipped are its values."""
    for section in sections.values():
        for row in section.rows:
            if row.option_of:
                names = sorted({str(v) for v in row.defaults.values()})
                row.allowed = " · ".join(f"`{n}`" for n in names) + f" (or a conf/{row.option_of}/ file of your own)"


def _share_docs(sections: dict[tuple, Section]) -> None:
    """A field documented in one option's yaml is documented for every option sharing that schema field."""
    docs = {}
    for section in sections.values():
        for row in section.rows:
            if row.doc:
                docs.setdefault(row.home, row.doc)
    for section in sections.values():
        for row in section.rows:
            row.doc = row.doc or docs.get(row.home, "")


def _preset_labels(preset: str, by_algo: dict[str, Any], algos: list[str], own: bool) -> list[tuple[str, Any]]:
    """``[(label, value)]`` of one preset's values of a key: ``quick`` when every algorithm's composition agrees
    (or the key is the algorithm's own), else ``quick with bcq, bear`` per value."""
    if not by_algo:
        return []
    values = list(by_algo.values())
    if own or (len(by_algo) == len(algos) and all(v == values[0] for v in values)):
        return [(preset, values[0])]
    groups: dict[str, list[str]] = {}
    for algo, value in by_algo.items():
        groups.setdefault(repr(value), []).append(algo)
    return [(f"{preset} with {', '.join(names)}", by_algo[names[0]]) for names in groups.values()]


def _flat(tree: dict, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists are values)."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def missing_docs(sections: list[Section]) -> list[str]:
    """``<group>.<key> (<schema>)`` of every row without a meaning."""
    return [f"{s.group + '.' if s.group else ''}{r.key} ({s.schema.__name__})"
            for s in sections for r in s.rows if not r.doc]


# ---------------------------------------------------------------------------------------------------------------
# markdown
# ---------------------------------------------------------------------------------------------------------------


def _value(v: Any) -> str:
    if isinstance(v, (DictConfig, ListConfig)):
        v = OmegaConf.to_container(v, resolve=False)
    text = "null" if v is None else str(v).lower() if isinstance(v, bool) else str(v)
    if "|" in text:  # a pipe would end the table cell, and an escaped one shows its backslash inside `code`
        return "<code>" + html.escape(text).replace("|", "&#124;") + "</code>"
    return f"`{text}`"


def _cell(text: str) -> str:
    """Plain text in a table cell: HTML-escaped outside `code` spans (``<run_dir>`` is no tag), pipes escaped, and
    the characters Markdown reads as emphasis escaped (``<algo>_seed<seed>_<name>`` is no italics)."""
    parts = text.split("`")
    if len(parts) % 2 == 0:  # an unpaired backtick: no code spans
        parts = [text]
    return "".join(_plain(part) if i % 2 == 0 else _value(part) for i, part in enumerate(parts))


def _plain(text: str) -> str:
    """Text outside code spans, as Markdown shows it literally: ``\\``, ``|``, ``*``, ``_`` escaped, HTML escaped."""
    text = re.sub(r"([\\|*_])", r"\\\1", text)
    return html.escape(text, quote=False)


def _default_cell(row: Row, options: list[str]) -> str:
    if row.option_of and all(str(row.defaults[o]) == o for o in options):  # env.name: hopper in env=hopper
        return f"the option's name (`{options[0]}` in `{row.option_of}={options[0]}`)"
    values = [row.defaults[o] for o in options]
    if all(v == values[0] for v in values):
        parts = [_value(values[0])]
    else:
        parts = [f"{o}: {_value(row.defaults[o])}" for o in options]
    overrides = {}
    for option, presets in row.presets.items():
        for preset, value in presets.items():
            overrides.setdefault((preset, repr(value)), (value, []))[1].append(option)
    for (preset, _), (value, opts) in overrides.items():
        where = "" if len(opts) == len(options) else f" ({', '.join(opts)})"
        parts.append(f"*{preset}*{where}: {_value(value)}")
    return "<br>".join(parts)


_INTRO = """\
# Configuration reference

Every key of every config group: its **type** and **allowed range** from the typed schemas (the dataclasses of
`torchrl_bail.configuration.config`, checked before a run starts), its **default** and **meaning** from the yaml file
under `conf/`
that sets it. This page is generated from both at every build by `docs/gen_config_reference.py`; a schema field
without a comment in the yaml fails the build. Defaults are those of the paper preset (`preset=paper`); where
`preset=quick` or `preset=study` sets another value, it is listed under the default. The groups themselves and how
to combine them: [Config groups](../guides/config-groups.md).

A key is set on the command line with its dotted name, e.g. `algo.envelope.lr=1e-3` or `eval.episodes=5`.
"""


def render(sections: list[Section]) -> str:
    lines = [_INTRO]
    for section in sections:
        name = section.schema.__name__
        if section.group is None:
            lines.append(f"## Top level {{ #top-level }}\n\n`conf/config.yaml`, schema `{name}`.\n")
            prefix = ""
        else:
            options = ", ".join(f"`{section.group}={o}`" for o in section.options)
            anchor = f"{section.group}-{section.options[0]}" if len(section.options) == 1 else \
                f"{section.group}-{name.lower()}"
            lines.append(f"## `{section.group}`: {', '.join(section.options)} {{ #{anchor} }}\n\n"
                         f"{options}: `conf/{section.group}/<option>.yaml`, schema `{name}`.\n")
            prefix = section.group + "."
        lines.append("| key | type | default | allowed | meaning |\n|---|---|---|---|---|")
        for row in section.rows:
            lines.append(f"| `{prefix}{row.key}` | {row.type} | {_default_cell(row, section.options)} | "
                         f"{_cell(row.allowed)} | {_cell(row.doc)} |")
        lines.append("")
    return "\n".join(lines)


def generate(conf: Path | None = None) -> str:
    """The page's markdown; raises :class:`MissingDocs` naming every undocumented schema field."""
    sections = collect(conf)
    missing = missing_docs(sections)
    if missing:
        raise MissingDocs("schema fields without a one-line comment in conf/**/*.yaml: " + ", ".join(missing)
                          + "; add '# <meaning>' on the key's line in its yaml file")
    return render(sections)


if __name__ == "__main__":
    try:
        text = generate()
    except MissingDocs as err:
        print(f"gen_config_reference: {err}", file=sys.stderr)
        sys.exit(2)
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(text)
    else:
        print(text)
