"""``magkf plugins``: the log readers, filters, measurement models and effects this installation knows."""

from __future__ import annotations

from . import common

__all__ = ["add_parsers", "run_plugins", "plugin_rows"]


def add_parsers(sub) -> None:
    """Register ``plugins``."""
    p = common.command(
        sub,
        "plugins",
        run_plugins,
        "the log readers, filters, measurement models and effects known here, and where each comes from",
    )
    p.add_argument(
        "--effect-file",
        action="append",
        default=[],
        metavar="FILE.py",
        help="also list the effects this Python file defines (it is run as Python code with your rights)",
    )
    p.add_argument("--json", action="store_true", help="one JSON object per plug-in kind on standard output")


def plugin_rows() -> dict[str, list[dict]]:
    """Every registered plug-in by kind (``magkf.plugins.REGISTRIES``): ``name``, ``origin`` (magkf's own, an
    entry point, or registered), ``source`` (``module:Class``) and ``summary`` (its docstring's first line; for
    one that cannot be loaded, why)."""
    from ..plugins import REGISTRIES, PluginError

    out = {}
    for kind, registry in REGISTRIES.items():
        rows = []
        for name in registry:
            row = {"name": name, "origin": registry.origin(name), "source": registry.source(name)}
            try:
                doc = (registry[name].__doc__ or "").strip()
                row["summary"] = " ".join(doc.split("\n\n")[0].split()).replace("``", "")
            except PluginError as exc:
                row["summary"] = f"cannot be loaded: {exc}"
            rows.append(row)
        out[kind] = rows
    return out


def run_plugins(args) -> int:
    """List the plug-ins, a table per kind (``--json``: the rows of ``plugin_rows``)."""
    import json
    import textwrap

    from ..effects import load_effect_file

    for path in args.effect_file:
        load_effect_file(path)
    rows = plugin_rows()
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for kind, items in rows.items():
        print(f"{kind}:")
        width = max(len(r["name"]) for r in items)
        for r in items:
            where = "" if r["origin"] == "magkf" else f" [{r['origin']}: {r['source']}]"
            text = textwrap.shorten(r["summary"], 100 - width, placeholder=" ...") if r["summary"] else ""
            print(f"  {r['name']:<{width}}  {text}{where}")
    return 0
