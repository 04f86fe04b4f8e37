"""Generates the table of the Algorithms page (``docs/guides/algorithms.md``) from the algorithm registry at every
build, so that it cannot drift from the registry or the yaml files.

One row per registered algorithm, in the registry's order
(:data:`torchrl_bail.configuration.algo_schemas.ALGO_SCHEMAS`):

* ``what`` and ``loss modules``: its registry entry (the schema's ``description``, whose ``{key}`` fields are filled
  with the paper preset's values, and ``losses``);
* ``batch · length`` and ``evaluation``: the paper preset's config, composed as the command line composes
  ``algo=<name>``; the number of updates is the training loop's (``epochs × samples_per_epoch`` over the samples one
  update counts, which the algorithm built on that config states: Progressive BAIL counts 0.8 of its batch).

The page holds :data:`MARKER` where the table goes; ``docs/hooks.py`` hands :func:`on_page_markdown` to MkDocs. A
registry entry without its ``description`` or ``losses`` stops the build, naming it (:class:`MissingEntry`;
``tests/test_contract.py`` checks it too). ``python docs/gen_algorithm_table.py`` prints the table.
"""

from __future__ import annotations

import math

#: where the generated table goes on the page
MARKER = "<!-- the algorithm table: docs/gen_algorithm_table.py -->"
PAGE = "guides/algorithms.md"


class MissingEntry(ValueError):
    """A registry entry lacks what the table shows."""


def _losses(paths: tuple[str, ...]) -> str:
    """``torchrl.objectives.BCLoss`` -> TorchRL `BCLoss`; this package's by their name."""
    return ", ".join(("TorchRL " if path.startswith("torchrl.") else "") + f"`{path.rsplit('.', 1)[1]}`"
                     for path in paths)


def _count(n: int) -> str:
    """An update count as the docs write it: 10^6, 125k, 1,234."""
    if n >= 10**6 and n % 10**6 == 0:
        return "10^6" if n == 10**6 else f"{n // 10**6} × 10^6"
    return f"{n // 1000}k" if n % 1000 == 0 else f"{n:,}"


def _length(name: str, cfg) -> str:
    """``batch · epochs (updates)``, then each block with a schedule of its own (BAIL's envelope: passes over the data
    it is fitted on)."""
    from torchrl_bail.algorithms import ALGORITHMS
    from torchrl_bail.configuration.algo_schemas import blocks_with
    from torchrl_bail.modules import action_spec_from_bounds

    algo = ALGORITHMS[name](11, action_spec_from_bounds([-1.0] * 3, [1.0] * 3), cfg.algo)
    updates = math.ceil(algo.epochs * cfg.samples_per_epoch / algo.samples_per_update)
    parts = [f"{cfg.algo.batch_size} · {cfg.algo.epochs:g} epochs ({_count(updates)} updates)"]
    for block in blocks_with(name, "epochs"):
        node = cfg.algo[block]
        parts.append(f"{block} {node.batch_size} · {node.epochs:g} passes")
    return "; ".join(parts)


def _description(name: str, schema, cfg) -> str:
    try:
        return schema.description.format_map(cfg.algo)
    except (KeyError, AttributeError) as err:  # OmegaConf's errors name the key in full_key
        key = getattr(err, "full_key", None) or err.args[0]
        raise MissingEntry(f"{schema.__name__}.description names {key}, which conf/algo/{name}.yaml lacks") from None


def table() -> str:
    """The table's markdown; raises :class:`MissingEntry` naming every registry entry that lacks its data."""
    from hydra import compose, initialize_config_dir

    from torchrl_bail.configuration.algo_schemas import ALGO_SCHEMAS, entry_gaps
    from torchrl_bail.configuration.hydra_setup import config_dir

    gaps = [gap for name in ALGO_SCHEMAS for gap in entry_gaps(name)]
    if gaps:
        raise MissingEntry("algorithm registry entries without what the Algorithms page shows: " + ", ".join(gaps)
                           + " (state them on the schema, in src/torchrl_bail/algorithms/<name>.py)")
    lines = ["| `algo=` | what | loss modules | batch · length (paper preset) | evaluation |", "|---|---|---|---|---|"]
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        for name, schema in ALGO_SCHEMAS.items():
            cfg = compose("config", overrides=[f"algo={name}"])
            every = cfg.eval.every_epochs
            lines.append(f"| `{name}` | {_description(name, schema, cfg)} | {_losses(schema.losses)} | "
                         f"{_length(name, cfg)} | every {every:g} epoch{'s' if every > 1 else ''} |")
    return "\n".join(lines) + "\n"


def on_page_markdown(markdown: str, page, config, files) -> str:
    """MkDocs hook: the table in place of :data:`MARKER` on :data:`PAGE`."""
    if page.file.src_uri != PAGE:
        return markdown
    from mkdocs.exceptions import PluginError

    if MARKER not in markdown:
        raise PluginError(f"{PAGE} lost the line {MARKER!r}, where the algorithm table goes")
    try:
        return markdown.replace(MARKER, table())
    except MissingEntry as err:
        raise PluginError(str(err)) from None


if __name__ == "__main__":
    print(table(), end="")
