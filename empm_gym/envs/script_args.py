"""Command-line parsing for the example scripts: an ``Args`` dataclass with one docstring per field.

``parse_args(Args)`` builds an argparse parser whose flags are the field names (``--total-steps``),
whose types and defaults come from the annotations and whose help is the docstring under each field
(read from the source, as CleanRL/tyro do), so a misspelt flag is an error, never a silent default.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap
import typing
from typing import Optional, Sequence, Type, TypeVar

__all__ = ["parse_args", "field_docs"]

T = TypeVar("T")


def field_docs(cls) -> dict:
    """{field name: docstring} of a dataclass, from the string literal after each field."""
    try:
        src = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    body = ast.parse(src).body[0].body
    docs = {}
    for a, b in zip(body, body[1:]):
        if isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr) \
                and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str):
            docs[a.target.id] = " ".join(b.value.value.split())
    return docs


def _bool(s: str) -> bool:
    if s.lower() in ("1", "true", "yes", "on"):
        return True
    if s.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean (true/false), got {s!r}")


def parse_args(cls: Type[T], argv: Optional[Sequence[str]] = None) -> T:
    """Parse ``argv`` (default sys.argv[1:]) into an instance of the dataclass ``cls``."""
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    p = argparse.ArgumentParser(description=(cls.__doc__ or "").strip(),
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter, allow_abbrev=False)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        optional = typing.get_origin(tp) is typing.Union and type(None) in typing.get_args(tp)
        if optional:
            tp = [a for a in typing.get_args(tp) if a is not type(None)][0]
        conv = _bool if tp is bool else tp
        if optional:
            base = conv
            conv = lambda s, base=base: None if s.lower() == "none" else base(s)  # noqa: E731
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        p.add_argument("--" + f.name.replace("_", "-"), dest=f.name, type=conv, default=default,
                       help=docs.get(f.name, ""))
    return cls(**vars(p.parse_args(argv)))
