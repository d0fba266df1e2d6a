"""Each option of a step declared once: on its ``Options`` dataclass field, from which the rest is derived.

A field made with :func:`option` carries its help text, its command-line flag,
its sidebar label and its limits. From that one declaration come:

* the ``procam`` command's argparse options (:func:`add_arguments`) and the
  options object built from them (:func:`from_arguments`);
* the checks of a value, wherever it comes from (:func:`validate`): type,
  finiteness, limits, choices — the one place an option's value is refused;
* the Blender properties of the sidebar (``panels/properties.py`` turns each
  :class:`Spec` into a ``bpy.props`` property: this module stays free of bpy),
  and the options object built from a scene (:func:`from_values`);
* the sidebar's names for the command's options in messages
  (:func:`sidebar_names`, used by ``operators/messages.py``).

What was taken from elsewhere, and why: from tyro (nerfstudio's configs), that
a typed dataclass is the source of truth and the parser is derived from its
field types and defaults; not tyro itself — it would be a new dependency inside
Blender, and our flags predate it (``--no-bias`` for ``use_bias``) so each flag
stays spelled as users know it. From glTF-Blender-IO, that the Blender
properties mirror the engine's settings one to one under a common prefix
(``export_*`` there, ``procam_*`` here) while the engine never imports bpy.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import types
import typing
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

from .errors import ProCamError

#: the metadata key of a field's :class:`Spec`
KEY = "procam"


@dataclasses.dataclass(frozen=True)
class Choice:
    """One value of an option with a fixed set of values: its label and description in the sidebar."""

    value: str
    label: str = ""
    description: str = ""
    #: offered on the command line and in the sidebar; False: a value only Python callers give
    offered: bool = True


@dataclasses.dataclass(frozen=True)
class Spec:
    """How one option is named, explained and bounded, for the command line and the sidebar alike."""

    help: str
    #: the command-line flag; None: derived from the field's name (``capture_every`` → ``--capture-every``);
    #: "" : not an option of the command
    flag: str | None = None
    #: for a bool that is True by default: the flag that turns it off (``--no-bias``)
    negate: str = ""
    #: the field's label in the sidebar; "": not a field of the sidebar
    label: str = ""
    #: the scene property; "": ``procam_`` + the field's name
    prop: str = ""
    choices: tuple[Choice, ...] = ()
    min: float | None = None
    max: float | None = None
    #: the sidebar slider's end, where ``max`` is not a hard limit
    soft_max: float | None = None
    #: text (the command line, a sidebar text field) → value, raising ValueError or a ProCamError
    parse: Callable[[str], Any] | None = None
    #: a further check of a value (its syntax, a range), raising a ProCamError that says what is wrong
    check: Callable[[Any], Any] | None = None
    #: the sidebar's value that stands for None (an empty text, 0 iterations)
    blank: Any = None
    metavar: str | None = None
    #: for a Path: the sidebar's subtype (DIR_PATH, FILE_PATH)
    subtype: str = ""
    #: the sidebar shows this option through a field of its own making (a mesh picker, a checkbox beside a value):
    #: its label names it in messages, but no scene property is made from the declaration
    own_field: bool = False
    #: the command line must give it (``evaluate --device``)
    required: bool = False

    def cli_flag(self, name: str) -> str:
        return ("--" + name.replace("_", "-")) if self.flag is None else self.flag

    @property
    def values(self) -> tuple[str, ...]:
        return tuple(c.value for c in self.choices)

    @property
    def offered(self) -> tuple[Choice, ...]:
        """The choices the command line and the sidebar offer."""
        return tuple(c for c in self.choices if c.offered)


def option(default: Any = dataclasses.MISSING, *, help: str, default_factory: Any = dataclasses.MISSING,
           **spec: Any) -> Any:
    """A dataclass field with its :class:`Spec` (``help`` and the keywords of :class:`Spec`)."""
    if isinstance(spec.get("choices"), (list, tuple)):
        spec["choices"] = tuple(c if isinstance(c, Choice) else Choice(str(c)) for c in spec["choices"])
    return dataclasses.field(default=default, default_factory=default_factory,
                             metadata={KEY: Spec(help=help, **spec)})


def spec_of(cls: type, name: str) -> Spec:
    """The :class:`Spec` of option ``name`` of ``cls``: for a dialog's own field that takes its label from there,
    or for another step's field that is the same option (:func:`same_option`)."""
    for f in dataclasses.fields(cls):
        if f.name == name and KEY in f.metadata:
            spec: Spec = f.metadata[KEY]
            return spec
    raise KeyError(f"{cls.__name__} declares no option {name!r}")


def same_option(cls: type, name: str, default: Any = dataclasses.MISSING, **changes: Any) -> Any:
    """A dataclass field that is option ``name`` of ``cls`` again, declared there once (its flag, help, limits),
    with the default ``default`` (else that field's; none when ``required``) and the :class:`Spec` fields in
    ``changes`` changed."""
    if default is dataclasses.MISSING and not changes.get("required"):
        default = next(f.default for f in dataclasses.fields(cls) if f.name == name)
    return dataclasses.field(default=default, metadata={KEY: dataclasses.replace(spec_of(cls, name), **changes)})


@dataclasses.dataclass(frozen=True)
class Declared:
    """One declared option of an ``Options`` class: its name, value type (None removed), default and spec."""

    name: str
    kind: type
    optional: bool
    default: Any
    spec: Spec


def declared(cls: type) -> Iterator[Declared]:
    """The fields of ``cls`` declared with :func:`option`, in order."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        spec = f.metadata.get(KEY)
        if spec is None:
            continue
        kind, optional = _unwrap(hints[f.name])
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        yield Declared(f.name, kind, optional, default, spec)


def _unwrap(hint: Any) -> tuple[type, bool]:
    """``int | None`` → (int, True); ``tuple[int, ...]`` → (tuple, False)."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        # several kinds (a surface's name, file or mesh): the command line gives text, Python any of them
        kind = _unwrap(rest[0])[0] if len(rest) == 1 else object
        return kind, len(rest) < len(args)
    origin = typing.get_origin(hint)
    return (origin or hint), False


# -- values ----------------------------------------------------------------------------------------------------

def check_value(d: Declared, value: Any, error: type[ProCamError] = ProCamError) -> Any:
    """``value`` for option ``d`` if it is one the option takes; else ``error`` naming the option and the limits."""
    what = d.spec.cli_flag(d.name) if d.spec.cli_flag(d.name) else d.name.replace("_", " ")
    if value is None:
        if d.optional:
            return None
        raise error(f"{what} needs a value")
    if d.kind is bool:
        if not isinstance(value, bool):
            raise error(f"{what} must be true or false, got {value!r}")
        return value
    if d.kind is int:
        if isinstance(value, bool) or not isinstance(value, int) and not (
                hasattr(value, "__index__") and not isinstance(value, float)):
            raise error(f"{what} must be a whole number, got {value!r}")
        value = int(value)
    elif d.kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
            raise error(f"{what} must be a finite number, got {value!r}")
        value = float(value)
    elif d.kind is str and not isinstance(value, str):
        raise error(f"{what} must be text, got {value!r}")
    elif d.kind is Path and isinstance(value, str):
        value = Path(value)
    if d.spec.choices and value not in d.spec.values:
        raise error(f"{what} must be one of {', '.join(c.value for c in d.spec.offered)}, got {value!r}")
    lo, hi = d.spec.min, d.spec.max
    if lo is not None and value < lo or hi is not None and value > hi:
        bounds = (f"≥ {lo:g}" if hi is None else f"≤ {hi:g}" if lo is None else f"between {lo:g} and {hi:g}")
        raise error(f"{what} must be {'a whole number ' if d.kind is int else ''}{bounds}, got {value!r}")
    if d.spec.check is not None:
        d.spec.check(value)
    return value


def validate(options: Any, error: type[ProCamError] = ProCamError) -> None:
    """Check every declared option of ``options`` (an ``Options`` instance): the one place a value is refused."""
    for d in declared(type(options)):
        check_value(d, getattr(options, d.name), error)


# -- the command line ------------------------------------------------------------------------------------------

def _number(kind: type, text: str, what: str) -> Any:
    """``kind(text)``, or a ValueError that says ``what`` the option takes and what it got (not Python's words)."""
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f"{what}, got {text!r}") from None


def _text_type(d: Declared) -> Callable[[str], Any]:
    """argparse's ``type``: text → a value :func:`check_value` accepts, with argparse's own message on failure."""
    def convert(text: str) -> Any:
        try:
            if d.spec.parse is not None:
                value = d.spec.parse(text)
            elif d.kind is int:
                value = _number(int, text, f"{d.spec.cli_flag(d.name)} takes a whole number")
            elif d.kind is float:
                value = _number(float, text, f"{d.spec.cli_flag(d.name)} takes a number")
            elif d.kind is Path:
                value = Path(text)
            else:
                value = text
            if d.spec.choices and value not in {c.value for c in d.spec.offered}:
                raise ValueError(f"{d.spec.cli_flag(d.name)} must be one of "
                                 f"{', '.join(c.value for c in d.spec.offered)}, got {value!r}")
            return check_value(d, value)
        except (ValueError, ProCamError) as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    convert.__name__ = d.kind.__name__  # argparse names the type in its message: "invalid int value"
    return convert


def _cli_help(d: Declared) -> str:
    text = d.spec.help.replace("%", "%%")
    if d.default not in (None, "", False, ()) and "default" not in text:
        text += f" (default {d.default})"
    return text


def add_arguments(parser: argparse.ArgumentParser | Any, cls: type, *, only: Sequence[str] = (),
                  exclude: Sequence[str] = ()) -> None:
    """Add the declared options of ``cls`` (``only`` these, or all but ``exclude``) to ``parser``."""
    for d in declared(cls):
        if (only and d.name not in only) or d.name in exclude:
            continue
        flag = d.spec.cli_flag(d.name)
        if d.spec.negate:
            parser.add_argument(d.spec.negate, dest=d.name, action="store_false", default=d.default,
                                help=f"{d.spec.help} (this flag turns it off)")
        elif not flag:
            continue
        elif d.kind is bool:
            parser.add_argument(flag, dest=d.name, action="store_true", default=d.default, help=d.spec.help)
        else:
            metavar = d.spec.metavar or ("{" + ",".join(c.value for c in d.spec.offered) + "}" if d.spec.choices
                                         else None)
            required = {"required": True} if d.spec.required else {}
            parser.add_argument(flag, dest=d.name, type=_text_type(d), default=d.default, metavar=metavar,
                                help=_cli_help(d), **required)


def from_arguments(cls: type, args: argparse.Namespace, **given: Any) -> Any:
    """An instance of ``cls`` from the parsed command line: every declared option the parser holds, then
    ``given``."""
    values = {d.name: getattr(args, d.name) for d in declared(cls) if hasattr(args, d.name)}
    return cls(**{**values, **given})


# -- the sidebar -----------------------------------------------------------------------------------------------

def sidebar_fields(cls: type) -> Iterator[Declared]:
    """The declared options of ``cls`` whose sidebar field is made from the declaration."""
    return (d for d in declared(cls) if d.spec.label and not d.spec.own_field)


def prop_name(d: Declared) -> str:
    return d.spec.prop or f"procam_{d.name}"


def from_values(cls: type, values: Callable[[str], Any], **given: Any) -> Any:
    """An instance of ``cls`` from the sidebar: ``values(prop)`` reads a scene property; the sidebar's blank
    value becomes None, a text field is parsed as the command line parses it; then ``given``."""
    out: dict[str, Any] = {}
    for d in sidebar_fields(cls):
        if d.name in given:
            continue
        value = values(prop_name(d))
        if isinstance(value, str):
            value = value.strip()
        if d.spec.blank is not None and value == d.spec.blank:
            value = None if d.optional else d.default
        elif isinstance(value, str) and d.spec.parse is not None:
            value = d.spec.parse(value)
        out[d.name] = value
    return cls(**{**out, **given})


def sidebar_names(classes: Iterable[type], only: Sequence[str] = ()) -> dict[str, str]:
    """The command's flags of the sidebar's fields (``only`` these options), each named by its label as a message
    says it."""
    names: dict[str, str] = {}
    for cls in classes:
        for d in declared(cls):
            if not d.spec.label or (only and d.name not in only):
                continue
            flag = d.spec.negate or d.spec.cli_flag(d.name)
            if flag:
                names[flag] = f"‘{d.spec.label}’"
    return names
