"""Stage configs on the command line: one ``--flag`` per dataclass field, and back.

Every stage has one config dataclass; :func:`add_config_arguments` adds a flag for each of
its scalar fields (``lambda_d2n`` → ``--lambda-d2n``) that the parser does not already have,
with no default of its own, so :func:`config_from_args` passes only what the user typed and
the dataclass (or its named preset) keeps every other default. Hand-written flags with
``dest`` equal to a field name are picked up the same way.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import typing

#: Largest magnitude accepted for an integer flag (sizes and counts become 32-bit values
#: in Dr.Jit; a larger number is a typo or an attack, never a setting).
INT_LIMIT = 2 ** 31 - 1


def _scalar_type(tp):
    """int/float/str/bool for ``T`` or ``T | None`` annotations, else None."""
    if isinstance(tp, str):
        tp = {"int": int, "float": float, "str": str, "bool": bool}.get(
            tp.replace(" | None", "").replace("None | ", ""), None)
        return tp
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if len(args) == 1:
        tp = args[0]
    return tp if tp in (int, float, str, bool) else None


def _parse_bool(s: str) -> bool:
    v = s.strip().lower()
    if v in ("1", "true", "yes", "on"):
        return True
    if v in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true/false, got {s!r}")


def add_config_arguments(parser: argparse.ArgumentParser, cls, exclude=(), presets=None) -> None:
    """Add ``--field-name`` for every scalar field of dataclass ``cls`` not yet in ``parser``.

    ``presets`` ({name: {field: value}}): the help also names the presets' own values, so
    ``--help`` shows what a run without the flag uses."""
    taken = {a.dest for a in parser._actions}
    defaults = cls()
    presets = presets or {}
    group = parser.add_argument_group(f"{cls.__name__} fields (defaults from the config)")
    for f in dataclasses.fields(cls):
        tp = _scalar_type(f.type)
        if f.name in taken or f.name in exclude or tp is None:
            continue
        group.add_argument("--" + f.name.replace("_", "-"), dest=f.name, default=None,
                           type=_parse_bool if tp is bool else tp, metavar=tp.__name__.upper(),
                           help=_default_help(getattr(defaults, f.name), f.name, presets))


def _default_help(default, name: str, presets: dict) -> str:
    own = [f"{p} preset {v[name]!r}" for p, v in presets.items() if name in v]
    return f"(default {default!r}{'; ' + ', '.join(own) if own else ''})"


def config_overrides(args: argparse.Namespace, cls) -> dict:
    """The fields of ``cls`` that ``args`` sets (flags left at None are not overrides)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return {k: v for k, v in vars(args).items() if k in names and v is not None}


def numeric_problem(parser: argparse.ArgumentParser, args: argparse.Namespace) -> str | None:
    """The first numeric flag of the chosen (sub)command that no stage can use: a float that
    is NaN/Inf (``nan``, ``inf``, ``1e309``) or an integer beyond ±``INT_LIMIT``; as
    ``"argument --flag: ..."``, or None. Range checks specific to a flag stay in the configs."""
    for action in _chosen_actions(parser, args):
        if not action.option_strings or action.dest not in vars(args):
            continue
        value = getattr(args, action.dest)
        for v in value if isinstance(value, (list, tuple)) else [value]:
            flag = "/".join(action.option_strings)
            if isinstance(v, float) and not math.isfinite(v):
                return f"argument {flag}: {v!r} is not a finite number"
            if isinstance(v, int) and not isinstance(v, bool) and abs(v) > INT_LIMIT:
                return f"argument {flag}: {v} is out of range (|n| <= {INT_LIMIT})"
    return None


def _chosen_actions(parser: argparse.ArgumentParser, args: argparse.Namespace):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            sub = action.choices.get(getattr(args, action.dest, None) or "")
            if sub is not None:
                yield from _chosen_actions(sub, args)
        else:
            yield action


class _DeprecatedVariant(argparse.Action):
    """``--variant`` where it still names the Mitsuba variant: stores it and says once on
    stderr that the flag is now ``--mitsuba-variant`` (kept so existing scripts run)."""

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog}: --variant is now --mitsuba-variant (the old name still works)",
              file=sys.stderr)
        setattr(namespace, self.dest, values)


def shared_options(*, out: dict | None = None, mitsuba_variant: bool = True,
                   quiet: bool = True, variant_alias: bool = True) -> argparse.ArgumentParser:
    """The flags every command spells the same way, as an argparse parent
    (``subparsers.add_parser(name, parents=[shared_options(...)])``).

    out: keyword arguments of ``--out`` (its ``required``/``default``/``metavar``/``help``
        differ per command: a folder, a file); None: the command has no ``--out``.
    mitsuba_variant: ``--mitsuba-variant NAME``, ``dest="mitsuba_variant"``, default
        ``auto``; ``core.variant.set_variant`` checks the name (unknown or scalar: an error).
    quiet: ``--quiet`` (no progress bars or per-step lines), ``dest="quiet"``.
    variant_alias: also accept the old ``--variant`` for the Mitsuba variant (hidden, with a
        note on stderr); False where ``--variant`` means something else (``render-comp``'s
        composite variant)."""
    p = argparse.ArgumentParser(add_help=False)
    if out is not None:
        p.add_argument("--out", **out)
    if mitsuba_variant:
        p.add_argument("--mitsuba-variant", dest="mitsuba_variant", default="auto",
                       metavar="MITSUBA_VARIANT",
                       help="Mitsuba variant: auto (default: cuda_ad_rgb when a GPU is "
                            "present, else llvm_ad_rgb), llvm_ad_rgb, cuda_ad_rgb")
        if variant_alias:
            p.add_argument("--variant", dest="mitsuba_variant", action=_DeprecatedVariant,
                           help=argparse.SUPPRESS)
    if quiet:
        p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p
