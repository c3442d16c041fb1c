"""Command-line flags from a settings model: every field of a pydantic-settings model becomes
``--NAME`` (``_`` -> ``-``, after an optional prefix), and the value is read back as flag over the
model's environment variable (``<env_prefix><NAME>``) over its default. Booleans are ``--NAME`` /
``--no-NAME``; lists are one comma-separated value; ``Literal`` fields list their choices. The servers
that speak NATS (serve, gateway) also take the NATS credentials as ``--nats-*`` (:func:`add_server_parser`)."""

from __future__ import annotations

import argparse
import typing
from collections.abc import Callable

from pydantic import SecretStr
from pydantic_settings import BaseSettings

from ..bridge.auth import NatsAuth

#: Prefix of the NATS credentials' flags (:class:`~touchreal.bridge.auth.NatsAuth`): ``--nats-*``.
NATS_PREFIX = "nats-"


def env_name(model: type[BaseSettings], name: str) -> str:
    """The environment variable of field ``name``."""
    return f"{model.model_config.get('env_prefix', '')}{name}".upper()


def flag_name(name: str, prefix: str = "") -> str:
    return f"--{prefix}{name.replace('_', '-')}"


def _shown(default: object) -> str:
    if isinstance(default, list):
        return ",".join(map(str, default)) or "(none)"
    if isinstance(default, SecretStr):
        return "(secret)"
    return str(default)


def add_model_flags(p: argparse.ArgumentParser, model: type[BaseSettings], prefix: str = "") -> None:
    """One flag per field of ``model``; its help is the field's description, environment variable and default."""
    for name, field in model.model_fields.items():
        default = field.get_default(call_default_factory=True)
        text = f"{field.description or ''} ({env_name(model, name)}; default {_shown(default)})".replace("%", "%%")
        dest = f"{prefix}{name}".replace("-", "_")
        if field.annotation is bool:
            p.add_argument(flag_name(name, prefix), dest=dest, action=argparse.BooleanOptionalAction, default=None,
                           help=text)
            continue
        choices = typing.get_args(field.annotation) if typing.get_origin(field.annotation) is typing.Literal else None
        p.add_argument(flag_name(name, prefix), dest=dest, default=None, choices=choices,
                       metavar=None if choices else name.upper(), help=text)


def model_from_args(model: type[BaseSettings], args: argparse.Namespace, prefix: str = ""):
    """``model`` from the flags given, over the environment, over the defaults (pydantic's
    ValidationError, a ValueError, names a bad value)."""
    given = {name: getattr(args, f"{prefix}{name}".replace("-", "_"), None) for name in model.model_fields}
    return model(**{k: v for k, v in given.items() if v is not None})


def add_server_parser(sub: argparse._SubParsersAction, name: str, model: type[BaseSettings],
                      run: Callable[[argparse.Namespace], int], *, help: str, description: str) -> argparse.ArgumentParser:
    """Subcommand ``name`` of a server that speaks NATS, running ``run``: one flag per field of its settings
    ``model`` and, as ``--nats-*``, of the NATS credentials (:func:`nats_auth_from_args`)."""
    p = sub.add_parser(name, help=help, description=description)
    add_model_flags(p, model)
    add_model_flags(p, NatsAuth, prefix=NATS_PREFIX)
    p.set_defaults(func=run)
    return p


def nats_auth_from_args(args: argparse.Namespace) -> NatsAuth:
    """The NATS credentials from the ``--nats-*`` flags given, over the environment, over the defaults."""
    return model_from_args(NatsAuth, args, prefix=NATS_PREFIX)
