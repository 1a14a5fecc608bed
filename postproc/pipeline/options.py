"""Stage options declared once: the options dataclasses say what each key is.

Each field's help is its `metadata["help"]` when given, else its entry in the class
docstring (`name: text`, the house style of every options dataclass); its unit is the
suffix of its name (`_m`, `_s`, `_px`...), its choices the `Literal` of its type, its
default the dataclass default. From that one declaration come:

- the command-line flags of a stage's subcommand (`add_flags`, `options_from_args`):
  each flag maps to one field (`Flag`), with a name kept from the existing command lines;
- the check of a project file's `stages:` mapping (`project.dataclass_from_mapping`,
  which follows the same types);
- the `stages:` section of deploy/project.example.yaml (`stages_example`,
  `update_example`; `wreckmap-post options --example` prints the file), so that the
  example documents every key of every stage with its default and unit.

Light on purpose (no stage module is imported here): the command lines import it.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

from shared.errors import InputError

# Name suffix -> unit, for help texts and the example's comments.
UNITS: dict[str, str] = {
    "_m": "m",
    "_s": "s",
    "_ns": "ns",
    "_px": "px",
    "_deg": "deg",
    "_rad": "rad",
    "_hz": "Hz",
    "_ppm": "ppm",
    "_per_m": "1/m",
    "_m_s": "m/s",
    "_m_s2": "m/s^2",
    "_m_per_sqrt_s": "m/sqrt(s)",
    "_rad_per_sqrt_s": "rad/sqrt(s)",
    "_deg_per_sqrt_s": "deg/sqrt(s)",
    "_rel": "x scene depth",
}

# "name: text" or "name_a / name_b: text" at the start of a docstring line.
_ENTRY = re.compile(r"^(\s*)([A-Za-z_]\w*(?:\s*/\s*[A-Za-z_]\w*)*): (.*)$")
_COMMENT_COLUMN = 34
_WIDTH = 100


def unit_of(name: str) -> str | None:
    """The unit a field's name carries (longest matching suffix), or None."""
    found = [suffix for suffix in UNITS if name.endswith(suffix)]
    return UNITS[max(found, key=len)] if found else None


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> its help: `metadata["help"]`, else the docstring's `name: text` entry
    (continuation lines joined), else an empty string."""
    docs: dict[str, str] = {}
    lines = (cls.__doc__ or "").splitlines()
    names = {f.name for f in dataclasses.fields(cls)}
    current: str | None = None
    indent = 0
    for line in lines:
        match = _ENTRY.match(line)
        entry = [n.strip() for n in match.group(2).split("/")] if match else []
        if entry and all(n in names for n in entry):
            current, indent = match.group(2), len(match.group(1))  # type: ignore[union-attr]
            docs[current] = match.group(3).strip()  # type: ignore[union-attr]
        elif current is not None and line.strip() and len(line) - len(line.lstrip()) > indent:
            docs[current] += " " + line.strip()
        else:
            current = None
    for key in [k for k in docs if "/" in k]:
        for n in key.split("/"):
            docs.setdefault(n.strip(), docs[key])
    # An entry ends where the next one starts inside its paragraph.
    for key, text in docs.items():
        for follows in re.finditer(r"[.;] ([A-Za-z_]\w*): ", text):
            if follows.group(1) in names:
                docs[key] = text[: follows.start() + 1]
                break
    # An entry inside a paragraph: "... model). refine_intrinsics: also adjust ... ."
    joined = " ".join(line.strip() for line in lines)
    for name in names - set(docs):
        inline = re.search(
            rf"(?:^|[.;] ){name}: (.*?)(?:[.;] [A-Za-z_]\w*: |\.\s*$|\.\s{{2,}}|$)", joined
        )
        if inline:
            docs[name] = inline.group(1).strip()
    for f in dataclasses.fields(cls):
        if "help" in f.metadata:
            docs[f.name] = str(f.metadata["help"])
    return {f.name: docs.get(f.name, "") for f in dataclasses.fields(cls)}


def _default(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _strip_optional(hint: Any) -> tuple[Any, bool]:
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return hint, False


def choices_of(hint: Any) -> tuple[Any, ...] | None:
    """The values of a Literal type (under Optional too), or None."""
    hint, _ = _strip_optional(hint)
    if typing.get_origin(hint) is Literal:
        return typing.get_args(hint)
    return None


# ------------------------------------------------------------------------------ flags


@dataclass(frozen=True, kw_only=True)
class Flag:
    """One command-line flag for one field of an options dataclass.

    field: the field's name, dotted for a nested one (`fusion.num_threads`).
    flag: the flag (`--max-offset`); None: `--` and the field name in kebab-case.
    negate: a boolean field that defaults to true, turned off by this flag (`--no-fuse`).
    zero_is_none: the value 0 means None (`--clock-window 0` turns the prior off).
    metavar: shown in the help instead of the field's name (one name per value for a
        fixed-length tuple field, `("R", "G", "B")`, which takes that many values).
    also: other fields (same type and default) that take the same value (`--threads`
        sets the threads of every step).
    off_flag: a field that is true, false or a third value by default (None, "auto"):
        `flag` sets it true, `off_flag` false, neither leaves the default.
    """

    field: str
    flag: str | None = None
    negate: bool = False
    zero_is_none: bool = False
    metavar: str | tuple[str, ...] | None = None
    also: tuple[str, ...] = ()
    off_flag: str | None = None

    @property
    def name(self) -> str:
        return self.flag or "--" + self.field.rsplit(".", 1)[-1].replace("_", "-")

    @property
    def dest(self) -> str:
        return "option__" + self.field.replace(".", "__")


def _resolve(cls: type, dotted: str) -> tuple[type, dataclasses.Field[Any], Any, Any]:
    """(owning class, field, type hint, default) of a dotted field of `cls`."""
    owner = cls
    parts = dotted.split(".")
    for k, part in enumerate(parts):
        fields = {f.name: f for f in dataclasses.fields(owner)}
        if part not in fields:
            raise KeyError(f"{owner.__name__} has no field {part!r}")
        hint = typing.get_type_hints(owner)[part]
        if k < len(parts) - 1:
            owner = hint
            continue
        return owner, fields[part], hint, _default(fields[part])
    raise KeyError(dotted)


def _fixed_tuple(hint: Any) -> tuple[type, int] | None:
    """(item type, length) of `tuple[T, T, ...]` with T int, float or str; else None."""
    if typing.get_origin(hint) is not tuple:
        return None
    items = typing.get_args(hint)
    if not items or Ellipsis in items or len(set(items)) != 1 or items[0] not in (int, float, str):
        return None
    return items[0], len(items)


def add_flags(parser: argparse.ArgumentParser, cls: type, flags: list[Flag]) -> None:
    """Add `flags` to `parser`, their type, default, choices and help from `cls`."""
    for flag in flags:
        owner, f, hint, default = _resolve(cls, flag.field)
        for other in flag.also:
            if _resolve(cls, other)[2:] != (hint, default):
                raise ValueError(
                    f"{flag.name}: {other} differs from {flag.field} in type or default"
                )
        text = field_docs(owner)[f.name].rstrip(".") or flag.field
        value_hint, optional = _strip_optional(hint)
        if flag.off_flag is not None:
            group = parser.add_mutually_exclusive_group()
            shown = "none" if default is None else default
            group.add_argument(
                flag.name, dest=flag.dest, action="store_const", const=True, default=default,
                help=f"{text} (default: {shown})",
            )  # fmt: skip
            group.add_argument(
                flag.off_flag, dest=flag.dest, action="store_const", const=False,
                help=f"turn off: {text}",
            )  # fmt: skip
            continue
        if value_hint is bool:
            if flag.negate != bool(default):
                raise ValueError(f"{flag.name}: negate must match {flag.field}'s default")
            parser.add_argument(
                flag.name,
                dest=flag.dest,
                action="store_false" if flag.negate else "store_true",
                default=default,
                help=f"turn off: {text}" if flag.negate else text,
            )
            continue
        choices = choices_of(hint)
        unit = unit_of(f.name)
        shown = "none" if default is None else default
        extra = f" ({unit}; default: {shown})" if unit else f" (default: {shown})"
        if flag.zero_is_none:
            extra += "; 0: none"
        kwargs: dict[str, Any] = {"dest": flag.dest, "default": default, "help": text + extra}
        if choices is not None:
            # Literal values given as text on the command line (`--dof 4` is the int 4).
            by_text = {str(c): c for c in choices}
            kwargs["choices"] = choices
            kwargs["type"] = lambda text, by_text=by_text: by_text.get(text, text)
        elif value_hint in (int, float, str, Path):
            kwargs["type"] = value_hint
        elif (fixed := _fixed_tuple(value_hint)) is not None:
            # A fixed-length tuple of one type (`tuple[float, float, float]`): that many
            # values after the flag (`--attenuation 0.4 0.13 0.11`).
            kwargs["type"], kwargs["nargs"] = fixed
        else:
            raise TypeError(f"{flag.field}: no command-line flag for type {hint!r}")
        if choices is None:
            kwargs["metavar"] = flag.metavar or f.name.upper()
        del optional
        parser.add_argument(flag.name, **kwargs)


class _LazyFlagsParser(argparse.ArgumentParser):
    """A subcommand's parser whose option flags are added when it is first used (parsed,
    or its help shown), so that building the whole command line imports no stage."""

    def _add_lazy_flags(self) -> None:
        add = self.__dict__.pop("_lazy_flags", None)
        if add is not None:
            add(self)

    def parse_known_args(  # type: ignore[override]
        self, args: Any = None, namespace: Any = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self._add_lazy_flags()
        return super().parse_known_args(args, namespace)

    def format_help(self) -> str:
        self._add_lazy_flags()
        return super().format_help()

    def format_usage(self) -> str:
        self._add_lazy_flags()
        return super().format_usage()


def add_flags_lazily(
    parser: argparse.ArgumentParser, options_type: Callable[[], type], flags: list[Flag]
) -> None:
    """`add_flags` on first use of `parser` (a subcommand's): `options_type` imports the
    stage's options class only then, and `wreckmap-post --help` stays instant."""
    parser.__class__ = _LazyFlagsParser
    parser._lazy_flags = lambda p: add_flags(p, options_type(), flags)  # type: ignore[attr-defined]


def options_from_args(cls: type, args: argparse.Namespace, flags: list[Flag]) -> Any:
    """The options dataclass `cls` with the values of `flags` parsed into `args` (every
    other field at its default; each dataclass built through its constructor, so its
    own checks run). Raises InputError naming the flag for a value the class refuses."""
    values: dict[str, Any] = {}
    for flag in flags:
        value = getattr(args, flag.dest)
        if flag.zero_is_none and value == 0:
            value = None
        if isinstance(value, list):  # a tuple field's values (nargs)
            value = tuple(value)
        for name in (flag.field, *flag.also):
            values[name] = value
    try:
        return _build(cls, values)
    except (TypeError, ValueError) as error:
        raise InputError(f"{cls.__name__}: {error}") from None


def _build(cls: type, values: dict[str, Any]) -> Any:
    """`cls(**...)` from dotted field names (nested dataclasses built the same way)."""
    top: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for name, value in values.items():
        head, _, rest = name.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            top[head] = value
    hints = typing.get_type_hints(cls)
    for head, inner in nested.items():
        top[head] = _build(hints[head], inner)
    return cls(**top)


# ------------------------------------------------------------------------------ example


def _yaml_value(value: Any) -> str:
    import yaml

    text = yaml.safe_dump(_plain(value), default_flow_style=True, width=1000).strip()
    return text.removesuffix("\n...").strip()


def _plain(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def _comment(text: str, name: str) -> str:
    """The first sentence of a field's help, with its unit (the dataclass has the rest)."""
    unit = unit_of(name)
    text = re.split(r"(?<=[a-z0-9)])\. (?=[A-Z])", text, maxsplit=1)[0].rstrip(".")
    return f"{text} [{unit}]" if unit and f"[{unit}]" not in text else text


def stages_example() -> str:
    """The `stages:` section of deploy/project.example.yaml, from the registry and the
    options dataclasses (every top-level key with its default; nested groups by name)."""
    from postproc.pipeline.stages import STAGES

    lines = ["stages:"]
    for name, stage in STAGES.items():
        cls = stage.options_type()
        lines += _commented(f"  {name}:", f"{cls.__module__}.{cls.__name__}")
        docs = field_docs(cls)
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if not f.init:
                continue
            hint, _ = _strip_optional(hints[f.name])
            default = _default(f)
            if dataclasses.is_dataclass(hint):
                value = "{}"
                first = (hint.__doc__ or "").strip().splitlines()[0].rstrip(".")
                # A field's type hint: the dataclass itself, never an instance.
                text = f"{cast(type, hint).__name__}: {first}"
            else:
                value = _yaml_value(default)
                text = _comment(docs[f.name] or f.name, f.name)
                choices = choices_of(hints[f.name])
                if choices is not None and not any(str(c) in text for c in choices):
                    text += " (" + ", ".join(str(c) for c in choices) + ")"
            lines += _commented(f"    {f.name}: {value}", text)
    return "\n".join(lines) + "\n"


def _commented(line: str, text: str) -> list[str]:
    """`line` with the comment `text` from column 34, wrapped at 100 characters."""
    import textwrap

    column = max(_COMMENT_COLUMN, len(line) + 1)
    wrapped = textwrap.wrap(text, _WIDTH - column - 2) or [""]
    out = [line.ljust(column) + "# " + wrapped[0]]
    out += [" " * column + "# " + more for more in wrapped[1:]]
    return out


_STAGES_START = "stages:\n"


def _split(text: str, path: Path) -> tuple[str, str]:
    """The example's text up to its `stages:` section, and from the next top-level line
    (a comment or a key) after it."""
    start = text.find("\n" + _STAGES_START)
    if start < 0:
        raise InputError(f"{path}: no top-level 'stages:' section")
    rest = text[start + 1 + len(_STAGES_START) :]
    end = re.search(r"^\S", rest, re.M)
    return text[: start + 1], rest[end.start() :] if end else ""


def example_text(path: Path) -> str:
    """deploy/project.example.yaml as it should read: its hand-written parts as they are,
    its `stages:` section generated."""
    head, tail = _split(path.read_text(encoding="utf-8"), path)
    return head + stages_example() + ("\n" + tail if tail else "")


def update_example(path: Path) -> bool:
    """Rewrite the `stages:` section of the example at `path` (atomically); True when it
    changed."""
    from shared.fsutil import write_text_atomic

    text = example_text(path)
    if text == path.read_text(encoding="utf-8"):
        return False
    write_text_atomic(path, text, overwrite=True)
    return True
