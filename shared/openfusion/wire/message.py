"""The base classes of every wire model and the schema registry.

A message is a pydantic model with a class-level ``schema_name`` and integer ``schema_version``;
defining a subclass of :class:`Message` with both set registers it, and :mod:`openfusion.wire.codec`
finds the class of a payload by its schema name here (:func:`message_class`). The schemas
themselves live in :mod:`openfusion.wire.schemas`.
"""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict

_REGISTRY: dict[str, type[Message]] = {}


class Record(BaseModel):
    """Base of every wire model (messages and their nested parts): strict about unknown fields
    and non-finite floats."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, arbitrary_types_allowed=True)


class Message(Record):
    """A top-level bus message. Subclasses set ``schema_name`` and ``schema_version``."""

    schema_name: ClassVar[str]
    schema_version: ClassVar[int]

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        super().__pydantic_init_subclass__(**kwargs)
        if "schema_name" not in cls.__dict__:
            return  # an abstract base (e.g. PinholeMessage)
        if not isinstance(cls.__dict__.get("schema_version"), int):
            raise TypeError(f"{cls.__qualname__} sets schema_name but no integer schema_version")
        name = cls.schema_name
        previous = _REGISTRY.get(name)
        if previous is not None and previous.__qualname__ != cls.__qualname__:
            raise TypeError(
                f"schema {name!r} is already registered by {previous.__module__}.{previous.__qualname__}"
            )
        # Same qualname: the module was imported twice (e.g. as __main__ and by name); keep the newest.
        _REGISTRY[name] = cls


def message_class(schema_name: str) -> type[Message] | None:
    """The message class registered under ``schema_name``, or None."""
    return _REGISTRY.get(schema_name)


def registered_schemas() -> dict[str, type[Message]]:
    """A copy of the registry: schema name -> message class (import
    :mod:`openfusion.wire.schemas` first so every schema of the package is registered)."""
    return dict(_REGISTRY)
