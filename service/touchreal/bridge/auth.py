"""How the publisher and the gateways authenticate to the broker: one of user/password, token, a
``.creds`` file (JWT + nkey seed) or an nkey seed file, optionally over TLS (docs/scale-out.md).

Flags ``--nats-*`` over ``TOUCHREAL_NATS_*`` environment variables; an empty variable counts as
unset (compose passes ``""`` for a variable it does not know). Secrets never appear in ``repr`` or
``/v1/status`` (:meth:`NatsAuth.describe`).
"""

from __future__ import annotations

import argparse
import ssl
from pathlib import Path
from typing import Any

from pydantic import SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

_FLAGS = (
    ("user", "NATS user name (with --nats-password)"),
    ("password", "NATS password; prefer the environment variable: flags show in the process list"),
    ("token", "NATS token; prefer the environment variable"),
    ("creds", "NATS .creds file (JWT and nkey seed, from nsc)"),
    ("nkey", "NATS nkey seed file (its public key is in the broker's config)"),
    ("tls-ca", "CA bundle to verify the broker's certificate (implies TLS)"),
    ("tls-cert", "client certificate for TLS client authentication to the broker (with --nats-tls-key)"),
    ("tls-key", "private key of --nats-tls-cert"),
)


class NatsAuth(BaseSettings):
    """Broker credentials (environment: ``TOUCHREAL_NATS_<NAME>``); all unset = anonymous."""

    model_config = SettingsConfigDict(env_prefix="TOUCHREAL_NATS_", extra="ignore")

    user: str | None = None
    password: SecretStr | None = None
    token: SecretStr | None = None
    creds: Path | None = None
    nkey: Path | None = None
    tls: bool = False  #: require TLS with the system's CAs (a ``tls://`` URL requires it too)
    tls_ca: Path | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None

    @field_validator("*", mode="before")
    @classmethod
    def _empty_is_unset(cls, v: Any) -> Any:
        return None if isinstance(v, str) and v == "" else v

    @model_validator(mode="after")
    def _one_method(self) -> NatsAuth:
        methods = [m for m, on in (("user/password", self.user is not None), ("token", self.token is not None),
                                   ("creds", self.creds is not None), ("nkey", self.nkey is not None)) if on]
        if len(methods) > 1:
            raise ValueError(f"NATS: use one authentication method, not {' and '.join(methods)}")
        if (self.password is not None) != (self.user is not None):
            raise ValueError("NATS: --nats-user and --nats-password go together")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("NATS: --nats-tls-cert and --nats-tls-key go together")
        for name in ("creds", "nkey", "tls_ca", "tls_cert", "tls_key"):
            path = getattr(self, name)
            if path is not None and not path.is_file():
                raise ValueError(f"NATS: --nats-{name.replace('_', '-')} {path} is not a readable file")
        return self

    def connect_options(self) -> dict[str, Any]:
        """Keyword arguments for ``nats.connect``."""
        out: dict[str, Any] = {}
        if self.user is not None:
            out.update(user=self.user, password=self.password.get_secret_value())
        if self.token is not None:
            out["token"] = self.token.get_secret_value()
        if self.creds is not None:
            out["user_credentials"] = str(self.creds)
        if self.nkey is not None:
            out["nkeys_seed"] = str(self.nkey)
        if self.tls or self.tls_ca or self.tls_cert:
            ctx = ssl.create_default_context(cafile=str(self.tls_ca) if self.tls_ca else None)
            if self.tls_cert is not None:
                ctx.load_cert_chain(str(self.tls_cert), str(self.tls_key))
            out["tls"] = ctx
        return out

    def describe(self) -> str:
        """The method in use, without secrets (for logs and ``/v1/status``)."""
        method = (f"user {self.user}" if self.user else "token" if self.token else f"creds {self.creds}" if self.creds
                  else f"nkey {self.nkey}" if self.nkey else "anonymous")
        return method + (" over TLS" if self.tls or self.tls_ca or self.tls_cert else "")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--nats-*`` flags of ``serve --publish`` and ``gateway``."""
    for flag, text in _FLAGS:
        p.add_argument(f"--nats-{flag}", default=None, help=f"{text} (TOUCHREAL_NATS_{flag.upper().replace('-', '_')})")
    p.add_argument("--nats-tls", action="store_true", default=None, help="NATS over TLS with the system's CAs "
                   "(TOUCHREAL_NATS_TLS; implied by a tls:// URL or --nats-tls-ca)")


def from_args(args: argparse.Namespace) -> NatsAuth:
    """Flags over the environment."""
    given = {name: getattr(args, f"nats_{name}") for name in ("user", "password", "token", "creds", "nkey", "tls",
                                                             "tls_ca", "tls_cert", "tls_key")}
    return NatsAuth(**{k: v for k, v in given.items() if v is not None})
