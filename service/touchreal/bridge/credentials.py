"""``touchreal gateway credentials --id ID --out DIR``: a gateway's own broker identity.

Writes an nkey seed (``DIR/ID.nk``, the gateway's secret: run it with ``--nats-nkey DIR/ID.nk
--gateway-id ID``) and its public key (``DIR/ID.pub``), and prints the broker's user entry for it:
the public key with :func:`.subjects.gateway_permissions` of ``ID``, so these credentials announce
demand under ``ID`` and no other id. The broker keeps only the public key.
"""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

import nkeys

from .subjects import check_gateway_id, gateway_permissions


def permissions_entry(gateway_id: str) -> str:
    """The ``permissions`` value of gateway ``gateway_id``'s user in nats-server's config (JSON, one line)."""
    return json.dumps(gateway_permissions(gateway_id))


def user_entry(public_key: str, gateway_id: str) -> str:
    """An nkey user's entry for the ``authorization.users`` list of nats-server's config."""
    return f'{{nkey: "{public_key}", permissions: {permissions_entry(gateway_id)}}}'


def issue(gateway_id: str, out: Path) -> tuple[Path, str]:
    """Write a new user nkey seed for ``gateway_id`` to ``out/ID.nk`` (owner-only, 0600) and its
    public key to ``out/ID.pub``; returns (seed path, public key). Never overwrites a seed."""
    check_gateway_id(gateway_id)
    seed = nkeys.encode_seed(secrets.token_bytes(32), nkeys.PREFIX_BYTE_USER)
    public = nkeys.from_seed(bytearray(seed)).public_key.decode()
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{gateway_id}.nk"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)  # FileExistsError (an OSError) if it exists
    with os.fdopen(fd, "wb") as f:
        f.write(seed + b"\n")
    (out / f"{gateway_id}.pub").write_text(public + "\n")
    return path, public

