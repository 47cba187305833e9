"""Config-dataclass fields as flags, with the spellings users already type.

:func:`add_config_flags` gives every field of a config a flag: first the fields a
:class:`Spelling` describes (an older name such as ``--res`` for ``resolution``, choices,
several values, an on/off switch), then every other scalar field through
``core.config.add_config_arguments`` (``lambda_d2n`` -> ``--lambda-d2n``). No flag has a
default of its own: :func:`field_overrides` returns only what the user typed, so the config
(or its preset) keeps every other default.

Example::

    add_config_flags(p, ObjectDatasetConfig, {"n_train": Spelling(("--views",))},
                     exclude=("out_dir", "variant"))
    cfg = ObjectDatasetConfig(out_dir=args.out, **field_overrides(args, ObjectDatasetConfig))
"""
from __future__ import annotations

import argparse
import dataclasses
import typing

from comgs_dr.core.config import _parse_bool, add_config_arguments, config_overrides

_SCALARS = (int, float, str, bool)
_VALUE = object()                 # Spelling.const of a value flag (not a switch)


@dataclasses.dataclass(frozen=True)
class Spelling:
    """How one config field is typed on the command line.

    flags: more option strings for the field's flag (``("--views",)``); the generated
        ``--field-name`` is always added too. With ``const``: the option strings of a switch.
    type: the value type where the annotation does not name one (``str | Path | None``).
    nargs: list-valued fields (``3``, ``"+"``, ``"*"``); the list becomes a tuple.
    const: a switch that sets the field to this value (``--no-texture``: ``None``); the
        field also keeps its value flag ``--field-name`` unless a switch already has it.
    """
    flags: tuple[str, ...] = ()
    help: str | None = None
    metavar: str | tuple[str, ...] | None = None
    type: type | None = None
    nargs: int | str | None = None
    choices: tuple | None = None
    const: object = _VALUE


@dataclasses.dataclass(frozen=True)
class _Switched:
    """What a switch to ``None`` stores (``--no-texture``): wrapped, so that it still counts
    as typed (``config_overrides`` drops None)."""
    value: object


def add_config_flags(parser: argparse.ArgumentParser, cls, spellings: dict | None = None, *,
                     exclude=(), presets: dict | None = None) -> None:
    """One flag per field of dataclass ``cls`` (see the module docstring); ``exclude``: fields
    the command sets itself (``out_dir`` from ``--out``); ``presets`` ({name: {field:
    value}}): their values are named in the help beside the config's defaults."""
    spellings = spellings or {}
    defaults, hints = cls(), typing.get_type_hints(cls)
    for name, sp in spellings.items():
        default = getattr(defaults, name)
        if sp.const is not _VALUE:
            parser.add_argument(*sp.flags, dest=name, action="store_const",
                                const=_Switched(None) if sp.const is None else sp.const,
                                default=None, help=sp.help)
            flag = "--" + name.replace("_", "-")
            value_type = sp.type or _scalar(hints[name])
            if flag not in sp.flags and value_type is not None:
                parser.add_argument(flag, dest=name, default=None,
                                    help=_help(None, default, name, presets or {}),
                                    type=_parse_bool if value_type is bool else value_type,
                                    metavar=value_type.__name__.upper())
            continue
        parser.add_argument(*_option_strings(name, sp), dest=name, default=None,
                            help=_help(sp.help, default, name, presets or {}),
                            **_value_kwargs(sp, hints[name]))
    add_config_arguments(parser, cls, exclude=tuple(exclude) + tuple(spellings),
                         presets=presets)


def field_overrides(args: argparse.Namespace, cls) -> dict:
    """The fields of ``cls`` the user typed (``core.config.config_overrides``), lists as
    tuples and switches to None unwrapped."""
    out = {}
    for k, v in config_overrides(args, cls).items():
        if isinstance(v, _Switched):
            v = v.value
        elif isinstance(v, list):
            v = tuple(v)
        out[k] = v
    return out


def preset_differences(presets: dict, base) -> dict:
    """{name: {field: value}} of the fields where each preset instance differs from ``base``
    (the presets' help entries of :func:`add_config_flags`)."""
    fields = [f.name for f in dataclasses.fields(base)]
    return {n: {f: getattr(p, f) for f in fields if getattr(p, f) != getattr(base, f)}
            for n, p in presets.items()}


def _option_strings(name: str, sp: Spelling) -> list[str]:
    generated = "--" + name.replace("_", "-")
    return list(sp.flags) + ([generated] if generated not in sp.flags else [])


def _value_kwargs(sp: Spelling, hint) -> dict:
    """type/nargs/choices/metavar of a value flag, its type from the annotation unless given."""
    kw = {k: v for k, v in (("nargs", sp.nargs), ("choices", sp.choices),
                            ("metavar", sp.metavar)) if v is not None}
    value_type = sp.type or (_element(hint) if sp.nargs is not None else _scalar(hint))
    if value_type is None:
        raise TypeError(f"Spelling: give the type of a field annotated {hint}")
    kw["type"] = _parse_bool if value_type is bool else value_type
    if "metavar" not in kw and "choices" not in kw:
        kw["metavar"] = value_type.__name__.upper()
    return kw


def _scalar(hint):
    """int/float/str/bool for ``T`` or ``T | None``, else None."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    tp = args[0] if len(args) == 1 else hint
    return tp if tp in _SCALARS else None


def _element(hint):
    """The element type of ``tuple[T, ...]`` / ``tuple[T, T]`` (optionally ``| None``)."""
    for h in [hint, *typing.get_args(hint)]:
        if typing.get_origin(h) in (tuple, list):
            elems = {a for a in typing.get_args(h) if a is not Ellipsis}
            if len(elems) == 1 and (tp := elems.pop()) in _SCALARS:
                return tp
    return None


def _help(text: str | None, default, name: str, presets: dict) -> str:
    own = [f"{p} preset {v[name]!r}" for p, v in presets.items() if name in v]
    tail = f"(default {default!r}{'; ' + ', '.join(own) if own else ''})"
    return f"{text} {tail}" if text else tail
