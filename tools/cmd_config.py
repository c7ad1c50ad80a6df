"""`slam config show [PRESET|FILE]`: every config key with its value, unit, allowed range and doc.

Nothing here is written twice: the docs are the config dataclasses' attribute docstrings (read
from their source), the units and ranges their fields' metadata (``slam.core.bounds``), the
values a loaded config (``slam.config.load_config``).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap
from dataclasses import dataclass
from typing import Any

WIDTH = 96
INDENT = "    "


@dataclass(frozen=True)
class KeyInfo:
    """One config key as `slam config show` prints it."""

    key: str
    """Dotted path, as in config error messages (``frontend.max_features``)."""
    value: Any
    unit: str
    allowed: str
    """``[1, 5000]``, ``(0, inf), less than frontend.max_depth_m``; ``""`` for non-numbers."""
    doc: str


def attribute_docs(cls: type) -> dict[str, str]:
    """``{field: docstring}`` of a dataclass: the string literal right below each field."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs: dict[str, str] = {}
    for node, after in zip(body, body[1:]):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def class_doc(cls: type) -> str:
    """The first sentence of a config class's docstring: its section's title."""
    text = " ".join(inspect.cleandoc(cls.__doc__ or "").split())
    return text.split(". ")[0].rstrip(".") + "." if text else ""


def describe(cfg: Any, where: str = "") -> list[KeyInfo]:
    """Every key of ``cfg`` (a config dataclass) and of the configs nested in it, in order."""
    from slam.core.bounds import field_bounds, field_unit

    docs = attribute_docs(type(cfg))
    keys: list[KeyInfo] = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            keys.extend(describe(value, f"{where}{f.name}."))
            continue
        bounds = field_bounds(f)
        allowed = ""
        if bounds is not None:
            allowed = bounds.interval()
            if bounds.below:
                relation = "at most" if bounds.below_or_equal else "less than"
                allowed += f", {relation} {where}{bounds.below}"
        keys.append(
            KeyInfo(f"{where}{f.name}", value, field_unit(f), allowed, docs.get(f.name, ""))
        )
    return keys


def _yaml_value(value: Any) -> str:
    """A value as it is written in a config file."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    return str(value)


def render(cfg: Any, title: str) -> str:
    """The listing `slam config show` prints."""
    lines = textwrap.wrap(
        f"{title} Change any key in a YAML file (nested: `frontend:` then `  max_features: "
        "300`, optionally `preset: NAME` first) and pass it with `slam run --config FILE`.",
        WIDTH,
        break_on_hyphens=False,  # never split a file path
        break_long_words=False,
    )
    section = None
    for k in describe(cfg):
        head = k.key.rpartition(".")[0]
        if head != section:
            section = head
            if head:
                nested = getattr(cfg, head)
                lines += ["", f"{head}: {class_doc(type(nested))}"]
            else:
                lines.append("")
        text = f"{k.key} = {_yaml_value(k.value)}" + (f" {k.unit}" if k.unit else "")
        if k.allowed:
            text += f"    in {k.allowed}"
        lines.append(text)
        if k.doc:
            lines.append(
                textwrap.fill(k.doc, WIDTH, initial_indent=INDENT, subsequent_indent=INDENT)
            )
    return "\n".join(lines)


def register(sub: argparse._SubParsersAction) -> None:
    from slam.config import PRESETS

    presets = ", ".join(sorted(PRESETS))
    p = sub.add_parser(
        "config",
        help="every configuration key with its default, unit, range and doc",
        description="Inspect the run configuration (`slam run --config`).",
    )
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    show = actions.add_parser(
        "show",
        help="print every key with its value, unit, allowed range and what it does",
        description="Print every configuration key of a preset or a YAML config file with its "
        "value, unit, allowed range and what it does. `slam run` starts from euroc-stereo-imu "
        "for a sequence with an IMU (euroc-mono-imu when it has one camera), else from "
        "stereo-vo.",
        epilog="examples:\n  slam config show euroc-stereo-imu\n  slam config show euroc-mono-imu\n"
        "  slam config show run1/config.yaml      # the configuration a run used\n"
        "  slam config show | grep -A2 depth",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    show.add_argument(
        "config",
        nargs="?",
        default="stereo-vo",
        metavar="PRESET",
        help=f"a preset ({presets}; default stereo-vo) or a YAML config file",
    )
    show.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    from slam.config import PRESETS, load_config

    cfg = load_config(args.config)
    what = f"preset {args.config}" if args.config in PRESETS else f"{args.config} ({cfg.preset})"
    print(render(cfg, f"Every configuration key of {what}: value, unit, allowed range, doc."))
    return 0
