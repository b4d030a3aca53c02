"""Keywords that moved into an options object: they keep working for one release, each with a
`DeprecationWarning` that names its new spelling."""

from __future__ import annotations

import dataclasses
import warnings

from .errors import InputError
from .precision import _caller_stacklevel


def moved_into(where: str, kwargs: dict, options, cls, name: str, rename: dict[str, str] | None = None):
    """`options` (an instance of the dataclass `cls`, or None for `cls()`) with the keywords of
    `kwargs` that are fields of `cls` (or keys of `rename`, the field's old spelling) set on it.
    Each one found is taken out of `kwargs` and warns (`DeprecationWarning`, pointing at the
    caller's line): `where: kw= is deprecated; pass name=cls(field=...)`.

    Raises `InputError` when `options` is neither None nor a `cls`."""
    if options is None:
        options = cls()
    elif not isinstance(options, cls):
        raise InputError(f"{where}: {name} must be a jsphere.{cls.__name__}; got {type(options).__name__}.")
    rename = rename or {}
    fields = {f.name for f in dataclasses.fields(cls)}
    moved = {}
    for kw in [k for k in kwargs if k in fields or k in rename]:
        field = rename.get(kw, kw)
        warnings.warn(
            f"{where}: {kw}= is deprecated; pass {name}={cls.__name__}({field}=...)",
            DeprecationWarning,
            stacklevel=_caller_stacklevel(),
        )
        moved[field] = kwargs.pop(kw)
    return dataclasses.replace(options, **moved) if moved else options


def no_other_keywords(where: str, kwargs: dict) -> None:
    """A `TypeError`, as Python's own, for a keyword that is neither a parameter nor a moved one."""
    if kwargs:
        raise TypeError(f"{where}() got an unexpected keyword argument {next(iter(kwargs))!r}")
