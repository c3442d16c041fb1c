"""How the publisher and the gateways authenticate to the broker: one of user/password, token, a
``.creds`` file (JWT + nkey seed) or an nkey seed file, optionally over TLS (docs/scale-out.md);
or credentials in the URL (``nats://USER:PASSWORD@HOST``, ``nats://TOKEN@HOST``).

Flags ``--nats-*`` (:mod:`touchreal.commands.flags`) over ``TOUCHREAL_NATS_*`` environment variables; an empty variable counts as
unset (compose passes ``""`` for a variable it does not know). Secrets never appear in ``repr`` or
``/v1/status`` (:meth:`NatsAuth.describe`; URLs are shown through :func:`touchreal.redaction.redact`).
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

def servers(urls: str) -> list[str]:
    """The broker URLs of a comma-separated list, each with its scheme: nats-py reads ``HOST:PORT``
    and ``USER:PASSWORD@HOST`` as ``nats://...``, and so does everything that shows them."""
    return [u if "://" in u else f"nats://{u}" for u in (u.strip() for u in urls.split(",")) if u]


def _in_url(url: str) -> str | None:
    """The method the credentials in ``url`` amount to, as nats-py uses them (None: there are none)."""
    parts = urlsplit(url)
    if parts.username is None:
        return None
    return "token (in the URL)" if parts.password is None else f"user {parts.username} (in the URL)"


class NatsAuth(BaseSettings):
    """Broker credentials (environment: ``TOUCHREAL_NATS_<NAME>``); all unset = anonymous."""

    model_config = SettingsConfigDict(env_prefix="TOUCHREAL_NATS_", extra="ignore")

    user: str | None = Field(default=None, description="NATS user name (with --nats-password)")
    password: SecretStr | None = Field(default=None, description="NATS password; prefer the environment variable: "
                                       "flags show in the process list")
    token: SecretStr | None = Field(default=None, description="NATS token; prefer the environment variable")
    creds: Path | None = Field(default=None, description="NATS .creds file (JWT and nkey seed, from nsc)")
    nkey: Path | None = Field(default=None, description="NATS nkey seed file (its public key is in the broker's "
                              "config; touchreal gateway credentials issues one)")
    tls: bool = Field(default=False, description="NATS over TLS with the system's CAs (implied by a tls:// URL or "
                      "--nats-tls-ca)")
    tls_ca: Path | None = Field(default=None, description="CA bundle to verify the broker's certificate (implies TLS)")
    tls_cert: Path | None = Field(default=None, description="client certificate for TLS client authentication to "
                                  "the broker (with --nats-tls-key)")
    tls_key: Path | None = Field(default=None, description="private key of --nats-tls-cert")

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

    def _method(self) -> str | None:
        """The method these settings give (None: none)."""
        return (f"user {self.user}" if self.user else "token" if self.token else f"creds {self.creds}" if self.creds
                else f"nkey {self.nkey}" if self.nkey else None)

    def check(self, urls: list[str]) -> None:
        """Refuse credentials both here and in a URL of ``urls`` (:func:`servers`): one method at a time."""
        if self._method() is not None and any(_in_url(u) for u in urls):
            raise ValueError("NATS: credentials both in the URL and in --nats-*/TOUCHREAL_NATS_*: use one method")

    def describe(self, urls: list[str]) -> str:
        """The method in use with the brokers ``urls`` (:func:`servers`), without secrets (for logs and
        ``/v1/status``): e.g. ``user gateway``, ``user publisher (in the URL)``, ``token (in the URL)``,
        ``nkey /path/seed.nk``, ``anonymous``; `` over TLS`` when TLS is required (flags or a ``tls://`` URL)."""
        in_urls = sorted({m for m in map(_in_url, urls) if m})
        method = self._method() or " and ".join(in_urls) or "anonymous"
        tls = self.tls or self.tls_ca or self.tls_cert or any(urlsplit(u).scheme == "tls" for u in urls)
        return method + (" over TLS" if tls else "")
